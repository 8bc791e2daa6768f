#!/usr/bin/env bash
# Set up (idempotent), then the main job on the embedded default scene:
# synthetic capture (real anny body + real CMU mocap) -> every avatar-prep stage -> verify
# -> train the avatar (CPU) -> evaluate on held-out cameras/frames -> turntable video
# -> train the appearance predictor -> drive the held-out frames autoregressively (video + metrics)
# -> train the baselines / ablations on the same schedule -> the results table (docs/results.md layout).
# Re-running resumes: finished stages and trainings are skipped.
# BASELINES=0 skips the baselines/ablations (the table then has the rows of Ours only).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export ANNY_CACHE_DIR=${ANNY_CACHE_DIR:-$PWD/.cache/anny}
export VTK_DEFAULT_OPENGL_WINDOW=${VTK_DEFAULT_OPENGL_WINDOW:-vtkEGLRenderWindow}
PRESET=${PRESET:-small}
OUT=${OUT:-$PWD/out/demo}
BASELINES=${BASELINES:-1}
if [ ! -f "$OUT/capture/capture.json" ]; then
    .venv/bin/avatar-prep synth --out "$OUT/capture" --preset "$PRESET"
fi
.venv/bin/avatar-prep all --capture "$OUT/capture" --out "$OUT/dataset"
.venv/bin/avatar-prep verify "$OUT/dataset"
.venv/bin/python -m gsavatar.prep.report "$OUT/dataset" --out "$OUT/report" > /dev/null
train() {  # train NAME [avatar-train flags...]: one run, resumed if it exists
    local name=$1
    shift
    .venv/bin/avatar-train avatar --dataset "$OUT/dataset" --out "$OUT/$name" --preset "$PRESET" "$@"
}
train run_ours
.venv/bin/avatar-train turntable --run "$OUT/run_ours" --out "$OUT/run_ours/turntable.mp4"
.venv/bin/avatar-train predictor --run "$OUT/run_ours" --steps 600 --window 8 --model.latent-pca-components 16
.venv/bin/avatar-drive --run "$OUT/run_ours" --motion "$OUT/capture" --split test --mode predictor_encoder_init \
    --out "$OUT/drive_test"
if [ "$BASELINES" = 1 ]; then
    train run_mmlps --variant mmlps_dagger
    train run_nrfgca --variant nrfgca_dagger
    train run_wo_local_pose --variant wo_local_pose
    train run_wo_local_pca --variant wo_local_pca
    if [ "$PRESET" = small ]; then  # speed against error: the same schedule with (64, 64) anchor MLPs
        .venv/bin/avatar-train avatar --dataset "$OUT/dataset" --out "$OUT/run_ours_tinymodel" --preset tiny \
            --steps 1200 --correctives-step 200 --checkpoint-every 200
    fi
fi
PYTHONPATH=src .venv/bin/python benchmarks/results_table.py --runs "$OUT" --out "$OUT/results.md"
echo
echo "UV textures (sharded, float16):   $OUT/dataset/project_uv/shard-*.npz  (manifest.json lists frames)"
echo "UV texture previews + accuracy:   $OUT/report/uv_*.png, $OUT/report/report.json"
echo "Figures (hierarchy, influence):   $OUT/dataset/localize/*.png"
echo "Trained avatar + metrics:         $OUT/run_ours/checkpoints/latest.pt, $OUT/run_ours/eval/metrics.json"
echo "Turntable video:                  $OUT/run_ours/turntable.mp4"
echo "Driven test sequence (predictor): $OUT/drive_test/drive.mp4, metrics.json, stability.png"
echo "Results table (all rows):         $OUT/results.md  (drives in $OUT/drive/)"
