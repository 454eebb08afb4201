// The AMX tile loops of the GEMM for many activation rows (docs/numerics.md, section 3), each written once
// over a Tiles type:
// - Tiles: NativeTiles issues the AMX instructions (the "amx" path, cpu/kernels_avx512_amx.cpp), and
//   EmulatedTiles performs the same tile operations in scalar C++, as the instructions define them, so
//   that the blocking, the tile configuration, the panel layouts and the epilogue are tested on every
//   CPU (gemm/gemm_cpu_amx_emulated.h).
// - act_bits 2, 4 and 8 (amx_int8_gemm): AMX-INT8 with the s8 weight codes q_w as the A operand and the
//   activation codes as B, per group of columns: the C tiles hold exact integer sums (below 2^24), which the
//   epilogue scales into fp32 totals, as the VNNI kernels do. AmxInt8 (act_bits 8): tdpbsud with u8 codes
//   q_x, and s_x s_w (sum q_x q_w - z_x sum q_w). AmxInt8Centered (act_bits 2/4): tdpbssd with the centered
//   codes q_x - z_x, which fit s8 below 8 bits, so that the C tiles hold P = sum (q_x - z_x) q_w itself:
//   the epilogue saves the z_x sum q_w term and the panels their sums of q_w.
// - act_bits 16 (amx_bf16_gemm): AMX-BF16 with the dequantized weights bf16(q_w s_w) as A and bf16(x) as B,
//   no per-group epilogue.
// Both take the weights as A so that a panel comes from the packed rows with no transpose: an A tile row is
// columns of one output row, in the order in which a 64-byte load holds their nibbles, and the activations,
// transposed into B tiles once per call, take the same order.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <memory>
#include <type_traits>
#include <vector>

#include "activation/act_quant_cpu_row.h"
#include "common/cpu_dtype.h"
#include "common/format.h"
#include "common/scratch.h"
#include "cpu/isa_region.h"
#include "cpu/x86_ops.h"
#include "parallel/parallel.h"

DYQ_ISA_BEGIN
namespace dyq::cpu::DYQ_ISA_NAMESPACE {

constexpr int64_t kAmxTileRows = 16;      // rows of an A or C tile
constexpr int64_t kAmxRowBlock = 32;      // activation rows per pass: two A tiles
constexpr int64_t kAmxPanelColumns = 32;  // output columns per panel: two B tiles
constexpr int64_t kAmxPanelDepth = 256;   // columns per unpacked slice: a multiple of every group size
constexpr int64_t kAmxMaxStepBytes = 64;  // an A tile row
constexpr int64_t kAmxQuadColumns = 8;    // columns of one quad (one dword of packed weights)
constexpr int64_t kAmxLoadColumns = 128;  // one 64-byte load of a packed row

// The s8 code of column c of a packed weight row.
inline int weight_code(const uint8_t* row, int64_t c) {
  return sign_extend_nibble(c % 2 == 0 ? row[c / 2] & 0xFu : row[c / 2] >> 4);
}

// The bf16 bit pattern of a float, rounded to nearest even (NaN stays NaN), as vcvtneps2bf16 rounds.
inline uint16_t bf16_bits(float value) {
  uint32_t bits;
  std::memcpy(&bits, &value, sizeof(bits));
  if ((bits & 0x7FFFFFFFu) > 0x7F800000u) return static_cast<uint16_t>((bits >> 16) | 0x40u);
  return static_cast<uint16_t>((bits + 0x7FFFu + ((bits >> 16) & 1u)) >> 16);
}

inline float bf16_value(uint16_t bits) {
  const uint32_t wide = uint32_t{bits} << 16;
  float value;
  std::memcpy(&value, &wide, sizeof(value));
  return value;
}

// The bf16 bit pattern of a dequantized weight q_w s_w: the fp32 product rounded to nearest even, a product
// below the smallest normal fp32 read as 0 (as vcvtne2ps2bf16, the packers' instruction, reads it).
inline uint16_t dequantized_bf16_bits(int code, float scale) {
  const float product = static_cast<float>(code) * scale;
  return bf16_bits(std::fabs(product) < 1.17549435e-38f ? 0.0f : product);
}

// The int8 kinds: kCentered stores q_x - z_x as s8 (act_bits 2 and 4, whose codes and zero points are at
// most 15) and multiplies with tdpbssd; otherwise u8 codes q_x with tdpbsud (the s8 weights as A, the u8
// activations as B) and z_x sum q_w in the epilogue.
template <bool kCenteredCodes>
struct AmxInt8Kind {
  static constexpr bool kCentered = kCenteredCodes;
  static constexpr bool kWeightSums = !kCenteredCodes;  // sum q_w per group, for the z_x term
  template <int kC, int kA, int kB, typename Tiles>
  static void product(Tiles& tiles) {
    if constexpr (kCentered) {
      tiles.template dpbssd<kC, kA, kB>();
    } else {
      tiles.template dpbsud<kC, kA, kB>();
    }
  }
};
using AmxInt8 = AmxInt8Kind<false>;
using AmxInt8Centered = AmxInt8Kind<true>;

// The tile registers in memory, with the operations the loop uses, each as the AMX instruction defines it.
struct EmulatedTiles {
  alignas(64) uint8_t tiles[8][16][64];
  int rows[8], bytes[8];

