// The AVX2 GEMM behind dyq::cpu::gemm on x86-64 CPUs without AVX-512 VNNI (docs/numerics.md, section 3).
//
// The row kernels of gemm_cpu_avx512.h at half the width and without VNNI. Both stream each packed
// weight row once per tile of up to 4 activation rows (16 ymm registers) and never materialize unpacked
// weights in memory:
// - act_bits 2/4/8: a 32-byte load holds 64 columns of one weight row; its low and high nibbles are the
//   even and the odd columns as s8 codes, and the activation codes are stored in the same even/odd order
//   (QuantizedBlock). vpmaddubsw (u8 q_x times s8 q_w, adjacent pairs summed to s16) of the even and of
//   the odd half, added, hold sums of 4 columns, at most 4 * 255 * 8 < 2^15, so nothing saturates;
//   vpmaddwd with ones then gives exact int32 sums of 8 columns per lane. Lane i covers columns
//   8i..8i+7, in one group for every group size, and carries its group's s_x, s_w and z_x; the zero-point
//   term z_x * sum(q_w) is subtracted in fp32, exact because both are integers below 2^24.
// - act_bits 16: 8 packed bytes (16 columns) are widened to int32 lanes, each nibble n sign-extended as
//   (n ^ 8) - 8 and converted to fp32; x is stored as even/odd halves per 16 columns to match, and each
//   group's fp32 partial sum is scaled by s_w once.
// Large M has no panel path here (the AVX-512 one is built on VNNI and 32 registers).
// K need only be even: the bytes of a row's last, partial block or chunk past K read as code 0 (as do the
// activation codes there), so the last group, which holds the remainder when G does not divide K, sums
// only its own columns (docs/numerics.md, section 4).
#pragma once

