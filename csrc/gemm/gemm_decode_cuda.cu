// The decode path (m <= kDecodeMaxRows = 8 rows): a GEMV that streams the packed INT4 weights once, at
// memory speed, with the activation quantization fused in.
//
// Thread mapping. A block of 4 warps owns 16 consecutive weight rows (outputs n), 4 per warp. A lane
// reads 32 consecutive columns of a row with one 16-byte load of the canonical packed layout
// (docs/numerics.md, section 1); a warp covers 1024 columns of a row per load, fully coalesced. The 32
// columns of a lane lie in one group (G >= 32 and aligned), so the lane forms that group's partial sum
// and scales it by itself; the lanes' contributions meet in one warp reduction at the end.
//
// K is walked in chunks. Per chunk: (1) issue the chunk's weight loads, (2) stage x's chunk in shared
// memory (quantized to u8 codes for 2, 4 and 8 bits; rounded to bf16 for 16), (3) consume the weights.
// The weight loads of step 1 are in flight while step 2 runs, and for the first chunk also while
// thread 0 reads the precision flag (a PCIe round trip when it lives in pinned host memory).
//
// Integer paths (A2, A4, A8): an INT4 word (8 columns) splits into s8x4 words of its even and odd
// columns; x's codes are staged as unsigned bytes in the same even/odd order; `dp4a.u32.s32` forms
// sum q_x q_w exactly and the zero point comes off as z * sum q_w (docs/numerics.md, section 3). The
// bit-width changes only the quantizer: at m <= 8 the weights are the bytes that matter.
// BF16 path (A16): each nibble becomes an exact fp32 from its bit pattern; fp32 FMAs against x rounded
// to bf16 (the rounding the prefill path's bf16 tensor cores impose, so both paths agree).
#include "activation/act_quant_cuda.cuh"
#include "common/precision.h"
#include "gemm/gemm_cuda.h"

