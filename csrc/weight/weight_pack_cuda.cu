// One thread per (row, group) for quantization, one per packed byte for dequantization: these are
// offline conversions, written for clarity. The last group of a row holds the remainder when the group
// size does not divide k.
#include "common/cuda_utils.cuh"
#include "weight/weight_pack_cuda.h"

namespace dyq::cuda {
namespace {

constexpr int kThreads = 256;

__global__ void __launch_bounds__(kThreads)
    quantize_weight_kernel(const float* weight, int64_t n, int64_t k, int group_size, uint8_t* qweight,
                           float* scales, int32_t* nonfinite) {
  const int64_t groups_per_row = group_count(k, group_size);
  const int64_t group = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (group >= n * groups_per_row) return;
  const int64_t row = group / groups_per_row, g = group % groups_per_row;
  const int64_t columns = group_columns(k, group_size, g);
  const float* w = weight + row * k + g * group_size;
  float absmax = 0.0f;
  bool finite = true;
  for (int64_t i = 0; i < columns; ++i) {
    finite = finite && isfinite(w[i]);
    absmax = fmaxf(absmax, fabsf(w[i]));
  }
  if (!finite) atomicExch(nonfinite, 1);
  float scale = weight_scale_from_absmax(absmax);
  const bool empty = scale == 0.0f;
  if (empty) scale = 1.0f;
  uint8_t* out = qweight + (row * k + g * group_size) / 2;
  for (int64_t i = 0; i < columns; i += 2) {
    const int even = empty ? 0 : weight_code(w[i], scale);
    const int odd = empty ? 0 : weight_code(w[i + 1], scale);
    out[i / 2] = pack_weight_pair(even, odd);
  }
  scales[group] = scale;
}

__global__ void __launch_bounds__(kThreads)
    dequantize_weight_kernel(const uint8_t* qweight, const float* scales, int64_t n, int64_t k, int group_size,
                             float* out) {
  const int64_t byte = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (byte >= n * k / 2) return;
  const int64_t row = byte / (k / 2);
  const int64_t col = (byte % (k / 2)) * 2;
  const float scale = scales[row * group_count(k, group_size) + col / group_size];
  const uint32_t packed = qweight[byte];
  out[row * k + col] = scale * static_cast<float>(sign_extend_nibble(packed & 0xFu));
  out[row * k + col + 1] = scale * static_cast<float>(sign_extend_nibble(packed >> 4));
}

unsigned blocks_for(int64_t items) { return static_cast<unsigned>((items + kThreads - 1) / kThreads); }

}  // namespace

cudaError_t quantize_weight(const float* weight, int64_t n, int64_t k, int group_size, uint8_t* qweight,
                            float* scales, int32_t* nonfinite, cudaStream_t stream) {
  const int64_t groups = n * group_count(k, group_size);
  if (groups == 0) return cudaSuccess;
  quantize_weight_kernel<<<blocks_for(groups), kThreads, 0, stream>>>(weight, n, k, group_size, qweight, scales,
                                                                      nonfinite);
  return cudaGetLastError();
}

cudaError_t dequantize_weight(const uint8_t* qweight, const float* scales, int64_t n, int64_t k, int group_size,
                              float* out, cudaStream_t stream) {
  const int64_t bytes = n * k / 2;
  if (bytes == 0) return cudaSuccess;
  dequantize_weight_kernel<<<blocks_for(bytes), kThreads, 0, stream>>>(qweight, scales, n, k, group_size, out);
  return cudaGetLastError();
}

}  // namespace dyq::cuda