  void configure(int64_t step_bytes) {
    for (int t = 0; t < 4; ++t) rows[t] = 16, bytes[t] = 64;                                // C: 16 x 16 dwords
    for (int t = 4; t < 6; ++t) rows[t] = 16, bytes[t] = static_cast<int>(step_bytes);      // A: 16 rows
    for (int t = 6; t < 8; ++t) rows[t] = static_cast<int>(step_bytes / 4), bytes[t] = 64;  // B: 16 dwords a row
  }
  template <int kTile>
  void zero() {
    std::memset(tiles[kTile], 0, sizeof(tiles[kTile]));
  }
  template <int kTile>
  void load(const void* base, int64_t stride) {
    for (int r = 0; r < rows[kTile]; ++r) std::memcpy(tiles[kTile][r], static_cast<const uint8_t*>(base) + r * stride, bytes[kTile]);
  }
  template <int kTile>
  void store(void* base, int64_t stride) {
    for (int r = 0; r < rows[kTile]; ++r) std::memcpy(static_cast<uint8_t*>(base) + r * stride, tiles[kTile][r], bytes[kTile]);
  }
  // tdpbsud / tdpbssd: C[m][n] += sum over the dwords i of A's row m of sum_b s8 A[m][4i + b] * B[i][4n + b],
  // B's bytes u8 (tdpbsud) or s8 (tdpbssd).
  template <bool kSignedB, int kC, int kA, int kB>
  void dot_bytes() {
    for (int m = 0; m < rows[kA]; ++m) {
      for (int n = 0; n < bytes[kC] / 4; ++n) {
        int32_t sum;
        std::memcpy(&sum, &tiles[kC][m][4 * n], 4);
        for (int i = 0; i < bytes[kA] / 4; ++i) {
          for (int b = 0; b < 4; ++b) {
            const uint8_t b_byte = tiles[kB][i][4 * n + b];
            const int32_t b_value = kSignedB ? int32_t{static_cast<int8_t>(b_byte)} : int32_t{b_byte};
            sum += int32_t{static_cast<int8_t>(tiles[kA][m][4 * i + b])} * b_value;
          }
        }
        std::memcpy(&tiles[kC][m][4 * n], &sum, 4);
      }
    }
  }
  template <int kC, int kA, int kB>
  void dpbsud() {
    dot_bytes<false, kC, kA, kB>();
  }
  template <int kC, int kA, int kB>
  void dpbssd() {
    dot_bytes<true, kC, kA, kB>();
  }
  // tdpbf16ps: for each dword i of A's row m, in order, C[m][n] += A[m][2i] * B[i][2n], then
  // C[m][n] += A[m][2i + 1] * B[i][2n + 1], each product exact and each sum rounded to fp32, with bf16
  // denormal inputs read as 0 and denormal results flushed to 0.
  template <int kC, int kA, int kB>
  void dpbf16ps() {
    auto word = [](const uint8_t* bytes, int index) {
      uint16_t bits;
      std::memcpy(&bits, bytes + 2 * index, 2);
      return (bits & 0x7F80u) == 0 ? 0.0f : bf16_value(bits);
    };
    auto flush = [](float value) { return std::fabs(value) < 1.17549435e-38f ? 0.0f * value : value; };
    for (int m = 0; m < rows[kA]; ++m) {
      for (int n = 0; n < bytes[kC] / 4; ++n) {
        float sum;
        std::memcpy(&sum, &tiles[kC][m][4 * n], 4);
        for (int i = 0; i < bytes[kA] / 4; ++i) {
          sum = flush(sum + word(tiles[kA][m], 2 * i) * word(tiles[kB][i], 2 * n));
          sum = flush(sum + word(tiles[kA][m], 2 * i + 1) * word(tiles[kB][i], 2 * n + 1));
        }
        std::memcpy(&tiles[kC][m][4 * n], &sum, 4);
      }
    }
  }
  void release() {}
};

#if defined(DYQ_AVX512_HAS_AMX)
// The same operations on the AMX tile registers tmm0..tmm7.
struct NativeTiles {
  void configure(int64_t step_bytes) {
    struct alignas(64) {
      uint8_t palette = 1, start_row = 0, reserved[14] = {};
      uint16_t colsb[16] = {};
      uint8_t rows[16] = {};
    } config;
    for (int t = 0; t < 4; ++t) config.colsb[t] = 64, config.rows[t] = 16;
    for (int t = 4; t < 6; ++t) config.colsb[t] = static_cast<uint16_t>(step_bytes), config.rows[t] = 16;
    for (int t = 6; t < 8; ++t) config.colsb[t] = 64, config.rows[t] = static_cast<uint8_t>(step_bytes / 4);
    // ldtilecfg through an operand of the whole 64 bytes: GCC 12's _tile_loadconfig declares a read of only
    // its first 8, so that the compiler may drop the stores of the tiles' shapes before it, which it did once
    // this was inlined into a benchmark (tilezero then raised SIGILL: no tile configured).
    asm volatile("{ldtilecfg %0|ldtilecfg %0}" ::"m"(config));
  }
  // The intrinsics' macros paste their tile argument into the register name, so it must be a literal;
  // the asm below prints the template argument as one (%c) instead. Both dialects, as the macros have.
  template <int kTile>
  void zero() {
    asm volatile("{tilezero %%tmm%c0|tilezero tmm%c0}" ::"i"(kTile));
  }
  template <int kTile>
  void load(const void* base, int64_t stride) {
    asm volatile("{tileloadd (%0,%1,1), %%tmm%c2|tileloadd tmm%c2, [%0+%1*1]}" ::"r"(base), "r"(stride), "i"(kTile)
                 : "memory");
  }
  template <int kTile>
  void store(void* base, int64_t stride) {
    asm volatile("{tilestored %%tmm%c2, (%0,%1,1)|tilestored [%0+%1*1], tmm%c2}" ::"r"(base), "r"(stride), "i"(kTile)
                 : "memory");
  }
  template <int kC, int kA, int kB>
  void dpbsud() {
    asm volatile("{tdpbsud %%tmm%c2, %%tmm%c1, %%tmm%c0|tdpbsud tmm%c0, tmm%c1, tmm%c2}" ::"i"(kC), "i"(kA), "i"(kB));
  }
  template <int kC, int kA, int kB>
  void dpbssd() {
    asm volatile("{tdpbssd %%tmm%c2, %%tmm%c1, %%tmm%c0|tdpbssd tmm%c0, tmm%c1, tmm%c2}" ::"i"(kC), "i"(kA), "i"(kB));
  }
  template <int kC, int kA, int kB>
  void dpbf16ps() {
    asm volatile("{tdpbf16ps %%tmm%c2, %%tmm%c1, %%tmm%c0|tdpbf16ps tmm%c0, tmm%c1, tmm%c2}" ::"i"(kC), "i"(kA),
                 "i"(kB));
  }
  void release() { _tile_release(); }
};
#endif

// Every output its bias (or 0): the product over no column. Returns whether every output is finite.
template <typename Element>
bool bias_outputs(const Element* bias, int64_t m, int64_t n, Element* out) {
  const std::vector<float> zeros(n, 0.0f);
  FiniteOutputs finite;
  for (int64_t r = 0; r < m; ++r) finite.note(store_row_from_fp32(zeros.data(), bias, n, out + r * n));
  return finite.all();
}

// outputs[m][j] = totals[j][m] for the 32 output rows j of a panel and the 32 activation rows m of a
// block ([16, 32) only with `second_half`).
inline void transpose_block_totals(const float* totals, bool second_half, float* outputs) {
  for (int64_t m_half = 0; m_half < (second_half ? 2 : 1); ++m_half) {
    for (int64_t j_half = 0; j_half < 2; ++j_half) {
      const float* from = totals + j_half * kAmxTileRows * kAmxRowBlock + m_half * kAmxTileRows;
      float* to = outputs + m_half * kAmxTileRows * kAmxPanelColumns + j_half * kAmxTileRows;
#if defined(DYQ_CPU_ISA_AVX512)
      __m512i rows[kAmxTileRows];
      for (int j = 0; j < kAmxTileRows; ++j) rows[j] = _mm512_loadu_si512(from + j * kAmxRowBlock);
      transpose_16x16_dwords(rows);
      for (int r = 0; r < kAmxTileRows; ++r) _mm512_storeu_si512(to + r * kAmxPanelColumns, rows[r]);
#else
      for (int j = 0; j < kAmxTileRows; ++j) {
        for (int r = 0; r < kAmxTileRows; ++r) to[r * kAmxPanelColumns + j] = from[j * kAmxRowBlock + r];
      }
#endif
    }
  }
}

#if defined(DYQ_AVX512_HAS_BF16)
// The bf16 outputs of a whole block (32 output rows x 32 activation rows) where no total (plus its bias) is a
// NaN or a denormal, which vcvtne2ps2bf16 reads otherwise than from_float: each output row's 32 totals
// converted into one vector of 32 words, and the 32 x 32 words transposed (8 rows at a time, an 8 x 8
// transpose within each 128-bit lane in three levels of unpacks, then 4 x 4 transposes of the lanes) into the
// activation rows' 64-byte runs: about 200 instructions a block where transposing the fp32 totals, then
// converting and storing them 16 at a time took about 700, a fifth of a W4A8 call of 256 rows of the
// policy's 256 x 256 layer. Returns false, having written nothing, where a total is a NaN or a denormal;
// `finite`: whether every output is finite (a total past bf16's largest value rounds to inf).
inline bool write_block_bf16_words(const float* block_totals, const Eigen::bfloat16* bias, int64_t n,
                                   int64_t row_begin, int64_t weight_row, Eigen::bfloat16* out, bool& finite) {
  constexpr __mmask32 kAll32 = ~__mmask32{0};
  __m512i words[kAmxPanelColumns];  // [output row j]: activation rows 0..31
  __mmask16 unusual = 0;
  for (int j = 0; j < kAmxPanelColumns; ++j) {
    __m512 low = _mm512_load_ps(block_totals + j * kAmxRowBlock);
    __m512 high = _mm512_load_ps(block_totals + j * kAmxRowBlock + kAmxTileRows);
    if (bias != nullptr) {
      const __m512 bias_j = _mm512_set1_ps(to_float(bias[weight_row + j]));
      low = _mm512_add_ps(low, bias_j);
      high = _mm512_add_ps(high, bias_j);
    }
    unusual |= _mm512_fpclass_ps_mask(low, kFpclassNanOrDenormal) | _mm512_fpclass_ps_mask(high, kFpclassNanOrDenormal);
    words[j] = reinterpret_cast<__m512i>(_mm512_cvtne2ps_pbh(high, low));
  }
  if (unusual != 0) return false;
  const __m512i exponent = _mm512_set1_epi16(0x7F80);
  __mmask32 nonfinite = 0;
  for (int j = 0; j < kAmxPanelColumns; ++j) {
    nonfinite |= _mm512_cmpeq_epi16_mask(_mm512_and_si512(words[j], exponent), exponent);
  }
  finite = nonfinite == 0;
  // Output rows 8a..8a+7: afterwards words[8a + c], lane L, holds activation row 8L + c of those 8 rows.
  for (int a = 0; a < 4; ++a) {
    __m512i* v = words + 8 * a;
    __m512i pairs[8], quads[8];
    for (int p = 0; p < 4; ++p) {
      pairs[2 * p] = _mm512_maskz_unpacklo_epi16(kAll32, v[2 * p], v[2 * p + 1]);
      pairs[2 * p + 1] = _mm512_maskz_unpackhi_epi16(kAll32, v[2 * p], v[2 * p + 1]);
    }
    // quads[4 h + i] (h: output rows 0..3 or 4..7 of the eight): two columns of each lane, each as a 4-row run.
    for (int h = 0; h < 2; ++h) {
      const __m512i* t = pairs + 4 * h;
      quads[4 * h] = _mm512_maskz_unpacklo_epi32(kAll16, t[0], t[2]);      // columns 0, 1
      quads[4 * h + 1] = _mm512_maskz_unpackhi_epi32(kAll16, t[0], t[2]);  // columns 2, 3
      quads[4 * h + 2] = _mm512_maskz_unpacklo_epi32(kAll16, t[1], t[3]);  // columns 4, 5
      quads[4 * h + 3] = _mm512_maskz_unpackhi_epi32(kAll16, t[1], t[3]);  // columns 6, 7
    }
    for (int q = 0; q < 4; ++q) {
      v[2 * q] = unpacklo_epi64(quads[q], quads[4 + q]);
      v[2 * q + 1] = unpackhi_epi64(quads[q], quads[4 + q]);
    }
  }
  for (int c = 0; c < 8; ++c) {
    const __m512i* x = words + c;  // x[8 a]: output rows 8a..8a+7
    const __m512i s0 = _mm512_maskz_shuffle_i32x4(kAll16, x[0], x[8], 0x44);
    const __m512i s1 = _mm512_maskz_shuffle_i32x4(kAll16, x[0], x[8], 0xEE);
    const __m512i s2 = _mm512_maskz_shuffle_i32x4(kAll16, x[16], x[24], 0x44);
    const __m512i s3 = _mm512_maskz_shuffle_i32x4(kAll16, x[16], x[24], 0xEE);
    const __m512i rows[4] = {_mm512_maskz_shuffle_i32x4(kAll16, s0, s2, 0x88),
                             _mm512_maskz_shuffle_i32x4(kAll16, s0, s2, 0xDD),
                             _mm512_maskz_shuffle_i32x4(kAll16, s1, s3, 0x88),
                             _mm512_maskz_shuffle_i32x4(kAll16, s1, s3, 0xDD)};
    for (int lane = 0; lane < 4; ++lane) {
      _mm512_storeu_si512(out + (row_begin + 8 * lane + c) * n + weight_row, rows[lane]);
    }
  }
  return true;
}
#endif

// The outputs (plus the bias) of the 32 output rows from weight_row and the block of activation rows from
// row_begin, from the block's totals [output row][activation row]. Returns whether every output is finite.
template <typename Element>
bool write_block_outputs(const float* block_totals, const Element* bias, int64_t m, int64_t n, int64_t row_begin,
                         int64_t weight_row, Element* out) {
#if defined(DYQ_AVX512_HAS_BF16)
  if constexpr (std::is_same_v<Element, Eigen::bfloat16>) {
    bool finite = true;
    if (n - weight_row >= kAmxPanelColumns && m - row_begin >= kAmxRowBlock &&
        write_block_bf16_words(block_totals, bias, n, row_begin, weight_row, out, finite)) {
      return finite;
    }
  }
#endif
  alignas(64) std::array<float, kAmxPanelColumns * kAmxRowBlock> outputs;  // [activation row][output row]
  const int64_t columns = std::min(kAmxPanelColumns, n - weight_row);
  const int64_t block_rows = std::min(kAmxRowBlock, m - row_begin);
  transpose_block_totals(block_totals, block_rows > kAmxTileRows, outputs.data());
  FiniteOutputs finite;
  for (int64_t r = 0; r < block_rows; ++r) {
    finite.note(store_row_from_fp32(&outputs[r * kAmxPanelColumns], bias != nullptr ? bias + weight_row : nullptr,
                                    columns, out + (row_begin + r) * n + weight_row));
  }
  return finite.all();
}

// The C tiles of a block to (kStore) or from a 32 x 32 buffer of dwords [output row][activation row]: C0 and
// C2 (activation rows 0..15), and with second_half C1 and C3 (16..31).
template <bool kStore, typename Tiles>
void move_block_tiles(Tiles& tiles, void* block, bool second_half) {
  constexpr int64_t kStride = kAmxRowBlock * 4;  // bytes between two output rows
  constexpr int64_t kLower = kAmxTileRows * kStride, kRight = kAmxTileRows * 4;
  auto* bytes = static_cast<uint8_t*>(block);
  auto move = [&](auto tile, int64_t offset) {
    if constexpr (kStore) {
      tiles.template store<decltype(tile)::value>(bytes + offset, kStride);
    } else {
      tiles.template load<decltype(tile)::value>(bytes + offset, kStride);
    }
  };
  move(std::integral_constant<int, 0>{}, 0);
  move(std::integral_constant<int, 2>{}, kLower);
  if (second_half) {
    move(std::integral_constant<int, 1>{}, kRight);
    move(std::integral_constant<int, 3>{}, kLower + kRight);
  }
}

// Clears the C tiles of a block: C0 and C2, and with second_half C1 and C3.
template <typename Tiles>
void zero_block_tiles(Tiles& tiles, bool second_half) {
  tiles.template zero<0>();
  tiles.template zero<2>();
  if (second_half) {
    tiles.template zero<1>();
    tiles.template zero<3>();
  }
}

#if defined(DYQ_AVX512_HAS_AMX)
// f(std::integral_constant<int, G>{}) for the group sizes the tile loops take (G divides 128), so that the
// packers' arithmetic of groups within a load is constant.
template <typename F>
void with_group_size(int group_size, F&& f) {
  if (group_size == 32) return f(std::integral_constant<int, 32>{});
  if (group_size == 64) return f(std::integral_constant<int, 64>{});
  f(std::integral_constant<int, 128>{});
}

// The pack() of a native panel (the scalar panels' signature): its pack_rows<G> at the call's group size.
template <typename Panel>
struct PackByGroupSize {
  void pack(const uint8_t* qweight, const float* all_scales, int64_t n, int64_t k, int group_size, int64_t row_begin,
            int64_t col_begin, int64_t depth) {
    with_group_size(group_size, [&](auto group) {
      static_cast<Panel*>(this)->template pack_rows<decltype(group)::value>(qweight, all_scales, n, k, row_begin,
                                                                            col_begin, depth);
    });
  }
};

// The packed bytes of a row's slice two slices on (row: the slice's first byte), which the packers read next:
// the rows of a pass, read 128 bytes a slice each, are more streams than the hardware prefetchers follow
// (without it, W4A16 on 4096 x 4096 at 16 rows took twice as long on the Xeon with AMX; one slice ahead
// was about as fast, 2 % to 10 % slower at 64 and 256 rows).
inline void prefetch_row_ahead(const uint8_t* row, int64_t col_begin, int64_t k) {
  constexpr int64_t kPrefetchSlices = 2;
  if (col_begin + kPrefetchSlices * kAmxPanelDepth < k) {
    const uint8_t* next = row + kPrefetchSlices * kAmxPanelDepth / 2;
    _mm_prefetch(reinterpret_cast<const char*>(next), _MM_HINT_T0);
    _mm_prefetch(reinterpret_cast<const char*>(next + 64), _MM_HINT_T0);
  }
}
#endif

// The activations as B tiles, both loops' layout: for every block of 32 rows and step (one tile product's
// columns), the B tiles of the block's rows 0..15 and 16..31; slice by slice of kAmxPanelDepth columns,
// within a slice block by block, within a block step by step, so that a block's pass over a slice reads one
// run. The rows past m of the last block are 0; a block's second tile with no row below m is not written,
// and the tile loops do not read it.
struct AmxBTiles {
  int64_t blocks = 0, steps = 0;            // steps over the padded columns
  int64_t step_columns = 0, tile_bytes = 0;  // of one step; of one B tile
  std::unique_ptr<uint8_t[]> bytes;