namespace dyq::cuda {
namespace {

constexpr int kWarps = 4;
constexpr int kThreads = kWarps * 32;
constexpr int kRowsPerWarp = 4;
constexpr int kRowsPerBlock = kWarps * kRowsPerWarp;
constexpr int kColsPerLane = 32;                   // one 16-byte load of packed INT4
constexpr int kColsPerWarpLoad = 32 * kColsPerLane;
constexpr int kStagingBatch = 4;                   // x runs loaded before any is quantized

// Columns of x staged per chunk. Fewer activation rows allow longer chunks, so that each lane has more
// weight loads in flight; the staging buffer stays at most 32 KiB.
template <int kRows>
constexpr int chunk_cols() {
  return kRows <= 2 ? 4096 : (kRows <= 4 ? 2048 : 1024);
}

// bf16 staging is the larger of the two uses of the buffer (codes: 1 byte per element + 8 bytes per group).
template <int kRows>
constexpr int staging_bytes() {
  return kRows * chunk_cols<kRows>() * 2;
}

template <int kRows>
__global__ void __launch_bounds__(kThreads) gemm_decode_kernel(const GemmArgs a) {
  constexpr int kChunk = chunk_cols<kRows>();
  constexpr int kLoads = kChunk / kColsPerWarpLoad;  // 16-byte weight loads per lane per row per chunk
  constexpr int kMaxGroups = kChunk / 32;
  constexpr int kRunsPerRow = kChunk / 8;
  constexpr int kStagingIters = kRows * kRunsPerRow / kThreads;
  static_assert(kStagingIters % kStagingBatch == 0, "staging loop is batched");

  extern __shared__ uint4 staging[];
  __shared__ int bits_shared;
  uint8_t* const codes = reinterpret_cast<uint8_t*>(staging);                         // [kRows][kChunk]
  float* const group_scale = reinterpret_cast<float*>(codes + kRows * kChunk);        // [kRows][kMaxGroups]
  int* const group_zero = reinterpret_cast<int*>(group_scale + kRows * kMaxGroups);  // [kRows][kMaxGroups]
  uint8_t* const x_bf16 = reinterpret_cast<uint8_t*>(staging);                        // [kRows][kChunk] bf16

  const int warp = threadIdx.x / 32;
  const int lane = threadIdx.x % 32;
  const int64_t k = a.k;
  const int group_size = a.group_size;
  const int group_shift = 31 - __clz(group_size);  // G is a power of two: no integer division
  const int group_lanes = group_size / 8;
  const int64_t groups_per_row = (k + group_size - 1) >> group_shift;  // the last group may be partial
  const int64_t first_row = static_cast<int64_t>(blockIdx.x) * kRowsPerBlock + warp * kRowsPerWarp;
  const int64_t element_bytes = a.dtype == ScalarType::kFloat32 ? 4 : 2;

  uint4 w[kRowsPerWarp][kLoads];
  float w_scale[kRowsPerWarp][kLoads];
  auto load_weights = [&](int64_t chunk_start) {
#pragma unroll
    for (int r = 0; r < kRowsPerWarp; ++r) {
#pragma unroll
      for (int l = 0; l < kLoads; ++l) {
        const int64_t row = first_row + r;
        const int64_t col = chunk_start + l * kColsPerWarpLoad + lane * kColsPerLane;
        if (row < a.n && col < k) {
          w[r][l] = __ldg(reinterpret_cast<const uint4*>(a.qweight + row * (k / 2) + col / 2));
          w_scale[r][l] = __ldg(a.scales + row * groups_per_row + (col >> group_shift));
        } else {
          w[r][l] = make_uint4(0, 0, 0, 0);
          w_scale[r][l] = 0.0f;
        }
      }
    }
  };

  if (k > 0) load_weights(0);
  if (threadIdx.x == 0) bits_shared = read_precision(a.precision);
  __syncthreads();
  const int act_bits = bits_shared;
  if (!is_valid_act_bits(act_bits)) {
    for (int r = 0; r < kRowsPerWarp; ++r) {
      const int64_t row = first_row + r;
      if (row >= a.n) break;
      for (int64_t m = lane; m < a.m; m += 32) store_from_float(a.out, m * a.n + row, a.dtype, NAN);
    }
    return;
  }
  const bool fallback = act_bits == kFallbackBits;

  float acc[kRowsPerWarp][kRows] = {};
  for (int64_t chunk_start = 0; chunk_start < k; chunk_start += kChunk) {
    // A multiple of 32; chunks start at group boundaries, so only the last group of a row can be partial,
    // and its columns past k stage as zeros (which change neither its range nor its sums).
    const int chunk_valid = static_cast<int>(k - chunk_start < kChunk ? k - chunk_start : kChunk);
    if (chunk_start > 0) load_weights(chunk_start);

    // Stage x[0:kRows, chunk]. A warp's 32 runs lie in one row, and a group is G/8 aligned lanes.
    for (int batch = 0; batch < kStagingIters; batch += kStagingBatch) {
      float v[kStagingBatch][8];
#pragma unroll
      for (int b = 0; b < kStagingBatch; ++b) {
        const int run = (batch + b) * kThreads + threadIdx.x;
        const int row = run / kRunsPerRow;
        const int col = (run % kRunsPerRow) * 8;
#pragma unroll
        for (int i = 0; i < 8; ++i) v[b][i] = 0.0f;
        if (row < a.m && col < chunk_valid) {
          load8_as_float(static_cast<const char*>(a.x) + (row * k + chunk_start + col) * element_bytes, a.dtype,
                         v[b]);
        }
      }
#pragma unroll
      for (int b = 0; b < kStagingBatch; ++b) {
        const int run = (batch + b) * kThreads + threadIdx.x;
        const int row = run / kRunsPerRow;
        const int col = (run % kRunsPerRow) * 8;
        if (fallback) {
          // Rows and columns outside x stage as zeros (v stayed 0).
          *reinterpret_cast<uint4*>(x_bf16 + (row * kChunk + col) * 2) =
              make_uint4(pack_bf16x2(v[b][0], v[b][1]), pack_bf16x2(v[b][2], v[b][3]),
                         pack_bf16x2(v[b][4], v[b][5]), pack_bf16x2(v[b][6], v[b][7]));
        } else {
          // Outside x the values are 0: scale 1, zero point 0, codes 0, so they add nothing.
          const ActivationGroupParams params = group_params_across_lanes(v[b], true, group_lanes, act_bits);
          uint32_t c[8];
          activation_codes8(v[b], params, act_bits, c);
          *reinterpret_cast<uint2*>(codes + row * kChunk + col) = deinterleaved_code_bytes8(c);
          if ((lane & (group_lanes - 1)) == 0) {
            group_scale[row * kMaxGroups + (col >> group_shift)] = params.scale;
            group_zero[row * kMaxGroups + (col >> group_shift)] = params.zero;
          }
        }
      }
    }
    __syncthreads();

#pragma unroll
    for (int r = 0; r < kRowsPerWarp; ++r) {
#pragma unroll
      for (int l = 0; l < kLoads; ++l) {
        const int col = l * kColsPerWarpLoad + lane * kColsPerLane;  // within the chunk
        if (first_row + r >= a.n || col >= chunk_valid) continue;
        const uint32_t words[4] = {w[r][l].x, w[r][l].y, w[r][l].z, w[r][l].w};
        if (fallback) {
          float partial[kRows] = {};
#pragma unroll
          for (int word = 0; word < 4; ++word) {
            float q[8];
#pragma unroll
            for (int i = 0; i < 8; ++i) q[i] = weight_nibble_as_float(words[word] >> (4 * i));
#pragma unroll
            for (int m = 0; m < kRows; ++m) {
              const uint4 xv = *reinterpret_cast<const uint4*>(x_bf16 + (m * kChunk + col + 8 * word) * 2);
              const uint32_t pairs[4] = {xv.x, xv.y, xv.z, xv.w};
#pragma unroll
              for (int p = 0; p < 4; ++p) {
                partial[m] = fmaf(bf16_low_as_float(pairs[p]), q[2 * p], partial[m]);
                partial[m] = fmaf(bf16_high_as_float(pairs[p]), q[2 * p + 1], partial[m]);
              }
            }
          }
#pragma unroll
          for (int m = 0; m < kRows; ++m) acc[r][m] = fmaf(w_scale[r][l], partial[m], acc[r][m]);
        } else {
          int weight_sum = 0;
          int dot[kRows] = {};
#pragma unroll
          for (int half = 0; half < 2; ++half) {
            const uint32_t even0 = weight_even_s8x4(words[2 * half]), odd0 = weight_odd_s8x4(words[2 * half]);
            const uint32_t even1 = weight_even_s8x4(words[2 * half + 1]);
            const uint32_t odd1 = weight_odd_s8x4(words[2 * half + 1]);
            weight_sum = dp4a_sum_s8(even0, dp4a_sum_s8(odd0, dp4a_sum_s8(even1, dp4a_sum_s8(odd1, weight_sum))));
#pragma unroll
            for (int m = 0; m < kRows; ++m) {
              // Two runs of 8 codes: (even, odd) bytes of columns col + 16 half + 0..7, then + 8..15.
              const uint4 cv = *reinterpret_cast<const uint4*>(codes + m * kChunk + col + 16 * half);
              dot[m] = dp4a_u8_s8(cv.x, even0, dot[m]);
              dot[m] = dp4a_u8_s8(cv.y, odd0, dot[m]);
              dot[m] = dp4a_u8_s8(cv.z, even1, dot[m]);
              dot[m] = dp4a_u8_s8(cv.w, odd1, dot[m]);
            }
          }
          const int group = col >> group_shift;
#pragma unroll
          for (int m = 0; m < kRows; ++m) {
            // |dot - z * sum q_w| <= 32 * 255 * 8 * 2 < 2^22: exact in fp32.
            const int centered = dot[m] - group_zero[m * kMaxGroups + group] * weight_sum;
            acc[r][m] = fmaf(group_scale[m * kMaxGroups + group] * w_scale[r][l], small_int_as_float(centered),
                             acc[r][m]);
          }
        }
      }
    }
    __syncthreads();  // the next chunk overwrites the staging buffer
  }

#pragma unroll
  for (int r = 0; r < kRowsPerWarp; ++r) {
    const int64_t row = first_row + r;
    const float bias = (a.bias != nullptr && row < a.n) ? load_as_float(a.bias, row, a.dtype) : 0.0f;
#pragma unroll
    for (int m = 0; m < kRows; ++m) {
      const float total = warp_sum(acc[r][m]);
      if (lane == 0 && row < a.n && m < a.m) store_from_float(a.out, m * a.n + row, a.dtype, total + bias);
    }
  }
}

template <int kRows>
cudaError_t launch_decode(const GemmArgs& a, cudaStream_t stream) {
  const int64_t blocks = (a.n + kRowsPerBlock - 1) / kRowsPerBlock;
  gemm_decode_kernel<kRows><<<static_cast<unsigned>(blocks), kThreads, staging_bytes<kRows>(), stream>>>(a);
  return cudaGetLastError();
}

}  // namespace

cudaError_t gemm_decode(const GemmArgs& args, cudaStream_t stream) {
  if (args.m == 0 || args.n == 0) return cudaSuccess;
  if (args.m > kDecodeMaxRows) return cudaErrorInvalidValue;  // more rows take the prefill path
  GemmArgs a = args;
  if (a.precision.flag != nullptr) {
    if (a.workspace == nullptr) return cudaErrorInvalidValue;  // gemm_workspace_bytes(..., true) bytes
    a.precision = snapshot_precision(a.precision, static_cast<int32_t*>(a.workspace), stream);
  }
  if (a.m == 1) return launch_decode<1>(a, stream);
  if (a.m <= 2) return launch_decode<2>(a, stream);
  if (a.m <= 4) return launch_decode<4>(a, stream);
  static_assert(kDecodeMaxRows == 8, "one instantiation per row count up to kDecodeMaxRows");
  return launch_decode<8>(a, stream);
}

}  // namespace dyq::cuda
