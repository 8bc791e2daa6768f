#!/usr/bin/env bash
# GPU check (docs/performance.md), from the repository root:
#   1. tests/render/test_rasterize.py: the gsplat CUDA rasterizer against our CPU compositor
#      (test_torch_backend_matches_gsplat_cuda, skipped without CUDA) plus the CPU reference tests;
#   2. `avatar-train avatar --preset paper --steps 300` on the tiny synthetic capture: iterations/s;
#   3. a short `avatar-train predictor`, then driving: frames/s of the streaming driver
#      (benchmarks/gpu_check.py drive-bench) and, where ffmpeg is available, of `avatar-drive`.
# Results: gpu_check.json + gpu_check.md (+ the log, metrics.jsonl, pytest XML) in $RESULTS
# (default: the device tool's $OUT, else out/gpu_check).
#
#   bash benchmarks/gpu_check.sh               # on a CUDA machine; refuses to run without CUDA
#   bash benchmarks/gpu_check.sh --cpu-smoke   # (or CPU_SMOKE=1) plumbing check on CPU: tiny preset, a few steps
#   bash benchmarks/gpu_check.sh --prepare     # on this (networked) CPU box: wheels + tiny dataset in $INPUT
#   bash benchmarks/gpu_check.sh --dry-run     # print the commands, run nothing
#
# Python: $GPU_CHECK_PYTHON if set, else .venv if present, else a python3 that has torch (the lent H200's image), with the
# wheels from --prepare installed under $WORK/site and src/ on PYTHONPATH; else scripts/setup.sh.
# Data: $INPUT/{capture,dataset} when present (built by --prepare), else built here with
# avatar-prep (needs the full setup: anny, open3d, ...). An offline GPU box has neither
# registry nor anny, so prepare here and carry $INPUT (docs/performance.md has the device call).
# Environment knobs (defaults GPU / CPU smoke): PRESET (paper / tiny), STEPS (300 / 6),
# BATCH (0 = preset's / 2), PRED_STEPS (50 / 4), DRIVE_FRAMES (240 / 8), DRIVE_SIZE (512 / 64),
# DRIVE_VIEWS (1), DATA_PRESET (tiny), INPUT (out/gpu_check_input), WORK (out/gpu_check_work).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD

CPU_SMOKE=${CPU_SMOKE:-0}
DRY=0
PREPARE=0
for arg in "$@"; do
    case $arg in
        --cpu-smoke) CPU_SMOKE=1 ;;
        --dry-run) DRY=1 ;;
        --prepare) PREPARE=1 ;;
        -h | --help) sed -n '2,26p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
        *) echo "gpu_check: unknown argument '$arg' (see --help)" >&2; exit 2 ;;
    esac
done

INPUT=${INPUT:-$ROOT/out/gpu_check_input}
WORK=${WORK:-$ROOT/out/gpu_check_work}
RESULTS=${RESULTS:-${OUT:-$ROOT/out/gpu_check}}
DATA_PRESET=${DATA_PRESET:-tiny}
export ANNY_CACHE_DIR=${ANNY_CACHE_DIR:-$ROOT/.cache/anny}
if [ "$CPU_SMOKE" = 1 ]; then
    MODE=cpu_smoke PRESET=${PRESET:-tiny} STEPS=${STEPS:-6} BATCH=${BATCH:-2} PRED_STEPS=${PRED_STEPS:-4}
    DRIVE_FRAMES=${DRIVE_FRAMES:-8} DRIVE_SIZE=${DRIVE_SIZE:-64} LOG_EVERY=${LOG_EVERY:-2} LPIPS=${LPIPS:-off}
else
    MODE=gpu PRESET=${PRESET:-paper} STEPS=${STEPS:-300} BATCH=${BATCH:-0} PRED_STEPS=${PRED_STEPS:-50}
    DRIVE_FRAMES=${DRIVE_FRAMES:-240} DRIVE_SIZE=${DRIVE_SIZE:-512} LOG_EVERY=${LOG_EVERY:-10} LPIPS=${LPIPS:-on}
fi
DRIVE_VIEWS=${DRIVE_VIEWS:-1}