  void allocate(int64_t m, int64_t padded_columns, int64_t columns_per_step, int64_t bytes_per_tile) {
    blocks = (m + kAmxRowBlock - 1) / kAmxRowBlock;
    steps = padded_columns / columns_per_step;
    step_columns = columns_per_step;
    tile_bytes = bytes_per_tile;
    bytes.reset(new uint8_t[blocks * steps * 2 * tile_bytes]);  // every byte the loops read is written
  }
  // The B tile of rows [16 half, 16 half + 16) of `block` at `step`; the block's next step follows its
  // second tile.
  uint8_t* tile(int64_t block, int64_t step, int half) const {
    const int64_t steps_per_slice = kAmxPanelDepth / step_columns;
    const int64_t slice = step / steps_per_slice;
    const int64_t slice_steps = std::min(steps_per_slice, steps - slice * steps_per_slice);
    const int64_t step_index = slice * steps_per_slice * blocks + block * slice_steps + step % steps_per_slice;
    return bytes.get() + (2 * step_index + half) * tile_bytes;
  }
};

// Panels per pass over the activations: the totals of a pass's panels stay in L2 while each slice of the
// activations is read once from memory per pass and from L2 once per panel.
constexpr int64_t kAmxPanelsPerPass = 8;

// The totals a thread keeps ([panel][block][output row][activation row]): those of a whole pass where K takes
// several slices, whose sums each block's totals carry from one slice to the next; where one slice covers K,
// a block's outputs are written as soon as its last group is in, and two blocks' totals taking turns suffice.
// Each block's first group of K stores its totals rather than adding to them, so none are cleared. (A
// pass's totals for 256 rows are 256 KiB: clearing them took 7 % of a W4A8 call on the policy's 768 x 256
// layer, and they pushed the outputs out of L2.)
struct AmxPassTotals {
  static constexpr int64_t kBlockTotals = kAmxPanelColumns * kAmxRowBlock;  // a panel's totals of one block
  static constexpr int64_t kTurns = 2;
  int64_t blocks = 0;
  bool one_slice = false;
  AlignedVector<float> values;

  AmxPassTotals(int64_t pass_size, int64_t row_blocks, int64_t k)
      : blocks(row_blocks), one_slice(k <= kAmxPanelDepth),
        values((one_slice ? kTurns : pass_size * row_blocks) * kBlockTotals) {}

  float* block(int64_t panel_in_pass, int64_t row_block) {
    const int64_t index = panel_in_pass * blocks + row_block;
    return values.data() + (one_slice ? index % kTurns : index) * kBlockTotals;
  }
};

// ---- AMX-INT8: the weights as the A operand ---------------------------------------------------------
//
// At act_bits 2, 4 and 8 the tiles multiply s8 weight codes q_w (A) with the activation codes (B), and each
// group's integer sums are scaled into fp32 totals by the epilogue. An A tile row is step_bytes columns of
// one output row (64, or the group where it is smaller), so that a panel comes from the packed rows with no
// transpose, and which columns make a step is free as long as the activations' B tiles pair the same ones:
// within each load of min(128, G) columns (64 packed bytes, or the group's), the steps take the low nibbles
// of the load's bytes, then their high nibbles (amx_int8_column). So a load of a row is two byte lookups
// (vpermb) and one word shift, where the weights as B had cost a 16 x 16 transpose of dwords for every
// step of 32 output rows, about 0.2 cycles a weight on the Xeon with AMX: most of a call at 16 rows.
//
// Tiles: C0..C3 = output rows (0..15, 16..31 of the panel) x activation rows (0..15, 16..31 of the block);
// A0/A1 = 16 weight rows x step_bytes; B0/B1 = step_bytes / 4 dword rows x 16 activation rows.

// The bytes of an A tile row, and the columns of a step: 64, or the group where it is smaller.
constexpr int64_t amx_int8_step_bytes(int64_t group_size) { return std::min(kAmxMaxStepBytes, group_size); }

// The columns of one load of the int8 kinds' order: 128, or the group where it is smaller.
inline int64_t amx_int8_load_columns(int group_size) { return std::min<int64_t>(kAmxLoadColumns, group_size); }

// The column, past the start of its load of `load_columns`, at position i of the load's order: the even
// columns (the low nibbles of the load's bytes), then the odd ones (their high nibbles).
inline int64_t amx_int8_column(int64_t i, int64_t load_columns) {
  return i < load_columns / 2 ? 2 * i : 2 * (i - load_columns / 2) + 1;
}

// The activations as B tiles (AmxBTiles), each step_bytes / 4 rows of 16 dwords (4 codes of each activation
// row, in amx_int8_column's order: u8 q_x, or s8 q_x - z_x for the centered kind). Columns past k are 0, and
// the rows past m have z_x and s_x 0. z_x and s_x per block and group, the block's 32 rows in a row, as the
// epilogue loads them. At act_bits 8 on 16 rows or fewer (zero_tiles), also per group a B tile row of z_x:
// dword r holds z_x of row r in each of its bytes (zero_row).
struct AmxInt8Activations : AmxBTiles {
  int64_t groups = 0;
  bool zero_tiles = false;
  AlignedVector<float> zeros, scales;  // [block][group][32]
  AlignedVector<uint8_t> zero_rows;    // [group][64], with zero_tiles

  // A B tile of z_x (group g's zero_row, loaded with stride 0 into every tile row).
  const uint8_t* zero_row(int64_t group) const { return zero_rows.data() + group * 64; }

