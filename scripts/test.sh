#!/usr/bin/env bash
# Runs every test: the C++ kernel tests through ctest, then the Python suite through pytest. Build output
# goes to build/ctest.log (printed only when the build fails), so that the run shows the test summaries.
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$PWD/.venv/bin:$PATH"

mkdir -p build
log=build/ctest.log
if ! { cmake -S . -B build/ctest -G Ninja -DDYQ_BUILD_PYTHON=OFF -DDYQ_BUILD_TESTS=ON -DDYQ_CUDA=OFF &&
       cmake --build build/ctest -j "$(nproc)"; } >"$log" 2>&1; then
  cat "$log"
  exit 1
fi
if ! ctest --test-dir build/ctest --output-on-failure --no-tests=error -j "$(nproc)" >>"$log" 2>&1; then
  tail -n 200 "$log"  # --output-on-failure put the failing tests' output there
  exit 1
fi
tail -n 3 "$log"

# Run from the tests folder so that `import dyq` is the installed package, not the source tree.
cd tests && python -m pytest -q -p no:cacheprovider "$@"
