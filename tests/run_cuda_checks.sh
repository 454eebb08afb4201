#!/usr/bin/env bash
# Memory and race checks of the CUDA kernels under compute-sanitizer (run on a machine with a GPU, after
# `pip install --no-build-isolation .`). Each tool runs the CUDA tests; racecheck, synccheck and
# initcheck skip the graph-capture test, whose replays those tools do not follow.
set -euo pipefail
cd "$(dirname "$0")/.."
sanitizer=${COMPUTE_SANITIZER:-compute-sanitizer}

# run TOOL TEST_FILTER [SANITIZER_OPTION...]
run() {
  local tool=$1 filter=$2
  shift 2
  echo "== compute-sanitizer --tool ${tool}"
  "$sanitizer" --tool "$tool" --error-exitcode 1 "$@" \
    python -m pytest -q -x -p no:cacheprovider tests/test_cuda.py -k "$filter"
}

run memcheck "cuda" --leak-check no
run racecheck "not graph" --racecheck-report hazard
run synccheck "not graph"
run initcheck "not graph"
echo "all compute-sanitizer checks passed"