  const float* params(const AlignedVector<float>& values, int64_t block, int64_t group) const {
    return values.data() + (block * groups + group) * kAmxRowBlock;
  }
};

template <typename Kind, typename Element>
AmxInt8Activations amx_int8_activations(const Element* x, int64_t m, int64_t k, int group_size, int act_bits) {
  AmxInt8Activations a;
  a.groups = group_count(k, group_size);
  const int64_t padded = a.groups * group_size;  // columns, zero past k
  const int64_t step_bytes = amx_int8_step_bytes(group_size);
  a.allocate(m, padded, step_bytes, step_bytes / 4 * 64);
  a.zeros.assign(a.blocks * a.groups * kAmxRowBlock, 0.0f);
  a.scales.assign(a.blocks * a.groups * kAmxRowBlock, 0.0f);
  a.zero_tiles = !Kind::kCentered && m <= kAmxTileRows;
  if (a.zero_tiles) a.zero_rows.assign(a.groups * 64, 0);
  const int64_t load_columns = amx_int8_load_columns(group_size);
  const int64_t quads = step_bytes / 4;  // B tile rows
  // The bytes of a load at positions [64 i, 64 i + 64) of its order, as indices into the load's 128 bytes.
  [[maybe_unused]] alignas(64) uint8_t load_order[2][64] = {};
  for (int64_t position = 0; position < load_columns; ++position) {
    load_order[position / 64][position % 64] = static_cast<uint8_t>(amx_int8_column(position, load_columns));
  }
  // B tile by B tile (16 rows): the rows' codes in column order, then each step's bytes in the load order,
  // transposed into the tile's dword rows.
  parallel_for(0, (m + kAmxTileRows - 1) / kAmxTileRows, 1, [&](int64_t tile_begin, int64_t tile_end) {
    std::vector<float> values(std::is_same_v<Element, float> ? 0 : rows_fp32_floats(kAmxTileRows, k));
    AlignedVector<uint8_t> codes(kAmxTileRows * padded);
    std::vector<ActivationGroupParams> params(kAmxTileRows * a.groups);
    for (int64_t t = tile_begin; t < tile_end; ++t) {
      const int64_t first_row = t * kAmxTileRows, rows = std::min(kAmxTileRows, m - first_row);
      std::fill(codes.begin(), codes.end(), uint8_t{0});  // 0 past k and for the rows past m
      quantize_activation_rows(x + first_row * k, rows, k, group_size, act_bits, values.data(), codes.data(), padded,
                               params.data());
      const int64_t block = t / 2, lane_offset = t % 2 * kAmxTileRows;
      for (int64_t r = 0; r < rows; ++r) {
        uint8_t* row_codes = codes.data() + r * padded;
        for (int64_t g = 0; g < a.groups; ++g) {
          const ActivationGroupParams& p = params[r * a.groups + g];
          if constexpr (Kind::kCentered) {
            // q_x - z_x as s8 bytes (the columns past k stay 0). z_x in a local: read through the reference
            // at every byte stored (a byte store may alias it), the loop was not vectorized, and W4A4 took
            // 1.5x W4A8's time on the policy's 256 x 768 layer at 256 rows.
            const int64_t columns = group_columns(k, group_size, g);
            const auto zero = static_cast<uint8_t>(p.zero);
            uint8_t* group_codes = row_codes + g * group_size;
            for (int64_t c = 0; c < columns; ++c) group_codes[c] = static_cast<uint8_t>(group_codes[c] - zero);
          }
          a.zeros[(block * a.groups + g) * kAmxRowBlock + lane_offset + r] = static_cast<float>(p.zero);
          if (a.zero_tiles) std::memset(&a.zero_rows[g * 64 + 4 * r], static_cast<int>(p.zero), 4);
          a.scales[(block * a.groups + g) * kAmxRowBlock + lane_offset + r] = p.scale;
        }
      }
      for (int64_t step = 0; step < a.steps; ++step) {
        const int64_t position = step * step_bytes % load_columns;  // of the step in its load's order
        const int64_t load_begin = step * step_bytes - position;
        uint8_t* tile = a.tile(block, step, static_cast<int>(t % 2));
#if defined(DYQ_CPU_ISA_AVX512)
        // The step's bytes of each row: one two-table byte permute of its load (load_order).
        const __m512i index = _mm512_load_si512(load_order[position / 64]);
        const __mmask64 load_mask = load_columns >= 64 ? ~__mmask64{0} : (__mmask64{1} << load_columns) - 1;
        __m512i dwords[kAmxTileRows];
        for (int64_t lane = 0; lane < kAmxTileRows; ++lane) {
          const uint8_t* load = codes.data() + lane * padded + load_begin;
          const __m512i first = _mm512_maskz_loadu_epi8(load_mask, load);
          const __m512i second = load_columns > 64 ? _mm512_loadu_si512(load + 64) : _mm512_setzero_si512();
          dwords[lane] = _mm512_permutex2var_epi8(first, index, second);
        }
        transpose_16x16_dwords(dwords);
        for (int64_t q = 0; q < quads; ++q) _mm512_storeu_si512(tile + 64 * q, dwords[q]);
#else
        for (int64_t lane = 0; lane < kAmxTileRows; ++lane) {
          const uint8_t* load = codes.data() + lane * padded + load_begin;
          for (int64_t q = 0; q < quads; ++q) {
            for (int b = 0; b < 4; ++b) {
              tile[64 * q + 4 * lane + b] = load[amx_int8_column(position + 4 * q + b, load_columns)];
            }
          }
        }
#endif
      }
    }
  });
  return a;
}

// A panel: 32 output rows x kAmxPanelDepth columns of s8 codes q_w, step by step (amx_int8_column's order),
// within a step row by row, so that an A tile is one run; each group's s_w and, for AmxInt8, sum q_w per
// output row. Rows past n and columns past k are 0. ScalarAmxInt8Panel is the emulation's, in plain C++.
template <typename Kind>
struct AmxInt8PanelLayout {
  static constexpr int64_t kGroups = kAmxPanelDepth / 32;  // at the smallest group size
  alignas(64) int8_t codes[kAmxPanelDepth * kAmxPanelColumns];
  alignas(64) float scales[kGroups * kAmxPanelColumns];       // [group][32]
  alignas(64) float weight_sums[kGroups * kAmxPanelColumns];  // [group][32], AmxInt8 unless zero tiles replace them
  bool with_weight_sums = Kind::kWeightSums;

