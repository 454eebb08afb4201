// The AVX-512 (VNNI) GEMM behind dyq::cpu::gemm on CPUs that have it (docs/numerics.md, section 3).
//
// Both kernels stream each packed weight row once per tile of activation rows and never materialize
// unpacked weights in memory:
// - act_bits 2/4/8: a 64-byte load holds 128 columns of one weight row. Splitting it into low and high
//   nibbles gives the even and the odd columns as s8 codes, so the activation codes are stored in the
//   same even/odd order (QuantizedBlock) and one vpdpbusd (u8 q_x times s8 q_w) per half forms exact
//   integer sums of 8 columns per int32 lane. Lane i covers columns 8i..8i+7, hence lies in a single
//   group for every group size: each lane carries its group's s_x, s_w and z_x, and the zero-point term
//   z_x * sum(q_w) is subtracted in fp32, which is exact because both are integers below 2^24.
// - act_bits 16: 16 packed bytes (32 columns) are widened to int32 lanes and mapped nibble -> fp32 code
//   with a 16-entry permute; x is stored as even/odd halves per 32 columns to match, and each group's
//   fp32 partial sum is scaled by s_w once.
// K need only be even: the row kernels mask the tail of each row (weight bytes past K load as 0, so the
// last group, which holds the remainder when G does not divide K, gets only its own columns), and the
// panel path runs on copies of x and the weights zero-padded to whole groups, which quantize and sum to
// the same numbers (zeros change neither a group's range nor its sums; docs/numerics.md, section 4).
#pragma once

#include <algorithm>
#include <new>
#include <cstring>
#include <type_traits>
#include <utility>
#include <vector>

#include "activation/act_quant_cpu_row.h"
#include "common/cpu_dtype.h"
#include "common/format.h"
#include "common/precision.h"
#include "cpu/isa_region.h"
#include "cpu/x86_ops.h"
#include "parallel/parallel.h"

