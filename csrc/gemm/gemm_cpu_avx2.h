// The AVX2 GEMM behind dyq::cpu::gemm on x86-64 CPUs without AVX-512 VNNI (docs/numerics.md, section 3).
//
// Packed weights are rows of K / 2 bytes, byte j holding column 2j in its low nibble and column 2j + 1 in
// its high one, each a two's-complement code q_w in [-8, 7]. Two kinds of kernel read them:
//
// Row kernels (decode). The work is one stream over the packed
// weights, so they spend as few instructions as they can per 32-byte load, keep several independent
// accumulators (an FMA's latency is longer than the work between two of a chain's FMAs) and prefetch
// the bytes kPrefetchBytes ahead, which, rows being adjacent, runs on into the next weight rows. Each
// weight row is read once per tile of up to kMaxTileRows activation rows (run_tiles, rows-per-block
// loop in gemm_cpu_row_tiles.inc).
// - act_bits 2/4/8: a 32-byte load holds 64 columns. The codes are read offset by 8, u = q_w + 8 =
//   nibble XOR 8 in [0, 15], which needs no sign-extending lookup: one XOR per load, then a mask and a
//   shift give the even and the odd columns' u as bytes. The activations are stored in the same
//   even/odd order (DecodeBlock); vpmaddubsw of the even and of the odd half, added, hold exact sums of 4
//   columns per 16-bit lane, and vpmaddwd with ones sums them to 8 columns per int32 lane: lane i covers
//   columns 8i..8i+7, which lie in one group for every group size. At act_bits 2/4 the activations are
//   stored centred, a = q_x - z_x in [-15, 15] (the s8 operand; u is the u8 one, sums at most
//   2 * 2 * 15 * 15); at act_bits 8 q_x must be the u8 operand and u takes the s8 one, and
//   z_x * sum(u), one more vpmaddubsw with z_x in every byte, is subtracted in 16 bits (each term at most
//   2 * 2 * 255 * 15 = 15300, so nothing saturates). The offset comes back as -8 * sum(q_x - z_x) over
//   the lane's columns, an integer of the activations alone that starts the lane's sum, so that the
//   lane holds exactly P of docs/numerics.md; it is converted to fp32 and multiplied by s_x * s_w.
// - act_bits 16: 8 packed bytes (16 columns) are widened to int32 lanes and turned into exact fp32
//   codes without a conversion: XOR-ing 0x4B000088 into a lane sets the exponent of 2^23 above the two
//   offset codes u, so masking with 0x4B00000F gives the float 2^23 + u_even and with 0x4B0000F0 the
//   float 2^23 + 16 u_odd, and subtracting 2^23 + 8 (2^23 + 128) leaves q_w (16 q_w) exactly. x is
//   stored as the 8 even then the 8 odd columns of every 16 to match; the even and the odd columns sum
//   in separate accumulators, and each group's partial sums are scaled once, the odd ones by s_w / 16
//   (a power of two: the same sum, scaled exactly).
//
// Large M has no panel path here yet: the row kernels run on tiles of rows.
//
// K need only be even. A row kernel reads a weight row's last, partial block or group from a padded
// copy against activation codes or values of 0 past K, so the last group, which holds the remainder
// when G does not divide K, sums only its own columns (docs/numerics.md, section 4).
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

constexpr int64_t kBlockColumns = 64;     // columns in 32 bytes of packed weights
constexpr int64_t kChunkColumns = 16;     // act_bits 16: columns in 8 bytes of packed weights
constexpr int kMaxTileRows = 4;           // activation rows that share one pass over a weight row
constexpr int64_t kPrefetchBytes = 1024;  // how far ahead of its loads a row kernel prefetches

// ---- row kernels, act_bits 2/4/8 --------------------------------------------------------------------

// 64 columns of one activation row for the integer row kernel.
struct alignas(32) DecodeBlock {
  uint8_t even_codes[32];  // columns 0, 2, ..., 62: a = q_x - z_x as s8 (act_bits 2/4) or q_x (act_bits 8)
  uint8_t odd_codes[32];   // columns 1, 3, ..., 63
  uint32_t zero_bytes[8];  // act_bits 8: z_x of lane i's group in each byte (0 past k)
  int32_t offsets[8];      // -8 * sum of (q_x - z_x) over lane i's columns 8i..8i+7 (0 past k)
  float scale_lanes[8];    // s_x of lane i's group (0 past k)
};

