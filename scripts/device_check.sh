#!/usr/bin/env bash
# Everything dyq checks on a GPU, in one unattended run, for a machine with a CUDA build of torch, nvcc and
# no network: build dyq against that torch, run the CUDA tests, time the kernels, then compute-sanitizer's
# memcheck. Each step has its own time limit and log; a failing step does not stop the ones after it
# (except the build). Results and logs land in $OUT (default build/device), summary.txt last.
#
#   pip download cmeel-eigen -d build/device_wheels    # beforehand, where the registry is reachable:
#                                                      # Eigen's headers, when the GPU machine has none
#   OUT=/some/dir bash scripts/device_check.sh         # on the GPU machine
#
# DYQ_CUDA_ARCHS (default 90a-real: H100 / H200; 80-real for A100, 89-real for Ada) picks what nvcc builds,
# so the build compiles for the one device there is. PYTHON (default python3) is the interpreter with torch.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-build/device}
PYTHON=${PYTHON:-python3}
mkdir -p "$OUT"
: > "$OUT/summary.txt"

# step NAME SECONDS COMMAND...: runs COMMAND under a time limit, its output in $OUT/NAME.log.
step() {
  local name=$1 limit=$2 start=$SECONDS rc
  shift 2
  echo "== $name (at most ${limit} s)"
  timeout --kill-after=10 "$limit" "$@" > "$OUT/$name.log" 2>&1
  rc=$?
  echo "$name: rc $rc, $((SECONDS - start)) s" | tee -a "$OUT/summary.txt"
  tail -n 15 "$OUT/$name.log"
  return "$rc"
}

{
  date -u
  nvidia-smi
  nvcc --version
  "$PYTHON" -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.get_device_name(0))"
} > "$OUT/environment.txt" 2>&1
tail -n 1 "$OUT/environment.txt"

if compgen -G "build/device_wheels/*.whl" > /dev/null; then
  "$PYTHON" -m pip install -q --no-index --no-deps build/device_wheels/*.whl > "$OUT/wheels.log" 2>&1 ||
    echo "installing build/device_wheels failed (see wheels.log); the build needs a system Eigen then"
fi

export CMAKE_ARGS="-DDYQ_CUDA=ON -DCMAKE_CUDA_ARCHITECTURES=${DYQ_CUDA_ARCHS:-90a-real} ${CMAKE_ARGS:-}"
export CMAKE_BUILD_PARALLEL_LEVEL=${CMAKE_BUILD_PARALLEL_LEVEL:-$(nproc)}
step build 420 "$PYTHON" -m pip install -v --no-build-isolation --no-deps . || {
  cat "$OUT/summary.txt"
  exit 1
}
# With a GPU there, the CUDA kernels must be registered: otherwise every CUDA test would skip and pass.
step import 60 "$PYTHON" -c "
import torch, dyq
cuda_ops = torch._C._dispatch_has_kernel_for_dispatch_key('dyq::gemm', 'CUDA')
print('dyq', dyq.__version__, 'GPU', torch.cuda.is_available(), 'CUDA ops', cuda_ops, dyq.cpu_info())
assert cuda_ops or not torch.cuda.is_available(), 'a GPU is there but dyq registered no CUDA kernels'"
step test_cuda 300 "$PYTHON" -m pytest -q -p no:cacheprovider tests/test_cuda.py --junitxml="$OUT/test_cuda.xml"
step bench_cuda 240 "$PYTHON" bench/bench_cuda.py --quick --out "$OUT"
step memcheck 300 compute-sanitizer --tool memcheck --error-exitcode 1 --leak-check no \
  "$PYTHON" -m pytest -q -x -p no:cacheprovider tests/test_cuda.py -k "not graph"
echo "== summary"
cat "$OUT/summary.txt"
