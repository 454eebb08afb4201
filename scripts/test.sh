#!/usr/bin/env bash
# Runs every test: the C++ kernel tests through ctest, then the Python suite through pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$PWD/.venv/bin:$PATH"

cmake -S . -B build/ctest -G Ninja -DDYQ_BUILD_PYTHON=OFF -DDYQ_BUILD_TESTS=ON -DDYQ_CUDA=OFF >/dev/null
cmake --build build/ctest -j "$(nproc)"
ctest --test-dir build/ctest --output-on-failure --no-tests=error -j "$(nproc)"

# Run from the tests folder so that `import dyq` is the installed package, not the source tree.
cd tests && python -m pytest -q -p no:cacheprovider "$@"