// Activations quantized into DecodeBlocks, ceil(k / 64) per row (zero past k).
template <typename Element>
std::vector<DecodeBlock> decode_activations(const Element* x, int64_t m, int64_t k, int group_size, int act_bits) {
  const int64_t blocks = (k + kBlockColumns - 1) / kBlockColumns;
  const bool centred = act_bits != 8;
  std::vector<DecodeBlock> quantized(m * blocks);
  parallel_for(0, m, 4, [&](int64_t row_begin, int64_t row_end) {
    std::vector<float> row(k);
    std::vector<uint8_t> codes(k);
    std::vector<ActivationGroupParams> params(group_count(k, group_size));
    for (int64_t r = row_begin; r < row_end; ++r) {
      quantize_activation_row(x + r * k, k, group_size, act_bits, row.data(), codes.data(), params.data());
      auto value = [&](int64_t column) {  // the stored code of a column: 0 past k
        if (column >= k) return 0;
        return centred ? codes[column] - params[column / group_size].zero : int{codes[column]};
      };
      for (int64_t t = 0; t < blocks; ++t) {
        DecodeBlock& block = quantized[r * blocks + t];
        const int64_t first = t * kBlockColumns;
        for (int j = 0; j < 32; ++j) {
          block.even_codes[j] = static_cast<uint8_t>(value(first + 2 * j));
          block.odd_codes[j] = static_cast<uint8_t>(value(first + 2 * j + 1));
        }
        for (int lane = 0; lane < 8; ++lane) {
          const int64_t begin = first + 8 * lane, end = std::min(begin + 8, k);
          const bool inside = begin < k;
          const int zero = inside ? params[begin / group_size].zero : 0;
          int32_t sum = 0;
          for (int64_t column = begin; column < end; ++column) sum += codes[column] - zero;
          block.zero_bytes[lane] = centred ? 0u : static_cast<uint32_t>(zero) * 0x01010101u;
          block.offsets[lane] = -8 * sum;
          block.scale_lanes[lane] = inside ? params[begin / group_size].scale : 0.0f;
        }
      }
    }
  });
  return quantized;
}

// s_w of each lane of block t (lane i: columns 8i..8i+7): one group for G >= 64; for G = 32 lanes 0-3
// and 4-7 belong to groups 2t and 2t + 1, the second absent when the row's last block ends before it.
inline __m256 weight_scale_lanes(const float* scales_row, int64_t t, int group_shift, int64_t groups) {
  if (group_shift > 5) return _mm256_broadcast_ss(scales_row + ((t * kBlockColumns) >> group_shift));
  const __m128 second = 2 * t + 1 < groups ? _mm_broadcast_ss(scales_row + 2 * t + 1) : _mm_setzero_ps();
  return _mm256_set_m128(second, _mm_broadcast_ss(scales_row + 2 * t));
}

// acc[r] += s_x s_w P of each lane of block t, for kRows activation rows and the block's 32 packed bytes.
template <int kRows, bool kWideCodes>
inline void accumulate_block(__m256i packed, __m256 weight_scales, const DecodeBlock* const* rows, int64_t t,
                             __m256* acc) {
  const __m256i low_nibbles = _mm256_set1_epi8(0x0F);
  const __m256i u = _mm256_xor_si256(packed, _mm256_set1_epi8(static_cast<char>(0x88)));
  const __m256i even = _mm256_and_si256(u, low_nibbles);
  const __m256i odd = _mm256_and_si256(_mm256_srli_epi16(u, 4), low_nibbles);
  [[maybe_unused]] const __m256i both = kWideCodes ? _mm256_add_epi8(even, odd) : even;  // u sums: below 31
  const __m256i ones = _mm256_set1_epi16(1);
  for (int r = 0; r < kRows; ++r) {
    const DecodeBlock& block = rows[r][t];
    const __m256i a_even = _mm256_load_si256(reinterpret_cast<const __m256i*>(block.even_codes));
    const __m256i a_odd = _mm256_load_si256(reinterpret_cast<const __m256i*>(block.odd_codes));
    __m256i pairs;  // exact sums of 4 columns
    if constexpr (kWideCodes) {
      pairs = _mm256_add_epi16(_mm256_maddubs_epi16(a_even, even), _mm256_maddubs_epi16(a_odd, odd));
      pairs = _mm256_sub_epi16(
          pairs, _mm256_maddubs_epi16(_mm256_load_si256(reinterpret_cast<const __m256i*>(block.zero_bytes)), both));
    } else {
      pairs = _mm256_add_epi16(_mm256_maddubs_epi16(even, a_even), _mm256_maddubs_epi16(odd, a_odd));
    }
    const __m256i dot = _mm256_add_epi32(_mm256_madd_epi16(pairs, ones),
                                         _mm256_load_si256(reinterpret_cast<const __m256i*>(block.offsets)));
    acc[r] = _mm256_fmadd_ps(_mm256_cvtepi32_ps(dot), _mm256_mul_ps(weight_scales, _mm256_load_ps(block.scale_lanes)),
                             acc[r]);
  }
}

