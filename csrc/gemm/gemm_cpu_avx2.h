// The AVX2 GEMM behind dyq::cpu::gemm on x86-64 CPUs without AVX-512 VNNI (docs/numerics.md, section 3),
// compiled twice: as the avx2 path, and as the avx_vnni one (DYQ_AVX2_HAS_VNNI, cpu/isa_region.h), where
// one vpdpbusd adds the products of 4 u8 and 4 s8 bytes into each int32 lane. That replaces vpmaddubsw's
// 16-bit pairs, their additions and the vpmaddwd that widens them: the row kernels spend two instructions
// on an activation row and a 32-byte load where they spent five (four where they spent seven at act_bits
// 8), and the panels one per quad of columns and vector where they spent about two. Both form the same
// exact integer sums and share the rest of the arithmetic, so the two paths' outputs agree bit for bit
// (tests/cpp/test_gemm.cpp).
//
// Packed weights are rows of K / 2 bytes, byte j holding column 2j in its low nibble and column 2j + 1 in
// its high one, each a two's-complement code q_w in [-8, 7]. Two kinds of kernel read them:
//
// Row kernels, for the few activation rows below use_panels' threshold (decode). The work is one stream
// over the packed weights, so they spend as few instructions as they can per 32-byte load, keep several
// independent accumulators (an FMA's latency is longer than the work between two of a chain's FMAs) and
// prefetch the bytes kPrefetchBytes ahead, which, rows being adjacent, runs on into the next weight rows. Each
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
//   lane holds exactly P of docs/numerics.md; it is converted to fp32 and multiplied by s_x * s_w. With
//   VNNI the same operands go through vpdpbusd, the offsets as its starting sums, as on the AVX-512 path.
// - act_bits 16: 8 packed bytes (16 columns) are widened to int32 lanes and turned into exact fp32
//   codes without a conversion: XOR-ing 0x4B000088 into a lane sets the exponent of 2^23 above the two
//   offset codes u, so masking with 0x4B00000F gives the float 2^23 + u_even and with 0x4B0000F0 the
//   float 2^23 + 16 u_odd, and subtracting 2^23 + 8 (2^23 + 128) leaves q_w (16 q_w) exactly. x is
//   stored as the 8 even then the 8 odd columns of every 16 to match; the even and the odd columns sum
//   in separate accumulators, and each group's partial sums are scaled once, the odd ones by s_w / 16
//   (a power of two: the same sum, scaled exactly).
//
// Panel path, from use_panels' threshold on (prefill). The weights of kPanelOutputs = 16 output rows are
// decoded once per slice of columns into a small buffer that stays in L1 / L2 (IntWeightPanel,
// Fp32WeightPanel) and reused by register-blocked micro-kernels over every activation row:
// - act_bits 2/4/8: s8 codes, 4 consecutive columns of one output per int32 lane (8 outputs per
//   vector), and 4 rows x 16 outputs of int32 accumulators. The u8 codes q_x of 4 columns are broadcast
//   and vpmaddubsw'd with the s8 codes; four of those added in 16 bits stay below 4 * 2 * 255 * 8 <
//   2^15, then one vpmaddwd with ones adds them into the accumulators. Per group P = sum q_x q_w -
//   z_x sum q_w, the second term in fp32 (integers below 2^24: exact), scaled by s_x * s_w. With VNNI one
//   vpdpbusd per quad and vector adds the products into the accumulators directly.
// - act_bits 16: fp32 codes, one column of 16 outputs per two vectors, and 6 rows x 16 outputs of FMA
//   accumulators, each group's partial sum scaled by s_w once.
//
// K need only be even. A row kernel reads a weight row's last, partial block or group from a padded
// copy against activation codes or values of 0 past K, and the panels decode the columns past K as
// code 0, so the last group, which holds the remainder when G does not divide K, sums only its own
// columns (docs/numerics.md, section 4).
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
#include "common/scratch.h"
#include "cpu/isa_region.h"
#include "cpu/x86_ops.h"
#include "parallel/parallel.h"