DYQ_ISA_BEGIN
namespace dyq::cpu::avx512 {

constexpr int64_t kBlockColumns = 128;  // columns in 64 bytes of packed weights
constexpr int64_t kChunkColumns = 32;   // act_bits 16: columns in 16 bytes of packed weights
constexpr int kMaxTileRows = 8;         // activation rows that share one pass over a weight row
// From this many activation rows on, the panel path (measured crossover between 8 and 16 rows).
constexpr int64_t kPanelMinRows = 12;

// Cache-line aligned storage, so that full-vector loads never split a line.
template <typename T>
struct CacheLineAllocator {
  using value_type = T;
  CacheLineAllocator() = default;
  template <typename U>
  CacheLineAllocator(const CacheLineAllocator<U>&) {}
  T* allocate(size_t count) { return static_cast<T*>(::operator new(count * sizeof(T), std::align_val_t{64})); }
  void deallocate(T* p, size_t) { ::operator delete(p, std::align_val_t{64}); }
  bool operator==(const CacheLineAllocator&) const { return true; }
  bool operator!=(const CacheLineAllocator&) const { return false; }
};
template <typename T>
using AlignedVector = std::vector<T, CacheLineAllocator<T>>;

// 128 columns of one activation row, in the lane order of the act_bits 2/4/8 kernel.
struct alignas(64) QuantizedBlock {
  uint8_t even_codes[64];  // q_x of columns 0, 2, ..., 126
  uint8_t odd_codes[64];   // q_x of columns 1, 3, ..., 127
  float zero_lanes[16];    // z_x of the group of columns 8i..8i+7 (0 past k)
  float scale_lanes[16];   // s_x of that group (0 past k)
};

inline __m512i even_byte_indices() {
  alignas(64) uint8_t idx[64];
  for (int i = 0; i < 64; ++i) idx[i] = static_cast<uint8_t>(2 * i);
  return _mm512_load_si512(idx);
}

// Activations quantized into QuantizedBlocks, ceil(k / 128) per row (the last one zero-padded).
template <typename Element>
std::vector<QuantizedBlock> quantize_activation_blocks(const Element* x, int64_t m, int64_t k, int group_size,
                                                       int act_bits) {
  const int64_t blocks = (k + kBlockColumns - 1) / kBlockColumns;
  std::vector<QuantizedBlock> quantized(m * blocks);
  parallel_for(0, m, 4, [&](int64_t row_begin, int64_t row_end) {
    std::vector<float> row(k);
    std::vector<uint8_t> codes(blocks * kBlockColumns, 0);
    std::vector<ActivationGroupParams> params(group_count(k, group_size));
    const __m512i even = even_byte_indices();
    const __m512i odd = _mm512_add_epi8(even, _mm512_set1_epi8(1));
    for (int64_t r = row_begin; r < row_end; ++r) {
      quantize_activation_row(x + r * k, k, group_size, act_bits, row.data(), codes.data(), params.data());
      for (int64_t t = 0; t < blocks; ++t) {
        QuantizedBlock& block = quantized[r * blocks + t];
        const __m512i first = _mm512_loadu_si512(codes.data() + t * kBlockColumns);
        const __m512i second = _mm512_loadu_si512(codes.data() + t * kBlockColumns + 64);
        _mm512_store_si512(block.even_codes, _mm512_permutex2var_epi8(first, even, second));
        _mm512_store_si512(block.odd_codes, _mm512_permutex2var_epi8(first, odd, second));
        for (int lane = 0; lane < 16; ++lane) {
          const int64_t column = t * kBlockColumns + 8 * lane;
          const bool inside = column < k;
          block.zero_lanes[lane] = inside ? static_cast<float>(params[column / group_size].zero) : 0.0f;
          block.scale_lanes[lane] = inside ? params[column / group_size].scale : 0.0f;
        }
      }
    }
  });
  return quantized;
}

// Columns rounded up to whole 32-column chunks: the row pitch of the act_bits 16 operand.
inline int64_t chunk_padded(int64_t k) { return (k + kChunkColumns - 1) / kChunkColumns * kChunkColumns; }

// act_bits 16: x in fp32, each 32 columns stored as the 16 even then the 16 odd ones; rows of
// chunk_padded(k) values, zero past k.
template <typename Element>
std::vector<float> deinterleave_activations(const Element* x, int64_t m, int64_t k) {
  const int64_t pitch = chunk_padded(k);
  std::vector<float> deinterleaved(m * pitch);
  parallel_for(0, m, 4, [&](int64_t row_begin, int64_t row_end) {
    std::vector<float> row(pitch, 0.0f);
    const __m512i even = _mm512_set_epi32(30, 28, 26, 24, 22, 20, 18, 16, 14, 12, 10, 8, 6, 4, 2, 0);
    const __m512i odd = _mm512_add_epi32(even, _mm512_set1_epi32(1));
    for (int64_t r = row_begin; r < row_end; ++r) {
      load_row_fp32(x + r * k, k, row.data());
      for (int64_t c = 0; c < pitch; c += kChunkColumns) {
        const __m512 first = _mm512_loadu_ps(row.data() + c);
        const __m512 second = _mm512_loadu_ps(row.data() + c + 16);
        _mm512_storeu_ps(&deinterleaved[r * pitch + c], _mm512_permutex2var_ps(first, even, second));
        _mm512_storeu_ps(&deinterleaved[r * pitch + c + 16], _mm512_permutex2var_ps(first, odd, second));
      }
    }
  });
  return deinterleaved;
}

// Splits 64 packed weight bytes into the s8 codes of their low nibbles (even columns) and high nibbles
// (odd columns), sign-extending with a 16-entry byte lookup.
inline void split_weight_nibbles(__m512i packed, __m512i& even, __m512i& odd) {
  const __m512i low_nibbles = _mm512_set1_epi8(0x0F);
  const __m512i nibble_values =
      broadcast_i32x4(_mm_setr_epi8(0, 1, 2, 3, 4, 5, 6, 7, -8, -7, -6, -5, -4, -3, -2, -1));
  even = _mm512_shuffle_epi8(nibble_values, _mm512_and_si512(packed, low_nibbles));
  odd = _mm512_shuffle_epi8(nibble_values, _mm512_and_si512(_mm512_srli_epi16(packed, 4), low_nibbles));
}

// sums[r] = y[r] (without bias) for one weight row and kRows quantized activation rows.
template <int kRows>
void quantized_row_kernel(const uint8_t* weight_row, const float* scales_row, int64_t k, int group_size,
                          const QuantizedBlock* const* rows, float* sums) {
  const int64_t full_blocks = k / kBlockColumns;
  const int64_t tail_columns = k % kBlockColumns;
  const int64_t groups_per_block = kBlockColumns / group_size;
  const __m512i ones = _mm512_set1_epi8(1);
  // Lane i covers columns 8i..8i+7 of the block: group i * 8 / group_size of it.
  const __m512i lane_group = srli_epi32(
      slli_epi32(_mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15), 3),
      __builtin_ctz(group_size));
  __m512 acc[kRows];
  for (int r = 0; r < kRows; ++r) acc[r] = _mm512_setzero_ps();
  const int64_t blocks = full_blocks + (tail_columns != 0);
  for (int64_t t = 0; t < blocks; ++t) {
    const bool full = t < full_blocks;
    const __mmask64 byte_mask = full ? ~__mmask64{0} : (__mmask64{1} << (tail_columns / 2)) - 1;
    const __mmask16 scale_mask =
        full ? (1u << groups_per_block) - 1 : (1u << group_count(tail_columns, group_size)) - 1;
    __m512i even, odd;
    split_weight_nibbles(_mm512_maskz_loadu_epi8(byte_mask, weight_row + t * (kBlockColumns / 2)), even, odd);
    const __m512 weight_sums = cvtepi32_ps(
        _mm512_dpbusd_epi32(_mm512_dpbusd_epi32(_mm512_setzero_si512(), ones, even), ones, odd));
    const __m512 weight_scales = permutexvar_ps(
        lane_group, _mm512_maskz_loadu_ps(scale_mask, scales_row + t * groups_per_block));
    for (int r = 0; r < kRows; ++r) {
      const QuantizedBlock& block = rows[r][t];
      const __m512i dot = _mm512_dpbusd_epi32(
          _mm512_dpbusd_epi32(_mm512_setzero_si512(), _mm512_load_si512(block.even_codes), even),
          _mm512_load_si512(block.odd_codes), odd);
      // P = sum q_x q_w - z_x sum q_w, exact in fp32 (integers below 2^24).
      const __m512 partial = _mm512_fnmadd_ps(weight_sums, _mm512_load_ps(block.zero_lanes), cvtepi32_ps(dot));
      acc[r] = _mm512_fmadd_ps(partial, _mm512_mul_ps(weight_scales, _mm512_load_ps(block.scale_lanes)), acc[r]);
    }
  }
  for (int r = 0; r < kRows; ++r) sums[r] = reduce_lanes<AddLanes>(acc[r]);
}

