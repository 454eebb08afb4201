// The prefill path (m > 16 rows): quantize the activations once (prepare_activations), then a tiled
// tensor-core GEMM that reads the packed INT4 weights in their canonical layout.
//
// Why two kernels: quantizing inside the GEMM would repeat it in every block column (n / 128 times),
// and at prefill sizes that arithmetic (an IEEE division per element) would cost more than the MMAs.
// Quantized once, the codes are written packed (b bits per element) and re-read from L2.
//
// Block tile 64 x 128 outputs, 8 warps as 2 (m) x 4 (n), each warp 32 x 32 = 2 x 4 MMA tiles of 16 x 8.
// K advances in tiles of 128 columns (64 for bf16), double-buffered in shared memory with cp.async
// (rows padded by 16 bytes against bank conflicts; out-of-range bytes zero-filled).
//
// Per bit-width and architecture (one template; the MMA kind is the width's trait in common/precision.h
// for __CUDA_ARCH__, the width the one the prepare kernel read from the precision flag):
//   A8, and A2/A4 on sm_90 or with G = 32:  m16n8k32 u8.s8. INT4 weights widened to s8 in registers;
//        activation codes (unsigned) widened to u8.
//   A4, A2 on sm_80/sm_89 with G >= 64:    m16n8k64 u4.s4, native INT4 tensor cores. Weights used as
//        loaded; 2-bit codes spread to nibbles in registers.
//   A16:                                   m16n8k16 bf16, fp32 accumulate; weights to exact bf16 in
//        registers (magic-number trick), x as bf16.
// Integer paths keep an int32 accumulator per group (exact) and fold it into the fp32 output
// accumulator at each group end with s_x * s_w, subtracting z_x * sum_k q_w (the weight group sums
// come from the same B fragments: dp4a plus a quad reduction). See docs/numerics.md, section 3.
//
// Thread-to-column assignment (the k permutation of mma_cuda.cuh): in a k32 step starting at column c,
// thread t's chunk 0 is the even and chunk 1 the odd columns of c + 8t .. c + 8t + 7, which is exactly
// one 32-bit word of packed weights split by the nibble masks; in a k64 step chunk 0 is c + 16t .. +7
// and chunk 1 is c + 16t + 8 .. +15, one 64-bit word used as is. The bf16 path pairs columns (j, j+4)
// of c + 8t .. +7, matching the nibble masks 0x000F000F.
#include <cuda_bf16.h>

#include <type_traits>

#include "activation/act_quant_cuda.h"
#include "common/cuda_utils.cuh"
#include "common/precision.h"
#include "gemm/gemm_cuda.h"
#include "gemm/mma_cuda.cuh"

