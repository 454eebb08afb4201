// Activation quantization kernels (docs/numerics.md, section 2). One thread quantizes a run of 8
// consecutive elements: 16-byte loads of x, group statistics by xor-shuffles among the G/8 lanes of the
// group, codes written packed once (8, 4 or 2 bytes per thread).
#include "activation/act_quant_cuda.cuh"
#include "activation/act_quant_cuda.h"
#include "common/precision.h"

namespace dyq::cuda {
namespace {

constexpr int kThreads = 256;

struct CodeTarget {
  uint8_t* codes;
  int64_t row_bytes;
  float* scales;
  uint8_t* zeros;
};

__device__ __forceinline__ const void* run_address(const void* x, ScalarType dtype, int64_t element) {
  const int64_t element_bytes = dtype == ScalarType::kFloat32 ? 4 : 2;
  return static_cast<const char*>(x) + element * element_bytes;
}

// Grid-stride over runs, a whole warp at a time so that the shuffles of a group see all its lanes. Rows
// are walked in whole groups: when the group size does not divide k, the runs past k of the last group are
// inactive (their values 0, which change no group's range) and store nothing.
__device__ void quantize_rows(const void* x, ScalarType dtype, int64_t m, int64_t k, int group_size, int act_bits,
                              CodeTarget target) {
  const int64_t groups = group_count(k, group_size);
  const int64_t runs_per_row = groups * group_size / 8;
  const int64_t total_runs = m * runs_per_row;
  const int lane = threadIdx.x % 32;
  const int lanes_per_group = group_size / 8;
  const int64_t stride = static_cast<int64_t>(gridDim.x) * blockDim.x;
  for (int64_t warp_first = static_cast<int64_t>(blockIdx.x) * blockDim.x + (threadIdx.x & ~31);
       warp_first < total_runs; warp_first += stride) {
    const int64_t run = warp_first + lane;
    const bool in_rows = run < total_runs;
    const int64_t row = in_rows ? run / runs_per_row : 0;
    const int64_t col = in_rows ? (run % runs_per_row) * 8 : 0;
    const bool active = in_rows && col < k;
    float v[8] = {};
    if (active) load8_as_float(run_address(x, dtype, row * k + col), dtype, v);
    const ActivationGroupParams params = group_params_across_lanes(v, active, lanes_per_group, act_bits);
    if (!active) continue;  // the loop bound is the same for the whole warp: every lane meets every shuffle
    uint32_t codes[8];
    activation_codes8(v, params, act_bits, codes);
    store_packed_codes8(codes, act_bits, target.codes + row * target.row_bytes + col * act_bits / 8);
    if (lane % lanes_per_group == 0) {
      const int64_t group = row * groups + col / group_size;
      target.scales[group] = params.scale;
      target.zeros[group] = static_cast<uint8_t>(params.zero);
    }
  }
}

// The BF16 fallback's operand: x rounded to bf16, rows of 2k bytes.
__device__ void convert_rows_to_bf16(const void* x, ScalarType dtype, int64_t m, int64_t k, uint8_t* out) {
  const int64_t total_runs = m * (k / 8);
  const int64_t stride = static_cast<int64_t>(gridDim.x) * blockDim.x;
  for (int64_t run = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x; run < total_runs; run += stride) {
    float v[8];
    load8_as_float(run_address(x, dtype, run * 8), dtype, v);
    reinterpret_cast<uint4*>(out)[run] =
        make_uint4(pack_bf16x2(v[0], v[1]), pack_bf16x2(v[2], v[3]), pack_bf16x2(v[4], v[5]), pack_bf16x2(v[6], v[7]));
  }
}

__global__ void __launch_bounds__(kThreads)
    quantize_activations_kernel(const void* x, ScalarType dtype, int64_t m, int64_t k, int group_size, int act_bits,
                                CodeTarget target) {
  quantize_rows(x, dtype, m, k, group_size, act_bits, target);
}

__global__ void __launch_bounds__(kThreads)
    prepare_activations_kernel(const void* x, ScalarType dtype, int64_t m, int64_t k, int group_size,
                               Precision precision, PreparedActivations out) {
  __shared__ int bits_shared;
  if (threadIdx.x == 0) {
    bits_shared = read_precision(precision);
    if (blockIdx.x == 0 && precision.flag != out.bits_used) *out.bits_used = bits_shared;
  }
  __syncthreads();
  dispatch_act_bits(
      bits_shared,
      [&](auto bits) {
        constexpr int kBits = decltype(bits)::value;
        if constexpr (ActivationTraits<kBits>::kQuantized) {
          quantize_rows(x, dtype, m, k, group_size, kBits,
                        CodeTarget{out.codes, prepared_row_bytes(k, kBits), out.scales, out.zeros});
        } else if (dtype != ScalarType::kBFloat16) {
          convert_rows_to_bf16(x, dtype, m, k, out.codes);
        }
      },
      [] {});  // any other value: nothing to prepare; the GEMM reads bits_used and writes NaN
}

// Grid-stride loops: any grid is correct; this one gives every run of whole groups a thread.
unsigned grid_for_runs(int64_t m, int64_t k) {
  const int64_t blocks = (m * ((k + 127) / 128 * 16) + kThreads - 1) / kThreads;
  return static_cast<unsigned>(blocks < 1 ? 1 : (blocks > 65535 ? 65535 : blocks));
}

}  // namespace

cudaError_t quantize_activations(const void* x, ScalarType dtype, int64_t m, int64_t k, int group_size, int act_bits,
                                 uint8_t* packed, float* scales, uint8_t* zeros, cudaStream_t stream) {
  if (m == 0 || k == 0) return cudaSuccess;
  quantize_activations_kernel<<<grid_for_runs(m, k), kThreads, 0, stream>>>(
      x, dtype, m, k, group_size, act_bits, CodeTarget{packed, k * act_bits / 8, scales, zeros});
  return cudaGetLastError();
}

cudaError_t prepare_activations(const void* x, ScalarType dtype, int64_t m, int64_t k, int group_size,
                                Precision precision, PreparedActivations out, cudaStream_t stream) {
  prepare_activations_kernel<<<grid_for_runs(m, k), kThreads, 0, stream>>>(x, dtype, m, k, group_size, precision,
                                                                           out);
  return cudaGetLastError();
}

}  // namespace dyq::cuda
