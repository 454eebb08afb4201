// The AMX-INT8 tile loop of the act_bits 2/4/8 GEMM (docs/numerics.md, section 3), written once over a
// Tiles type: NativeTiles issues the AMX instructions (the "amx" path, cpu/kernels_avx512_amx.cpp), and
// EmulatedTiles performs the same tile operations in scalar C++, so that the blocking, the tile
// configuration and the epilogue are tested on every CPU (gemm/gemm_cpu_amx_emulated.h).
//
// Data layout. The activations are u8 codes q_x, row-major with a pitch of whole groups (zeros past k,
// rows padded to 32 with zeros), with each (row, group)'s z_x and s_x beside them. A panel of 32 weight
// rows is packed as s8 codes in the VNNI order tdpbusd reads its B operand in: row t of the packed panel
// holds, for each of the 32 output columns j, the four codes q_w[j, 4t..4t+3] (128 bytes a row), so that
// its left and right 64 bytes are the B tiles of output columns 0..15 and 16..31. Tiles: C0..C3 = the 2 x 2
// int32 accumulators of 32 activation rows x 32 output columns, A0/A1 = 16 activation rows x kStep bytes,
// B0/B1 = kStep / 4 rows x 64 bytes. kStep is 64 columns (the widest A tile), or the group size where it is
// smaller, so that one group is a whole number of steps.
//
// Per group, the C tiles hold the exact integer sums sum q_x q_w (below 2^24); they are stored and the
// epilogue forms s_x s_w (sum q_x q_w - z_x sum q_w) in fp32, as the VNNI kernels do.
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <vector>

#include "activation/act_quant_cpu_row.h"
#include "common/cpu_dtype.h"
#include "common/format.h"
#include "cpu/isa_region.h"
#include "parallel/parallel.h"

DYQ_ISA_BEGIN
namespace dyq::cpu::DYQ_ISA_NAMESPACE {

constexpr int64_t kAmxTileRows = 16;    // rows of an A or C tile
constexpr int64_t kAmxRowBlock = 32;    // activation rows per pass: two A tiles
constexpr int64_t kAmxPanelColumns = 32;  // output columns per panel: two B tiles
constexpr int64_t kAmxMaxStep = 64;     // columns of K per tdpbusd: an A tile row of 64 bytes

inline int64_t amx_step(int group_size) { return std::min<int64_t>(kAmxMaxStep, group_size); }

// The tile registers in memory, with the operations the loop uses, each as the AMX instruction defines it.
struct EmulatedTiles {
  alignas(64) uint8_t tiles[8][16][64];
  int rows[8], bytes[8];