say() { echo "[gpu_check] $*"; }
run() {  # run CMD...: echo it; execute it unless --dry-run
    echo "+ $*"
    [ "$DRY" = 1 ] || "$@"
}
phase() {  # phase NAME CMD...: run and record its wall seconds in $WORK/timings.tsv
    local name=$1 t0 t1
    shift
    t0=$(date +%s.%N)
    run "$@"
    t1=$(date +%s.%N)
    [ "$DRY" = 1 ] || printf '%s\t%s\n' "$name" "$(awk "BEGIN {printf \"%.1f\", $t1 - $t0}")" >>"$WORK/timings.tsv"
}

# --- the Python that runs everything ------------------------------------------------------
use_carried_wheels() {  # install $INPUT/wheels for $PY under $WORK/site; gsavatar from src/
    if [ -d "$INPUT/wheels" ] && ls "$INPUT"/wheels/*.whl >/dev/null 2>&1; then
        run "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
            --target "$WORK/site" "$INPUT"/wheels/*.whl
    fi
    export PYTHONPATH="$ROOT/src:$WORK/site${PYTHONPATH:+:$PYTHONPATH}"
}
pick_python() {
    if [ -n "${GPU_CHECK_PYTHON:-}" ]; then  # an interpreter that has torch (tests the offline path too)
        PY=$GPU_CHECK_PYTHON
        use_carried_wheels
    elif [ -x .venv/bin/python ]; then
        PY=$ROOT/.venv/bin/python
    elif python3 -c "import torch" 2>/dev/null; then  # e.g. the lent H200: torch, no registry
        PY=python3
        use_carried_wheels
    else
        run bash scripts/setup.sh
        PY=$ROOT/.venv/bin/python
    fi
}

build_data() {  # build_data CAPTURE DATASET: the synthetic capture and every avatar-prep stage
    local cap=$1 ds=$2
    [ -f "$cap/capture.json" ] || phase synth_capture "$PY" -m gsavatar.prep.cli synth --out "$cap" --preset "$DATA_PRESET"
    phase prep_dataset "$PY" -m gsavatar.prep.cli all --capture "$cap" --out "$ds" --no-figures \
        --workers "${PREP_WORKERS:-2}"
}

mkdir -p "$WORK"
[ "$DRY" = 1 ] || : >"$WORK/timings.tsv"

# --- --prepare: everything an offline GPU box cannot fetch or build --------------------------
if [ "$PREPARE" = 1 ]; then
    [ -x .venv/bin/python ] || run bash scripts/setup.sh
    PY=$ROOT/.venv/bin/python
    mkdir -p "$INPUT/wheels" "$INPUT/lpips"
    # Pure-Python packages missing from the H200 image (see /work/.library/device/KINDS.md),
    # at the versions installed here. imageio-ffmpeg (68 MB) and stlpips-pytorch (60 MB) are
    # too big to carry: the ST-LPIPS AlexNet weights travel alone (--lpips-weights).
    pins=$("$PY" -c "import importlib.metadata as m; print(' '.join(f'{n}=={m.version(n)}' for n in
        ('gsplat', 'tyro', 'docstring-parser', 'typeguard')))")
    # shellcheck disable=SC2086  # pins is a word list
    run "$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux2014_x86_64 -d "$INPUT/wheels" $pins
    run cp "$("$PY" -c "from gsavatar.metrics.lpips import stlpips_weights_path as p; print(p('alex'))")" "$INPUT/lpips/"
    build_data "$INPUT/capture" "$INPUT/dataset"
    [ "$DRY" = 1 ] || du -sh "$INPUT"
    say "prepared $INPUT; on the GPU box (device tool): carry it and run this script (docs/performance.md)"
    exit 0
fi

# --- the check ----------------------------------------------------------------------------
pick_python
if [ "$DRY" != 1 ] && ! "$PY" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)"; then
    if [ "$CPU_SMOKE" != 1 ]; then
        echo "gpu_check: no CUDA device visible to $PY ($("$PY" -c 'import torch; print("torch", torch.__version__)'))." >&2
        echo "gpu_check: this script measures the GPU path; run it on a CUDA machine, or with CPU_SMOKE=1" \
            "(--cpu-smoke) for a plumbing check on CPU." >&2
        exit 2
    fi
    DEVICE=cpu
else
    DEVICE=${DEVICE:-$([ "$CPU_SMOKE" = 1 ] && echo cpu || echo cuda)}
fi
mkdir -p "$RESULTS"
exec > >(tee "$RESULTS/gpu_check.log") 2>&1
say "mode $MODE, python $PY, device $DEVICE, results $RESULTS"
run "$PY" benchmarks/gpu_check.py env --out "$WORK/env.json"

if [ "$DEVICE" != cpu ]; then
    # gsplat 1.5.3 JIT-compiles its CUDA kernels on first use: do it once, timed, for this GPU only.
    if [ -z "${TORCH_CUDA_ARCH_LIST:-}" ]; then
        TORCH_CUDA_ARCH_LIST=$("$PY" -c "import torch; print('%d.%d' % torch.cuda.get_device_capability())")
        export TORCH_CUDA_ARCH_LIST
    fi
    export MAX_JOBS=${MAX_JOBS:-$(nproc)} TORCH_EXTENSIONS_DIR=${TORCH_EXTENSIONS_DIR:-$WORK/torch_extensions}
    phase gsplat_jit "$PY" -c "from gsplat.cuda._backend import _C; assert _C is not None, 'gsplat CUDA build failed'"
fi

# 1. renderer: CPU reference tests + the gsplat CUDA comparison (the latter skips on CPU).
phase test_rasterize "$PY" -m pytest -q -p no:cacheprovider tests/render/test_rasterize.py -m "not slow" -rs \
    --junitxml "$WORK/pytest_rasterize.xml" || say "test_rasterize.py FAILED (see the log); continuing"

# 2. data: carried (--prepare) or built here.
CAPTURE=$INPUT/capture
DATASET=$INPUT/dataset
if [ -f "$DATASET/dataset.json" ] && [ -f "$CAPTURE/capture.json" ]; then
    run "$PY" benchmarks/gpu_check.py relocate --dataset "$DATASET" --capture "$CAPTURE"
else
    CAPTURE=$WORK/capture DATASET=$WORK/dataset
    build_data "$CAPTURE" "$DATASET"
fi

# 3. training speed (a fresh run: the rate is read from its metrics.jsonl).
lpips_args=(--lpips "$LPIPS")
if [ "$LPIPS" != off ] && [ -f "$INPUT/lpips/alex_shift_tolerant.pth" ]; then  # = the stlpips wheel's AlexNet file
    lpips_args+=(--lpips-weights "$INPUT/lpips/alex_shift_tolerant.pth")
fi
[ "$DRY" = 1 ] || rm -rf "$WORK/run" "$WORK/drive"
phase train "$PY" -m gsavatar.train.cli avatar --dataset "$DATASET" --out "$WORK/run" --preset "$PRESET" \
    --steps "$STEPS" --batch-size "$BATCH" --log-every "$LOG_EVERY" --checkpoint-every "$STEPS" --no-evaluate \
    --device "$DEVICE" "${lpips_args[@]}"

# 4. driving speed: a predictor (its quality does not matter here), then the streaming driver.
phase train_predictor "$PY" -m gsavatar.train.cli predictor --run "$WORK/run" --steps "$PRED_STEPS" \
    --log-every "$PRED_STEPS" --checkpoint-every "$PRED_STEPS" --no-evaluate --device "$DEVICE"
phase drive_bench "$PY" benchmarks/gpu_check.py drive-bench --run "$WORK/run" --motion "$CAPTURE" \
    --frames "$DRIVE_FRAMES" --size "$DRIVE_SIZE" --views "$DRIVE_VIEWS" --device "$DEVICE" --out "$WORK/drive_bench.json"
if "$PY" -c "import imageio_ffmpeg; imageio_ffmpeg.get_ffmpeg_exe()" 2>/dev/null; then
    phase drive_cli "$PY" -m gsavatar.drive.cli --run "$WORK/run" --motion "$CAPTURE" --out "$WORK/drive" \
        --cameras orbit --orbit-views "$DRIVE_VIEWS" --orbit-size "$DRIVE_SIZE" --no-write-frames --lpips off \
        --device "$DEVICE"
else
    say "no ffmpeg for imageio: avatar-drive (which always writes an mp4) skipped; drive-bench covers frames/s"
fi

# 5. summary
if [ "$DRY" != 1 ]; then
    cp "$WORK/run/metrics.jsonl" "$RESULTS/metrics.jsonl"
    cp "$WORK/pytest_rasterize.xml" "$RESULTS/pytest_rasterize.xml" 2>/dev/null || true
    "$PY" benchmarks/gpu_check.py summarize --work "$WORK" --out "$RESULTS" --mode "$MODE" --timings "$WORK/timings.tsv"
fi
say "done: $RESULTS/gpu_check.md"