template <int kRows>
void fp32_row_kernel(const uint8_t* weight_row, const float* scales_row, int64_t k, int group_size,
                     const float* const* rows, float* sums) {
  const __m512 code_values = _mm512_setr_ps(0, 1, 2, 3, 4, 5, 6, 7, -8, -7, -6, -5, -4, -3, -2, -1);
  __m512 acc[kRows];
  for (int r = 0; r < kRows; ++r) acc[r] = _mm512_setzero_ps();
  for (int64_t g = 0; g < group_count(k, group_size); ++g) {
    __m512 group_acc[kRows];
    for (int r = 0; r < kRows; ++r) group_acc[r] = _mm512_setzero_ps();
    const int64_t group_end = std::min<int64_t>((g + 1) * group_size, k);
    for (int64_t c = g * group_size; c < group_end; c += kChunkColumns) {
      __m128i packed;
      if (c + kChunkColumns <= k) {
        packed = _mm_loadu_si128(reinterpret_cast<const __m128i*>(weight_row + c / 2));
      } else {  // the row's last, partial chunk: the bytes past k read as code 0
        alignas(16) uint8_t tail[16] = {};
        std::memcpy(tail, weight_row + c / 2, (k - c) / 2);
        packed = _mm_load_si128(reinterpret_cast<const __m128i*>(tail));
      }
      const __m512i bytes = cvtepu8_epi32(packed);
      // vpermps reads only the low 4 bits of each index: the low nibble, then the high one shifted down.
      const __m512 even = permutexvar_ps(bytes, code_values);
      const __m512 odd = permutexvar_ps(srli_epi32(bytes, 4), code_values);
      for (int r = 0; r < kRows; ++r) {
        group_acc[r] = _mm512_fmadd_ps(even, _mm512_loadu_ps(rows[r] + c), group_acc[r]);
        group_acc[r] = _mm512_fmadd_ps(odd, _mm512_loadu_ps(rows[r] + c + 16), group_acc[r]);
      }
    }
    const __m512 scale = _mm512_set1_ps(scales_row[g]);
    for (int r = 0; r < kRows; ++r) acc[r] = _mm512_fmadd_ps(group_acc[r], scale, acc[r]);
  }
  for (int r = 0; r < kRows; ++r) sums[r] = reduce_lanes<AddLanes>(acc[r]);
}

