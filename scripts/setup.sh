#!/usr/bin/env bash
# Installs everything dyq needs on a fresh Debian machine and builds it into ./.venv:
# system packages (Eigen, GoogleTest), a virtual environment with torch 2.13 (CPU), the Python
# dependencies, and dyq itself (with a CPU torch, the CPU ops only: .ci/run compiles the CUDA kernels).
set -euo pipefail
cd "$(dirname "$0")/.."

SUDO=""
if [ "$(id -u)" != 0 ]; then SUDO="sudo"; fi
if ! dpkg -s libeigen3-dev libgtest-dev cmake >/dev/null 2>&1; then
  $SUDO apt-get update -qq
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libeigen3-dev libgtest-dev cmake g++ >/dev/null
fi

PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
# torch is pinned: any looser spec may pull several GB of CUDA wheels.
.venv/bin/python -m pip install -q "torch==2.13.0" numpy "setuptools>=77" ninja \
  pytest hypothesis expecttest "transformers>=4.40" matplotlib safetensors h5py tqdm imageio \
  "bitsandbytes>=0.45"  # a peer of the benchmarks, tested on the CPU
# The simulator for the closed loop (the `sim` extra): robosuite needs mujoco 3.3.x, not 4.
.venv/bin/python -m pip install -q "robosuite==1.5.2" "mujoco==3.3.7"
# Built against the torch installed above, hence no build isolation (warm rebuilds; a plain
# `pip install .` works too, building in an isolated environment of its own).
.venv/bin/python -m pip install -q --no-build-isolation .
.venv/bin/python -c "import dyq, torch; print('dyq', dyq.__version__, 'built against torch', torch.__version__)"
