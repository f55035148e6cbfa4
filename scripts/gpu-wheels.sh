#!/usr/bin/env bash
# Download, on a machine with network, the wheels a bare GPU machine lacks (it has PyTorch with
# CUDA, accelerate, transformers, numpy, scipy, scikit-image, matplotlib, tqdm; no network) into
# .whl/ (git-ignored), for the Python and platform it runs: `scripts/gpu-check.sh` installs them
# there with --no-index. Set GPU_PYTHON (default 3.12) to that machine's Python version.
# gsplat (the optional [cuda] rasterizer) is left out unless GSPLAT=1: it compiles its CUDA
# kernels on first use, minutes on a fresh machine.
set -euo pipefail
cd "$(dirname "$0")/.."
py=${GPU_PYTHON:-3.12}
mkdir -p .whl
# pinned to what this project's CPU machines run (scripts/setup-venv.sh resolves the same names)
wheels=(diffusers==0.42.1 importlib_metadata==8.7.0 openimageio==3.2.2.0 emcee==3.1.6)
[ "${GSPLAT:-0}" = 1 ] && wheels+=(gsplat==1.5.3)
python3 -m pip download -q --no-deps --only-binary=:all: --python-version "$py" --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform any -d .whl "${wheels[@]}"
du -sh .whl
ls .whl