#include "gemm/gemm_cpu_row_tiles.inc"

// ---- panel path for many activation rows -------------------------------------------------------
//
// For large m the work is compute-bound, so the weights are unpacked once per call into panels of
// kPanelColumns weight rows by kPanelDepth columns, transposed so that one micro-kernel step loads the
// codes of all 32 output columns as two vectors and multiplies them with a broadcast activation: 32
// output columns x kPanelTileRows activation rows of accumulators stay in registers for a whole group,
// whose scales are then applied once. act_bits 2/4/8 step over 4 columns with vpdpbusd (u8 q_x
// broadcast as a dword, s8 q_w) and correct the zero point per group as in the row kernel; act_bits
// 16 step over one column with fp32 FMAs.
constexpr int64_t kPanelColumns = 32;
constexpr int kPanelTileRows = 6;  // 12 accumulators; 8 or 12 rows measured slower
constexpr int64_t kPanelDepth = 512;  // a multiple of 128, hence of every group size

// Weight row segment -> one s8 code per column (columns a multiple of 32).
inline void unpack_weight_codes(const uint8_t* packed, int64_t columns, int8_t* codes) {
  alignas(64) uint8_t first_indices[64], second_indices[64];
  for (int i = 0; i < 32; ++i) {
    first_indices[2 * i] = static_cast<uint8_t>(i);  // low nibble of byte i: column 2i
    first_indices[2 * i + 1] = static_cast<uint8_t>(64 + i);
    second_indices[2 * i] = static_cast<uint8_t>(32 + i);
    second_indices[2 * i + 1] = static_cast<uint8_t>(96 + i);
  }
  const __m512i first_order = _mm512_load_si512(first_indices), second_order = _mm512_load_si512(second_indices);
  auto prefix_mask = [](int64_t count) { return count >= 64 ? ~__mmask64{0} : (__mmask64{1} << count) - 1; };
  for (int64_t c = 0; c < columns; c += kBlockColumns) {
    const int64_t count = std::min(kBlockColumns, columns - c);
    __m512i even, odd;
    split_weight_nibbles(_mm512_maskz_loadu_epi8(prefix_mask(count / 2), packed + c / 2), even, odd);
    _mm512_mask_storeu_epi8(codes + c, prefix_mask(count), _mm512_permutex2var_epi8(even, first_order, odd));
    if (count > 64) {
      _mm512_mask_storeu_epi8(codes + c + 64, prefix_mask(count - 64),
                              _mm512_permutex2var_epi8(even, second_order, odd));
    }
  }
}

template <bool kQuantized>
struct WeightPanel {
  // kQuantized: [depth / 4][32] dwords, the 4 s8 codes of columns 4t..4t+3 of each output column.
  // Otherwise: [depth][32] fp32 codes.
  using Step = std::conditional_t<kQuantized, int32_t, float>;
  static constexpr int64_t kStepColumns = kQuantized ? 4 : 1;
  std::vector<int8_t> row_codes = std::vector<int8_t>(kPanelColumns * kPanelDepth);  // [32][depth]
  AlignedVector<Step> steps = AlignedVector<Step>(kPanelColumns * kPanelDepth / kStepColumns);
  AlignedVector<float> scales = AlignedVector<float>(kPanelColumns * kPanelDepth / 32);       // [group][32]
  AlignedVector<float> weight_sums = AlignedVector<float>(kPanelColumns * kPanelDepth / 32);  // [group][32]