  // The A tile of output rows [16 half, 16 half + 16) at `step` (of the slice); its rows are step_bytes apart.
  const uint8_t* tile(int64_t step, int64_t step_bytes, int half) const {
    return reinterpret_cast<const uint8_t*>(codes) + (step * kAmxPanelColumns + half * kAmxTileRows) * step_bytes;
  }
};

template <typename Kind>
struct ScalarAmxInt8Panel : AmxInt8PanelLayout<Kind> {
  void pack(const uint8_t* qweight, const float* all_scales, int64_t n, int64_t k, int group_size, int64_t row_begin,
            int64_t col_begin, int64_t depth) {
    const int64_t groups = group_count(k, group_size);
    const int64_t first_group = col_begin / group_size;
    const int64_t panel_groups = group_count(depth, group_size);
    const int64_t step_bytes = amx_int8_step_bytes(group_size);
    const int64_t load_columns = amx_int8_load_columns(group_size);
    for (int64_t j = 0; j < kAmxPanelColumns; ++j) {
      const int64_t output = row_begin + j;
      const uint8_t* row = qweight + output * (k / 2);
      for (int64_t i = 0; i < panel_groups * group_size; ++i) {
        const int64_t column =
            col_begin + i / load_columns * load_columns + amx_int8_column(i % load_columns, load_columns);
        this->codes[(i / step_bytes * kAmxPanelColumns + j) * step_bytes + i % step_bytes] =
            static_cast<int8_t>(output < n && column < k ? weight_code(row, column) : 0);
      }
      for (int64_t g = 0; g < panel_groups; ++g) {
        this->scales[g * kAmxPanelColumns + j] = output < n ? all_scales[output * groups + first_group + g] : 0.0f;
        if (this->with_weight_sums) {
          const int64_t first = col_begin + g * group_size, last = output < n ? std::min(first + group_size, k) : first;
          float sum = 0.0f;
          for (int64_t c = first; c < last; ++c) sum += static_cast<float>(weight_code(row, c));
          this->weight_sums[g * kAmxPanelColumns + j] = sum;
        }
      }
    }
  }
};

#if defined(DYQ_AVX512_HAS_AMX)
// The same panel from AVX-512: per 64-byte load of a row (128 columns), the s8 codes of its low nibbles are
// a byte lookup (vpermb, which reads the low six bits of each index byte, in a table of the 16 codes four
// times over), and those of its high nibbles the same lookup of the bytes shifted down by 4 within each
// word. At G = 128 they are the load's two steps; at G = 64 and 32 the halves or quarters of both make
// each group's step (one two-source permute of quadwords each). sum q_w: the bytes' sums (vpsadbw) of the
// low plus the high codes plus 128, reduced across 8 rows at a time (add_group_sums).
template <typename Kind>
struct AmxInt8Panel : AmxInt8PanelLayout<Kind>, PackByGroupSize<AmxInt8Panel<Kind>> {
  // pack(): PackByGroupSize.
  template <int kGroup>
  void pack_rows(const uint8_t* qweight, const float* all_scales, int64_t n, int64_t k, int64_t row_begin,
                 int64_t col_begin, int64_t depth) {
    constexpr int kGroupsPerLoad = kAmxLoadColumns / kGroup;
    constexpr int64_t kStepBytes = amx_int8_step_bytes(kGroup);
    constexpr int64_t kStepStride = kAmxPanelColumns * kStepBytes;  // bytes from a row's step to its next
    alignas(64) static constexpr int8_t kCodes[64] = {
        0, 1, 2, 3, 4, 5, 6, 7, -8, -7, -6, -5, -4, -3, -2, -1, 0, 1, 2, 3, 4, 5, 6, 7, -8, -7, -6, -5, -4, -3, -2, -1,
        0, 1, 2, 3, 4, 5, 6, 7, -8, -7, -6, -5, -4, -3, -2, -1, 0, 1, 2, 3, 4, 5, 6, 7, -8, -7, -6, -5, -4, -3, -2, -1};
    const __m512i codes = _mm512_load_si512(kCodes);
    const __m512i offset = _mm512_set1_epi8(static_cast<char>(0x80));
    // The quadword lanes of a step from the low (0..7) and high (8..15) codes: at G = 64 the halves, at G = 32
    // the quarters of each, side by side.
    const __m512i first_steps = kGroup == 64 ? _mm512_setr_epi64(0, 1, 2, 3, 8, 9, 10, 11)
                                             : _mm512_setr_epi64(0, 1, 8, 9, 2, 3, 10, 11);
    const __m512i second_steps = kGroup == 64 ? _mm512_setr_epi64(4, 5, 6, 7, 12, 13, 14, 15)
                                              : _mm512_setr_epi64(4, 5, 12, 13, 6, 7, 14, 15);
    const int64_t groups = group_count(k, kGroup);
    const int64_t first_group = col_begin / kGroup;
    const int64_t panel_groups = group_count(depth, kGroup);
    const int64_t loads = group_count(panel_groups * kGroup, kAmxLoadColumns);
    const int64_t row_bytes = k / 2;
    auto* out = reinterpret_cast<uint8_t*>(this->codes);
    // AmxInt8: per load and row the quadword sums of q_w (16 columns each, plus 8 x 128), reduced below 8 rows
    // at once.
    [[maybe_unused]] __m512i row_sums[kAmxPanelDepth / kAmxLoadColumns][kAmxPanelColumns];
    for (int64_t j = 0; j < kAmxPanelColumns; ++j) {
      const int64_t output = row_begin + j;
      if (output >= n) {
        for (int64_t i = 0; i < panel_groups * kGroup / kStepBytes; ++i) {
          std::memset(out + i * kStepStride + j * kStepBytes, 0, kStepBytes);
        }
        for (int64_t g = 0; g < panel_groups; ++g) this->scales[g * kAmxPanelColumns + j] = 0.0f;
        // The quadword sums of all-zero codes: sum q_w = 0.
        for (int64_t load = 0; load < loads; ++load) row_sums[load][j] = _mm512_set1_epi64(8 * 128);
        continue;
      }
      const uint8_t* row = qweight + output * row_bytes + col_begin / 2;
      for (int64_t g = 0; g < panel_groups; ++g) {
        this->scales[g * kAmxPanelColumns + j] = all_scales[output * groups + first_group + g];
      }
      prefetch_row_ahead(row, col_begin, k);
      for (int64_t load = 0; load < loads; ++load) {
        const int64_t column = col_begin + load * kAmxLoadColumns;
        // Past k the load reads nothing (code 0): the row may end there, and the matrix with it.
        const int64_t bytes = std::max<int64_t>(0, std::min<int64_t>((k - column) / 2, 64));
        const __mmask64 byte_mask = bytes >= 64 ? ~__mmask64{0} : (__mmask64{1} << bytes) - 1;
        const __m512i packed = _mm512_maskz_loadu_epi8(byte_mask, row + load * 64);
        const __m512i low = permutexvar_epi8(packed, codes);
        const __m512i high = permutexvar_epi8(_mm512_srli_epi16(packed, 4), codes);
        uint8_t* steps = out + load * (kAmxLoadColumns / kStepBytes) * kStepStride + j * kStepBytes;
        if constexpr (kGroup == 128) {
          _mm512_store_si512(steps, low);
          _mm512_store_si512(steps + kStepStride, high);
        } else {
          const __m512i first = _mm512_permutex2var_epi64(low, first_steps, high);
          const __m512i second = _mm512_permutex2var_epi64(low, second_steps, high);
          if constexpr (kGroup == 64) {
            _mm512_store_si512(steps, first);
            _mm512_store_si512(steps + kStepStride, second);
          } else {
            _mm256_store_si256(reinterpret_cast<__m256i*>(steps), extracti64x4<0>(first));
            _mm256_store_si256(reinterpret_cast<__m256i*>(steps + kStepStride), extracti64x4<1>(first));
            _mm256_store_si256(reinterpret_cast<__m256i*>(steps + 2 * kStepStride), extracti64x4<0>(second));
            _mm256_store_si256(reinterpret_cast<__m256i*>(steps + 3 * kStepStride),
                               extracti64x4<1>(second));
          }
        }
        if (Kind::kWeightSums && this->with_weight_sums) {
          // Per quadword the sum over 8 bytes of (low + high codes) + 128 (below 256): 16 columns of one group.
          const __m512i offset_sums = _mm512_xor_si512(_mm512_add_epi8(low, high), offset);
          row_sums[load][j] = _mm512_sad_epu8(offset_sums, _mm512_setzero_si512());
        }
      }
    }
    if (Kind::kWeightSums && this->with_weight_sums) {
      for (int64_t load = 0; load < loads; ++load) {
        for (int64_t j = 0; j < kAmxPanelColumns; j += 8) {
          add_group_sums<kGroupsPerLoad>(row_sums[load] + j, load * kGroupsPerLoad, panel_groups, j);
        }
      }
    }
  }