// sums[r] = y[r] (without bias) for one weight row and kRows integer activation rows. Two accumulators
// per row, for even and odd blocks.
template <int kRows, bool kWideCodes>
void decode_int_kernel(const uint8_t* weight_row, const float* scales_row, int64_t k, int group_size,
                       const DecodeBlock* const* rows, float* sums) {
  const int64_t groups = group_count(k, group_size);
  const int group_shift = __builtin_ctz(group_size);
  const int64_t full_blocks = k / kBlockColumns;
  __m256 acc[2][kRows];
  for (int r = 0; r < kRows; ++r) acc[0][r] = acc[1][r] = _mm256_setzero_ps();
  int64_t t = 0;
  for (; t + 2 <= full_blocks; t += 2) {
    const uint8_t* packed = weight_row + t * (kBlockColumns / 2);
    _mm_prefetch(reinterpret_cast<const char*>(packed + kPrefetchBytes), _MM_HINT_T0);
    accumulate_block<kRows, kWideCodes>(_mm256_loadu_si256(reinterpret_cast<const __m256i*>(packed)),
                                        weight_scale_lanes(scales_row, t, group_shift, groups), rows, t, acc[0]);
    accumulate_block<kRows, kWideCodes>(_mm256_loadu_si256(reinterpret_cast<const __m256i*>(packed + 32)),
                                        weight_scale_lanes(scales_row, t + 1, group_shift, groups), rows, t + 1,
                                        acc[1]);
  }
  if (t < full_blocks) {
    accumulate_block<kRows, kWideCodes>(
        _mm256_loadu_si256(reinterpret_cast<const __m256i*>(weight_row + t * (kBlockColumns / 2))),
        weight_scale_lanes(scales_row, t, group_shift, groups), rows, t, acc[0]);
    ++t;
  }
  if (k % kBlockColumns != 0) {
    // The row's last, partial block: the bytes past k read as u = 0 (nibbles 8), so that they add
    // nothing to z_x * sum(u); their activation codes are 0.
    alignas(32) uint8_t tail[32];
    std::memset(tail, 0x88, sizeof(tail));
    std::memcpy(tail, weight_row + t * (kBlockColumns / 2), (k % kBlockColumns) / 2);
    accumulate_block<kRows, kWideCodes>(_mm256_load_si256(reinterpret_cast<const __m256i*>(tail)),
                                        weight_scale_lanes(scales_row, t, group_shift, groups), rows, t, acc[1]);
  }
  for (int r = 0; r < kRows; ++r) sums[r] = reduce_lanes<AddLanes>(_mm256_add_ps(acc[0][r], acc[1][r]));
}

// ---- row kernels, act_bits 16 -------------------------------------------------------------------------

// Columns rounded up to whole groups: the row pitch of the act_bits 16 operands (zero past k).
inline int64_t group_padded(int64_t k, int group_size) { return group_count(k, group_size) * group_size; }

