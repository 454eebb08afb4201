// The online Hadamard rotation on CUDA (formula and layout: activation/hadamard_cpu.h, whose CPU kernel
// computes the same, also in fp32).
//
// One block of 256 threads per row (a grid-stride loop over rows when there are more rows than blocks). The
// row lives in shared memory as fp32, n floats of dynamic shared memory:
//   1. load: thread t reads elements t, t + 256, ... (coalesced, any alignment) and multiplies by signs;
//   2. butterfly: log2(p) stages; in stage h the n/2 pairs (j, j + h) of every p-block (blocks of 2h tile the
//      row, so one flat pair index covers all m blocks) are spread over the threads, a barrier between stages;
//   3. left factor: out[k p + l] = sum_i left[i, k] y[i p + l] / sqrt(p), one output element per thread at a
//      time; a warp reads consecutive l (no bank conflicts) and mostly one k (left's entries broadcast from
//      the read-only cache); rounded once to dtype.
// A barrier before the next row overwrites the buffer. Stages with h < 32 see two-way bank conflicts at
// most; the transform is a small part of down_proj's time (n log2 p + m n operations against n d).
#include "activation/hadamard_cuda.h"
#include "common/cuda_utils.cuh"

namespace dyq::cuda {
namespace {

constexpr int kThreads = 256;
constexpr int kMaxBlocks = 65535;
constexpr size_t kSharedBytesWithoutOptIn = 48 * 1024;

__global__ void __launch_bounds__(kThreads)
    hadamard_transform_kernel(const void* x, ScalarType dtype, const float* __restrict__ signs,
                              const float* __restrict__ left, int64_t rows, int m, int log2_p, float norm,
                              void* out) {
  extern __shared__ float row_values[];  // the current row, viewed as [m, p]
  const int p = 1 << log2_p;
  const int n = m * p;
  for (int64_t row = blockIdx.x; row < rows; row += gridDim.x) {
    for (int i = threadIdx.x; i < n; i += kThreads) {
      row_values[i] = load_as_float(x, row * n + i, dtype) * __ldg(signs + i);
    }
    __syncthreads();
    for (int log2_h = 0; log2_h < log2_p; ++log2_h) {
      const int h = 1 << log2_h;
      for (int pair = threadIdx.x; pair < n / 2; pair += kThreads) {
        const int low = ((pair >> log2_h) << (log2_h + 1)) | (pair & (h - 1));
        const float a = row_values[low], b = row_values[low + h];
        row_values[low] = a + b;
        row_values[low + h] = a - b;
      }
      __syncthreads();
    }
    for (int i = threadIdx.x; i < n; i += kThreads) {
      const int k = i >> log2_p, l = i & (p - 1);
      float sum = 0.0f;
      for (int j = 0; j < m; ++j) sum = fmaf(__ldg(left + j * m + k), row_values[j * p + l], sum);
      store_from_float(out, row * n + i, dtype, sum * norm);
    }
    __syncthreads();
  }
}

}  // namespace

cudaError_t hadamard_transform(const void* x, ScalarType dtype, const float* signs, const float* left, int64_t rows,
                               int64_t n, int64_t m, void* out, cudaStream_t stream) {
  if (rows == 0 || n == 0) return cudaSuccess;
  int log2_p = 0;
  while ((m << (log2_p + 1)) <= n) ++log2_p;
  const size_t shared_bytes = static_cast<size_t>(n) * sizeof(float);
  if (shared_bytes > kSharedBytesWithoutOptIn) {
    const cudaError_t err = cudaFuncSetAttribute(hadamard_transform_kernel, cudaFuncAttributeMaxDynamicSharedMemorySize,
                                                 static_cast<int>(shared_bytes));
    if (err != cudaSuccess) return err;
  }
  const unsigned blocks = static_cast<unsigned>(rows < kMaxBlocks ? rows : kMaxBlocks);
  const float norm = static_cast<float>(1.0 / sqrt(static_cast<double>(n / m)));
  hadamard_transform_kernel<<<blocks, kThreads, shared_bytes, stream>>>(x, dtype, signs, left, rows, static_cast<int>(m),
                                                                         log2_p, norm, out);
  return cudaGetLastError();
}

cudaError_t hadamard_max_columns(int device, int64_t* columns) {
  int bytes = 0;
  const cudaError_t err = cudaDeviceGetAttribute(&bytes, cudaDevAttrMaxSharedMemoryPerBlockOptin, device);
  *columns = err == cudaSuccess ? bytes / static_cast<int64_t>(sizeof(float)) : 0;
  return err;
}

}  // namespace dyq::cuda