  // weight_sums of rows j..j+7 for the groups [first_group, first_group + kGroupsPerLoad) of one load (those
  // below panel_groups) from the rows' quadword sums (16 columns of q_w, plus 8 x 128): three levels of
  // pairwise sums across the rows (a vector per 8 rows, where one row at a time took a horizontal sum each),
  // the groups of a load being its quadwords' halves (G = 64) or quarters (G = 32), which the first levels
  // hold apart.
  template <int kGroupsPerLoad>
  void add_group_sums(const __m512i* rows, int64_t first_group, int64_t panel_groups, int64_t j) {
    constexpr int64_t kGroup = kAmxLoadColumns / kGroupsPerLoad;
    constexpr int64_t kOffset = 8 * 128 * kGroup / 16;  // of a group's quadwords
    // Level 1: lane l of pairs[p] = (row 2p, row 2p + 1) over quadwords 2l and 2l + 1 (G = 32: group l).
    __m512i pairs[4];
    for (int p = 0; p < 4; ++p) {
      pairs[p] = _mm512_add_epi64(unpacklo_epi64(rows[2 * p], rows[2 * p + 1]),
                                  unpackhi_epi64(rows[2 * p], rows[2 * p + 1]));
    }
    alignas(64) int64_t lanes[8];
    if constexpr (kGroupsPerLoad == 4) {
      for (int p = 0; p < 4; ++p) {
        _mm512_store_si512(lanes, pairs[p]);
        for (int g = 0; g < 4 && first_group + g < panel_groups; ++g) {
          for (int e = 0; e < 2; ++e) {
            this->weight_sums[(first_group + g) * kAmxPanelColumns + j + 2 * p + e] =
                static_cast<float>(lanes[2 * g + e] - kOffset);
          }
        }
      }
      return;
    }
    // Level 2: quads[q] lanes = rows (4q, 4q + 1) over quadwords 0..3, then 4..7 (G = 64: groups 0 and 1),
    // then rows (4q + 2, 4q + 3) the same.
    __m512i quads[2];
    for (int q = 0; q < 2; ++q) {
      quads[q] = _mm512_add_epi64(shuffle_i64x2<0x88>(pairs[2 * q], pairs[2 * q + 1]),
                                  shuffle_i64x2<0xDD>(pairs[2 * q], pairs[2 * q + 1]));
    }
    if constexpr (kGroupsPerLoad == 2) {
      for (int q = 0; q < 2; ++q) {
        _mm512_store_si512(lanes, quads[q]);
        for (int g = 0; g < 2 && first_group + g < panel_groups; ++g) {
          for (int half = 0; half < 2; ++half) {
            for (int e = 0; e < 2; ++e) {
              this->weight_sums[(first_group + g) * kAmxPanelColumns + j + 4 * q + 2 * half + e] =
                  static_cast<float>(lanes[4 * half + 2 * g + e] - kOffset);
            }
          }
        }
      }
      return;
    }
    // Level 3: rows 0..7 in order, each over its whole load (G = 128: its group).
    const __m512i totals = _mm512_add_epi64(shuffle_i64x2<0x88>(quads[0], quads[1]),
                                            shuffle_i64x2<0xDD>(quads[0], quads[1]));
    const __m256 sums = _mm512_cvtepi64_ps(_mm512_sub_epi64(totals, _mm512_set1_epi64(kOffset)));
    _mm256_storeu_ps(&this->weight_sums[first_group * kAmxPanelColumns + j], sums);
  }
};
#endif

// totals[j][0..16) (and [16, 32) with kSecondHalf) += one group's contribution for the 32 output rows j of a
// panel and a block's activation rows (= with `first`, the first group of K, so that no totals need clearing),
// from the group's C tiles `sums` ([output row][activation row]; the epilogue of the int8 kinds,
// docs/numerics.md section 3):
// - AmxInt8: P = sum q_x q_w - z_x sum q_w, exact in fp32 (integers below 2^24), times s_x s_w;
// - AmxInt8 with zero tiles (kZeroTiles: 16 rows or fewer): the C tiles of the activation rows 16..31 hold
//   z_x sum q_w itself (the zero rows' products), and P is the difference of the two integers;
// - AmxInt8Centered: P = the C tiles' sum (q_x - z_x) q_w, times s_x s_w.
// zeros and row_scales: z_x and s_x of the block's 32 rows; weight_scales and weight_sums: s_w and sum q_w of
// the 32 output rows. On AVX-512 the rows' factors stay in registers over the outputs; the scaling runs on
// the vector units beside the AMX unit's tile products and costs about as much, so every instruction counts.
template <typename Kind, bool kSecondHalf, bool kZeroTiles = false>
void add_group_to_totals(const uint32_t (*sums)[kAmxRowBlock], const float* zeros, const float* row_scales,
                         const float* weight_scales, const float* weight_sums, bool first, float* totals) {
  static_assert(!(kZeroTiles && (kSecondHalf || Kind::kCentered)), "zero tiles take the second half's C tiles");
  constexpr int64_t kRows = kSecondHalf ? kAmxRowBlock : kAmxTileRows;
  constexpr bool kWeightSumsTerm = !Kind::kCentered && !kZeroTiles;
#if defined(DYQ_CPU_ISA_AVX512)
  constexpr int kHalves = kRows / 16;
  __m512 row_scale[kHalves], zero[kHalves];
  for (int h = 0; h < kHalves; ++h) {
    row_scale[h] = _mm512_loadu_ps(row_scales + 16 * h);
    if constexpr (kWeightSumsTerm) zero[h] = _mm512_loadu_ps(zeros + 16 * h);
  }
  for (int64_t j = 0; j < kAmxPanelColumns; ++j) {
    const __m512 weight_scale = _mm512_set1_ps(weight_scales[j]);
    float* total = totals + j * kAmxRowBlock;
    for (int h = 0; h < kHalves; ++h) {
      __m512i sum = _mm512_load_si512(sums[j] + 16 * h);
      if constexpr (kZeroTiles) sum = _mm512_sub_epi32(sum, _mm512_load_si512(sums[j] + 16));
      __m512 partial = cvtepi32_ps(sum);
      if constexpr (kWeightSumsTerm) partial = _mm512_fnmadd_ps(zero[h], _mm512_set1_ps(weight_sums[j]), partial);
      const __m512 scale = _mm512_mul_ps(row_scale[h], weight_scale);
      const __m512 previous = first ? _mm512_setzero_ps() : _mm512_load_ps(total + 16 * h);
      _mm512_store_ps(total + 16 * h, _mm512_fmadd_ps(partial, scale, previous));
    }
  }
#else
  for (int64_t j = 0; j < kAmxPanelColumns; ++j) {
    for (int64_t r = 0; r < kRows; ++r) {
      // The centered codes' sums are P already: no z_x term.
      const int32_t sum = static_cast<int32_t>(sums[j][r]) - (kZeroTiles ? static_cast<int32_t>(sums[j][16 + r]) : 0);
      const float partial = static_cast<float>(sum) - (kWeightSumsTerm ? zeros[r] * weight_sums[j] : 0.0f);
      const float previous = first ? 0.0f : totals[j * kAmxRowBlock + r];
      totals[j * kAmxRowBlock + r] = previous + partial * (row_scales[r] * weight_scales[j]);
    }
  }
#endif
}

// out = x W^T (+ bias) through the AMX-INT8 tiles with the weights as A (above): AmxInt8Centered at act_bits
// 2/4, AmxInt8 at 8; Panel is ScalarAmxInt8Panel<Kind> or AmxInt8Panel<Kind>. Threads split the panels of
// 32 output rows; each takes them kAmxPanelsPerPass at a time, and per slice of columns unpacks each panel
// of the pass into a buffer that stays in L1 and runs it against every block of activation rows, group by
// group: the group's C tiles go to one of two buffers, and the previous group's are scaled into the
// totals (AmxPassTotals: [panel][block][output row][activation row]) after this group's tile products are
// issued, so that the AMX unit works through those while the vector units scale (they would otherwise take
// turns). Two panel buffers alternate, so that the group being scaled keeps its panel's s_w and sum q_w
// while the next panel is unpacked. Returns whether every output is finite.
template <typename Tiles, typename Kind, typename Panel, typename Element>
bool amx_int8_gemm(const Element* x, const uint8_t* qweight, const float* scales, const Element* bias, int64_t m,
                   int64_t n, int64_t k, int group_size, int act_bits, Element* out) {
  // No column: no slice runs the loop below, whose last group writes the outputs.
  if (k == 0) return bias_outputs(bias, m, n, out);
  const AmxInt8Activations a = amx_int8_activations<Kind>(x, m, k, group_size, act_bits);
  const int64_t step_bytes = a.step_columns;  // a byte per column
  const int64_t b_tile_bytes = a.tile_bytes;
  // Everything the loops step by, computed once: a division per group cost as much as a tile product.
  const int64_t steps_per_group = group_size / step_bytes;
  const int64_t groups_per_slice = kAmxPanelDepth / group_size;
  const int64_t panels = (n + kAmxPanelColumns - 1) / kAmxPanelColumns;
  FiniteOutputs finite;
  parallel_for(0, panels, 1, [&](int64_t panel_begin, int64_t panel_end) {
    Tiles tiles;
    tiles.configure(step_bytes);
    std::unique_ptr<Panel[]> panel_buffers(new Panel[2]);
    int panel_buffer = 0;
    const int64_t pass_size = std::min(kAmxPanelsPerPass, panel_end - panel_begin);
    AmxPassTotals totals(pass_size, a.blocks, k);
    alignas(64) uint32_t sums[2][kAmxPanelColumns][kAmxRowBlock];  // [buffer][output row][activation row]
    int sums_buffer = 0;
    // A group whose C tiles wait in sums[sums_buffer ^ 1] to be scaled into the totals.
    struct Pending {
      const Panel* panel = nullptr;  // nullptr: none
      int64_t group = 0, global_group = 0, block = 0, weight_row = 0;
      float* block_totals = nullptr;
    } pending;
    auto scale_pending = [&] {
      const Pending& job = pending;
      if (job.panel == nullptr) return;
      const int64_t row_begin = job.block * kAmxRowBlock;
      const float* zeros = a.params(a.zeros, job.block, job.global_group);
      const float* row_scales = a.params(a.scales, job.block, job.global_group);
      const float* weight_scales = &job.panel->scales[job.group * kAmxPanelColumns];
      const float* weight_sums = &job.panel->weight_sums[job.group * kAmxPanelColumns];
      const bool second_half = m - row_begin > kAmxTileRows;
      const bool first = job.global_group == 0;
      if (second_half) {
        add_group_to_totals<Kind, true>(sums[sums_buffer ^ 1], zeros, row_scales, weight_scales, weight_sums, first,
                                        job.block_totals);
      } else if (a.zero_tiles) {
        if constexpr (!Kind::kCentered) {
          add_group_to_totals<Kind, false, true>(sums[sums_buffer ^ 1], zeros, row_scales, weight_scales,
                                                 weight_sums, first, job.block_totals);
        }
      } else {
        add_group_to_totals<Kind, false>(sums[sums_buffer ^ 1], zeros, row_scales, weight_scales, weight_sums, first,
                                         job.block_totals);
      }
      // The block's last group: its outputs, while its totals are in L1.
      if (job.global_group + 1 == a.groups) {
        finite.note(write_block_outputs(job.block_totals, bias, m, n, row_begin, job.weight_row, out));
      }
      pending.panel = nullptr;
    };
    for (int64_t pass_begin = panel_begin; pass_begin < panel_end; pass_begin += pass_size) {
      const int pass_count = static_cast<int>(std::min(pass_size, panel_end - pass_begin));
      for (int64_t slice = 0, slice_group = 0; slice < k; slice += kAmxPanelDepth, slice_group += groups_per_slice) {
        const int64_t depth = std::min(kAmxPanelDepth, k - slice);
        const int64_t slice_groups = group_count(depth, group_size);
        const int64_t first_step = slice / step_bytes;
        for (int i = 0; i < pass_count; ++i) {
          const int64_t weight_row = (pass_begin + i) * kAmxPanelColumns;
          Panel& panel = panel_buffers[panel_buffer];
          panel_buffer ^= 1;
          panel.with_weight_sums = Kind::kWeightSums && !a.zero_tiles;
          panel.pack(qweight, scales, n, k, group_size, weight_row, slice, depth);
          for (int64_t block = 0; block < a.blocks; ++block) {
            // A block of 16 rows or fewer (M <= 16, or the rows' last block) has nothing in its second B
            // tile: C1 and C3 are neither computed nor loaded or stored, half the block's tile work, or with
            // zero tiles they take the products of the weights with the zero row.
            const bool second_half = m - block * kAmxRowBlock > kAmxTileRows;
            const bool upper_tiles = second_half || a.zero_tiles;  // C1 and C3 in use
            float* block_totals = totals.block(i, block);
            const uint8_t* b_tile = a.tile(block, first_step, 0);
            for (int64_t group = 0; group < slice_groups; ++group) {
              zero_block_tiles(tiles, upper_tiles);
              if (a.zero_tiles) tiles.template load<7>(a.zero_row(slice_group + group), 0);
              for (int64_t s = group * steps_per_group; s < (group + 1) * steps_per_group; ++s) {
                tiles.template load<6>(b_tile, 64);
                tiles.template load<4>(panel.tile(s, step_bytes, 0), step_bytes);
                Kind::template product<0, 4, 6>(tiles);
                tiles.template load<5>(panel.tile(s, step_bytes, 1), step_bytes);
                Kind::template product<2, 5, 6>(tiles);
                if (upper_tiles) {
                  if (second_half) tiles.template load<7>(b_tile + b_tile_bytes, 64);
                  Kind::template product<1, 4, 7>(tiles);
                  Kind::template product<3, 5, 7>(tiles);
                }
                b_tile += 2 * b_tile_bytes;
              }
              scale_pending();
              move_block_tiles<true>(tiles, sums[sums_buffer], upper_tiles);
              pending = {&panel, group, slice_group + group, block, weight_row, block_totals};
              sums_buffer ^= 1;
            }
          }
        }
      }
      // The pass's last group, before the next pass's first groups store theirs.
      scale_pending();
    }
    tiles.release();
  });
  return finite.all();
}

// ---- AMX-BF16: the weights as the A operand ---------------------------------------------------------
//
// At act_bits 16 the tiles multiply bf16(x) with the dequantized weights bf16(q_w s_w), which no
// per-group scale follows, so the C tiles accumulate a whole slice onto the running totals. Here the
// weights are the A tiles and the activations the B tiles, so that a weight panel comes from the packed
// rows with no transpose: an A tile row is 32 columns of one output row. Which 32 is free, as long as the
// B tiles pair the same columns of x, and the panels take the order in which the packed bytes hold them:
// a 64-byte load of a row is 128 columns, 32 words of four nibbles (column 4 w + p in nibble p of word w),
// and step p of those 128 columns is the 32 columns of nibble p (nibble_order_words). So a step of a row
// is one word shift and one word lookup in a table of its groups' values (bf16(q s_w) for the 16 codes),
// where columns in order had cost a byte permute more, and the activations are put in that order once per
// call, as they are transposed into B tiles. The transposes move to the activations (once per call) and
// the outputs (once per output); with the weights as B, every call transposed all of them into their
// tile layout, three times the instructions, and at 16 activation rows that unpacking was most of the
// call.
//
// Tiles: C0..C3 = output rows (0..15, 16..31 of the panel) x activation rows (0..15, 16..31 of the block);
// A0/A1 = 16 weight rows x 32 columns (64 bytes); B0/B1 = 16 column pairs x 16 activation rows.

// The bf16 bit patterns of 8 fp32 values, in column order.
inline void bf16_quad_bytes(const float* values, uint8_t* out) {
  for (int i = 0; i < 8; ++i) {
    const uint16_t bits = bf16_bits(values[i]);
    std::memcpy(out + 2 * i, &bits, 2);
  }
}

// The bf16 bytes of one step from its fp32 values, of which the first `columns_in_k` exist (zeros past
// k, the tail of the last group, which the fp32 input does not hold). A whole 32-column step goes through
// vcvtne2ps2bf16 where it is compiled in; that instruction reads fp32 denormals as 0 where the format
// rounds them (bf16_bits), so a step that holds one is converted one value at a time.
inline void bf16_step_bytes(const float* values, int64_t columns_in_k, int64_t step_columns, uint8_t* out) {
#if defined(DYQ_AVX512_HAS_BF16)
  if (step_columns == 32 && columns_in_k >= 32) {
    const __m512 low = _mm512_loadu_ps(values), high = _mm512_loadu_ps(values + 16);
    constexpr int kDenormal = 0x20;  // vfpclassps: denormal
    if ((_mm512_fpclass_ps_mask(low, kDenormal) | _mm512_fpclass_ps_mask(high, kDenormal)) == 0) {
      _mm512_storeu_si512(out, reinterpret_cast<__m512i>(_mm512_cvtne2ps_pbh(high, low)));
      return;
    }
  }
#endif
  for (int64_t c = 0; c < step_columns; c += kAmxQuadColumns) {
    if (c + kAmxQuadColumns <= columns_in_k) {
      bf16_quad_bytes(values + c, out + 2 * c);
    } else {
      float quad[kAmxQuadColumns] = {};
      for (int64_t i = 0; i < kAmxQuadColumns && c + i < columns_in_k; ++i) quad[i] = values[c + i];
      bf16_quad_bytes(quad, out + 2 * c);
    }
  }
}

constexpr int64_t kAmxBf16StepColumns = 32;                  // columns of one tile product
constexpr int64_t kAmxBf16TileBytes = 16 * 64;               // one A or B tile
constexpr int64_t kAmxBf16StepsPerSlice = kAmxPanelDepth / kAmxBf16StepColumns;

// vpermt2w's indices for step p of a 128-column block (nibble_order_words): word w from word 4 w + p of a
// pair of 32-word vectors (0..63), the first for w < 16 and the second beyond.
struct NibbleOrderTable {
  alignas(64) uint16_t index[4][32];
  constexpr NibbleOrderTable() : index() {
    for (int p = 0; p < 4; ++p) {
      for (int w = 0; w < 32; ++w) index[p][w] = static_cast<uint16_t>((4 * w + p) % 64);
    }
  }
};
inline constexpr NibbleOrderTable kNibbleOrder{};

// The 128 words (bf16 values) of a 128-column block, in column order, put in the order of the nibbles that
// hold those columns in a 64-byte load of packed weights: out[32 p + w] = in[4 w + p], step p the columns
// of nibble p. The AMX-BF16 activations, and the AVX-512 bf16 row kernels' (gemm/gemm_cpu_avx512.h).
inline void nibble_order_words(const uint16_t* in, uint16_t* out) {
#if defined(DYQ_CPU_ISA_AVX512)
  const __m512i first[2] = {_mm512_loadu_si512(in), _mm512_loadu_si512(in + 32)};
  const __m512i second[2] = {_mm512_loadu_si512(in + 64), _mm512_loadu_si512(in + 96)};
  for (int p = 0; p < 4; ++p) {
    const __m512i index = _mm512_load_si512(kNibbleOrder.index[p]);
    const __m512i low = _mm512_permutex2var_epi16(first[0], index, first[1]);
    const __m512i high = _mm512_permutex2var_epi16(second[0], index, second[1]);
    _mm512_storeu_si512(out + 32 * p, _mm512_mask_mov_epi16(low, 0xFFFF0000u, high));
  }
#else
  for (int p = 0; p < 4; ++p) {
    for (int w = 0; w < 32; ++w) out[32 * p + w] = in[4 * w + p];
  }
#endif
}

// Column c of a slice's panel (past its start) in the order of nibble_order_words: the slice's steps in
// groups of four per 128 columns.
inline int64_t nibble_order_column(int64_t step, int64_t element) {
  return step / 4 * kAmxLoadColumns + 4 * element + step % 4;
}

// The activations as B tiles (AmxBTiles), steps of 32 columns (nibble_order_words), each tile 16 rows (the
// step's column pairs) of 16 dwords (the bf16 pair of each activation row). Columns past k are 0.
template <typename Element>
AmxBTiles amx_bf16_activations(const Element* x, int64_t m, int64_t k) {
  AmxBTiles a;
  // Whole loads of 128 columns, which hold whole groups (G divides 128).
  const int64_t padded = group_count(k, kAmxLoadColumns) * kAmxLoadColumns;
  a.allocate(m, padded, kAmxBf16StepColumns, kAmxBf16TileBytes);
  constexpr int64_t kStepBytes = kAmxBf16StepColumns * 2;  // one step of one row: 16 bf16 pairs
  // B tile by B tile (16 rows): the rows' bf16 pairs in row order, then each step's 16 x 16 dwords
  // transposed into the tile. A tile whose rows pass m gets zero rows; a block's second tile with no row
  // below m is not written, and the tile loop does not read it.
  parallel_for(0, (m + kAmxTileRows - 1) / kAmxTileRows, 1, [&](int64_t tile_begin, int64_t tile_end) {
    std::vector<float> row(padded, 0.0f);  // x in fp32, where it is not fp32 already
    std::unique_ptr<uint8_t[]> pairs(new uint8_t[kAmxTileRows * a.steps * kStepBytes]);  // [row][step][64]
    for (int64_t t = tile_begin; t < tile_end; ++t) {
      for (int64_t lane = 0; lane < kAmxTileRows; ++lane) {
        const int64_t r = t * kAmxTileRows + lane;
        uint8_t* row_pairs = pairs.get() + lane * a.steps * kStepBytes;
        if (r >= m) {
          std::memset(row_pairs, 0, a.steps * kStepBytes);
          continue;
        }
        const float* values = row_as_fp32(x + r * k, k, row.data());
        for (int64_t column = 0; column < padded; column += kAmxLoadColumns) {
          alignas(64) uint16_t in_order[kAmxLoadColumns];
          for (int64_t c = 0; c < kAmxLoadColumns; c += kAmxBf16StepColumns) {
            bf16_step_bytes(values + column + c, k - column - c, kAmxBf16StepColumns,
                            reinterpret_cast<uint8_t*>(in_order + c));
          }
          nibble_order_words(in_order, reinterpret_cast<uint16_t*>(row_pairs + column * 2));
        }
      }
      const int64_t block = t / 2;
      const int half = static_cast<int>(t % 2);
      for (int64_t step = 0; step < a.steps; ++step) {
        uint8_t* tile = a.tile(block, step, half);
        const uint8_t* step_pairs = pairs.get() + step * kStepBytes;
#if defined(DYQ_CPU_ISA_AVX512)
        __m512i dwords[kAmxTileRows];
        for (int lane = 0; lane < kAmxTileRows; ++lane) {
          dwords[lane] = _mm512_loadu_si512(step_pairs + lane * a.steps * kStepBytes);
        }
        transpose_16x16_dwords(dwords);
        for (int p = 0; p < 16; ++p) _mm512_storeu_si512(tile + 64 * p, dwords[p]);
#else
        for (int lane = 0; lane < kAmxTileRows; ++lane) {
          const uint8_t* lane_pairs = step_pairs + lane * a.steps * kStepBytes;
          for (int p = 0; p < 16; ++p) std::memcpy(tile + 64 * p + 4 * lane, lane_pairs + 4 * p, 4);
        }
#endif
      }
    }
  });
  return a;
}

// A panel in plain C++ (the emulation's; the native path has AmxBf16Panel): 32 output rows x
// kAmxPanelDepth columns of bf16(q_w s_w), step by step (32 columns in the order of nibble_order_words),
// within a step row by row: an A tile is 1 KiB in one run. Rows past n and columns past k are 0.
struct ScalarAmxBf16Panel {
  alignas(64) uint16_t values[kAmxBf16StepsPerSlice][kAmxPanelColumns][kAmxBf16StepColumns];