// act_bits 16 row operand: x in fp32, each 16 columns stored as the 8 even then the 8 odd ones.
template <typename Element>
std::vector<float> deinterleave_activations(const Element* x, int64_t m, int64_t k, int group_size) {
  const int64_t pitch = group_padded(k, group_size);
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

// The exact fp32 codes of 8 packed bytes (16 columns): q_w of the even columns and 16 q_w of the odd ones.
inline void fp32_weight_codes(const uint8_t* packed, __m256& even, __m256& odd_times16) {
  const __m256i lanes = _mm256_xor_si256(_mm256_cvtepu8_epi32(_mm_loadl_epi64(reinterpret_cast<const __m128i*>(packed))),
                                         _mm256_set1_epi32(0x4B000088));
  even = _mm256_sub_ps(_mm256_castsi256_ps(_mm256_and_si256(lanes, _mm256_set1_epi32(0x4B00000F))),
                       _mm256_set1_ps(8388616.0f));  // 2^23 + 8
  odd_times16 = _mm256_sub_ps(_mm256_castsi256_ps(_mm256_and_si256(lanes, _mm256_set1_epi32(0x4B0000F0))),
                              _mm256_set1_ps(8388736.0f));  // 2^23 + 128
}

// sums[r] = y[r] (without bias) for one weight row and kRows fp32 activation rows (deinterleaved,
// group_padded). One row alone gets four accumulator chains (two 16-column chunks, even and odd),
// several rows two each.
template <int kRows>
void fp32_row_kernel(const uint8_t* weight_row, const float* scales_row, int64_t k, int group_size,
                     const float* const* rows, float* sums) {
  constexpr int kChains = kRows == 1 ? 4 : 2;  // chain c takes the even (c even) or odd columns
  const int64_t groups = group_count(k, group_size);
  __m256 total[kRows];
  for (int r = 0; r < kRows; ++r) total[r] = _mm256_setzero_ps();
  alignas(16) uint8_t tail[64];  // the last group's bytes when it is partial, zero past k
  for (int64_t g = 0; g < groups; ++g) {
    const int64_t first = g * group_size;
    const uint8_t* packed = weight_row + first / 2;
    if (first + group_size > k) {
      std::memset(tail, 0, sizeof(tail));
      std::memcpy(tail, packed, (k - first) / 2);
      packed = tail;
    }
    __m256 acc[kRows][kChains];
    for (int r = 0; r < kRows; ++r) {
      for (int c = 0; c < kChains; ++c) acc[r][c] = _mm256_setzero_ps();
    }
    for (int64_t c = 0; c < group_size; c += 2 * kChunkColumns) {
      _mm_prefetch(reinterpret_cast<const char*>(weight_row + (first + c) / 2 + kPrefetchBytes), _MM_HINT_T0);
      __m256 w[4];
      fp32_weight_codes(packed + c / 2, w[0], w[1]);
      fp32_weight_codes(packed + c / 2 + 8, w[2], w[3]);
      for (int r = 0; r < kRows; ++r) {
        const float* x = rows[r] + first + c;
        for (int j = 0; j < 4; ++j) acc[r][j % kChains] = _mm256_fmadd_ps(w[j], _mm256_loadu_ps(x + 8 * j), acc[r][j % kChains]);
      }
    }
    const __m256 scale = _mm256_broadcast_ss(scales_row + g);
    const __m256 odd_scale = _mm256_mul_ps(scale, _mm256_set1_ps(1.0f / 16));
    for (int r = 0; r < kRows; ++r) {
      __m256 even = acc[r][0], odd = acc[r][1];
      if constexpr (kChains == 4) {
        even = _mm256_add_ps(even, acc[r][2]);
        odd = _mm256_add_ps(odd, acc[r][3]);
      }
      total[r] = _mm256_add_ps(total[r], _mm256_fmadd_ps(even, scale, _mm256_mul_ps(odd, odd_scale)));
    }
  }
  for (int r = 0; r < kRows; ++r) sums[r] = reduce_lanes<AddLanes>(total[r]);
}

#include "gemm/gemm_cpu_row_tiles.inc"

template <int kBits, typename Element>
void gemm_typed(const Element* x, const uint8_t* qweight, const float* scales, const Element* bias, int64_t m,
                int64_t n, int64_t k, int group_size, Element* out) {
  if constexpr (ActivationTraits<kBits>::kQuantized) {
    const int64_t blocks = (k + kBlockColumns - 1) / kBlockColumns;
    const std::vector<DecodeBlock> activations = decode_activations(x, m, k, group_size, kBits);
    run_tiles<kMaxTileRows>(
        qweight, scales, bias, m, n, k, group_size, out, [&](int64_t r) { return activations.data() + r * blocks; },
        [&](auto tile_rows, const uint8_t* weight_row, const float* scales_row, const DecodeBlock* const* rows,
            float* sums) {
          decode_int_kernel<decltype(tile_rows)::value, kBits == 8>(weight_row, scales_row, k, group_size, rows, sums);
        });
  } else {
    const int64_t pitch = group_padded(k, group_size);
    const std::vector<float> activations = deinterleave_activations(x, m, k, group_size);
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