namespace dyq::cuda {
namespace {

constexpr int kBlockM = 64;
constexpr int kBlockN = 128;
constexpr int kWarpsN = 4;
constexpr int kThreads = 256;
constexpr int kWarpM = 32;
constexpr int kWarpN = 32;
constexpr int kMmaTilesM = kWarpM / 16;
constexpr int kMmaTilesN = kWarpN / 8;
constexpr int kSmemPad = 16;

template <int kBits, MmaKind kMma>
struct TileShape {
  static constexpr int kTileK = kBits == kFallbackBits ? 64 : 128;
  static constexpr int kStepK = kMma == MmaKind::kU4S4 ? 64 : 32;
  static constexpr int kARowBytes = kTileK * kBits / 8;
  static constexpr int kAPitch = kARowBytes + kSmemPad;
  static constexpr int kBRowBytes = kTileK / 2;
  static constexpr int kBPitch = kBRowBytes + kSmemPad;
  static constexpr int kStageBytes = kBlockM * kAPitch + kBlockN * kBPitch;
};

// Two stages of the largest tile (8-bit codes).
constexpr int kSmemBytes = 2 * TileShape<8, MmaKind::kU8S8>::kStageBytes;
static_assert(2 * TileShape<16, MmaKind::kBf16>::kStageBytes <= kSmemBytes, "bf16 tiles fit");

__device__ constexpr bool has_int4_tensor_cores() {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
  return false;
#else
  return true;
#endif
}

// Even and odd columns of 8 activation codes (unsigned b-bit) as u8x4 words.
template <int kBits>
__device__ __forceinline__ void codes8_even_odd(const uint8_t* p, uint32_t& even, uint32_t& odd) {
  if constexpr (kBits == 8) {
    const uint2 v = *reinterpret_cast<const uint2*>(p);
    even = __byte_perm(v.x, v.y, 0x6420);
    odd = __byte_perm(v.x, v.y, 0x7531);
  } else {
    const uint32_t nibbles = kBits == 4 ? *reinterpret_cast<const uint32_t*>(p)
                                        : spread_2bit_to_nibbles(*reinterpret_cast<const uint16_t*>(p));
    even = nibbles & 0x0F0F0F0Fu;
    odd = (nibbles >> 4) & 0x0F0F0F0Fu;
  }
}

// 16 activation codes as two u4x8 words (columns 0..7, 8..15).
template <int kBits>
__device__ __forceinline__ void codes16_nibbles(const uint8_t* p, uint32_t& low, uint32_t& high) {
  if constexpr (kBits == 4) {
    const uint2 v = *reinterpret_cast<const uint2*>(p);
    low = v.x;
    high = v.y;
  } else {
    const uint32_t v = *reinterpret_cast<const uint32_t*>(p);
    low = spread_2bit_to_nibbles(v & 0xFFFFu);
    high = spread_2bit_to_nibbles(v >> 16);
  }
}

// The pair of INT4 nibbles at bit offsets s and s + 16 of `offset_word` (= packed word ^ 0x88888888) as
// an exact bf16x2: 0x4300 | u is 128 + u, minus 136 gives u - 8 = q_w.
__device__ __forceinline__ uint32_t weight_pair_bf16x2(uint32_t offset_word, int shift) {
  const uint32_t biased = ((offset_word >> shift) & 0x000F000Fu) | 0x43004300u;
  const __nv_bfloat162 value =
      __hsub2(*reinterpret_cast<const __nv_bfloat162*>(&biased), __floats2bfloat162_rn(136.0f, 136.0f));
  return *reinterpret_cast<const uint32_t*>(&value);
}

// The fragments of one integer MMA kind (layouts in mma_cuda.cuh): which columns a thread's two
// k-chunks cover, how its A chunks come from b-bit codes and its B chunks from packed INT4 weights, and
// the instruction. Both kinds add the thread's weight codes to `weight_sum` for the zero-point term.
template <MmaKind kKind>
struct IntegerFragments;

// m16n8k32 u8.s8: thread t covers columns 8t .. 8t + 7 of the step, even ones in chunk 0, odd in chunk 1.
template <>
struct IntegerFragments<MmaKind::kU8S8> {
  static constexpr int kThreadColumns = 8;

  template <int kBits>
  __device__ __forceinline__ static void load_a(const uint8_t* codes, uint32_t& chunk0, uint32_t& chunk1) {
    codes8_even_odd<kBits>(codes, chunk0, chunk1);
  }

  __device__ __forceinline__ static void load_b(const uint8_t* weights, uint32_t& b0, uint32_t& b1, int& weight_sum) {
    const uint32_t word = *reinterpret_cast<const uint32_t*>(weights);
    b0 = weight_even_s8x4(word);
    b1 = weight_odd_s8x4(word);
    weight_sum = dp4a_sum_s8(b0, dp4a_sum_s8(b1, weight_sum));
  }

  __device__ __forceinline__ static void mma(int (&c)[4], const uint32_t (&a)[4], uint32_t b0, uint32_t b1) {
    mma_m16n8k32_u8s8(c, a, b0, b1);
  }
};

// m16n8k64 u4.s4: thread t covers columns 16t .. 16t + 15, the first 8 in chunk 0; weights used as loaded.
template <>
struct IntegerFragments<MmaKind::kU4S4> {
  static constexpr int kThreadColumns = 16;

  template <int kBits>
  __device__ __forceinline__ static void load_a(const uint8_t* codes, uint32_t& chunk0, uint32_t& chunk1) {
    codes16_nibbles<kBits>(codes, chunk0, chunk1);
  }

  __device__ __forceinline__ static void load_b(const uint8_t* weights, uint32_t& b0, uint32_t& b1, int& weight_sum) {
    const uint2 words = *reinterpret_cast<const uint2*>(weights);
    b0 = words.x;
    b1 = words.y;
    weight_sum = dp4a_sum_s8(weight_even_s8x4(words.x), dp4a_sum_s8(weight_odd_s8x4(words.x), weight_sum));
    weight_sum = dp4a_sum_s8(weight_even_s8x4(words.y), dp4a_sum_s8(weight_odd_s8x4(words.y), weight_sum));
  }