  void configure(int64_t step) {
    for (int t = 0; t < 4; ++t) rows[t] = 16, bytes[t] = 64;                    // C: 16 x 16 int32
    for (int t = 4; t < 6; ++t) rows[t] = 16, bytes[t] = static_cast<int>(step);  // A: 16 rows x step u8
    for (int t = 6; t < 8; ++t) rows[t] = static_cast<int>(step / 4), bytes[t] = 64;  // B: step/4 rows x 16 x 4 s8
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
  // tdpbusd: C[m][n] += sum over the dwords i of A's row m of sum_b u8 A[m][4i + b] * s8 B[i][4n + b].
  template <int kC, int kA, int kB>
  void dpbusd() {
    for (int m = 0; m < rows[kA]; ++m) {
      for (int n = 0; n < bytes[kC] / 4; ++n) {
        int32_t sum;
        std::memcpy(&sum, &tiles[kC][m][4 * n], 4);
        for (int i = 0; i < bytes[kA] / 4; ++i) {
          for (int b = 0; b < 4; ++b) {
            sum += int32_t{tiles[kA][m][4 * i + b]} * int32_t{static_cast<int8_t>(tiles[kB][i][4 * n + b])};
          }
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
  void configure(int64_t step) {
    struct alignas(64) {
      uint8_t palette = 1, start_row = 0, reserved[14] = {};
      uint16_t colsb[16] = {};
      uint8_t rows[16] = {};
    } config;
    for (int t = 0; t < 4; ++t) config.colsb[t] = 64, config.rows[t] = 16;
    for (int t = 4; t < 6; ++t) config.colsb[t] = static_cast<uint16_t>(step), config.rows[t] = 16;
    for (int t = 6; t < 8; ++t) config.colsb[t] = 64, config.rows[t] = static_cast<uint8_t>(step / 4);
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
  void release() { _tile_release(); }
};
#endif

// Activations as the tile loop reads them.
struct AmxActivations {
  int64_t rows = 0, pitch = 0, groups = 0;
  std::vector<uint8_t> codes;  // [rows padded to kAmxRowBlock][pitch]
  std::vector<float> zeros, scales;  // [m][groups]
};

template <typename Element>
AmxActivations quantize_amx_activations(const Element* x, int64_t m, int64_t k, int group_size, int act_bits) {
  AmxActivations a;
  a.groups = group_count(k, group_size);
  a.pitch = a.groups * group_size;
  a.rows = (m + kAmxRowBlock - 1) / kAmxRowBlock * kAmxRowBlock;
  a.codes.assign(a.rows * a.pitch, 0);
  a.zeros.assign(m * a.groups, 0.0f);
  a.scales.assign(m * a.groups, 0.0f);
  parallel_for(0, m, 4, [&](int64_t row_begin, int64_t row_end) {
    std::vector<float> row(k);
    std::vector<ActivationGroupParams> params(a.groups);
    for (int64_t r = row_begin; r < row_end; ++r) {
      quantize_activation_row(x + r * k, k, group_size, act_bits, row.data(), a.codes.data() + r * a.pitch,
                              params.data());
      for (int64_t g = 0; g < a.groups; ++g) {
        a.zeros[r * a.groups + g] = static_cast<float>(params[g].zero);
        a.scales[r * a.groups + g] = params[g].scale;
      }
    }
  });
  return a;
}

// Weight rows [row_begin, row_begin + 32) in the VNNI order of the B tiles, [pitch / 4][32][4] s8 (rows past
// n and columns past k are 0), and each group's sum q_w per output column, [groups][32].
inline void pack_amx_panel(const uint8_t* qweight, int64_t n, int64_t k, int group_size, int64_t pitch,
                           int64_t row_begin, int8_t* panel, float* weight_sums) {
  const int64_t groups = pitch / group_size;
  std::memset(panel, 0, pitch * kAmxPanelColumns);
  std::fill(weight_sums, weight_sums + groups * kAmxPanelColumns, 0.0f);
  for (int64_t j = 0; j < kAmxPanelColumns && row_begin + j < n; ++j) {
    const uint8_t* row = qweight + (row_begin + j) * (k / 2);
    for (int64_t c = 0; c < k; ++c) {
      const int code = sign_extend_nibble(c % 2 == 0 ? row[c / 2] & 0xFu : row[c / 2] >> 4);
      panel[(c / 4) * kAmxPanelColumns * 4 + j * 4 + c % 4] = static_cast<int8_t>(code);
      weight_sums[(c / group_size) * kAmxPanelColumns + j] += static_cast<float>(code);
    }
  }
}

// out = x W^T (+ bias) at a quantized act_bits through the tile loop. Threads split the panels; each
// thread configures its own tiles.
template <typename Tiles, typename Element>
void amx_gemm(const Element* x, const uint8_t* qweight, const float* scales, const Element* bias, int64_t m, int64_t n,
              int64_t k, int group_size, int act_bits, Element* out) {
  const AmxActivations a = quantize_amx_activations(x, m, k, group_size, act_bits);
  const int64_t step = amx_step(group_size);
  const int64_t panels = (n + kAmxPanelColumns - 1) / kAmxPanelColumns;
  parallel_for(0, panels, 1, [&](int64_t panel_begin, int64_t panel_end) {
    Tiles tiles;
    tiles.configure(step);
    std::vector<int8_t> panel(a.pitch * kAmxPanelColumns);
    std::vector<float> weight_sums(a.groups * kAmxPanelColumns);
    alignas(64) int32_t sums[kAmxRowBlock][kAmxPanelColumns];
    std::vector<float> totals(kAmxRowBlock * kAmxPanelColumns);
    for (int64_t p = panel_begin; p < panel_end; ++p) {
      const int64_t weight_row = p * kAmxPanelColumns;
      const int64_t columns = std::min(kAmxPanelColumns, n - weight_row);
      pack_amx_panel(qweight, n, k, group_size, a.pitch, weight_row, panel.data(), weight_sums.data());
      for (int64_t row_begin = 0; row_begin < m; row_begin += kAmxRowBlock) {
        const int64_t rows = std::min(kAmxRowBlock, m - row_begin);
        std::fill(totals.begin(), totals.end(), 0.0f);
        for (int64_t g = 0; g < a.groups; ++g) {
          tiles.template zero<0>();
          tiles.template zero<1>();
          tiles.template zero<2>();
          tiles.template zero<3>();
          for (int64_t c = g * group_size; c < (g + 1) * group_size; c += step) {
            const uint8_t* a_tile = a.codes.data() + row_begin * a.pitch + c;
            const int8_t* b_tile = panel.data() + (c / 4) * kAmxPanelColumns * 4;
            tiles.template load<4>(a_tile, a.pitch);
            tiles.template load<5>(a_tile + kAmxTileRows * a.pitch, a.pitch);
            tiles.template load<6>(b_tile, kAmxPanelColumns * 4);
            tiles.template load<7>(b_tile + 64, kAmxPanelColumns * 4);
            tiles.template dpbusd<0, 4, 6>();
            tiles.template dpbusd<1, 4, 7>();
            tiles.template dpbusd<2, 5, 6>();
            tiles.template dpbusd<3, 5, 7>();
          }
          constexpr int64_t kStride = kAmxPanelColumns * 4;
          tiles.template store<0>(&sums[0][0], kStride);
          tiles.template store<1>(&sums[0][16], kStride);
          tiles.template store<2>(&sums[16][0], kStride);
          tiles.template store<3>(&sums[16][16], kStride);
          const float* group_sums = weight_sums.data() + g * kAmxPanelColumns;
          for (int64_t r = 0; r < rows; ++r) {
            const float zero = a.zeros[(row_begin + r) * a.groups + g];
            const float row_scale = a.scales[(row_begin + r) * a.groups + g];
            for (int64_t j = 0; j < columns; ++j) {
              // P = sum q_x q_w - z_x sum q_w, exact in fp32 (integers below 2^24).
              const float partial = static_cast<float>(sums[r][j]) - zero * group_sums[j];
              const float scale = row_scale * scales[(weight_row + j) * a.groups + g];
              totals[r * kAmxPanelColumns + j] += partial * scale;
            }
          }
        }
        for (int64_t r = 0; r < rows; ++r) {
          for (int64_t j = 0; j < columns; ++j) {
            const float bias_value = bias != nullptr ? to_float(bias[weight_row + j]) : 0.0f;
            out[(row_begin + r) * n + weight_row + j] = from_float<Element>(totals[r * kAmxPanelColumns + j] + bias_value);
          }
        }
      }
    }
    tiles.release();
  });
}

}  // namespace dyq::cpu::DYQ_ISA_NAMESPACE
DYQ_ISA_END