  // Columns [col_begin, col_begin + depth) of weight rows [row_begin, row_begin + 32); rows past n read as 0.
  void pack(const uint8_t* qweight, const float* all_scales, int64_t n, int64_t k, int group_size, int64_t row_begin,
            int64_t col_begin, int64_t depth) {
    const int64_t groups = k / group_size, block_groups = depth / group_size;
    for (int64_t j = 0; j < kPanelColumns; ++j) {
      const int64_t row = row_begin + j;
      int8_t* codes = row_codes.data() + j * depth;
      if (row < n) {
        unpack_weight_codes(qweight + row * (k / 2) + col_begin / 2, depth, codes);
      } else {
        std::memset(codes, 0, depth);
      }
      for (int64_t g = 0; g < block_groups; ++g) {
        scales[g * kPanelColumns + j] = row < n ? all_scales[row * groups + col_begin / group_size + g] : 0.0f;
      }
    }
    // Transpose with dword gathers: lane l of half h reads 4 codes of output column 16h + l.
    const __m512i column_offsets =
        _mm512_mullo_epi32(_mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15),
                           _mm512_set1_epi32(static_cast<int>(depth)));
    const __m512i half_offset = _mm512_set1_epi32(static_cast<int>(16 * depth));
    const __m512i ones = _mm512_set1_epi8(1);
    for (int64_t g = 0; g < block_groups; ++g) {
      __m512i sums[2] = {_mm512_setzero_si512(), _mm512_setzero_si512()};
      for (int64_t quad = g * group_size / 4; quad < (g + 1) * group_size / 4; ++quad) {
        for (int h = 0; h < 2; ++h) {
          const __m512i offsets = h == 0 ? column_offsets : _mm512_add_epi32(column_offsets, half_offset);
          const __m512i four_codes = i32gather_epi32(offsets, row_codes.data() + 4 * quad);
          if constexpr (kQuantized) {
            _mm512_store_si512(steps.data() + quad * kPanelColumns + 16 * h, four_codes);
            sums[h] = _mm512_dpbusd_epi32(sums[h], ones, four_codes);
          } else {
            for (int b = 0; b < 4; ++b) {
              const __m512i code = srai_epi32(slli_epi32(four_codes, 24 - 8 * b), 24);
              _mm512_store_ps(steps.data() + (4 * quad + b) * kPanelColumns + 16 * h, cvtepi32_ps(code));
            }
          }
        }
      }
      for (int h = 0; h < 2; ++h) {
        _mm512_storeu_ps(&weight_sums[g * kPanelColumns + 16 * h], cvtepi32_ps(sums[h]));
      }
    }
  }
};

// Activations as the panel kernel reads them: fp32 x, or u8 codes with per-group zero points and scales.
template <bool kQuantized>
struct PanelActivations {
  std::vector<std::conditional_t<kQuantized, uint8_t, float>> values;  // [m, k]
  std::vector<float> zeros, scales;                                     // [m, k / group_size], kQuantized only
};

template <typename Element>
PanelActivations<true> quantize_panel_activations(const Element* x, int64_t m, int64_t k, int group_size,
                                                  int act_bits) {
  const int64_t groups = k / group_size;
  PanelActivations<true> a{std::vector<uint8_t>(m * k), std::vector<float>(m * groups), std::vector<float>(m * groups)};
  parallel_for(0, m, 4, [&](int64_t row_begin, int64_t row_end) {
    std::vector<float> row(k);
    std::vector<ActivationGroupParams> params(groups);
    for (int64_t r = row_begin; r < row_end; ++r) {
      quantize_activation_row(x + r * k, k, group_size, act_bits, row.data(), a.values.data() + r * k, params.data());
      for (int64_t g = 0; g < groups; ++g) {
        a.zeros[r * groups + g] = static_cast<float>(params[g].zero);
        a.scales[r * groups + g] = params[g].scale;
      }
    }
  });
  return a;
}

template <typename Element>
PanelActivations<false> convert_panel_activations(const Element* x, int64_t m, int64_t k) {
  PanelActivations<false> a{std::vector<float>(m * k), {}, {}};
  parallel_for(0, m, 16, [&](int64_t row_begin, int64_t row_end) {
    for (int64_t r = row_begin; r < row_end; ++r) load_row_fp32(x + r * k, k, a.values.data() + r * k);
  });
  return a;
}

template <bool kQuantized>
struct PanelAccumulator {
  using Type = __m512;
};
template <>
struct PanelAccumulator<true> {
  using Type = __m512i;  // exact int32 sums of one group
};