#include <algorithm>
#include <cstdint>
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
namespace dyq::cpu::avx2 {

constexpr int64_t kBlockColumns = 64;  // columns in 32 bytes of packed weights
constexpr int64_t kChunkColumns = 16;  // act_bits 16: columns in 8 bytes of packed weights
constexpr int kMaxTileRows = 4;        // activation rows that share one pass over a weight row

// 64 columns of one activation row, in the lane order of the act_bits 2/4/8 kernel.
struct alignas(32) QuantizedBlock {
  uint8_t even_codes[32];  // q_x of columns 0, 2, ..., 62
  uint8_t odd_codes[32];   // q_x of columns 1, 3, ..., 63
  float zero_lanes[8];     // z_x of the group of columns 8i..8i+7 (0 past k)
  float scale_lanes[8];    // s_x of that group (0 past k)
};

// Activations quantized into QuantizedBlocks, ceil(k / 64) per row (the last one zero-padded).
template <typename Element>
std::vector<QuantizedBlock> quantize_activation_blocks(const Element* x, int64_t m, int64_t k, int group_size,
                                                       int act_bits) {
  const int64_t blocks = (k + kBlockColumns - 1) / kBlockColumns;
  std::vector<QuantizedBlock> quantized(m * blocks);
  parallel_for(0, m, 4, [&](int64_t row_begin, int64_t row_end) {
    std::vector<float> row(k);
    std::vector<uint8_t> codes(blocks * kBlockColumns, 0);
    std::vector<ActivationGroupParams> params(group_count(k, group_size));
    for (int64_t r = row_begin; r < row_end; ++r) {
      quantize_activation_row(x + r * k, k, group_size, act_bits, row.data(), codes.data(), params.data());
      for (int64_t t = 0; t < blocks; ++t) {
        QuantizedBlock& block = quantized[r * blocks + t];
        const uint8_t* block_codes = codes.data() + t * kBlockColumns;
        for (int j = 0; j < 32; ++j) {
          block.even_codes[j] = block_codes[2 * j];
          block.odd_codes[j] = block_codes[2 * j + 1];
        }
        for (int lane = 0; lane < 8; ++lane) {
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

// Columns rounded up to whole 16-column chunks: the row pitch of the act_bits 16 operand.
inline int64_t chunk_padded(int64_t k) { return (k + kChunkColumns - 1) / kChunkColumns * kChunkColumns; }

// act_bits 16: x in fp32, each 16 columns stored as the 8 even then the 8 odd ones; rows of
// chunk_padded(k) values, zero past k.
template <typename Element>
std::vector<float> deinterleave_activations(const Element* x, int64_t m, int64_t k) {
  const int64_t pitch = chunk_padded(k);
  std::vector<float> deinterleaved(m * pitch);
  parallel_for(0, m, 4, [&](int64_t row_begin, int64_t row_end) {
    std::vector<float> row(pitch, 0.0f);
    for (int64_t r = row_begin; r < row_end; ++r) {
      load_row_fp32(x + r * k, k, row.data());
      float* out = deinterleaved.data() + r * pitch;
      for (int64_t c = 0; c < pitch; c += kChunkColumns) {
        for (int j = 0; j < 8; ++j) {
          out[c + j] = row[c + 2 * j];
          out[c + 8 + j] = row[c + 2 * j + 1];
        }
      }
    }
  });
  return deinterleaved;
}

// Splits 32 packed weight bytes into the s8 codes of their low nibbles (even columns) and high nibbles
// (odd columns), sign-extending with a 16-entry byte lookup (vpshufb looks up within each 128-bit lane).
inline void split_weight_nibbles(__m256i packed, __m256i& even, __m256i& odd) {
  const __m256i low_nibbles = _mm256_set1_epi8(0x0F);
  const __m256i nibble_values =
      _mm256_broadcastsi128_si256(_mm_setr_epi8(0, 1, 2, 3, 4, 5, 6, 7, -8, -7, -6, -5, -4, -3, -2, -1));
  even = _mm256_shuffle_epi8(nibble_values, _mm256_and_si256(packed, low_nibbles));
  odd = _mm256_shuffle_epi8(nibble_values, _mm256_and_si256(_mm256_srli_epi16(packed, 4), low_nibbles));
}

// sums[r] = y[r] (without bias) for one weight row and kRows quantized activation rows.
template <int kRows>
void quantized_row_kernel(const uint8_t* weight_row, const float* scales_row, int64_t k, int group_size,
                          const QuantizedBlock* const* rows, float* sums) {
  const int64_t full_blocks = k / kBlockColumns;
  const int64_t tail_columns = k % kBlockColumns;
  const int64_t blocks = full_blocks + (tail_columns != 0);
  const int group_shift = __builtin_ctz(group_size);
  const __m256i ones_u8 = _mm256_set1_epi8(1);
  const __m256i ones_s16 = _mm256_set1_epi16(1);
  __m256 acc[kRows];
  for (int r = 0; r < kRows; ++r) acc[r] = _mm256_setzero_ps();
  for (int64_t t = 0; t < blocks; ++t) {
    const bool full = t < full_blocks;
    const uint8_t* packed = weight_row + t * (kBlockColumns / 2);
    // The tail block holds tail_columns / 2 bytes; the rest read as code 0.
    __m256i bytes;
    if (full) {
      bytes = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(packed));
    } else {
      alignas(32) uint8_t tail[32] = {};
      std::memcpy(tail, packed, tail_columns / 2);
      bytes = _mm256_load_si256(reinterpret_cast<const __m256i*>(tail));
    }
    __m256i even, odd;
    split_weight_nibbles(bytes, even, odd);
    const __m256 weight_sums = _mm256_cvtepi32_ps(_mm256_madd_epi16(
        _mm256_add_epi16(_mm256_maddubs_epi16(ones_u8, even), _mm256_maddubs_epi16(ones_u8, odd)), ones_s16));
    // Group 32 splits a block between two groups (lanes 0-3 and 4-7) when the block reaches past its
    // first 32 columns; larger groups hold it whole.
    const float* block_scales = scales_row + ((t * kBlockColumns) >> group_shift);
    const bool two_groups = group_size < kBlockColumns && (full || tail_columns > kBlockColumns / 2);
    const __m256 weight_scales = two_groups
                                     ? _mm256_setr_m128(_mm_set1_ps(block_scales[0]), _mm_set1_ps(block_scales[1]))
                                     : _mm256_set1_ps(block_scales[0]);
    for (int r = 0; r < kRows; ++r) {
      const QuantizedBlock& block = rows[r][t];
      const __m256i pair_sums =
          _mm256_add_epi16(_mm256_maddubs_epi16(_mm256_load_si256(reinterpret_cast<const __m256i*>(block.even_codes)), even),
                           _mm256_maddubs_epi16(_mm256_load_si256(reinterpret_cast<const __m256i*>(block.odd_codes)), odd));
      const __m256i dot = _mm256_madd_epi16(pair_sums, ones_s16);
      // P = sum q_x q_w - z_x sum q_w, exact in fp32 (integers below 2^24).
      const __m256 partial = _mm256_fnmadd_ps(weight_sums, _mm256_load_ps(block.zero_lanes), _mm256_cvtepi32_ps(dot));
      acc[r] = _mm256_fmadd_ps(partial, _mm256_mul_ps(weight_scales, _mm256_load_ps(block.scale_lanes)), acc[r]);
    }
  }
  for (int r = 0; r < kRows; ++r) sums[r] = reduce_lanes<AddLanes>(acc[r]);
}

template <int kRows>
void fp32_row_kernel(const uint8_t* weight_row, const float* scales_row, int64_t k, int group_size,
                     const float* const* rows, float* sums) {
  const __m256i low_nibble = _mm256_set1_epi32(0xF);
  const __m256i eight = _mm256_set1_epi32(8);
  __m256 acc[kRows];
  for (int r = 0; r < kRows; ++r) acc[r] = _mm256_setzero_ps();
  for (int64_t g = 0; g < group_count(k, group_size); ++g) {
    __m256 group_acc[kRows];
    for (int r = 0; r < kRows; ++r) group_acc[r] = _mm256_setzero_ps();
    const int64_t group_end = std::min<int64_t>((g + 1) * group_size, k);
    for (int64_t c = g * group_size; c < group_end; c += kChunkColumns) {
      __m128i packed;
      if (c + kChunkColumns <= k) {
        packed = _mm_loadl_epi64(reinterpret_cast<const __m128i*>(weight_row + c / 2));
      } else {  // the row's last, partial chunk: the bytes past k read as code 0
        alignas(16) uint8_t tail[16] = {};
        std::memcpy(tail, weight_row + c / 2, (k - c) / 2);
        packed = _mm_load_si128(reinterpret_cast<const __m128i*>(tail));
      }
      const __m256i bytes = _mm256_cvtepu8_epi32(packed);
      const __m256 even = _mm256_cvtepi32_ps(
          _mm256_sub_epi32(_mm256_xor_si256(_mm256_and_si256(bytes, low_nibble), eight), eight));
      const __m256 odd = _mm256_cvtepi32_ps(_mm256_sub_epi32(_mm256_xor_si256(_mm256_srli_epi32(bytes, 4), eight), eight));
      for (int r = 0; r < kRows; ++r) {
        group_acc[r] = _mm256_fmadd_ps(even, _mm256_loadu_ps(rows[r] + c), group_acc[r]);
        group_acc[r] = _mm256_fmadd_ps(odd, _mm256_loadu_ps(rows[r] + c + 8), group_acc[r]);
      }
    }
    const __m256 scale = _mm256_set1_ps(scales_row[g]);
    for (int r = 0; r < kRows; ++r) acc[r] = _mm256_fmadd_ps(group_acc[r], scale, acc[r]);
  }
  for (int r = 0; r < kRows; ++r) sums[r] = reduce_lanes<AddLanes>(acc[r]);
}

#include "gemm/gemm_cpu_row_tiles.inc"

template <int kBits, typename Element>
void gemm_typed(const Element* x, const uint8_t* qweight, const float* scales, const Element* bias, int64_t m,
                int64_t n, int64_t k, int group_size, Element* out) {
  if constexpr (ActivationTraits<kBits>::kQuantized) {
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

inline const char* gemm_kernel(int64_t, int64_t, int, int act_bits) {
  return act_bits == kFallbackBits ? "avx2/rows-fp32" : "avx2/rows-maddubs";
}

}  // namespace dyq::cpu::avx2
DYQ_ISA_END
