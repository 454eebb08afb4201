// The AMX tile loop of the GEMM for many activation rows (docs/numerics.md, section 3), written once over
// a Tiles type and a tile-product kind:
// - Tiles: NativeTiles issues the AMX instructions (the "amx" path, cpu/kernels_avx512_amx.cpp), and
//   EmulatedTiles performs the same tile operations in scalar C++, as the instructions define them, so
//   that the blocking, the tile configuration, the panel layout and the epilogue are tested on every
//   CPU (gemm/gemm_cpu_amx_emulated.h).
// - AmxInt8 (act_bits 8): tdpbusd of u8 activation codes q_x with s8 weight codes q_w. Per group the
//   C tiles hold the exact integer sums sum q_x q_w (below 2^24), and the epilogue forms
//   s_x s_w (sum q_x q_w - z_x sum q_w) in fp32, as the VNNI kernels do.
// - AmxInt8Centered (act_bits 2/4): tdpbssd of the centered codes q_x - z_x, which fit s8 below 8 bits,
//   so that the C tiles hold P = sum (q_x - z_x) q_w itself, the same integer: the epilogue saves the
//   z_x sum q_w term (a quarter of its vector work, which does not overlap the tile products) and the
//   panels their sums of q_w.
// - act_bits 16 has a loop of its own, with the weights as the A operand (amx_bf16_gemm, below).
//
// Weight panels. 32 output rows at a time, over a slice of kAmxPanelDepth columns, are unpacked once
// into the layout of the AVX-512 panel path (gemm/gemm_cpu_avx512.h, WeightPanel): steps[quad][step][32]
// dwords, quad q covering columns 8q..8q+7 and each step one dword per output row. That is the layout of
// B tiles: a B row is one step of the 32 output rows (128 bytes), its left 64 bytes in the B tile of
// outputs 0..15 and its right 64 bytes in that of outputs 16..31, and consecutive steps are consecutive
// B rows.
// - AmxInt8 has two steps per quad, the s8 codes of the even columns 8q, 8q + 2, 8q + 4, 8q + 6, then
//   of the odd ones; the activation codes are stored in the same order within every 8 columns, so that
//   A's dword i meets B's row i.
// The native path unpacks with the AVX-512 panel packers, once per slice and panel for every activation
// row, so that unpacking is a small share of the tile work (the scalar unpacking of every call's whole
// weight matrix that came before cost more than the tile products themselves); the emulation unpacks the
// same layout in plain C++ (ScalarAmxPanel).
//
// Tiles: C0..C3 = the 2 x 2 accumulators of 32 activation rows x 32 output columns, A0/A1 = 16 activation
// rows x a step's bytes, B0/B1 = a step's bytes / 4 rows x 64 bytes. A step is 64 bytes of A (64 columns
// of codes), or the group's bytes where the group is smaller, so that a group is a whole number of steps.
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
// most 15) and multiplies with tdpbssd; otherwise u8 codes q_x with tdpbusd and z_x sum q_w in the epilogue.
template <bool kCenteredCodes>
struct AmxInt8Kind {
  static constexpr int64_t kStepsPerQuad = 2;  // B rows per 8 columns
  static constexpr bool kCentered = kCenteredCodes;
  static constexpr bool kWeightSums = !kCenteredCodes;  // sum q_w per group, for the z_x term
  // The A bytes of 8 columns from their codes: the even columns, then the odd ones.
  static void quad_bytes(const uint8_t* codes, uint8_t* out) {
    for (int i = 0; i < 4; ++i) out[i] = codes[2 * i], out[4 + i] = codes[2 * i + 1];
  }
  // The dword of step s of quad q for one output row (packed weights `row`; columns past k are 0); the
  // codes themselves (the group's scale is applied in the epilogue).
  static uint32_t step_dword(const uint8_t* row, int64_t k, int64_t quad, int s) {
    uint32_t dword = 0;
    for (int b = 0; b < 4; ++b) {
      const int64_t c = quad * kAmxQuadColumns + 2 * b + s;
      const int code = c < k ? weight_code(row, c) : 0;
      dword |= uint32_t{static_cast<uint8_t>(static_cast<int8_t>(code))} << (8 * b);
    }
    return dword;
  }
  template <int kC, int kA, int kB, typename Tiles>
  static void product(Tiles& tiles) {
    if constexpr (kCentered) {
      tiles.template dpbssd<kC, kA, kB>();
    } else {
      tiles.template dpbusd<kC, kA, kB>();
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
  // tdpbusd / tdpbssd: C[m][n] += sum over the dwords i of A's row m of sum_b A[m][4i + b] * s8 B[i][4n + b],
  // A's bytes u8 (tdpbusd) or s8 (tdpbssd).
  template <bool kSignedA, int kC, int kA, int kB>
  void dot_bytes() {
    for (int m = 0; m < rows[kA]; ++m) {
      for (int n = 0; n < bytes[kC] / 4; ++n) {
        int32_t sum;
        std::memcpy(&sum, &tiles[kC][m][4 * n], 4);
        for (int i = 0; i < bytes[kA] / 4; ++i) {
          for (int b = 0; b < 4; ++b) {
            const uint8_t a_byte = tiles[kA][m][4 * i + b];
            const int32_t a_value = kSignedA ? int32_t{static_cast<int8_t>(a_byte)} : int32_t{a_byte};
            sum += a_value * int32_t{static_cast<int8_t>(tiles[kB][i][4 * n + b])};
          }
        }
        std::memcpy(&tiles[kC][m][4 * n], &sum, 4);
      }
    }
  }
  template <int kC, int kA, int kB>
  void dpbusd() {
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
    _tile_loadconfig(&config);
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
  void dpbusd() {
    asm volatile("{tdpbusd %%tmm%c2, %%tmm%c1, %%tmm%c0|tdpbusd tmm%c0, tmm%c1, tmm%c2}" ::"i"(kC), "i"(kA), "i"(kB));
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

// Activations as the tile loop reads them, in the order it loads the A tiles: slice by slice of
// kAmxPanelDepth columns, within a slice block by block of kAmxRowBlock rows (the last padded with zero
// rows), within a block step by step, the step's bytes of the block's 32 rows. So a tile load reads 1 KiB
// in one run (rows k bytes apart would fall into the same few sets of the L1 cache at k = 4096), and a
// panel's pass over the activations reads them in one sequence, which the prefetchers follow. Every 8
// columns are laid out by Kind::quad_bytes, zero past k up to whole groups: the codes (u8 q_x, or s8
// q_x - z_x), and each (row, group)'s z_x and s_x.
template <typename Kind>
struct AmxActivations {
  int64_t rows = 0, groups = 0, step_bytes = 0, steps = 0;  // steps: of all the padded columns
  std::unique_ptr<uint8_t[]> bytes;  // left uninitialized: amx_activations writes every byte
  std::vector<float> zeros, scales;  // [m][groups]

  int64_t step_columns() const { return step_bytes; }  // a byte per column
  // The byte of (row, column), column a multiple of 8.
  int64_t offset(int64_t row, int64_t column) const {
    const int64_t steps_per_slice = kAmxPanelDepth / step_columns();
    const int64_t slice = column / kAmxPanelDepth;
    const int64_t slice_steps = std::min(steps_per_slice, steps - slice * steps_per_slice);
    const int64_t step = column % kAmxPanelDepth / step_columns();
    const int64_t line = slice * steps_per_slice * rows + (row / kAmxRowBlock * slice_steps + step) * kAmxRowBlock +
                         row % kAmxRowBlock;
    return line * step_bytes + column % step_columns();
  }
  // The A tile of rows [row_begin, row_begin + 16) (row_begin a multiple of 16) at `column` (a multiple
  // of step_columns()); its rows are stride() bytes apart.
  const uint8_t* tile(int64_t row_begin, int64_t column) const { return bytes.get() + offset(row_begin, column); }
  int64_t stride() const { return step_bytes; }
  // Steps of the slice starting at `column` (the last slice may hold fewer).
  int64_t slice_steps(int64_t column) const {
    const int64_t steps_per_slice = kAmxPanelDepth / step_columns();
    return std::min(steps_per_slice, steps - column / kAmxPanelDepth * steps_per_slice);
  }
};

// The bytes of A's rows in one step (the header's "Tiles").
inline int64_t amx_step_bytes(int group_size) { return std::min<int64_t>(kAmxMaxStepBytes, group_size); }

// The A bytes of one step of the int8 kind from its codes in column order (step_columns a multiple of 16):
// within every 8 columns the even ones, then the odd ones (AmxInt8::quad_bytes), one byte shuffle per 16
// columns where SSSE3 is compiled in.
inline void int8_step_bytes(const uint8_t* codes, int64_t step_columns, uint8_t* out) {
#if defined(DYQ_ISA_TARGET)
  const __m128i even_then_odd = _mm_setr_epi8(0, 2, 4, 6, 1, 3, 5, 7, 8, 10, 12, 14, 9, 11, 13, 15);
  for (int64_t c = 0; c < step_columns; c += 16) {
    const __m128i chunk = _mm_loadu_si128(reinterpret_cast<const __m128i*>(codes + c));
    _mm_storeu_si128(reinterpret_cast<__m128i*>(out + c), _mm_shuffle_epi8(chunk, even_then_odd));
  }
#else
  for (int64_t c = 0; c < step_columns; c += kAmxQuadColumns) AmxInt8::quad_bytes(codes + c, out + c);
#endif
}

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

template <typename Kind, typename Element>
AmxActivations<Kind> amx_activations(const Element* x, int64_t m, int64_t k, int group_size, int act_bits) {
  AmxActivations<Kind> a;
  a.groups = group_count(k, group_size);
  a.step_bytes = amx_step_bytes(group_size);
  a.steps = a.groups * group_size / a.step_columns();
  a.rows = (m + kAmxRowBlock - 1) / kAmxRowBlock * kAmxRowBlock;
  // Every byte of the rows below m is written below; only the padding rows of the last block are zeroed.
  a.bytes.reset(new uint8_t[a.rows * a.steps * a.step_bytes]);
  a.zeros.resize(m * a.groups);
  a.scales.resize(m * a.groups);
  const int64_t padded = a.groups * group_size;  // columns, zero past k
  const int64_t step_columns = a.step_columns();
  const int64_t line_bytes = kAmxRowBlock * a.step_bytes;  // a slice's consecutive steps of one row
  for (int64_t r = m; r < a.rows; ++r) {
    for (int64_t slice = 0; slice < padded; slice += kAmxPanelDepth) {
      uint8_t* line = a.bytes.get() + a.offset(r, slice);
      for (int64_t step = slice; step < std::min(padded, slice + kAmxPanelDepth); step += step_columns) {
        std::memset(line, 0, a.step_bytes);
        line += line_bytes;
      }
    }
  }
  parallel_for(0, m, 16, [&](int64_t row_begin, int64_t row_end) {
    std::vector<float> row(padded, 0.0f);  // x in fp32, where it is not fp32 already
    std::vector<uint8_t> codes(padded, 0);  // stays 0 past k
    for (int64_t r = row_begin; r < row_end; ++r) {
      const float* values = row_as_fp32(x + r * k, k, row.data());
      for (int64_t g = 0; g < a.groups; ++g) {
        const int64_t columns = group_columns(k, group_size, g);
        uint8_t* group_codes = codes.data() + g * group_size;
        const ActivationGroupParams params = quantize_group(values + g * group_size, columns, act_bits, group_codes);
        if constexpr (Kind::kCentered) {
          // q_x - z_x as s8 bytes (the columns past k stay 0).
          for (int64_t c = 0; c < columns; ++c) group_codes[c] = static_cast<uint8_t>(group_codes[c] - params.zero);
        }
        a.zeros[r * a.groups + g] = static_cast<float>(params.zero);
        a.scales[r * a.groups + g] = params.scale;
      }
      // Step by step into the row's line of each step's tile (one offset per slice: the steps of a
      // slice's block are a line of 32 rows apart).
      for (int64_t slice = 0; slice < padded; slice += kAmxPanelDepth) {
        uint8_t* line = a.bytes.get() + a.offset(r, slice);
        const int64_t slice_end = std::min(padded, slice + kAmxPanelDepth);
        for (int64_t step = slice; step < slice_end; step += step_columns, line += line_bytes) {
          int8_step_bytes(codes.data() + step, step_columns, line);
        }
      }
    }
  });
  return a;
}

// The panel layout in plain C++ (the emulation's unpacking; the native path uses the AVX-512 packers of
// the same layout): the steps, each group's s_w and, for AmxInt8, sum q_w per output row.
template <typename Kind>
struct ScalarAmxPanel {
  static constexpr int64_t kQuads = kAmxPanelDepth / kAmxQuadColumns;
  static constexpr int64_t kGroups = kAmxPanelDepth / 32;  // at the smallest group size
  std::vector<int32_t> steps = std::vector<int32_t>(kQuads * Kind::kStepsPerQuad * kAmxPanelColumns);
  std::vector<float> scales = std::vector<float>(kGroups * kAmxPanelColumns);
  std::vector<float> weight_sums = std::vector<float>(kGroups * kAmxPanelColumns);

  // Columns [col_begin, col_begin + depth) of weight rows [row_begin, row_begin + 32); rows past n and
  // columns past k are 0.
  void pack(const uint8_t* qweight, const float* all_scales, int64_t n, int64_t k, int group_size, int64_t row_begin,
            int64_t col_begin, int64_t depth) {
    const int64_t groups = group_count(k, group_size);
    const int64_t first_group = col_begin / group_size;
    const int64_t panel_groups = group_count(depth, group_size);
    std::fill(steps.begin(), steps.end(), 0);
    std::fill(weight_sums.begin(), weight_sums.end(), 0.0f);
    for (int64_t j = 0; j < kAmxPanelColumns; ++j) {
      const int64_t output = row_begin + j;
      if (output >= n) {
        for (int64_t g = 0; g < panel_groups; ++g) scales[g * kAmxPanelColumns + j] = 0.0f;
        continue;
      }
      const uint8_t* row = qweight + output * (k / 2);
      for (int64_t quad = 0; quad * kAmxQuadColumns < depth; ++quad) {
        for (int s = 0; s < Kind::kStepsPerQuad; ++s) {
          const uint32_t dword = Kind::step_dword(row, k, col_begin / kAmxQuadColumns + quad, s);
          std::memcpy(&steps[(quad * Kind::kStepsPerQuad + s) * kAmxPanelColumns + j], &dword, 4);
        }
      }
      for (int64_t g = 0; g < panel_groups; ++g) {
        scales[g * kAmxPanelColumns + j] = all_scales[output * groups + first_group + g];
        if constexpr (Kind::kWeightSums) {
          const int64_t first = col_begin + g * group_size, last = std::min(first + group_size, k);
          float sum = 0.0f;
          for (int64_t c = first; c < last; ++c) sum += static_cast<float>(weight_code(row, c));
          weight_sums[g * kAmxPanelColumns + j] = sum;
        }
      }
    }
  }
};

// Groups whose sums are scaled into the totals together: each row's totals are loaded and stored once for
// all of them.
constexpr int kAmxBatchGroups = 2;

// totals[r][0..32) += the contributions of `count` (at most kAmxBatchGroups) consecutive groups for rows
// [first_row, last_row), from the groups' C tiles `batch_sums[b]` (the epilogue of the int8 kinds,
// docs/numerics.md section 3), group by group:
// - AmxInt8: P = sum q_x q_w - z_x sum q_w, exact in fp32 (integers below 2^24), times s_x s_w;
// - AmxInt8Centered: P = the C tiles' sum (q_x - z_x) q_w, times s_x s_w.
// z_x and s_x of row r's group b are zeros[r * params_stride + b] and row_scales[r * params_stride + b], the
// group's s_w and sum q_w at weight_scales and weight_sums + b * 32. On AVX-512 the 32 outputs' factors stay
// in registers over the rows; the scaling runs on the vector units beside the AMX unit's tile products, and
// it costs about as much as they do, so every instruction of it counts.
template <typename Kind>
void add_groups_to_totals(const uint32_t (*batch_sums)[kAmxRowBlock][kAmxPanelColumns], int count, int64_t first_row,
                          int64_t last_row, const float* zeros, const float* row_scales, int64_t params_stride,
                          const float* weight_scales, const float* weight_sums, float* totals) {
#if defined(DYQ_CPU_ISA_AVX512)
  __m512 scales_low[kAmxBatchGroups], scales_high[kAmxBatchGroups], sums_low[kAmxBatchGroups],
      sums_high[kAmxBatchGroups];
  for (int b = 0; b < count; ++b) {
    scales_low[b] = _mm512_loadu_ps(weight_scales + b * kAmxPanelColumns);
    scales_high[b] = _mm512_loadu_ps(weight_scales + b * kAmxPanelColumns + 16);
    if constexpr (!Kind::kCentered) {
      sums_low[b] = _mm512_loadu_ps(weight_sums + b * kAmxPanelColumns);
      sums_high[b] = _mm512_loadu_ps(weight_sums + b * kAmxPanelColumns + 16);
    }
  }
  for (int64_t r = first_row; r < last_row; ++r) {
    float* total = totals + r * kAmxPanelColumns;
    __m512 total_low = _mm512_loadu_ps(total), total_high = _mm512_loadu_ps(total + 16);
    for (int b = 0; b < count; ++b) {
      const __m512 row_scale = _mm512_set1_ps(row_scales[r * params_stride + b]);
      __m512 low = cvtepi32_ps(_mm512_load_si512(batch_sums[b][r]));
      __m512 high = cvtepi32_ps(_mm512_load_si512(batch_sums[b][r] + 16));
      if constexpr (!Kind::kCentered) {
        const __m512 zero = _mm512_set1_ps(zeros[r * params_stride + b]);
        low = _mm512_fnmadd_ps(zero, sums_low[b], low);
        high = _mm512_fnmadd_ps(zero, sums_high[b], high);
      }
      total_low = _mm512_fmadd_ps(low, _mm512_mul_ps(row_scale, scales_low[b]), total_low);
      total_high = _mm512_fmadd_ps(high, _mm512_mul_ps(row_scale, scales_high[b]), total_high);
    }
    _mm512_storeu_ps(total, total_low);
    _mm512_storeu_ps(total + 16, total_high);
  }
#else
  for (int64_t r = first_row; r < last_row; ++r) {
    float* total = totals + r * kAmxPanelColumns;
    for (int b = 0; b < count; ++b) {
      for (int64_t j = 0; j < kAmxPanelColumns; ++j) {
        // The centered codes' sums are P already: no z_x term.
        const float partial =
            static_cast<float>(static_cast<int32_t>(batch_sums[b][r][j])) -
            (Kind::kCentered ? 0.0f : zeros[r * params_stride + b] * weight_sums[b * kAmxPanelColumns + j]);
        total[j] += partial * (row_scales[r * params_stride + b] * weight_scales[b * kAmxPanelColumns + j]);
      }
    }
  }
#endif
}

// Panels unpacked per pass over the activations: each block of 32 activation rows is run against every
// panel of the pass while its A tiles are in the L1 cache, instead of coming from L2 once per panel, and
// each pass reads all the activations once (for 256 rows of k = 4096, 1 MiB of codes: half a core's L2,
// so that more panels per pass mean fewer reads of them from L3). Two panels' slices (2 x 8 KiB) and a
// block's A steps (8 KiB) leave room in a 48 KiB L1 for the C tile buffers and the totals being scaled.
constexpr int64_t kAmxPanelsPerPass = 2;

// Every output its bias (or 0): the product over no column. Returns whether every output is finite.
template <typename Element>
bool bias_outputs(const Element* bias, int64_t m, int64_t n, Element* out) {
  const std::vector<float> zeros(n, 0.0f);
  FiniteOutputs finite;
  for (int64_t r = 0; r < m; ++r) finite.note(store_row_from_fp32(zeros.data(), bias, n, out + r * n));
  return finite.all();
}

// out = x W^T (+ bias) through the tile loop: AmxInt8Centered at act_bits 2/4, AmxInt8 at 8.
// Panel is ScalarAmxPanel<Kind> or a packer of the same layout. Threads split the panels of 32 output rows; each
// configures its own tiles, takes its panels kAmxPanelsPerPass at a time, unpacks each slice of them once,
// runs the slice against every activation row, and keeps the running totals of their outputs for all rows.
// Returns whether every output is finite.
template <typename Tiles, typename Kind, typename Panel, typename Element>
bool amx_gemm(const Element* x, const uint8_t* qweight, const float* scales, const Element* bias, int64_t m, int64_t n,
              int64_t k, int group_size, int act_bits, Element* out) {
  // No column: no slice runs the loop below, whose last slice writes the outputs.
  if (k == 0) return bias_outputs(bias, m, n, out);
  const AmxActivations<Kind> a = amx_activations<Kind>(x, m, k, group_size, act_bits);
  const int64_t step_bytes = a.step_bytes;
  const int64_t step_columns = a.step_columns();
  constexpr int64_t kBStride = kAmxPanelColumns * 4;  // bytes of one B row: a dword per output
  // Everything the loops step by, computed once: a division per group cost as much as a tile product.
  const int64_t steps_per_group = group_size / step_columns;
  const int64_t groups_per_slice = kAmxPanelDepth / group_size;
  const int64_t a_step_bytes = kAmxRowBlock * step_bytes;                                  // a block's step
  const int64_t b_step_bytes = step_columns / (kAmxQuadColumns / Kind::kStepsPerQuad) * kBStride;  // B tile rows
  const int64_t panels = (n + kAmxPanelColumns - 1) / kAmxPanelColumns;
  FiniteOutputs finite;
  parallel_for(0, panels, 1, [&](int64_t panel_begin, int64_t panel_end) {
    Tiles tiles;
    tiles.configure(step_bytes);
    Panel pass_panels[kAmxPanelsPerPass];
    // A batch of groups' C tiles (kAmxBatchGroups consecutive groups of a block and panel) goes to one of
    // two buffers, and the previous batch's are scaled into the totals while this batch's tile products run,
    // a part of its rows after each group's products are issued: the AMX unit works through those while the
    // vector units scale, which would otherwise take turns (the scaling costs about as much as the products).
    alignas(64) uint32_t sums[2][kAmxBatchGroups][kAmxRowBlock][kAmxPanelColumns];
    struct Pending {
      int64_t row_begin = -1, rows = 0, group = 0, global_group = 0;  // group: the first, within the slice
      int count = 0, panel = 0;                                       // groups; panel within the pass
    } pending;
    std::vector<float> totals(kAmxPanelsPerPass * a.rows * kAmxPanelColumns);  // [panel][row][32]
    int64_t pass_begin = panel_begin;
    // The outputs (plus the bias) of a block of rows from its finished totals.
    auto write_outputs = [&](int panel, int64_t row_begin, int64_t rows, const float* block_totals) {
      const int64_t weight_row = (pass_begin + panel) * kAmxPanelColumns;
      const int64_t columns = std::min(kAmxPanelColumns, n - weight_row);
      for (int64_t r = 0; r < rows; ++r) {
        const float* total = block_totals + r * kAmxPanelColumns;
        finite.note(store_row_from_fp32(total, bias != nullptr ? bias + weight_row : nullptr, columns,
                                        out + (row_begin + r) * n + weight_row));
      }
    };
    // Adds a batch's contribution to the totals of rows [first_row, last_row) of its block.
    auto scale_into_totals = [&](const Pending& job, const uint32_t (*batch_sums)[kAmxRowBlock][kAmxPanelColumns],
                                 int64_t first_row, int64_t last_row) {
      const Panel& panel = pass_panels[job.panel];
      float* block_totals = &totals[(job.panel * a.rows + job.row_begin) * kAmxPanelColumns];
      add_groups_to_totals<Kind>(batch_sums, job.count, first_row, last_row,
                                 &a.zeros[job.row_begin * a.groups + job.global_group],
                                 &a.scales[job.row_begin * a.groups + job.global_group], a.groups,
                                 &panel.scales[job.group * kAmxPanelColumns],
                                 &panel.weight_sums[job.group * kAmxPanelColumns], block_totals);
      // The rows' last group: their outputs, written while the totals are in L1, and spread over the last
      // slice's tile work instead of in one burst at the end.
      if (job.global_group + job.count == a.groups) {
        write_outputs(job.panel, job.row_begin + first_row, last_row - first_row,
                      block_totals + first_row * kAmxPanelColumns);
      }
    };
    for (; pass_begin < panel_end; pass_begin += kAmxPanelsPerPass) {
      const int pass_count = static_cast<int>(std::min(kAmxPanelsPerPass, panel_end - pass_begin));
      std::fill(totals.begin(), totals.end(), 0.0f);
      for (int64_t slice = 0, slice_group = 0; slice < k; slice += kAmxPanelDepth, slice_group += groups_per_slice) {
        const int64_t depth = std::min(kAmxPanelDepth, k - slice);
        const int64_t slice_groups = group_count(depth, group_size);
        for (int i = 0; i < pass_count; ++i) {
          pass_panels[i].pack(qweight, scales, n, k, group_size, (pass_begin + i) * kAmxPanelColumns, slice, depth);
        }
        int buffer = 0;
        // The block's steps in this slice, one after another (AmxActivations).
        const uint8_t* a_steps = a.tile(0, slice);
        const int64_t a_block_bytes = a.slice_steps(slice) * a_step_bytes;
        for (int64_t row_begin = 0; row_begin < m; row_begin += kAmxRowBlock, a_steps += a_block_bytes) {
          for (int i = 0; i < pass_count; ++i) {
            const auto* b_steps = reinterpret_cast<const uint8_t*>(pass_panels[i].steps.data());
            // A last group cut by k reads steps past `depth`: their activations are 0, so whatever a packer
            // left there adds nothing.
            const uint8_t* a_tile = a_steps;
            const uint8_t* b_tile = b_steps;
            // One step of the 2 x 2 tiles, each operand loaded just before its first product.
            // A block of 16 rows or fewer (M <= 16, or the rows' last block) has nothing in its lower A tile:
            // its C2 and C3 are neither computed nor loaded or stored, half the block's tile work.
            const bool lower_half = m - row_begin > kAmxTileRows;
            auto step = [&] {
              tiles.template load<4>(a_tile, step_bytes);
              tiles.template load<6>(b_tile, kBStride);
              Kind::template product<0, 4, 6>(tiles);
              tiles.template load<7>(b_tile + 64, kBStride);
              Kind::template product<1, 4, 7>(tiles);
              if (lower_half) {
                tiles.template load<5>(a_tile + kAmxTileRows * step_bytes, step_bytes);
                Kind::template product<2, 5, 6>(tiles);
                Kind::template product<3, 5, 7>(tiles);
              }
              a_tile += a_step_bytes;
              b_tile += b_step_bytes;
            };
            for (int64_t group = 0; group < slice_groups; group += kAmxBatchGroups) {
              const int count = static_cast<int>(std::min<int64_t>(kAmxBatchGroups, slice_groups - group));
              for (int b = 0; b < count; ++b) {
                tiles.template zero<0>();
                tiles.template zero<1>();
                if (lower_half) {
                  tiles.template zero<2>();
                  tiles.template zero<3>();
                }
                for (int64_t s = 0; s < steps_per_group; ++s) step();
                if (pending.row_begin >= 0) {
                  scale_into_totals(pending, sums[buffer ^ 1], pending.rows * b / count,
                                    pending.rows * (b + 1) / count);
                }
                uint32_t(*group_sums)[kAmxPanelColumns] = sums[buffer][b];
                tiles.template store<0>(&group_sums[0][0], kBStride);
                tiles.template store<1>(&group_sums[0][16], kBStride);
                if (lower_half) {
                  tiles.template store<2>(&group_sums[16][0], kBStride);
                  tiles.template store<3>(&group_sums[16][16], kBStride);
                }
              }
              pending = {row_begin, std::min(kAmxRowBlock, m - row_begin), group, slice_group + group, count, i};
              buffer ^= 1;
            }
          }
        }
        // The slice's last batch, before the next slice is packed over its scales.
        scale_into_totals(pending, sums[buffer ^ 1], 0, pending.rows);
        pending = {};
      }
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

constexpr int64_t kAmxBf16StepColumns = 32;                  // columns of one tile product
constexpr int64_t kAmxBf16TileBytes = 16 * 64;               // one A or B tile
constexpr int64_t kAmxBf16StepsPerSlice = kAmxPanelDepth / kAmxBf16StepColumns;
constexpr int64_t kAmxBf16LoadColumns = 128;  // one 64-byte load of a packed row: four steps

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
  return step / 4 * kAmxBf16LoadColumns + 4 * element + step % 4;
}

// The activations as B tiles: for every block of 32 rows and step of 32 columns (nibble_order_words), the
// B tiles of its rows 0..15 and 16..31, each 16 rows (the step's column pairs) of 16 dwords (the bf16 pair
// of each activation row); slice by slice, within a slice block by block, within a block step by step, so
// that a block's pass over a slice reads one run. Columns past k, and the rows past m of the last block,
// are 0.
struct AmxBf16Activations {
  int64_t blocks = 0, steps = 0;  // steps over the columns padded to whole 128-column loads
  std::unique_ptr<uint8_t[]> bytes;

  // The B tile of rows [16 half, 16 half + 16) of `block` at `step`.
  uint8_t* tile(int64_t block, int64_t step, int half) const {
    const int64_t slice = step / kAmxBf16StepsPerSlice;
    const int64_t slice_steps = std::min(kAmxBf16StepsPerSlice, steps - slice * kAmxBf16StepsPerSlice);
    const int64_t step_index =
        slice * kAmxBf16StepsPerSlice * blocks + block * slice_steps + step % kAmxBf16StepsPerSlice;
    return bytes.get() + (2 * step_index + half) * kAmxBf16TileBytes;
  }
};

template <typename Element>
AmxBf16Activations amx_bf16_activations(const Element* x, int64_t m, int64_t k) {
  AmxBf16Activations a;
  a.blocks = (m + kAmxRowBlock - 1) / kAmxRowBlock;
  // Whole loads of 128 columns, which hold whole groups (G divides 128).
  const int64_t padded = group_count(k, kAmxBf16LoadColumns) * kAmxBf16LoadColumns;
  a.steps = padded / kAmxBf16StepColumns;
  a.bytes.reset(new uint8_t[a.blocks * a.steps * 2 * kAmxBf16TileBytes]);
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
        for (int64_t column = 0; column < padded; column += kAmxBf16LoadColumns) {
          alignas(64) uint16_t in_order[kAmxBf16LoadColumns];
          for (int64_t c = 0; c < kAmxBf16LoadColumns; c += kAmxBf16StepColumns) {
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
    const int64_t steps = group_count(depth, kAmxBf16LoadColumns) * kAmxBf16LoadColumns / kAmxBf16StepColumns;
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
struct AmxBf16Panel {
  // As ScalarAmxBf16Panel's.
  alignas(64) uint16_t values[kAmxBf16StepsPerSlice][kAmxPanelColumns][kAmxBf16StepColumns];

  void pack(const uint8_t* qweight, const float* all_scales, int64_t n, int64_t k, int group_size, int64_t row_begin,
            int64_t col_begin, int64_t depth) {
    if (group_size == 32) return pack_rows<32>(qweight, all_scales, n, k, row_begin, col_begin, depth);
    if (group_size == 64) return pack_rows<64>(qweight, all_scales, n, k, row_begin, col_begin, depth);
    pack_rows<128>(qweight, all_scales, n, k, row_begin, col_begin, depth);
  }

 private:
  template <int kGroup>
  void pack_rows(const uint8_t* qweight, const float* all_scales, int64_t n, int64_t k, int64_t row_begin,
                 int64_t col_begin, int64_t depth) {
    alignas(64) static constexpr float kCodes[16] = {0, 1, 2, 3, 4, 5, 6, 7, -8, -7, -6, -5, -4, -3, -2, -1};
    constexpr int kGroupsPerLoad = kAmxBf16LoadColumns / kGroup;
    constexpr int64_t kPrefetchSlices = 2;
    const __m512 codes = _mm512_load_ps(kCodes);
    const __m512i low_nibble = _mm512_set1_epi16(0x000F);
    // The group of each word of a load, in index bits 4 and 5: w / 16 at G = 64, w / 8 at G = 32.
    alignas(64) uint16_t word_groups[32];
    for (int w = 0; w < 32; ++w) word_groups[w] = static_cast<uint16_t>((w * kGroupsPerLoad / 32) << 4);
    const __m512i group_bits = _mm512_load_si512(word_groups);
    const int64_t groups = group_count(k, kGroup);
    const int64_t loads = group_count(depth, kAmxBf16LoadColumns);
    const int64_t row_bytes = k / 2;
    for (int64_t j = 0; j < kAmxPanelColumns; ++j) {
      const int64_t output = row_begin + j;
      if (output >= n) {
        for (int64_t step = 0; step < 4 * loads; ++step) std::memset(values[step][j], 0, sizeof(values[step][j]));
        continue;
      }
      const uint8_t* row = qweight + output * row_bytes + col_begin / 2;
      const float* row_scales = all_scales + output * groups;
      // The row's bytes two slices on: the rows of a pass, read 128 bytes a slice each, are more streams than
      // the hardware prefetchers follow (without it, 4096 x 4096 at 16 rows took twice as long on the Xeon
      // with AMX; one slice ahead was about as fast, 2 % to 10 % slower at 64 and 256 rows).
      if (col_begin + kPrefetchSlices * kAmxPanelDepth < k) {
        const uint8_t* next = row + kPrefetchSlices * kAmxPanelDepth / 2;
        _mm_prefetch(reinterpret_cast<const char*>(next), _MM_HINT_T0);
        _mm_prefetch(reinterpret_cast<const char*>(next + 64), _MM_HINT_T0);
      }
      for (int64_t load = 0; load < loads; ++load) {
        const int64_t column = col_begin + load * kAmxBf16LoadColumns;
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

// Panels per pass over the activations (AMX-BF16): the totals of a pass's panels stay in L2 while each slice
// of the activations (16 KiB per block) is read once from memory per pass and from L2 once per panel.
constexpr int64_t kAmxBf16PanelsPerPass = 8;

// out = x W^T (+ bias) at act_bits 16 through the AMX-BF16 tiles with the weights as A (above). Panel is
// ScalarAmxBf16Panel or AmxBf16Panel. Threads split the panels of 32 output rows; each takes them
// kAmxBf16PanelsPerPass at a time, and per slice of columns unpacks each panel of the pass into one buffer
// and runs it against every block of activation rows, accumulating onto the totals of the pass,
// [panel][block][output row][activation row], which the C tiles load and store once per slice. The buffer
// (16 KiB) stays in L1 from its unpacking to its last tile load: with the pass's slices unpacked at once
// (128 KiB), their stores went to L2 and bound the unpacking (4096 x 4096 at 16 rows, one thread, the
// unpacking alone 1.2 to 1.4 ms against 0.65 to 1.05 into one buffer), and the tile loads read the same
// bytes from L2 (the weights then, the activations now).
template <typename Tiles, typename Panel, typename Element>
bool amx_bf16_gemm(const Element* x, const uint8_t* qweight, const float* scales, const Element* bias, int64_t m,
                   int64_t n, int64_t k, int group_size, Element* out) {
  // No column: no slice runs the loop below, whose last slice writes the outputs.
  if (k == 0) return bias_outputs(bias, m, n, out);
  const AmxBf16Activations a = amx_bf16_activations(x, m, k);
  constexpr int64_t kBlockTotals = kAmxPanelColumns * kAmxRowBlock;  // a panel's totals of one block
  constexpr int64_t kTotalsStride = kAmxRowBlock * 4;                // bytes between two output rows' totals
  const int64_t panels = (n + kAmxPanelColumns - 1) / kAmxPanelColumns;
  constexpr int64_t kWeightStride = kAmxBf16StepColumns * 2;    // bytes between two rows of a panel's step
  constexpr int64_t kLowerRows = kAmxTileRows * kWeightStride;  // a step's rows 16..31
  FiniteOutputs finite;
  parallel_for(0, panels, 1, [&](int64_t panel_begin, int64_t panel_end) {
    Tiles tiles;
    tiles.configure(64);
    std::unique_ptr<Panel> panel(new Panel);
    // As many panels as a pass of this thread takes: a small layer's call allocates no more.
    const int64_t pass_size = std::min(kAmxBf16PanelsPerPass, panel_end - panel_begin);
    // [panel][block][output row 0..31][activation row 0..31]: a C tile's rows 128 bytes apart.
    std::vector<float> totals(pass_size * a.blocks * kBlockTotals);
    alignas(64) std::array<float, kBlockTotals> outputs;  // a block's outputs: [activation row][output row]
    const auto* weights = reinterpret_cast<const uint8_t*>(&panel->values[0][0][0]);
    for (int64_t pass_begin = panel_begin; pass_begin < panel_end; pass_begin += pass_size) {
      const int pass_count = static_cast<int>(std::min(pass_size, panel_end - pass_begin));
      std::fill(totals.begin(), totals.end(), 0.0f);
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
            float* block_totals = &totals[(i * a.blocks + block) * kBlockTotals];
            uint8_t* totals_bytes = reinterpret_cast<uint8_t*>(block_totals);
            constexpr int64_t kLowerTotals = kAmxTileRows * kTotalsStride, kRightTotals = kAmxTileRows * 4;
            tiles.template load<0>(totals_bytes, kTotalsStride);
            tiles.template load<2>(totals_bytes + kLowerTotals, kTotalsStride);
            if (second_half) {
              tiles.template load<1>(totals_bytes + kRightTotals, kTotalsStride);
              tiles.template load<3>(totals_bytes + kLowerTotals + kRightTotals, kTotalsStride);
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
            tiles.template store<0>(totals_bytes, kTotalsStride);
            tiles.template store<2>(totals_bytes + kLowerTotals, kTotalsStride);
            if (second_half) {
              tiles.template store<1>(totals_bytes + kRightTotals, kTotalsStride);
              tiles.template store<3>(totals_bytes + kLowerTotals + kRightTotals, kTotalsStride);
            }
            if (last_slice) {
              // The block's outputs (plus the bias): its totals transposed to activation rows.
              const int64_t columns = std::min(kAmxPanelColumns, n - weight_row);
              const int64_t row_begin = block * kAmxRowBlock, block_rows = std::min(kAmxRowBlock, m - row_begin);
              transpose_block_totals(block_totals, second_half, outputs.data());
              for (int64_t r = 0; r < block_rows; ++r) {
                finite.note(store_row_from_fp32(&outputs[r * kAmxPanelColumns],
                                                bias != nullptr ? bias + weight_row : nullptr, columns,
                                                out + (row_begin + r) * n + weight_row));
              }
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
