#!/usr/bin/env bash
# One-time (idempotent) set-up: system packages, a venv in .venv, CPU torch FIRST, then gsavatar.
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PKGS="libusb-1.0-0 libegl1 libegl-mesa0 libgl1-mesa-dri assimp-testmodels"
APT_PKGS="$APT_PKGS chromium"  # headless browser test of avatar-drive --view (tests/drive/test_viewer.py)
missing=""
for p in $APT_PKGS; do dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"; done
if [ -n "$missing" ]; then
  echo "[setup] apt-get install$missing"
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq $missing >/dev/null
fi

PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
# torch first, pinned: any later unpinned request would otherwise pull a multi-GB CUDA build.
.venv/bin/python -c "import torch, sys; sys.exit(0 if torch.__version__.startswith('2.13.0') else 1)" 2>/dev/null \
  || .venv/bin/pip install -q torch==2.13.0
.venv/bin/pip install -q -e '.[body,smplx,test]'
# anny's declared dependencies pull warp-lang and other torch builds; its runtime needs
# are in the [body] extra above.
.venv/bin/python -c "import anny" 2>/dev/null || .venv/bin/pip install -q --no-deps anny==0.6.2
# ST-LPIPS weights (AlexNet/VGG) for the perceptual loss/metric; its code needs torchvision, we only read its weight files.
.venv/bin/python -c "import importlib.util as u, sys; sys.exit(0 if u.find_spec('stlpips_pytorch') else 1)" || .venv/bin/pip install -q --no-deps stlpips-pytorch==0.0.2
echo "[setup] ok: $(.venv/bin/python -c 'import torch, gsavatar; print("torch", torch.__version__, "gsavatar", gsavatar.__version__)')"
