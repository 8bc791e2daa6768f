#!/usr/bin/env bash
# Controlled capture experiment (docs/train.md "What a derivative trigger changes"): `small` rendered without the
# room's light (albedo only, as out/small_unlit), with ONE change: the `sleeve` hysteresis flips on a SIGNAL of the
# right hand other than its height (default `speed`), so no single pose shows when it flips. Builds the capture, preps
# it, trains the avatar, the demo's predictor recipe and its no-history ablation (N_b = 1, no velocities), then scores
# every source and oracle with benchmarks/predictor_psnr.py --oracles.
#   bash benchmarks/trigger_experiment.sh                   # -> out/small_unlit_speed (about 45 min on the 2-core box)
#   OUT=out/x SIGNAL=vertical_velocity STEPS=1200 bash benchmarks/trigger_experiment.sh
#   WINDOW=16 bash benchmarks/trigger_experiment.sh         # the predictors' training window (default 8)
#   OUT=out/small_unlit_dyn DROP=sleeve SIGNAL=height bash benchmarks/trigger_experiment.sh  # without the sleeve
#   OUT=out/small_dynamic DYNAMIC=1 bash benchmarks/trigger_experiment.sh  # trigger_capture.py --dynamic
#   OUT=out/second_springs SECOND_SPRINGS=1 bash benchmarks/trigger_experiment.sh  # --second-springs
# Re-running resumes (finished trainings are skipped). Needs the set-up of scripts/setup.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-out/small_unlit_speed}
SIGNAL=${SIGNAL:-speed}
STEPS=${STEPS:-400}
WINDOW=${WINDOW:-8}
DROP=${DROP:-}  # motion effects left out of the capture (space-separated names)
DYNAMIC=${DYNAMIC:-0}  # 1: the design candidate of trigger_capture.py --dynamic instead
SECOND_SPRINGS=${SECOND_SPRINGS:-0}  # 1: trigger_capture.py --second-springs (01_03, three springs, unlit) instead
TAG=s$STEPS
[ "$WINDOW" != 8 ] && TAG=${TAG}_w$WINDOW
export ANNY_CACHE_DIR=${ANNY_CACHE_DIR:-$PWD/.cache/anny}
export VTK_DEFAULT_OPENGL_WINDOW=${VTK_DEFAULT_OPENGL_WINDOW:-vtkEGLRenderWindow}
PRED="--steps $STEPS --window $WINDOW --model.latent-pca global --model.latent-pca-components 8 --ensemble 2 --model.world-orientation"
if [ ! -f "$OUT/capture/capture.json" ]; then
    PYTHONPATH=src .venv/bin/python benchmarks/trigger_capture.py "$OUT/capture" "$SIGNAL" ${DROP:+--drop $DROP} \
        $([ "$DYNAMIC" = 1 ] && echo --dynamic) $([ "$SECOND_SPRINGS" = 1 ] && echo --second-springs)
fi
.venv/bin/avatar-prep all --capture "$OUT/capture" --out "$OUT/dataset" --no-figures
OMP_NUM_THREADS=2 .venv/bin/avatar-train avatar --dataset "$OUT/dataset" --out "$OUT/run_ours" --preset small
# the two predictors side by side, one thread each
OMP_NUM_THREADS=1 .venv/bin/avatar-train predictor --run "$OUT/run_ours" --out "$OUT/run_ours/predictor_$TAG" \
    $PRED > "$OUT/predictor_$TAG.log" 2>&1 &
full=$!
OMP_NUM_THREADS=1 .venv/bin/avatar-train predictor --run "$OUT/run_ours" --out "$OUT/run_ours/predictor_nohist_$TAG" \
    $PRED --model.history 1 --model.no-velocities > "$OUT/predictor_nohist_$TAG.log" 2>&1
wait "$full"
OMP_NUM_THREADS=2 PYTHONPATH=src .venv/bin/python benchmarks/predictor_psnr.py --run "$OUT/run_ours" \
    --predictors "full=$OUT/run_ours/predictor_$TAG/latest.pt" \
    "nohist=$OUT/run_ours/predictor_nohist_$TAG/latest.pt" --every 3 --oracles --json "$OUT/oracles_$TAG.json"