  __device__ __forceinline__ static void mma(int (&c)[4], const uint32_t (&a)[4], uint32_t b0, uint32_t b1) {
    mma_m16n8k64_u4s4(c, a, b0, b1);
  }
};

template <int kBits, MmaKind kMma>
__device__ void prefill_block(const GemmArgs& a, const PreparedActivations& prepared, uint8_t* smem) {
  using Shape = TileShape<kBits, kMma>;
  constexpr bool kInteger = kMma != MmaKind::kBf16;
  constexpr int kStepsPerTile = Shape::kTileK / Shape::kStepK;
  using GroupAcc = std::conditional_t<kInteger, int, float>;

  const int warp = threadIdx.x / 32, lane = threadIdx.x % 32;
  const int g = lane / 4, t = lane % 4;
  const int warp_row = (warp / kWarpsN) * kWarpM;
  const int warp_col = (warp % kWarpsN) * kWarpN;
  const int64_t m0 = static_cast<int64_t>(blockIdx.y) * kBlockM;
  const int64_t n0 = static_cast<int64_t>(blockIdx.x) * kBlockN;
  const int64_t k = a.k;
  const int group_size = a.group_size;
  const int group_shift = 31 - __clz(group_size);  // G is a power of two: no integer division
  const int64_t groups_per_row = (k + group_size - 1) >> group_shift;  // the last group may be partial

  const uint8_t* a_src = prepared.codes;
  int64_t a_pitch = prepared_row_bytes(k, kBits);
  if constexpr (kBits == kFallbackBits) {
    if (a.dtype == ScalarType::kBFloat16) a_src = static_cast<const uint8_t*>(a.x);
  }

  auto stage_a = [&](int stage) { return smem + stage * Shape::kStageBytes; };
  auto stage_b = [&](int stage) { return smem + stage * Shape::kStageBytes + kBlockM * Shape::kAPitch; };

  auto load_tile = [&](int stage, int64_t tile_k) {
    const int valid_cols = static_cast<int>(k - tile_k < Shape::kTileK ? k - tile_k : Shape::kTileK);
    constexpr int kAChunks = Shape::kARowBytes / 16;
    for (int c = threadIdx.x; c < kBlockM * kAChunks; c += kThreads) {
      const int row = c / kAChunks, offset = (c % kAChunks) * 16;
      const int64_t global_row = m0 + row;
      const int remaining = valid_cols * kBits / 8 - offset;
      const int bytes = global_row < a.m ? (remaining < 0 ? 0 : (remaining > 16 ? 16 : remaining)) : 0;
      const uint8_t* src = bytes > 0 ? a_src + global_row * a_pitch + tile_k * kBits / 8 + offset : a_src;
      cp_async_16(stage_a(stage) + row * Shape::kAPitch + offset, src, bytes);
    }
    constexpr int kBChunks = Shape::kBRowBytes / 16;
    for (int c = threadIdx.x; c < kBlockN * kBChunks; c += kThreads) {
      const int row = c / kBChunks, offset = (c % kBChunks) * 16;
      const int64_t global_row = n0 + row;
      const int remaining = valid_cols / 2 - offset;
      const int bytes = global_row < a.n ? (remaining < 0 ? 0 : (remaining > 16 ? 16 : remaining)) : 0;
      const uint8_t* src = bytes > 0 ? a.qweight + global_row * (k / 2) + tile_k / 2 + offset : a.qweight;
      cp_async_16(stage_b(stage) + row * Shape::kBPitch + offset, src, bytes);
    }
  };

  float acc[kMmaTilesM][kMmaTilesN][4] = {};
  GroupAcc group_acc[kMmaTilesM][kMmaTilesN][4] = {};
  int weight_sum[kMmaTilesN] = {};  // this thread's share of sum_k q_w of column g of each n-tile
  float act_scale[kMmaTilesM][2] = {};
  int act_zero[kMmaTilesM][2] = {};
  float w_scale[kMmaTilesN][2] = {};

  // Scales of one group, for this thread's rows (g, g + 8 of each m-tile) and columns (2t, 2t + 1).
  auto load_group_scales = [&](int64_t group) {
#pragma unroll
    for (int i = 0; i < kMmaTilesM; ++i) {
#pragma unroll
      for (int h = 0; h < 2; ++h) {
        const int64_t row = m0 + warp_row + i * 16 + g + 8 * h;
        if constexpr (kInteger) {
          act_scale[i][h] = row < a.m ? prepared.scales[row * groups_per_row + group] : 0.0f;
          act_zero[i][h] = row < a.m ? prepared.zeros[row * groups_per_row + group] : 0;
        }
      }
    }
#pragma unroll
    for (int j = 0; j < kMmaTilesN; ++j) {
#pragma unroll
      for (int c = 0; c < 2; ++c) {
        const int64_t col = n0 + warp_col + j * 8 + 2 * t + c;
        w_scale[j][c] = col < a.n ? __ldg(a.scales + col * groups_per_row + group) : 0.0f;
      }
    }
  };

  auto flush_group = [&]() {
    if constexpr (kInteger) {
      int column_sum[kMmaTilesN][2];
#pragma unroll
      for (int j = 0; j < kMmaTilesN; ++j) {
        int s = weight_sum[j];
        s += __shfl_xor_sync(0xFFFFFFFFu, s, 1);
        s += __shfl_xor_sync(0xFFFFFFFFu, s, 2);  // every lane of quad g: sum of column g
        column_sum[j][0] = __shfl_sync(0xFFFFFFFFu, s, 4 * (2 * t));
        column_sum[j][1] = __shfl_sync(0xFFFFFFFFu, s, 4 * (2 * t + 1));
        weight_sum[j] = 0;
      }
#pragma unroll
      for (int i = 0; i < kMmaTilesM; ++i) {
#pragma unroll
        for (int j = 0; j < kMmaTilesN; ++j) {
#pragma unroll
          for (int e = 0; e < 4; ++e) {
            // |sum q_x q_w| and |z sum q_w| are each <= 255 * 8 * 128: the difference is exact in fp32.
            const int centered = group_acc[i][j][e] - act_zero[i][e >> 1] * column_sum[j][e & 1];
            acc[i][j][e] = fmaf(act_scale[i][e >> 1] * w_scale[j][e & 1], small_int_as_float(centered), acc[i][j][e]);
            group_acc[i][j][e] = 0;
          }
        }
      }
    } else {
#pragma unroll
      for (int i = 0; i < kMmaTilesM; ++i) {
#pragma unroll
        for (int j = 0; j < kMmaTilesN; ++j) {
#pragma unroll
          for (int e = 0; e < 4; ++e) {
            acc[i][j][e] = fmaf(w_scale[j][e & 1], group_acc[i][j][e], acc[i][j][e]);
            group_acc[i][j][e] = 0.0f;
          }
        }
      }
    }
  };

  // One k step (32 or 64 columns) at column `col` of the tile in `stage`.
  auto mma_step = [&](int stage, int col) {
    const uint8_t* tile_a = stage_a(stage);
    const uint8_t* tile_b = stage_b(stage);
    if constexpr (kInteger) {
      using Fragments = IntegerFragments<kMma>;
      const int thread_col = col + Fragments::kThreadColumns * t;
      uint32_t frag_a[kMmaTilesM][4];
#pragma unroll
      for (int i = 0; i < kMmaTilesM; ++i) {
#pragma unroll
        for (int h = 0; h < 2; ++h) {
          const int row = warp_row + i * 16 + g + 8 * h;
          Fragments::template load_a<kBits>(tile_a + row * Shape::kAPitch + thread_col * kBits / 8, frag_a[i][h],
                                            frag_a[i][2 + h]);
        }
      }
#pragma unroll
      for (int j = 0; j < kMmaTilesN; ++j) {
        const int n = warp_col + j * 8 + g;
        uint32_t b0, b1;
        Fragments::load_b(tile_b + n * Shape::kBPitch + thread_col / 2, b0, b1, weight_sum[j]);
#pragma unroll
        for (int i = 0; i < kMmaTilesM; ++i) Fragments::mma(group_acc[i][j], frag_a[i], b0, b1);
      }
    } else {
      // Two k16 MMAs over columns col + 8t .. +7: step 0 pairs (0,4) and (1,5), step 1 (2,6) and (3,7).
      uint32_t frag_a[2][kMmaTilesM][4];
#pragma unroll
      for (int i = 0; i < kMmaTilesM; ++i) {
#pragma unroll
        for (int h = 0; h < 2; ++h) {
          const int row = warp_row + i * 16 + g + 8 * h;
          const uint4 x8 = *reinterpret_cast<const uint4*>(tile_a + row * Shape::kAPitch + (col + 8 * t) * 2);
          frag_a[0][i][h] = __byte_perm(x8.x, x8.z, 0x5410);
          frag_a[0][i][2 + h] = __byte_perm(x8.x, x8.z, 0x7632);
          frag_a[1][i][h] = __byte_perm(x8.y, x8.w, 0x5410);
          frag_a[1][i][2 + h] = __byte_perm(x8.y, x8.w, 0x7632);
        }
      }
#pragma unroll
      for (int j = 0; j < kMmaTilesN; ++j) {
        const int n = warp_col + j * 8 + g;
        const uint32_t offset_word =
            *reinterpret_cast<const uint32_t*>(tile_b + n * Shape::kBPitch + (col + 8 * t) / 2) ^ 0x88888888u;
        const uint32_t pair04 = weight_pair_bf16x2(offset_word, 0), pair15 = weight_pair_bf16x2(offset_word, 4);
        const uint32_t pair26 = weight_pair_bf16x2(offset_word, 8), pair37 = weight_pair_bf16x2(offset_word, 12);
#pragma unroll
        for (int i = 0; i < kMmaTilesM; ++i) {
          mma_m16n8k16_bf16(group_acc[i][j], frag_a[0][i], pair04, pair15);
          mma_m16n8k16_bf16(group_acc[i][j], frag_a[1][i], pair26, pair37);
        }
      }
    }
  };

  const int64_t num_tiles = (k + Shape::kTileK - 1) / Shape::kTileK;
  if (num_tiles > 0) load_tile(0, 0);
  cp_async_commit();
  for (int64_t tile = 0; tile < num_tiles; ++tile) {
    const int64_t tile_k = tile * Shape::kTileK;
    if (tile + 1 < num_tiles) load_tile((tile + 1) % 2, tile_k + Shape::kTileK);
    cp_async_commit();
    cp_async_wait<1>();  // every group but the one just committed has landed: this tile is in place
    __syncthreads();
    const int stage = static_cast<int>(tile % 2);
    // Valid columns are a multiple of the step (k % 32 == 0, and k % 64 == 0 for k64 steps) and G of the
    // step: a step never crosses a group or the end of K. The last group ends at K, maybe short of G.
    const int valid_steps = static_cast<int>((k - tile_k < Shape::kTileK ? k - tile_k : Shape::kTileK) / Shape::kStepK);
#pragma unroll
    for (int step = 0; step < kStepsPerTile; ++step) {
      if (step < valid_steps) {
        const int64_t step_k = tile_k + step * Shape::kStepK;
        if ((step_k & (group_size - 1)) == 0) load_group_scales(step_k >> group_shift);
        mma_step(stage, step * Shape::kStepK);
        if (((step_k + Shape::kStepK) & (group_size - 1)) == 0 || step_k + Shape::kStepK == k) flush_group();
      }
    }
    __syncthreads();  // the next iteration's copy overwrites this stage
  }

#pragma unroll
  for (int i = 0; i < kMmaTilesM; ++i) {
#pragma unroll
    for (int j = 0; j < kMmaTilesN; ++j) {
#pragma unroll
      for (int e = 0; e < 4; ++e) {
        const int64_t row = m0 + warp_row + i * 16 + g + 8 * (e >> 1);
        const int64_t col = n0 + warp_col + j * 8 + 2 * t + (e & 1);
        if (row < a.m && col < a.n) {
          const float bias = a.bias != nullptr ? load_as_float(a.bias, col, a.dtype) : 0.0f;
          store_from_float(a.out, row * a.n + col, a.dtype, acc[i][j][e] + bias);
        }
      }
    }
  }
}

// The MMA kind of a width on the architecture being compiled (common/precision.h).
template <int kBits>
__device__ void prefill_block_for_width(const GemmArgs& a, const PreparedActivations& prepared, uint8_t* smem) {
  using Traits = ActivationTraits<kBits>;
  constexpr MmaKind kMma = has_int4_tensor_cores() ? Traits::kMmaWithInt4Cores : Traits::kMmaWithoutInt4Cores;
  if constexpr (kMma == MmaKind::kU4S4) {
    // A k64 step must stay inside one group and inside K.
    if (a.group_size >= 64 && a.k % 64 == 0) {
      prefill_block<kBits, MmaKind::kU4S4>(a, prepared, smem);
      return;
    }
    prefill_block<kBits, MmaKind::kU8S8>(a, prepared, smem);
  } else {
    prefill_block<kBits, kMma>(a, prepared, smem);
  }
}

__device__ void fill_block_with_nan(const GemmArgs& a) {
  for (int idx = threadIdx.x; idx < kBlockM * kBlockN; idx += kThreads) {
    const int64_t row = static_cast<int64_t>(blockIdx.y) * kBlockM + idx / kBlockN;
    const int64_t col = static_cast<int64_t>(blockIdx.x) * kBlockN + idx % kBlockN;
    if (row < a.m && col < a.n) store_from_float(a.out, row * a.n + col, a.dtype, NAN);
  }
}

// The bit-width comes from the prepare kernel that ran just before on the same stream, so both kernels
// of one GEMM use the same value even if the flag were rewritten in between.
__global__ void __launch_bounds__(kThreads) gemm_prefill_kernel(const GemmArgs a, const PreparedActivations prepared) {
  __shared__ __align__(16) uint8_t smem[kSmemBytes];
  dispatch_act_bits(
      *prepared.bits_used, [&](auto bits) { prefill_block_for_width<decltype(bits)::value>(a, prepared, smem); },
      [&] { fill_block_with_nan(a); });
}

constexpr int64_t kWorkspaceAlign = 256;

int64_t align_up(int64_t bytes) { return (bytes + kWorkspaceAlign - 1) / kWorkspaceAlign * kWorkspaceAlign; }

// Workspace: [bits_used | codes (m rows of up to 2k bytes) | scales | zeros], each 256-byte aligned.
PreparedActivations workspace_layout(void* workspace, int64_t m, int64_t k, int group_size, int64_t* total_bytes) {
  const int64_t code_bytes = align_up(m * prepared_row_bytes(k, kFallbackBits));
  const int64_t scale_bytes = align_up(m * group_count(k, group_size) * 4);
  const int64_t zero_bytes = align_up(m * group_count(k, group_size));
  uint8_t* base = static_cast<uint8_t*>(workspace);
  if (total_bytes != nullptr) *total_bytes = kWorkspaceAlign + code_bytes + scale_bytes + zero_bytes;
  return PreparedActivations{reinterpret_cast<int32_t*>(base), base + kWorkspaceAlign,
                             reinterpret_cast<float*>(base + kWorkspaceAlign + code_bytes),
                             base + kWorkspaceAlign + code_bytes + scale_bytes};
}

}  // namespace

int64_t gemm_workspace_bytes(int64_t m, int64_t k, int group_size, bool flag_routed) {
  if (m <= kDecodeMaxRows) return flag_routed ? kWorkspaceAlign : 0;
  int64_t total = 0;
  workspace_layout(nullptr, m, k, group_size, &total);
  return total;
}

cudaError_t gemm_prefill(const GemmArgs& a, cudaStream_t stream) {
  if (a.m == 0 || a.n == 0) return cudaSuccess;
  const int64_t blocks_m = (a.m + kBlockM - 1) / kBlockM;
  if (blocks_m > 65535) return cudaErrorInvalidValue;
  const PreparedActivations prepared = workspace_layout(a.workspace, a.m, a.k, a.group_size, nullptr);
  // A flag is read once, into bits_used, which the prepare kernel's blocks then read from device memory.
  const Precision precision = a.precision.flag != nullptr
                                  ? snapshot_precision(a.precision, prepared.bits_used, stream)
                                  : a.precision;
  const cudaError_t err = prepare_activations(a.x, a.dtype, a.m, a.k, a.group_size, precision, prepared, stream);
  if (err != cudaSuccess) return err;
  const dim3 grid(static_cast<unsigned>((a.n + kBlockN - 1) / kBlockN), static_cast<unsigned>(blocks_m));
  gemm_prefill_kernel<<<grid, kThreads, 0, stream>>>(a, prepared);
  return cudaGetLastError();
}

}  // namespace dyq::cuda
