#!/usr/bin/env bash
# Everything dyq checks on a GPU, in one unattended run, for a machine with a CUDA build of torch, nvcc and
# no network: build dyq against that torch, run the CUDA tests, time the kernels, then compute-sanitizer's
# memcheck and racecheck. Each step has its own time limit and log; a failing step does not stop the ones
# after it (except the build). Results and logs land in $OUT (default build/device), summary.txt last.
#
#   pip download cmeel-eigen -d build/device_wheels    # beforehand, where the registry is reachable:
#                                                      # Eigen's headers, when the GPU machine has none
#   pip download bitsandbytes --no-deps -d build/device_wheels   # bench_cuda.py's bitsandbytes peers
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

# The environment heads the summary; at most 8 files come back from some machines, so there is one log a step.
{
  date -u
  nvidia-smi
  nvcc --version
  "$PYTHON" -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.get_device_name(0))"
} >> "$OUT/summary.txt" 2>&1
tail -n 1 "$OUT/summary.txt"

# The system's compilers: a GPU image seen here sets CXX to a /opt/gcc that links libstdc++ statically into
# shared objects, which the build refuses (cmake/check_shared_libstdcxx.cmake).
if [[ -x /usr/bin/g++ ]]; then
  export CC=/usr/bin/gcc CXX=/usr/bin/g++ CUDAHOSTCXX=/usr/bin/g++
fi
export CMAKE_ARGS="-DDYQ_CUDA=ON -DCMAKE_CUDA_ARCHITECTURES=${DYQ_CUDA_ARCHS:-90a-real} ${CMAKE_ARGS:-}"
export CMAKE_BUILD_PARALLEL_LEVEL=${CMAKE_BUILD_PARALLEL_LEVEL:-$(nproc)}
if compgen -G "build/device_wheels/*.whl" > /dev/null; then
  "$PYTHON" -m pip install -q --no-index --no-deps build/device_wheels/*.whl >> "$OUT/summary.txt" 2>&1 ||
    echo "installing build/device_wheels failed; the build needs a system Eigen then" | tee -a "$OUT/summary.txt"
fi
step build "${BUILD_LIMIT:-300}" "$PYTHON" -m pip install -v --no-build-isolation --no-deps . || {
  cat "$OUT/summary.txt"
  exit 1
}
# With a GPU there, the CUDA kernels must be registered: otherwise every CUDA test would skip and pass.
step import 60 "$PYTHON" -c "
import torch, dyq
cuda_ops = torch._C._dispatch_has_kernel_for_dispatch_key('dyq::gemm', 'CUDA')
print('dyq', dyq.__version__, 'GPU', torch.cuda.is_available(), 'CUDA ops', cuda_ops, dyq.cpu_info())
assert cuda_ops or not torch.cuda.is_available(), 'a GPU is there but dyq registered no CUDA kernels'"
# On 8 workers where pytest-xdist is installed: the tests' float64 references run on the CPU.
workers=()
"$PYTHON" -c "import xdist" 2> /dev/null && workers=(-n 8)
step test_cuda "${TEST_LIMIT:-240}" "$PYTHON" -m pytest -q -p no:cacheprovider "${workers[@]}" tests/test_cuda.py -rfE \
  ${TEST_ARGS:-}
step bench_cuda "${BENCH_LIMIT:-240}" "$PYTHON" bench/bench_cuda.py ${BENCH_ARGS:-} --out "$OUT"
# The sanitizers on a decode and a prefill case of every width (they slow the kernels many times).
gemm_case=tests/test_cuda.py::test_gemm_matches_reference_and_cpu
prefill_cases=() decode_cases=()
for bits in 2 4 8 16; do
  decode_cases+=("$gemm_case[128-$bits-1]")
  prefill_cases+=("$gemm_case[128-$bits-300]")
done
step memcheck "${SANITIZER_LIMIT:-120}" compute-sanitizer --tool memcheck --error-exitcode 1 --leak-check no \
  "$PYTHON" -m pytest -q -x -p no:cacheprovider "${decode_cases[@]}" "${prefill_cases[@]}" \
  "tests/test_cuda.py::test_cuda_graph_replays_at_the_precision_the_flag_holds[64]"
step racecheck "${SANITIZER_LIMIT:-120}" compute-sanitizer --tool racecheck --racecheck-report hazard \
  --error-exitcode 1 "$PYTHON" -m pytest -q -x -p no:cacheprovider "${prefill_cases[@]}" "${decode_cases[@]}"
echo "== summary"
cat "$OUT/summary.txt"