// totals[r][0..32) += the contribution of columns [col_begin, col_begin + depth) for activation rows
// row_begin + r.
template <bool kQuantized, int kRows>
void panel_kernel(const WeightPanel<kQuantized>& panel, const PanelActivations<kQuantized>& activations, int64_t k,
                  int group_size, int64_t row_begin, int64_t col_begin, int64_t depth, float* totals) {
  using Accumulator = typename PanelAccumulator<kQuantized>::Type;
  constexpr int64_t kStepColumns = WeightPanel<kQuantized>::kStepColumns;
  const int64_t groups = k / group_size;
  const auto* steps = panel.steps.data();
  const std::conditional_t<kQuantized, uint8_t, float>* row_values[kRows];
  for (int r = 0; r < kRows; ++r) row_values[r] = activations.values.data() + (row_begin + r) * k + col_begin;
  for (int64_t g = 0; g < depth / group_size; ++g) {
    Accumulator acc[kRows][2];
    for (int r = 0; r < kRows; ++r) {
      for (int h = 0; h < 2; ++h) {
        if constexpr (kQuantized) acc[r][h] = _mm512_setzero_si512(); else acc[r][h] = _mm512_setzero_ps();
      }
    }
    for (int64_t col = g * group_size; col < (g + 1) * group_size; col += kStepColumns) {
      const auto* step = steps + (col / kStepColumns) * kPanelColumns;
      if constexpr (kQuantized) {
        const __m512i first = _mm512_load_si512(step), second = _mm512_load_si512(step + 16);
        for (int r = 0; r < kRows; ++r) {
          int32_t four_codes;
          std::memcpy(&four_codes, row_values[r] + col, 4);
          const __m512i broadcast = _mm512_set1_epi32(four_codes);
          acc[r][0] = _mm512_dpbusd_epi32(acc[r][0], broadcast, first);
          acc[r][1] = _mm512_dpbusd_epi32(acc[r][1], broadcast, second);
        }
      } else {
        const __m512 first = _mm512_load_ps(step), second = _mm512_load_ps(step + 16);
        for (int r = 0; r < kRows; ++r) {
          const __m512 broadcast = _mm512_set1_ps(row_values[r][col]);
          acc[r][0] = _mm512_fmadd_ps(broadcast, first, acc[r][0]);
          acc[r][1] = _mm512_fmadd_ps(broadcast, second, acc[r][1]);
        }
      }
    }
    // The totals stay in memory: keeping them in registers too would make the compiler spill the inner loop.
    const int64_t group = col_begin / group_size + g;
    for (int h = 0; h < 2; ++h) {
      const __m512 weight_scales = _mm512_loadu_ps(&panel.scales[g * kPanelColumns + 16 * h]);
      if constexpr (kQuantized) {
        const __m512 weight_sums = _mm512_loadu_ps(&panel.weight_sums[g * kPanelColumns + 16 * h]);
        for (int r = 0; r < kRows; ++r) {
          const int64_t at = (row_begin + r) * groups + group;
          // P = sum q_x q_w - z_x sum q_w, exact in fp32 (integers below 2^24).
          const __m512 partial =
              _mm512_fnmadd_ps(weight_sums, _mm512_set1_ps(activations.zeros[at]), cvtepi32_ps(acc[r][h]));
          float* total = totals + r * kPanelColumns + 16 * h;
          const __m512 scale = _mm512_mul_ps(weight_scales, _mm512_set1_ps(activations.scales[at]));
          _mm512_storeu_ps(total, _mm512_fmadd_ps(partial, scale, _mm512_loadu_ps(total)));
        }
      } else {
        for (int r = 0; r < kRows; ++r) {
          float* total = totals + r * kPanelColumns + 16 * h;
          _mm512_storeu_ps(total, _mm512_fmadd_ps(acc[r][h], weight_scales, _mm512_loadu_ps(total)));
        }
      }
    }
  }
}

template <bool kQuantized, typename Element>
void run_panels(const PanelActivations<kQuantized>& activations, const uint8_t* qweight, const float* scales,
                const Element* bias, int64_t m, int64_t n, int64_t k, int group_size, Element* out) {
  const int64_t panels = (n + kPanelColumns - 1) / kPanelColumns;
  parallel_for(0, panels, 1, [&](int64_t panel_begin, int64_t panel_end) {
    WeightPanel<kQuantized> panel;
    std::vector<float> totals(m * kPanelColumns);  // [m][32]
    for (int64_t p = panel_begin; p < panel_end; ++p) {
      const int64_t weight_row = p * kPanelColumns;
      std::fill(totals.begin(), totals.end(), 0.0f);
      for (int64_t col = 0; col < k; col += kPanelDepth) {
        const int64_t depth = std::min(kPanelDepth, k - col);
        panel.pack(qweight, scales, n, k, group_size, weight_row, col, depth);
        for (int64_t row = 0; row < m; row += kPanelTileRows) {
          const int rows = static_cast<int>(std::min<int64_t>(kPanelTileRows, m - row));
          dispatch_tile_rows<kPanelTileRows>(rows, [&](auto tile_rows) {
            panel_kernel<kQuantized, decltype(tile_rows)::value>(panel, activations, k, group_size, row, col, depth,
                                                                 totals.data() + row * kPanelColumns);
          });
        }
      }
      const int64_t columns = std::min(kPanelColumns, n - weight_row);
      for (int64_t row = 0; row < m; ++row) {
        for (int64_t j = 0; j < columns; ++j) {
          const float bias_value = bias != nullptr ? to_float(bias[weight_row + j]) : 0.0f;
          out[row * n + weight_row + j] = from_float<Element>(totals[row * kPanelColumns + j] + bias_value);
        }
      }
    }
  });
}

