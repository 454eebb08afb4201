// RMSNorm on CUDA (formula and layout: activation/rms_norm_cpu.h, whose CPU kernel computes the same, in
// fp32 with the same two roundings).
//
// One block of 256 threads per row (a grid-stride loop over rows when there are more rows than blocks):
//   1. thread t sums the squares of elements t, t + 256, ... (coalesced, any alignment), a warp's sums meet
//      by shuffles and the 8 warps' in shared memory, so every thread holds the row's sum;
//   2. thread t writes the same elements: h = dtype(x r), then dtype(w h), each rounded to nearest even.
// The row is read twice from global memory (the second time mostly from L1/L2): a norm is a small part of a
// layer's time, and no shared-memory bound on n is needed.
#include "activation/rms_norm_cuda.h"
#include "common/cuda_utils.cuh"

namespace dyq::cuda {
namespace {

constexpr int kThreads = 256;
constexpr int kWarps = kThreads / 32;
constexpr int kMaxBlocks = 65535;

// value rounded to dtype and widened back (the framework's .to(dtype) between the two products).
__device__ __forceinline__ float rounded_to(ScalarType dtype, float value) {
  switch (dtype) {
    case ScalarType::kFloat32: return value;
    case ScalarType::kBFloat16: return __bfloat162float(__float2bfloat16_rn(value));
    default: return __half2float(__float2half_rn(value));
  }
}

__global__ void __launch_bounds__(kThreads)
    rms_norm_kernel(const void* x, ScalarType dtype, const void* weight, int64_t rows, int n, float eps, void* out) {
  __shared__ float warp_sums[kWarps];
  const int lane = threadIdx.x % 32, warp = threadIdx.x / 32;
  for (int64_t row = blockIdx.x; row < rows; row += gridDim.x) {
    float sum = 0.0f;
    for (int i = threadIdx.x; i < n; i += kThreads) {
      const float v = load_as_float(x, row * n + i, dtype);
      sum = fmaf(v, v, sum);
    }
    for (int offset = 16; offset > 0; offset /= 2) sum += __shfl_xor_sync(0xffffffffu, sum, offset);
    if (lane == 0) warp_sums[warp] = sum;
    __syncthreads();
    sum = 0.0f;
    for (int w = 0; w < kWarps; ++w) sum += warp_sums[w];
    const float inverse_rms = 1.0f / sqrtf(sum / static_cast<float>(n) + eps);
    for (int i = threadIdx.x; i < n; i += kThreads) {
      const float h = rounded_to(dtype, load_as_float(x, row * n + i, dtype) * inverse_rms);
      store_from_float(out, row * n + i, dtype, load_as_float(weight, i, dtype) * h);
    }
    __syncthreads();  // warp_sums is written again for the next row
  }
}

}  // namespace

cudaError_t rms_norm(const void* x, ScalarType dtype, const void* weight, int64_t rows, int64_t n, float eps,
                     void* out, cudaStream_t stream) {
  if (rows == 0 || n == 0) return cudaSuccess;
  const unsigned blocks = static_cast<unsigned>(rows < kMaxBlocks ? rows : kMaxBlocks);
  rms_norm_kernel<<<blocks, kThreads, 0, stream>>>(x, dtype, weight, rows, static_cast<int>(n), eps, out);
  return cudaGetLastError();
}

}  // namespace dyq::cuda
