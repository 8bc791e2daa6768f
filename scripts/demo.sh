#!/usr/bin/env bash
# Set up (idempotent), then the main job on the embedded default scene:
# synthetic capture (real anny body + real CMU mocap) -> every avatar-prep stage -> verify
# -> train the avatar (CPU) -> evaluate on held-out cameras/frames -> turntable video
# -> train the appearance predictor -> drive the held-out frames autoregressively (video + metrics).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export ANNY_CACHE_DIR=${ANNY_CACHE_DIR:-$PWD/.cache/anny}
export VTK_DEFAULT_OPENGL_WINDOW=${VTK_DEFAULT_OPENGL_WINDOW:-vtkEGLRenderWindow}
PRESET=${PRESET:-small}
OUT=${OUT:-$PWD/out/demo}
.venv/bin/avatar-prep synth --out "$OUT/capture" --preset "$PRESET"
.venv/bin/avatar-prep all --capture "$OUT/capture" --out "$OUT/dataset"
.venv/bin/avatar-prep verify "$OUT/dataset"
.venv/bin/python -m gsavatar.prep.report "$OUT/dataset" --out "$OUT/report" > /dev/null
.venv/bin/avatar-train avatar --dataset "$OUT/dataset" --out "$OUT/run_ours" --preset "$PRESET"
.venv/bin/avatar-train turntable --run "$OUT/run_ours" --out "$OUT/run_ours/turntable.mp4"
.venv/bin/avatar-train predictor --run "$OUT/run_ours" --steps 600 --window 8 --model.latent-pca-components 16
.venv/bin/avatar-drive --run "$OUT/run_ours" --motion "$OUT/capture" --split test --mode predictor_encoder_init \
    --out "$OUT/drive_test"
echo
echo "UV textures (sharded, float16):   $OUT/dataset/project_uv/shard-*.npz  (manifest.json lists frames)"
echo "UV texture previews + accuracy:   $OUT/report/uv_*.png, $OUT/report/report.json"
echo "Figures (hierarchy, influence):   $OUT/dataset/localize/*.png"
echo "Trained avatar + metrics:         $OUT/run_ours/checkpoints/latest.pt, $OUT/run_ours/eval/metrics.json"
echo "Turntable video:                  $OUT/run_ours/turntable.mp4"
echo "Driven test sequence (predictor): $OUT/drive_test/drive.mp4, metrics.json, stability.png"