DYQ_ISA_BEGIN
namespace dyq::cpu::DYQ_ISA_NAMESPACE {

constexpr int64_t kBlockColumns = 64;     // columns in 32 bytes of packed weights
constexpr int64_t kChunkColumns = 16;     // act_bits 16: columns in 8 bytes of packed weights
constexpr int kMaxTileRows = 4;           // activation rows that share one pass over a weight row
// How far ahead of its loads a row kernel prefetches, into L2: on the AMD EPYC (Zen 4) forced to this path,
// 1 KiB ahead into L1 left the integer kernels' cold M = 1 decode of the Llama-7B shapes at 44 to 61 % of
// the streaming read on one thread (45 to 57 % on two), 4 KiB into L2 reached 70 to 86 % (79 to 102 %);
// 8 KiB, with the two-row kernels' sweep over the next rows at least 16 KiB ahead (kSweepAheadBytes), took
// W4A8 from 12.4-15.5 to 15.0-15.7 GB/s on one thread and from 25.8-29.5 to 29.3-30.9 on two in alternating
// runs (W4A16 unchanged, bound by its arithmetic at 9 GB/s on one thread there). No AVX2-only CPU was
// measured.
constexpr int64_t kPrefetchBytes = 8192;
constexpr int64_t kSweepAheadBytes = 16384;

#if defined(DYQ_AVX2_HAS_VNNI)
// acc + the sum of the products of 4 u8 bytes of u and 4 s8 bytes of s in each int32 lane (vpdpbusd), in
// the encoding of the path's region (cpu/isa_region.h).
inline __m256i dot_u8s8(__m256i acc, __m256i u, __m256i s) {
#if defined(DYQ_AVX2_VNNI_EVEX)
  return _mm256_dpbusd_epi32(acc, u, s);
#else
  return _mm256_dpbusd_avx_epi32(acc, u, s);
#endif
}
#endif

// ---- row kernels, act_bits 2/4/8 --------------------------------------------------------------------

// 64 columns of one activation row for the integer row kernel: 96 bytes, the per-group parameters apart
// (DecodeActivations), so that a row takes 16.5 KiB at K = 11008 rather than the 38.5 KiB it took with
// s_x and z_x of each lane in every block (224 bytes), more than a 32 KiB L1, which the weights also stream
// through.
struct alignas(32) DecodeBlock {
  uint8_t even_codes[32];  // columns 0, 2, ..., 62: a = q_x - z_x as s8 (act_bits 2/4) or q_x (act_bits 8)
  uint8_t odd_codes[32];   // columns 1, 3, ..., 63
  int32_t offsets[8];      // -8 * sum of (q_x - z_x) over lane i's columns 8i..8i+7 (0 past k)
};

// act_bits 8 at G = 32, whose blocks hold two groups: z_x of lane i's group in each byte (0 past k).
struct alignas(32) ZeroLanes {
  uint32_t bytes[8];
};

// An activation row as the integer row kernel reads it.
struct DecodeRow {
  const DecodeBlock* blocks;
  const float* scales;          // s_x per group
  const uint32_t* zero_words;   // act_bits 8: z_x of each group in each byte
  const ZeroLanes* zero_lanes;  // act_bits 8 at G = 32: per block
};

struct DecodeActivations {
  std::vector<DecodeBlock> blocks;    // [m][ceil(k / 64)], zero past k
  std::vector<float> scales;          // [m][groups]
  std::vector<uint32_t> zero_words;   // [m][groups], act_bits 8
  std::vector<ZeroLanes> zero_lanes;  // [m][ceil(k / 64)], act_bits 8 at G = 32
  int64_t blocks_per_row = 0, groups = 0;
  DecodeRow row(int64_t r) const {
    return {blocks.data() + r * blocks_per_row, scales.data() + r * groups,
            zero_words.empty() ? nullptr : zero_words.data() + r * groups,
            zero_lanes.empty() ? nullptr : zero_lanes.data() + r * blocks_per_row};
  }
};

// The m rows of x quantized for the integer row kernel.
template <typename Element>
DecodeActivations decode_activations(const Element* x, int64_t m, int64_t k, int group_size, int act_bits) {
  DecodeActivations out;
  out.blocks_per_row = (k + kBlockColumns - 1) / kBlockColumns;
  out.groups = group_count(k, group_size);
  const int64_t blocks = out.blocks_per_row;
  const bool centred = act_bits != 8;
  const int group_shift = __builtin_ctz(group_size);  // group sizes are powers of two, at least 8 (a lane)
  out.blocks.resize(m * blocks);
  out.scales.resize(m * out.groups);
  if (!centred) {
    out.zero_words.resize(m * out.groups);
    if (group_size < kBlockColumns) out.zero_lanes.resize(m * blocks);
  }
  parallel_for(0, m, 4, [&](int64_t row_begin, int64_t row_end) {
    std::vector<float> row(k);
    std::vector<uint8_t> codes(k);
    std::vector<ActivationGroupParams> params(out.groups);
    for (int64_t r = row_begin; r < row_end; ++r) {
      quantize_activation_row(x + r * k, k, group_size, act_bits, row.data(), codes.data(), params.data());
      for (int64_t g = 0; g < out.groups; ++g) {
        out.scales[r * out.groups + g] = params[g].scale;
        if (!centred) out.zero_words[r * out.groups + g] = static_cast<uint32_t>(params[g].zero) * 0x01010101u;
      }
      // Lane by lane (8 columns, inside one group): the group's parameters once, then its columns.
      for (int64_t t = 0; t < blocks; ++t) {
        DecodeBlock& block = out.blocks[r * blocks + t];
        for (int lane = 0; lane < 8; ++lane) {
          const int64_t begin = t * kBlockColumns + 8 * lane;
          const int columns = static_cast<int>(std::clamp<int64_t>(k - begin, 0, 8));  // before k
          const int zero = columns > 0 ? params[begin >> group_shift].zero : 0;
          int32_t sum = 0;
          for (int j = 0; j < 8; ++j) {
            const int code = j < columns ? codes[begin + j] : 0;
            const int value = j < columns && centred ? code - zero : code;  // the stored code: 0 past k
            sum += j < columns ? code - zero : 0;
            (j % 2 == 0 ? block.even_codes : block.odd_codes)[4 * lane + j / 2] = static_cast<uint8_t>(value);
          }
          block.offsets[lane] = -8 * sum;
          if (!out.zero_lanes.empty()) out.zero_lanes[r * blocks + t].bytes[lane] = static_cast<uint32_t>(zero) * 0x01010101u;
        }
      }
    }
  });
  return out;
}

// The lanes' values of a per-group array for block t (lane i: columns 8i..8i+7): for G >= 64 those of
// group `group`, the block's; for G = 32 (kTwoGroups) lanes 0-3 and 4-7 belong to groups 2t and 2t + 1,
// which the array holds (zero past the last group, where the row's last block ends before it).
template <bool kTwoGroups>
inline __m256 group_lanes(const float* per_group, int64_t t, int64_t group) {
  if constexpr (kTwoGroups) {
    return _mm256_set_m128(_mm_broadcast_ss(per_group + 2 * t + 1), _mm_broadcast_ss(per_group + 2 * t));
  } else {
    return _mm256_broadcast_ss(per_group + group);
  }
}

// products[r * pitch + g] = s_w[g] * s_x[r][g] for every group, zero from `groups` to the pitch, for one
// weight row and kRows activation rows: formed once per weight row, 8 groups an instruction, so that each
// block multiplies its lanes' P by one broadcast rather than by s_w and s_x apart (the same fp32 product).
template <int kRows>
void group_products(const float* scales_row, int64_t groups, const DecodeRow* rows, float* products, int64_t pitch) {
  for (int r = 0; r < kRows; ++r) {
    int64_t g = 0;
    for (; g + 8 <= groups; g += 8) {
      _mm256_storeu_ps(products + r * pitch + g,
                       _mm256_mul_ps(_mm256_loadu_ps(scales_row + g), _mm256_loadu_ps(rows[r].scales + g)));
    }
    for (; g < pitch; ++g) products[r * pitch + g] = g < groups ? scales_row[g] * rows[r].scales[g] : 0.0f;
  }
}

// Groups of a weight row rounded up for group_products: past the last one, the second group of a G = 32
// block that the row ends before.
inline int64_t products_pitch(int64_t groups) { return groups + 2; }

// acc[r] += s_x s_w P of each lane of block t, for kRows activation rows and the block's 32 packed bytes;
// products: the weight row's s_w s_x per group of each activation row, `pitch` apart, or with
// kInlineProducts (G >= 64) the weight row's s_w per group, multiplied here by each row's s_x; `group`: the
// block's (G >= 64).
template <int kRows, bool kWideCodes, bool kTwoGroups, bool kInlineProducts>
inline void accumulate_block(__m256i packed, const float* products, int64_t pitch, const DecodeRow* rows,
                             int64_t t, int64_t group, __m256* acc) {
  static_assert(!(kInlineProducts && kTwoGroups), "a block of two groups takes its products from group_products");
  const __m256i low_nibbles = _mm256_set1_epi8(0x0F);
  const __m256i u = _mm256_xor_si256(packed, _mm256_set1_epi8(static_cast<char>(0x88)));
  const __m256i even = _mm256_and_si256(u, low_nibbles);
  const __m256i odd = _mm256_and_si256(_mm256_srli_epi16(u, 4), low_nibbles);
  [[maybe_unused]] const __m256i both = kWideCodes ? _mm256_add_epi8(even, odd) : even;  // u sums: below 31
  [[maybe_unused]] const __m256i ones = _mm256_set1_epi16(1);
  for (int r = 0; r < kRows; ++r) {
    const DecodeBlock& block = rows[r].blocks[t];
    const __m256i a_even = _mm256_load_si256(reinterpret_cast<const __m256i*>(block.even_codes));
    const __m256i a_odd = _mm256_load_si256(reinterpret_cast<const __m256i*>(block.odd_codes));
    const __m256i offsets = _mm256_load_si256(reinterpret_cast<const __m256i*>(block.offsets));
    // z_x in every byte of every lane (act_bits 8): the lanes past k multiply u = 0.
    [[maybe_unused]] __m256i zero_bytes;
    if constexpr (kWideCodes) {
      zero_bytes = kTwoGroups ? _mm256_load_si256(reinterpret_cast<const __m256i*>(rows[r].zero_lanes[t].bytes))
                              : _mm256_set1_epi32(static_cast<int>(rows[r].zero_words[group]));
    }
#if defined(DYQ_AVX2_HAS_VNNI)
    __m256i dot;  // P of each lane, as on the AVX-512 path
    if constexpr (kWideCodes) {
      dot = dot_u8s8(dot_u8s8(offsets, a_even, even), a_odd, odd);
      dot = _mm256_sub_epi32(dot, dot_u8s8(_mm256_setzero_si256(), zero_bytes, both));
    } else {
      dot = dot_u8s8(dot_u8s8(offsets, even, a_even), odd, a_odd);
    }
#else
    __m256i pairs;  // exact sums of 4 columns
    if constexpr (kWideCodes) {
      pairs = _mm256_add_epi16(_mm256_maddubs_epi16(a_even, even), _mm256_maddubs_epi16(a_odd, odd));
      pairs = _mm256_sub_epi16(pairs, _mm256_maddubs_epi16(zero_bytes, both));
    } else {
      pairs = _mm256_add_epi16(_mm256_maddubs_epi16(even, a_even), _mm256_maddubs_epi16(odd, a_odd));
    }
    const __m256i dot = _mm256_add_epi32(_mm256_madd_epi16(pairs, ones), offsets);
#endif
    const __m256 product = kInlineProducts
                               ? _mm256_mul_ps(_mm256_broadcast_ss(products + group), _mm256_broadcast_ss(rows[r].scales + group))
                               : group_lanes<kTwoGroups>(products + r * pitch, t, group);
    acc[r] = _mm256_fmadd_ps(_mm256_cvtepi32_ps(dot), product, acc[r]);
  }
}

// Weight rows per call of the integer row kernel with kRows activation rows: two at once share the
// activation loads and the per-call set-up, which for short weight rows cost more than their blocks (as on
// the AVX-512 path; on the AMD EPYC forced to AVX2, M = 1 of a 768 x 256 layer at A8 10.4 -> 9.4 us). Four,
// as on AVX-512, were no faster there and 3 to 5 % slower on hot Llama-7B rows at A8, whose wider codes
// leave fewer of the 16 vector registers.
constexpr int decode_columns(int rows) { return rows <= 2 ? 2 : 1; }

// One activation row against weight rows of at most this many groups (G >= 64) forms each block's
// s_w * s_x in the loop rather than storing them all before it, as on the AVX-512 path
// (gemm/gemm_cpu_avx512.h). M = 1, in cache, one thread, the AMD EPYC forced to this path (a C++ loop, the
// two forms alternating in one process; outputs bit for bit the same): on `avx2` 768 x 256 1.25x faster at
// A8 and 1.51x at A4, 256 x 768 1.15x and 1.13x, 4096 x 1024 1.06x and 1.10x; on `avx_vnni` 1.39x and
// 1.46x, 1.11x and 1.15x, 1.06x and 1.10x.
constexpr int64_t kInlineProductMaxGroups = 8;

// sums[c * kRows + r] = y[r] (without bias) of weight row c, for kCols consecutive weight rows (row c at
// weight_rows + c * k / 2, its scales at scales_rows + c * groups) and kRows integer activation rows. One
// weight row alone alternates two accumulators per activation row between the even and the odd blocks;
// several rows' accumulators are independent chains already.
template <int kRows, int kCols, bool kWideCodes, bool kTwoGroups>
void decode_int_kernel(const uint8_t* weight_rows, const float* scales_rows, int64_t k, int group_size,
                       const DecodeRow* rows, float* sums) {
  constexpr int kChains = kCols == 1 ? 2 : 1;
  const int64_t groups = group_count(k, group_size);
  const int group_shift = __builtin_ctz(group_size);
  const int64_t row_bytes = k / 2;
  const int64_t pitch = products_pitch(groups);
  const bool inline_products = kRows == 1 && !kTwoGroups && groups <= kInlineProductMaxGroups;
  float* products = nullptr;  // [c][r][group]
  if (!inline_products) {
    products = scratch_floats(kCols * kRows * pitch);
    for (int c = 0; c < kCols; ++c) {
      group_products<kRows>(scales_rows + c * groups, groups, rows, products + c * kRows * pitch, pitch);
    }
  }
  const int64_t full_blocks = k / kBlockColumns;
  __m256 acc[kChains][kCols][kRows];
  for (auto& chain : acc) {
    for (auto& column : chain) {
      for (__m256& value : column) value = _mm256_setzero_ps();
    }
  }
  // Block t of every weight row into the accumulators of `chain`; `tail`: the rows' last, partial block,
  // whose bytes past k read as u = 0 (nibbles 8), so that they add nothing to z_x * sum(u) (their
  // activation codes are 0).
  // Unrolled, so that the accumulators stay registers: indexed in a loop, GCC kept them on the stack, a load
  // and a store around every multiply-add.
  auto accumulate = [&](int64_t t, int chain, bool tail, auto products_inline) __attribute__((always_inline)) {
    constexpr bool kInline = decltype(products_inline)::value && !kTwoGroups;
    const int64_t group = (t * kBlockColumns) >> group_shift;  // the block's, for G >= 64
#pragma GCC unroll 4
    for (int c = 0; c < kCols; ++c) {
      const uint8_t* packed = weight_rows + c * row_bytes + t * (kBlockColumns / 2);
      alignas(32) uint8_t tail_bytes[32];
      if (tail) {
        std::memset(tail_bytes, 0x88, sizeof(tail_bytes));
        std::memcpy(tail_bytes, packed, (k % kBlockColumns) / 2);
        packed = tail_bytes;
      }
      accumulate_block<kRows, kWideCodes, kTwoGroups, kInline>(
          _mm256_loadu_si256(reinterpret_cast<const __m256i*>(packed)),
          kInline ? scales_rows + c * groups : products + c * kRows * pitch, pitch, rows, t, group, acc[chain][c]);
    }
  };
  // Every block of the rows, the full ones in steps of kChains, then the partial last one.
  auto sweep = [&](auto products_inline) __attribute__((always_inline)) {
    int64_t t = 0;
    for (; t + kChains <= full_blocks; t += kChains) {
      if constexpr (kCols == 1) {
        _mm_prefetch(reinterpret_cast<const char*>(weight_rows + t * (kBlockColumns / 2) + kPrefetchBytes),
                     _MM_HINT_T1);
      } else {  // the next rows in one sweep: the kCols / 2 lines this step reads of its own rows
        for (int line = 0; line < kCols / 2; ++line) {
          prefetch_next_rows<_MM_HINT_T1, kSweepAheadBytes>(weight_rows, kCols * row_bytes,
                                                            t * kCols * (kBlockColumns / 2) + 64 * line);
        }
      }
#pragma GCC unroll 2
      for (int chain = 0; chain < kChains; ++chain) accumulate(t + chain, chain, false, products_inline);
    }
    if (t < full_blocks) accumulate(t++, 0, false, products_inline);
    if (k % kBlockColumns != 0) accumulate(t, kChains - 1, true, products_inline);
  };
  if (inline_products) {
    sweep(std::true_type{});
  } else {
    sweep(std::false_type{});
  }
  for (int c = 0; c < kCols; ++c) {
    for (int r = 0; r < kRows; ++r) {
      __m256 total = acc[0][c][r];
      for (int chain = 1; chain < kChains; ++chain) total = _mm256_add_ps(total, acc[chain][c][r]);
      sums[c * kRows + r] = reduce_lanes<AddLanes>(total);
    }
  }
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
// several rows two each. The group size is a template argument, so that a group's steps unroll into
// straight code (M = 1 on the AMD EPYC forced to AVX2, 4096 x 4096 in cache: G = 128 0.863 -> 0.791 ms,
// G = 64 1.03 -> 0.90, G = 32 1.39 -> 1.12; three rows within 2 % but G = 32, 2.27 -> 2.14).
template <int kRows, int kGroupSize>
void fp32_row_kernel(const uint8_t* weight_row, const float* scales_row, int64_t k, const float* const* rows,
                     float* sums) {
  constexpr int kChains = kRows == 1 ? 4 : 2;  // chain c takes the even (c even) or odd columns
  // One activation row keeps the even and the odd columns' scaled sums apart, so that each group adds its
  // two in a multiply-add each (M = 1 on the AMD EPYC forced to AVX2, 4096 x 4096 in cache: 0.914-0.922 ->
  // 0.863-0.866 ms at G = 128, 1.06-1.08 -> 1.03 at G = 64). With three rows the three more accumulators
  // did not fit the 16 registers (G = 32: 2.27 -> 2.56-2.59 ms).
  constexpr bool kOddTotals = kRows == 1;
  const int64_t groups = group_count(k, kGroupSize);
  __m256 total[kRows];
  [[maybe_unused]] __m256 odd_total[kRows];
  for (int r = 0; r < kRows; ++r) total[r] = odd_total[r] = _mm256_setzero_ps();
  alignas(16) uint8_t tail[64];  // the last group's bytes when it is partial, zero past k
  for (int64_t g = 0; g < groups; ++g) {
    const int64_t first = g * kGroupSize;
    const uint8_t* packed = weight_row + first / 2;
    if (first + kGroupSize > k) {
      std::memset(tail, 0, sizeof(tail));
      std::memcpy(tail, packed, (k - first) / 2);
      packed = tail;
    }
    __m256 acc[kRows][kChains];
    for (int r = 0; r < kRows; ++r) {
      for (int c = 0; c < kChains; ++c) acc[r][c] = _mm256_setzero_ps();
    }
    for (int64_t c = 0; c < kGroupSize; c += 2 * kChunkColumns) {
      if ((first + c) % 128 == 0) {  // once per 64-byte line
        _mm_prefetch(reinterpret_cast<const char*>(weight_row + (first + c) / 2 + kPrefetchBytes), _MM_HINT_T1);
      }
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
      if constexpr (kOddTotals) {
        total[r] = _mm256_fmadd_ps(even, scale, total[r]);
        odd_total[r] = _mm256_fmadd_ps(odd, odd_scale, odd_total[r]);
      } else {
        total[r] = _mm256_add_ps(total[r], _mm256_fmadd_ps(even, scale, _mm256_mul_ps(odd, odd_scale)));
      }
    }
  }
  for (int r = 0; r < kRows; ++r) {
    sums[r] = reduce_lanes<AddLanes>(kOddTotals ? _mm256_add_ps(total[r], odd_total[r]) : total[r]);
  }
}

#include "gemm/gemm_cpu_row_tiles.inc"

// ---- panel path ---------------------------------------------------------------------------------------

constexpr int64_t kPanelOutputs = 16;  // weight rows (outputs) per panel: two vectors of 8

// A vector's worth of bytes, as an element of std::vector (aligned by C++17's aligned new).
struct alignas(32) VectorBytes {
  uint8_t bytes[32];
};

// The 16 bytes (32 columns) of weight row `row` from `column` on; past n or k they read as 0.
inline __m128i load_weight_chunk(const uint8_t* qweight, int64_t n, int64_t k, int64_t row, int64_t column) {
  if (row >= n || column >= k) return _mm_setzero_si128();
  const uint8_t* packed = qweight + row * (k / 2) + column / 2;
  if (k - column >= 32) return _mm_loadu_si128(reinterpret_cast<const __m128i*>(packed));
  alignas(16) uint8_t tail[16] = {};
  std::memcpy(tail, packed, (k - column) / 2);
  return _mm_load_si128(reinterpret_cast<const __m128i*>(tail));
}

// Loads 32 columns of 8 weight rows and transposes them as 16-bit words: on return words[q] holds, in
// word o, the two bytes of output row_begin + o for columns column + 4q .. column + 4q + 3.
inline void load_transposed_words(const uint8_t* qweight, int64_t n, int64_t k, int64_t row_begin, int64_t column,
                                  __m128i words[8]) {
  __m128i t[8], u[8];
  for (int i = 0; i < 8; ++i) t[i] = load_weight_chunk(qweight, n, k, row_begin + i, column);
  for (int i = 0; i < 4; ++i) {
    u[2 * i] = _mm_unpacklo_epi16(t[2 * i], t[2 * i + 1]);
    u[2 * i + 1] = _mm_unpackhi_epi16(t[2 * i], t[2 * i + 1]);
  }
  // u[0]: rows 0-1, words 0-3; u[1]: rows 0-1, words 4-7; u[2], u[3]: rows 2-3; ...
  for (int i = 0; i < 2; ++i) {
    t[4 * i + 0] = _mm_unpacklo_epi32(u[4 * i], u[4 * i + 2]);      // rows 4i..4i+3, words 0-1
    t[4 * i + 1] = _mm_unpackhi_epi32(u[4 * i], u[4 * i + 2]);      // words 2-3
    t[4 * i + 2] = _mm_unpacklo_epi32(u[4 * i + 1], u[4 * i + 3]);  // words 4-5
    t[4 * i + 3] = _mm_unpackhi_epi32(u[4 * i + 1], u[4 * i + 3]);  // words 6-7
  }
  for (int j = 0; j < 4; ++j) {
    words[2 * j] = _mm_unpacklo_epi64(t[j], t[4 + j]);
    words[2 * j + 1] = _mm_unpackhi_epi64(t[j], t[4 + j]);
  }
}

// act_bits 2/4/8: s8 codes of a panel's slice of columns; per group, each output's s_w and sum of codes.
struct IntWeightPanel {
  std::vector<VectorBytes> codes;  // [quad][half]: lane o of half h holds columns 4 quad..+3 of output 8h + o
  std::vector<float> scales;       // [group][16]
  std::vector<float> sums;         // [group][16]

  void pack(const uint8_t* qweight, const float* all_scales, int64_t n, int64_t k, int group_size,
            int64_t row_begin, int64_t col_begin, int64_t depth) {
    const int64_t quads = depth / 4, panel_groups = depth / group_size;
    codes.resize(quads * 2);
    scales.resize(panel_groups * kPanelOutputs);
    sums.resize(panel_groups * kPanelOutputs);
    const __m128i low_nibbles = _mm_set1_epi8(0x0F);
    const __m256i nibble_values =
        _mm256_broadcastsi128_si256(_mm_setr_epi8(0, 1, 2, 3, 4, 5, 6, 7, -8, -7, -6, -5, -4, -3, -2, -1));
    for (int half = 0; half < 2; ++half) {
      for (int64_t c = 0; c < depth; c += 32) {
        __m128i words[8];
        load_transposed_words(qweight, n, k, row_begin + 8 * half, col_begin + c, words);
        for (int q = 0; q < 8; ++q) {
          // Each word's 4 nibbles in column order: low and high nibble of its first byte, then of its second.
          const __m128i low = _mm_and_si128(words[q], low_nibbles);
          const __m128i high = _mm_and_si128(_mm_srli_epi16(words[q], 4), low_nibbles);
          const __m256i nibbles = _mm256_set_m128i(_mm_unpackhi_epi8(low, high), _mm_unpacklo_epi8(low, high));
          _mm256_store_si256(reinterpret_cast<__m256i*>(codes[(c / 4 + q) * 2 + half].bytes),
                             _mm256_shuffle_epi8(nibble_values, nibbles));
        }
      }
    }
    const int64_t quads_per_group = group_size / 4;
    const int64_t first_group = col_begin / group_size, groups = group_count(k, group_size);
    const __m256i ones_u8 = _mm256_set1_epi8(1), ones_s16 = _mm256_set1_epi16(1);
    for (int64_t g = 0; g < panel_groups; ++g) {
      for (int half = 0; half < 2; ++half) {
        __m256i sum = _mm256_setzero_si256();
        for (int64_t q = g * quads_per_group; q < (g + 1) * quads_per_group; ++q) {
          const __m256i quad = _mm256_load_si256(reinterpret_cast<const __m256i*>(codes[q * 2 + half].bytes));
          sum = _mm256_add_epi32(sum, _mm256_madd_epi16(_mm256_maddubs_epi16(ones_u8, quad), ones_s16));
        }
        _mm256_storeu_ps(&sums[g * kPanelOutputs + 8 * half], _mm256_cvtepi32_ps(sum));
      }
      for (int64_t j = 0; j < kPanelOutputs; ++j) {
        const int64_t row = row_begin + j;
        scales[g * kPanelOutputs + j] = row < n ? all_scales[row * groups + first_group + g] : 0.0f;
      }
    }
  }
};

// act_bits 2/4/8 panel operand: q_x per row (zero past k), s_x and z_x per group.
struct PanelCodes {
  std::vector<uint8_t> codes;  // [m][group_padded(k)]
  std::vector<float> scales;   // [m][groups]
  std::vector<float> zeros;    // [m][groups]
  int64_t pitch = 0, groups = 0;
};

template <typename Element>
PanelCodes panel_codes(const Element* x, int64_t m, int64_t k, int group_size, int act_bits) {
  PanelCodes out;
  out.pitch = group_padded(k, group_size);
  out.groups = group_count(k, group_size);
  out.codes.assign(m * out.pitch, 0);
  out.scales.resize(m * out.groups);
  out.zeros.resize(m * out.groups);
  parallel_for(0, m, 4, [&](int64_t row_begin, int64_t row_end) {
    std::vector<float> row(k);
    std::vector<ActivationGroupParams> params(out.groups);
    for (int64_t r = row_begin; r < row_end; ++r) {
      quantize_activation_row(x + r * k, k, group_size, act_bits, row.data(), out.codes.data() + r * out.pitch,
                              params.data());
      for (int64_t g = 0; g < out.groups; ++g) {
        out.scales[r * out.groups + g] = params[g].scale;
        out.zeros[r * out.groups + g] = static_cast<float>(params[g].zero);
      }
    }
  });
  return out;
}

struct IntPanelRow {
  const uint8_t* codes;
  const float* scales;
  const float* zeros;
};

inline __m256i broadcast_quad(const uint8_t* codes) {
  int32_t quad;
  std::memcpy(&quad, codes, 4);
  return _mm256_set1_epi32(quad);
}

// The slice's contribution for activation rows rows[0..kRows), each at the slice's first column and group
// (PanelSums says where it goes). Returns the output lanes that came out inf or NaN.
template <int kRows, typename Element>
unsigned int_panel_kernel(const IntWeightPanel& panel, const IntPanelRow* rows, int64_t depth, int group_size,
                          const PanelSums<Element, kPanelOutputs>& sums) {
  [[maybe_unused]] const __m256i ones = _mm256_set1_epi16(1);
  const int64_t quads_per_group = group_size / 4;
  const auto* codes = reinterpret_cast<const __m256i*>(panel.codes.data());
  const int64_t groups = depth / group_size;
  unsigned nonfinite = 0;
  for (int64_t g = 0; g < groups; ++g) {
    __m256i acc[kRows][2];
    for (int r = 0; r < kRows; ++r) acc[r][0] = acc[r][1] = _mm256_setzero_si256();
#if defined(DYQ_AVX2_HAS_VNNI)
    // Four quads a step, each quad's two vectors of codes against every row's broadcast q_x, straight into
    // the accumulators (exact: int32 sums). One quad a step, GCC copied every accumulator to another
    // register and back each step (W4A4 4096 x 4096 at M = 256, one thread on the AMD EPYC: 33.3 ms against
    // 27.2). Six rows a tile rather than four were no faster there.
    for (int64_t q = g * quads_per_group; q < (g + 1) * quads_per_group; q += 4) {
#pragma GCC unroll 4
      for (int j = 0; j < 4; ++j) {
        const __m256i low = _mm256_load_si256(codes + 2 * (q + j));
        const __m256i high = _mm256_load_si256(codes + 2 * (q + j) + 1);
#pragma GCC unroll 4
        for (int r = 0; r < kRows; ++r) {
          const __m256i x = broadcast_quad(rows[r].codes + 4 * (q + j));
          acc[r][0] = dot_u8s8(acc[r][0], x, low);
          acc[r][1] = dot_u8s8(acc[r][1], x, high);
        }
      }
    }
#else
    for (int64_t q = g * quads_per_group; q < (g + 1) * quads_per_group; q += 4) {
      const __m256i* w = codes + 2 * q;  // w[2 j + h]: quad q + j, outputs 8h..8h+7
      for (int r = 0; r < kRows; ++r) {
        const uint8_t* x = rows[r].codes + 4 * q;
        const __m256i a0 = broadcast_quad(x), a1 = broadcast_quad(x + 4), a2 = broadcast_quad(x + 8),
                      a3 = broadcast_quad(x + 12);
        for (int h = 0; h < 2; ++h) {
          // Four quads summed in 16 bits: at most 4 * 2 * 255 * 8 = 16320.
          const __m256i pairs =
              _mm256_add_epi16(_mm256_add_epi16(_mm256_maddubs_epi16(a0, w[h]), _mm256_maddubs_epi16(a1, w[2 + h])),
                               _mm256_add_epi16(_mm256_maddubs_epi16(a2, w[4 + h]), _mm256_maddubs_epi16(a3, w[6 + h])));
          acc[r][h] = _mm256_add_epi32(acc[r][h], _mm256_madd_epi16(pairs, ones));
        }
      }
    }
#endif
    // The totals stay in memory: registers for them would make the compiler spill the inner loop. Unrolled,
    // so that the accumulators stay registers.
    const bool add_totals = !(sums.first_slice && g == 0), to_output = sums.out != nullptr && g + 1 == groups;
    sums.for_group(add_totals, to_output, [&](auto add, auto store_output) __attribute__((always_inline)) {
#pragma GCC unroll 2
      for (int h = 0; h < 2; ++h) {
        const __m256 weight_scales = _mm256_loadu_ps(&panel.scales[g * kPanelOutputs + 8 * h]);
        const __m256 weight_sums = _mm256_loadu_ps(&panel.sums[g * kPanelOutputs + 8 * h]);
#pragma GCC unroll 4
        for (int r = 0; r < kRows; ++r) {
          // P = sum q_x q_w - z_x sum q_w, exact in fp32 (integers below 2^24).
          const __m256 partial =
              _mm256_fnmadd_ps(weight_sums, _mm256_broadcast_ss(rows[r].zeros + g), _mm256_cvtepi32_ps(acc[r][h]));
          nonfinite |= sums.finish(
              r, 8 * h, _mm256_mul_ps(partial, _mm256_mul_ps(weight_scales, _mm256_broadcast_ss(rows[r].scales + g))),
              add, store_output);
        }
      }
    });
  }
  return nonfinite;
}

struct IntPanel {
  using WeightPanel = IntWeightPanel;
  using Row = IntPanelRow;
  static constexpr int kTileRows = 4;
  static constexpr int64_t kDepth = 1024;  // columns per decoded slice: 16 KB of codes
  static Row advance(Row row, int64_t column, int64_t group) {
    return {row.codes + column, row.scales + group, row.zeros + group};
  }
  template <int kRows, typename Element>
  static unsigned kernel(const WeightPanel& panel, const Row* rows, int64_t depth, int group_size,
                         const PanelSums<Element, kPanelOutputs>& sums) {
    return int_panel_kernel<kRows>(panel, rows, depth, group_size, sums);
  }
};

// act_bits 16: fp32 codes of a panel's slice of columns; each output's s_w per group.
struct Fp32WeightPanel {
  std::vector<VectorBytes> codes;  // [column][half]: lane o of half h is output 8h + o
  std::vector<float> scales;       // [group][16]

  void pack(const uint8_t* qweight, const float* all_scales, int64_t n, int64_t k, int group_size,
            int64_t row_begin, int64_t col_begin, int64_t depth) {
    const int64_t panel_groups = depth / group_size;
    codes.resize(depth * 2);
    scales.resize(panel_groups * kPanelOutputs);
    for (int half = 0; half < 2; ++half) {
      for (int64_t c = 0; c < depth; c += 32) {
        __m128i words[8];
        load_transposed_words(qweight, n, k, row_begin + 8 * half, col_begin + c, words);
        for (int q = 0; q < 8; ++q) {
          const __m256i lanes = _mm256_cvtepu16_epi32(words[q]);
          for (int j = 0; j < 4; ++j) {  // nibble j of the word is column 4q + j: to the top, then back down
            const __m256i code = _mm256_srai_epi32(_mm256_slli_epi32(lanes, 28 - 4 * j), 28);
            _mm256_store_ps(reinterpret_cast<float*>(codes[(c + 4 * q + j) * 2 + half].bytes), _mm256_cvtepi32_ps(code));
          }
        }
      }
    }
    const int64_t first_group = col_begin / group_size, groups = group_count(k, group_size);
    for (int64_t g = 0; g < panel_groups; ++g) {
      for (int64_t j = 0; j < kPanelOutputs; ++j) {
        const int64_t row = row_begin + j;
        scales[g * kPanelOutputs + j] = row < n ? all_scales[row * groups + first_group + g] : 0.0f;
      }
    }
  }
};

template <int kRows, typename Element>
unsigned fp32_panel_kernel(const Fp32WeightPanel& panel, const float* const* rows, int64_t depth, int group_size,
                           const PanelSums<Element, kPanelOutputs>& sums) {
  const auto* codes = reinterpret_cast<const float*>(panel.codes.data());
  const int64_t groups = depth / group_size;
  unsigned nonfinite = 0;
  for (int64_t g = 0; g < groups; ++g) {
    __m256 acc[kRows][2];
    for (int r = 0; r < kRows; ++r) acc[r][0] = acc[r][1] = _mm256_setzero_ps();
    for (int64_t c = g * group_size; c < (g + 1) * group_size; ++c) {
      const __m256 low = _mm256_load_ps(codes + 16 * c), high = _mm256_load_ps(codes + 16 * c + 8);
      for (int r = 0; r < kRows; ++r) {
        const __m256 x = _mm256_broadcast_ss(rows[r] + c);
        acc[r][0] = _mm256_fmadd_ps(x, low, acc[r][0]);
        acc[r][1] = _mm256_fmadd_ps(x, high, acc[r][1]);
      }
    }
    const bool add_totals = !(sums.first_slice && g == 0), to_output = sums.out != nullptr && g + 1 == groups;
    sums.for_group(add_totals, to_output, [&](auto add, auto store_output) __attribute__((always_inline)) {
#pragma GCC unroll 2
      for (int h = 0; h < 2; ++h) {
        const __m256 weight_scales = _mm256_loadu_ps(&panel.scales[g * kPanelOutputs + 8 * h]);
#pragma GCC unroll 6
        for (int r = 0; r < kRows; ++r) {
          nonfinite |= sums.finish(r, 8 * h, _mm256_mul_ps(acc[r][h], weight_scales), add, store_output);
        }
      }
    });
  }
  return nonfinite;
}

struct Fp32Panel {
  using WeightPanel = Fp32WeightPanel;
  using Row = const float*;
  static constexpr int kTileRows = 6;
  static constexpr int64_t kDepth = 256;  // columns per decoded slice: 16 KB of codes
  static Row advance(Row row, int64_t column, int64_t) { return row + column; }
  template <int kRows, typename Element>
  static unsigned kernel(const WeightPanel& panel, const Row* rows, int64_t depth, int group_size,
                         const PanelSums<Element, kPanelOutputs>& sums) {
    return fp32_panel_kernel<kRows>(panel, rows, depth, group_size, sums);
  }
};

// Threads split the panels; each decodes a panel's slice of columns once and runs it against every
// activation row. Slices are whole groups (Kind::kDepth is a multiple of every group size). Returns whether
// every output is finite.
template <typename Kind, typename Element, typename ActivationRow>
bool run_panels(ActivationRow&& activation_row, const uint8_t* qweight, const float* scales, const Element* bias,
                int64_t m, int64_t n, int64_t k, int group_size, Element* out) {
  const int64_t panels = (n + kPanelOutputs - 1) / kPanelOutputs;
  const int64_t padded = group_padded(k, group_size);
  FiniteOutputs finite;
  parallel_for(0, panels, 1, [&](int64_t panel_begin, int64_t panel_end) {
    typename Kind::WeightPanel panel;
    std::vector<float> totals(m * kPanelOutputs);  // [m][16]
    std::vector<typename Kind::Row> rows(m);
    for (int64_t p = panel_begin; p < panel_end; ++p) {
      const int64_t row_begin = p * kPanelOutputs;
      const int64_t outputs = std::min(kPanelOutputs, n - row_begin);
      unsigned nonfinite = 0;
      for (int64_t col = 0; col < padded; col += Kind::kDepth) {
        const int64_t depth = std::min(Kind::kDepth, padded - col);
        const bool to_output = outputs == kPanelOutputs && col + depth == padded;
        panel.pack(qweight, scales, n, k, group_size, row_begin, col, depth);
        for (int64_t r = 0; r < m; ++r) rows[r] = Kind::advance(activation_row(r), col, col / group_size);
        for (int64_t r = 0; r < m; r += Kind::kTileRows) {
          const PanelSums<Element, kPanelOutputs> sums{totals.data() + r * kPanelOutputs, col == 0,
                                                       to_output ? out + r * n + row_begin : nullptr, n,
                                                       bias != nullptr ? bias + row_begin : nullptr};
          dispatch_tile_rows<Kind::kTileRows>(static_cast<int>(std::min<int64_t>(Kind::kTileRows, m - r)),
                                              [&](auto tile_rows) {
                                                nonfinite |= Kind::template kernel<decltype(tile_rows)::value>(
                                                    panel, rows.data() + r, depth, group_size, sums);
                                              });
        }
      }
      finite.note(nonfinite == 0);
      if (outputs < kPanelOutputs || padded == 0) {
        finite.note(store_panel_totals<kPanelOutputs>(totals.data(), m, n, padded, row_begin, outputs, bias, out));
      }
    }
  });
  return finite.all();
}

// Whether m activation rows take the panel path rather than the row kernels, which need no packing but pay
// per activation row: on the AMD EPYC forced to this path (alternating runs, one thread) the panels were
// faster from 4 rows on at the integer widths (1.0x to 1.5x at 4, 1.2x to 1.8x at 5, on the Llama-7B and
// the policy's shapes) and from 5 at W4A16 (1.05x to 1.4x). No AVX2-only CPU was measured.
inline bool use_panels(int64_t m, int act_bits) { return m >= (act_bits == kFallbackBits ? 5 : 4); }

// out = x W^T (+ bias) at kBits; returns whether every output is finite.
template <int kBits, typename Element>
bool gemm_typed(const Element* x, const uint8_t* qweight, const float* scales, const Element* bias, int64_t m,
                int64_t n, int64_t k, int group_size, Element* out) {
  if constexpr (ActivationTraits<kBits>::kQuantized) {
    if (use_panels(m, kBits)) {
      return split_panel_rows(m, n, k, IntPanel::kTileRows, kPanelRowSplitRatio, [&](int64_t row_begin, int64_t rows) {
        const PanelCodes activations = panel_codes(x + row_begin * k, rows, k, group_size, kBits);
        return run_panels<IntPanel>(
            [&](int64_t r) {
              return IntPanelRow{activations.codes.data() + r * activations.pitch,
                                 activations.scales.data() + r * activations.groups,
                                 activations.zeros.data() + r * activations.groups};
            },
            qweight, scales, bias, rows, n, k, group_size, out + row_begin * n);
      });
    }
    const DecodeActivations activations = decode_activations(x, m, k, group_size, kBits);
    return run_tiles<kMaxTileRows, decode_columns>(
        qweight, scales, bias, m, n, k, group_size, out, [&](int64_t r) { return activations.row(r); },
        [&](auto tile_rows, auto tile_columns, const uint8_t* weight_rows, const float* scales_rows,
            const DecodeRow* rows, float* sums) {
          constexpr int kRows = decltype(tile_rows)::value, kCols = decltype(tile_columns)::value;
          if (group_size == 32) {
            decode_int_kernel<kRows, kCols, kBits == 8, true>(weight_rows, scales_rows, k, group_size, rows, sums);
          } else {
            decode_int_kernel<kRows, kCols, kBits == 8, false>(weight_rows, scales_rows, k, group_size, rows, sums);
          }
        });
  } else {
    const int64_t pitch = group_padded(k, group_size);
    if (use_panels(m, kBits)) {
      return split_panel_rows(m, n, k, Fp32Panel::kTileRows, kPanelRowSplitRatio, [&](int64_t row_begin, int64_t rows) {
        std::vector<float> activations(rows * pitch, 0.0f);
        parallel_for(0, rows, 16, [&](int64_t first, int64_t last) {
          for (int64_t r = first; r < last; ++r) {
            load_row_fp32(x + (row_begin + r) * k, k, activations.data() + r * pitch);
          }
        });
        return run_panels<Fp32Panel>(
            [&](int64_t r) { return static_cast<const float*>(activations.data() + r * pitch); }, qweight, scales, bias,
            rows, n, k, group_size, out + row_begin * n);
      });
    }
    const std::vector<float> activations = deinterleave_activations(x, m, k, group_size);
    return run_tiles<kMaxTileRows>(
        qweight, scales, bias, m, n, k, group_size, out, [&](int64_t r) { return activations.data() + r * pitch; },
        [&](auto tile_rows, auto, const uint8_t* weight_row, const float* scales_row, const float* const* rows,
            float* sums) {
          constexpr int kRows = decltype(tile_rows)::value;
          dispatch_group_size(group_size, [&](auto group) {
            fp32_row_kernel<kRows, decltype(group)::value>(weight_row, scales_row, k, rows, sums);
          });
        });
  }
}

inline const char* gemm_kernel(int64_t m, int64_t, int, int act_bits) {
  const bool panel = use_panels(m, act_bits);
  if (act_bits == kFallbackBits) return panel ? DYQ_ISA_NAME "/panel-fp32" : DYQ_ISA_NAME "/rows-fp32";
#if defined(DYQ_AVX2_VNNI_EVEX)  // the benchmarks' JSON says which encoding ran
  return panel ? DYQ_ISA_NAME "/panel-vnni-evex" : DYQ_ISA_NAME "/rows-vnni-evex";
#elif defined(DYQ_AVX2_HAS_VNNI)
  return panel ? DYQ_ISA_NAME "/panel-vnni" : DYQ_ISA_NAME "/rows-vnni";
#else
  return panel ? DYQ_ISA_NAME "/panel-maddubs" : DYQ_ISA_NAME "/rows-maddubs";
#endif
}

}  // namespace dyq::cpu::DYQ_ISA_NAMESPACE
DYQ_ISA_END