  void pack(const uint8_t* qweight, const float* all_scales, int64_t n, int64_t k, int group_size, int64_t row_begin,
            int64_t col_begin, int64_t depth) {
    const int64_t groups = group_count(k, group_size);
    const int64_t steps = group_count(depth, kAmxLoadColumns) * kAmxLoadColumns / kAmxBf16StepColumns;
    for (int64_t j = 0; j < kAmxPanelColumns; ++j) {
      const int64_t output = row_begin + j;
      for (int64_t step = 0; step < steps; ++step) {
        for (int64_t e = 0; e < kAmxBf16StepColumns; ++e) {
          const int64_t column = col_begin + nibble_order_column(step, e);
          values[step][j][e] = output < n && column < k
                                   ? dequantized_bf16_bits(weight_code(qweight + output * (k / 2), column),
                                                           all_scales[output * groups + column / group_size])
                                   : uint16_t{0};
        }
      }
    }
  }
};

#if defined(DYQ_AVX512_HAS_AMX)
// The same panel from AVX-512 BF16: per 64-byte load of a row (128 columns, 32 words of four nibbles), step
// p is the word lookup (vpermw) of the words shifted down by 4 p, whose low four bits are nibble p, in a
// table of bf16(q s_w) for the 16 codes (vcvtne2ps2bf16 of q s_w formed in fp32, which reads a product below
// fp32's normal range as 0, as dequantized_bf16_bits does). The fifth index bit picks the table's second
// half: at G = 128 a copy of the first (the bit is nibble p + 1's lowest, which does not matter), at G = 64
// the second group of the load (words 16..31, set by a ternary logic that masks the nibble); at G = 32,
// four groups, two index bits select among two tables (vpermt2w).
struct AmxBf16Panel : PackByGroupSize<AmxBf16Panel> {
  // As ScalarAmxBf16Panel's.
  alignas(64) uint16_t values[kAmxBf16StepsPerSlice][kAmxPanelColumns][kAmxBf16StepColumns];