template <int kBits, typename Element>
void gemm_typed(const Element* x, const uint8_t* qweight, const float* scales, const Element* bias, int64_t m, int64_t n,
                int64_t k, int group_size, Element* out);

// The panel path for a k that group_size does not divide: x and the weights copied with zero columns up
// to whole groups (the scales already have one entry per group, the last one for the remainder).
template <int kBits, typename Element>
void gemm_panels_padded(const Element* x, const uint8_t* qweight, const float* scales, const Element* bias, int64_t m,
                        int64_t n, int64_t k, int group_size, Element* out) {
  const int64_t padded = group_count(k, group_size) * group_size;
  std::vector<Element> x_padded(m * padded, Element(0.0f));
  std::vector<uint8_t> qweight_padded(n * padded / 2, 0);
  parallel_for(0, std::max(m, n), 16, [&](int64_t begin, int64_t end) {
    for (int64_t r = begin; r < end; ++r) {
      if (r < m) std::memcpy(x_padded.data() + r * padded, x + r * k, k * sizeof(Element));
      if (r < n) std::memcpy(qweight_padded.data() + r * padded / 2, qweight + r * k / 2, k / 2);
    }
  });
  gemm_typed<kBits>(x_padded.data(), qweight_padded.data(), scales, bias, m, n, padded, group_size, out);
}

template <int kBits, typename Element>
void gemm_typed(const Element* x, const uint8_t* qweight, const float* scales, const Element* bias, int64_t m, int64_t n,
                int64_t k, int group_size, Element* out) {
  constexpr bool kQuantized = ActivationTraits<kBits>::kQuantized;
  if (m >= kPanelMinRows && k % group_size != 0) {
    gemm_panels_padded<kBits>(x, qweight, scales, bias, m, n, k, group_size, out);
  } else if (m >= kPanelMinRows) {
    if constexpr (kQuantized) {
      run_panels(quantize_panel_activations(x, m, k, group_size, kBits), qweight, scales, bias, m, n, k, group_size,
                 out);
    } else {
      run_panels(convert_panel_activations(x, m, k), qweight, scales, bias, m, n, k, group_size, out);
    }
  } else if constexpr (kQuantized) {
    const int64_t blocks = (k + kBlockColumns - 1) / kBlockColumns;
    const std::vector<QuantizedBlock> activations = quantize_activation_blocks(x, m, k, group_size, kBits);
    run_tiles<kMaxTileRows>(
        qweight, scales, bias, m, n, k, group_size, out, [&](int64_t r) { return activations.data() + r * blocks; },
        [&](auto tile_rows, const uint8_t* weight_row, const float* scales_row, const QuantizedBlock* const* rows,
            float* sums) {
          quantized_row_kernel<decltype(tile_rows)::value>(weight_row, scales_row, k, group_size, rows, sums);
        });
  } else {
    const std::vector<float> activations = deinterleave_activations(x, m, k);
    const int64_t pitch = chunk_padded(k);
    run_tiles<kMaxTileRows>(
        qweight, scales, bias, m, n, k, group_size, out, [&](int64_t r) { return activations.data() + r * pitch; },
        [&](auto tile_rows, const uint8_t* weight_row, const float* scales_row, const float* const* rows, float* sums) {
          fp32_row_kernel<decltype(tile_rows)::value>(weight_row, scales_row, k, group_size, rows, sums);
        });
  }
}

inline const char* gemm_kernel(int64_t m, int64_t, int, int act_bits) {
  if (act_bits == kFallbackBits) return m >= kPanelMinRows ? "avx512/panel-fp32" : "avx512/rows-fp32";
  return m >= kPanelMinRows ? "avx512/panel-vnni" : "avx512/rows-vnni";
}

}  // namespace dyq::cpu::avx512
DYQ_ISA_END