  // pack(): PackByGroupSize.
  template <int kGroup>
  void pack_rows(const uint8_t* qweight, const float* all_scales, int64_t n, int64_t k, int64_t row_begin,
                 int64_t col_begin, int64_t depth) {
    alignas(64) static constexpr float kCodes[16] = {0, 1, 2, 3, 4, 5, 6, 7, -8, -7, -6, -5, -4, -3, -2, -1};
    constexpr int kGroupsPerLoad = kAmxLoadColumns / kGroup;
    const __m512 codes = _mm512_load_ps(kCodes);
    const __m512i low_nibble = _mm512_set1_epi16(0x000F);
    // The group of each word of a load, in index bits 4 and 5: w / 16 at G = 64, w / 8 at G = 32.
    alignas(64) uint16_t word_groups[32];
    for (int w = 0; w < 32; ++w) word_groups[w] = static_cast<uint16_t>((w * kGroupsPerLoad / 32) << 4);
    const __m512i group_bits = _mm512_load_si512(word_groups);
    const int64_t groups = group_count(k, kGroup);
    const int64_t loads = group_count(depth, kAmxLoadColumns);
    const int64_t row_bytes = k / 2;
    for (int64_t j = 0; j < kAmxPanelColumns; ++j) {
      const int64_t output = row_begin + j;
      if (output >= n) {
        for (int64_t step = 0; step < 4 * loads; ++step) std::memset(values[step][j], 0, sizeof(values[step][j]));
        continue;
      }
      const uint8_t* row = qweight + output * row_bytes + col_begin / 2;
      const float* row_scales = all_scales + output * groups;
      prefetch_row_ahead(row, col_begin, k);
      for (int64_t load = 0; load < loads; ++load) {
        const int64_t column = col_begin + load * kAmxLoadColumns;
        // Past k the load reads nothing (code 0, value 0): the row may end there, and the matrix with it.
        const int64_t bytes = std::min<int64_t>((k - column) / 2, 64);
        const __mmask64 byte_mask = bytes >= 64 ? ~__mmask64{0} : (__mmask64{1} << bytes) - 1;
        const __m512i words = _mm512_maskz_loadu_epi8(byte_mask, row + load * 64);
        // bf16(q s_w) of the load's groups, 16 codes each; a group past the row's last (k ends in the load)
        // covers no column, and its scale is not read.
        __m512i tables[2];
        for (int t = 0; t < (kGroupsPerLoad + 1) / 2; ++t) {
          __m512 products[2];
          for (int h = 0; h < 2; ++h) {
            const int64_t group = column / kGroup + 2 * t + h;
            products[h] = kGroupsPerLoad == 1 && h == 1
                              ? products[0]
                              : _mm512_mul_ps(codes, _mm512_set1_ps(group < groups ? row_scales[group] : 0.0f));
          }
          tables[t] = reinterpret_cast<__m512i>(_mm512_cvtne2ps_pbh(products[1], products[0]));
        }
#pragma GCC unroll 4
        for (int p = 0; p < 4; ++p) {
          const __m512i shifted = p == 0 ? words : _mm512_srli_epi16(words, 4 * p);
          __m512i step;
          if constexpr (kGroupsPerLoad == 1) {
            step = _mm512_permutexvar_epi16(shifted, tables[0]);
          } else {
            // (shifted & 0xF) | group_bits is ternary logic 0xEA on (shifted, low_nibble, group_bits).
            const __m512i index = _mm512_ternarylogic_epi32(shifted, low_nibble, group_bits, 0xEA);
            step = kGroupsPerLoad == 2 ? _mm512_permutexvar_epi16(index, tables[0])
                                       : _mm512_permutex2var_epi16(tables[0], index, tables[1]);
          }
          _mm512_store_si512(values[4 * load + p][j], step);
        }
      }
    }
  }
};
#endif

// out = x W^T (+ bias) at act_bits 16 through the AMX-BF16 tiles with the weights as A (above). Panel is
// ScalarAmxBf16Panel or AmxBf16Panel. Threads split the panels of 32 output rows; each takes them
// kAmxPanelsPerPass at a time, and per slice of columns unpacks each panel of the pass into one buffer
// and runs it against every block of activation rows, accumulating onto the totals of the pass,
// [panel][block][output row][activation row] (AmxPassTotals), which the C tiles store once per slice and
// load again for every slice but the first, which starts from zeroed tiles. The buffer
// (16 KiB) stays in L1 from its unpacking to its last tile load: with the pass's slices unpacked at once
// (128 KiB), their stores went to L2 and bound the unpacking (4096 x 4096 at 16 rows, one thread, the
// unpacking alone 1.2 to 1.4 ms against 0.65 to 1.05 into one buffer), and the tile loads read the same
// bytes from L2 (the weights then, the activations now).
template <typename Tiles, typename Panel, typename Element>
bool amx_bf16_gemm(const Element* x, const uint8_t* qweight, const float* scales, const Element* bias, int64_t m,
                   int64_t n, int64_t k, int group_size, Element* out) {
  // No column: no slice runs the loop below, whose last slice writes the outputs.
  if (k == 0) return bias_outputs(bias, m, n, out);
  const AmxBTiles a = amx_bf16_activations(x, m, k);
  const int64_t panels = (n + kAmxPanelColumns - 1) / kAmxPanelColumns;
  constexpr int64_t kWeightStride = kAmxBf16StepColumns * 2;    // bytes between two rows of a panel's step
  constexpr int64_t kLowerRows = kAmxTileRows * kWeightStride;  // a step's rows 16..31
  FiniteOutputs finite;
  parallel_for(0, panels, 1, [&](int64_t panel_begin, int64_t panel_end) {
    Tiles tiles;
    tiles.configure(64);
    std::unique_ptr<Panel> panel(new Panel);
    // As many panels as a pass of this thread takes: a small layer's call allocates no more.
    const int64_t pass_size = std::min(kAmxPanelsPerPass, panel_end - panel_begin);
    // [output row 0..31][activation row 0..31] per block: a C tile's rows 128 bytes apart.
    AmxPassTotals totals(pass_size, a.blocks, k);
    const auto* weights = reinterpret_cast<const uint8_t*>(&panel->values[0][0][0]);
    for (int64_t pass_begin = panel_begin; pass_begin < panel_end; pass_begin += pass_size) {
      const int pass_count = static_cast<int>(std::min(pass_size, panel_end - pass_begin));
      for (int64_t slice = 0; slice < k; slice += kAmxPanelDepth) {
        const int64_t depth = std::min(kAmxPanelDepth, k - slice);
        const int64_t first_step = slice / kAmxBf16StepColumns;
        const int64_t slice_steps = std::min(kAmxBf16StepsPerSlice, a.steps - first_step);
        const bool last_slice = slice + kAmxPanelDepth >= k;
        for (int i = 0; i < pass_count; ++i) {
          const int64_t weight_row = (pass_begin + i) * kAmxPanelColumns;
          panel->pack(qweight, scales, n, k, group_size, weight_row, slice, depth);
          for (int64_t block = 0; block < a.blocks; ++block) {
            // A block of 16 rows or fewer (M <= 16, or the rows' last block) has nothing in its second B
            // tile: C1 and C3 are neither computed nor loaded or stored, half the block's tile work.
            const bool second_half = m - block * kAmxRowBlock > kAmxTileRows;
            float* block_totals = totals.block(i, block);
            // The first slice starts from zero, the others from the block's totals so far.
            if (slice == 0) {
              zero_block_tiles(tiles, second_half);
            } else {
              move_block_tiles<false>(tiles, block_totals, second_half);
            }
            const uint8_t* b_tile = a.tile(block, first_step, 0);
            for (int64_t s = 0; s < slice_steps; ++s, b_tile += 2 * kAmxBf16TileBytes) {
              const uint8_t* a_tile = weights + s * kAmxPanelColumns * kWeightStride;
              tiles.template load<6>(b_tile, 64);
              tiles.template load<4>(a_tile, kWeightStride);
              tiles.template dpbf16ps<0, 4, 6>();
              tiles.template load<5>(a_tile + kLowerRows, kWeightStride);
              tiles.template dpbf16ps<2, 5, 6>();
              if (second_half) {
                tiles.template load<7>(b_tile + kAmxBf16TileBytes, 64);
                tiles.template dpbf16ps<1, 4, 7>();
                tiles.template dpbf16ps<3, 5, 7>();
              }
            }
            move_block_tiles<true>(tiles, block_totals, second_half);
            if (last_slice) {
              finite.note(write_block_outputs(block_totals, bias, m, n, block * kAmxRowBlock, weight_row, out));
            }
          }
        }
      }
    }
    tiles.release();
  });
  return finite.all();
}

}  // namespace dyq::cpu::DYQ_ISA_NAMESPACE
DYQ_ISA_END
