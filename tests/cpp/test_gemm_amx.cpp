// The AMX tile loop (gemm/gemm_cpu_amx.h) against the double-precision naive GEMM: through scalar tile
// operations on every CPU, and through the AMX instructions where the CPU has them.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <string>
#include <tuple>
#include <vector>

#include "cpu/cpu_isa.h"
#include "gemm/gemm_cpu_amx.h"
#include "gemm/gemm_cpu_amx_emulated.h"
#include "naive_reference.h"

namespace {

struct AmxProblem {
  int64_t m, n, k;
  int group_size;
};

template <typename Gemm>
void expect_matches_reference(const AmxProblem& p, int act_bits, Gemm&& gemm, const std::string& what) {
  const auto x = naive::random_values(p.m * p.k, 11u + static_cast<uint32_t>(p.m));
  const auto weight = naive::random_values(p.n * p.k, 12u + static_cast<uint32_t>(p.n), 0.05f);
  const auto bias = naive::random_values(p.n, 13u);
  const auto quantized = naive::quantize_weight(weight, p.n, p.k, p.group_size);
  const auto qweight = naive::pack_weight(quantized.codes);
  const auto ref = naive::gemm(x, quantized, bias, p.m, p.n, p.k, p.group_size, act_bits);
  std::vector<float> out(p.m * p.n, -12345.0f);
  gemm(x.data(), qweight.data(), quantized.scales.data(), bias.data(), out.data());
  // fp32 sums; at act_bits 16 the tile loop rounds x and the dequantized weights q_w s_w to bf16
  // (docs/numerics.md, section 3): up to 2^-7 + 2^-16 of each term (2^-8 each, and their product).
  const double relative = 1e-5 + (act_bits == 16 ? std::ldexp(1.0, -7) + std::ldexp(1.0, -16) : 0.0);
  double worst = 0.0;
  for (size_t i = 0; i < out.size(); ++i) {
    ASSERT_NEAR(out[i], ref.value[i], 1e-6 + relative * ref.magnitude[i]) << what << " element " << i;
    worst = std::max(worst, std::fabs(out[i] - ref.value[i]) / (1e-6 + ref.magnitude[i]));
  }
  if (act_bits == 16) {
    // Rounding to bf16 must show: an fp32 loop that skipped it would be far more exact than 2^-8.
    EXPECT_GT(worst, 1e-5) << what << ": x was not rounded to bf16";
  }
}

// m below, at and above the 32 rows of a block, and from the rows where the dispatch takes the tiles (W4A16
// from 4, W4A4 and W4A2 from 10, W4A8 from 12); n not a multiple of a 32-column panel (output rows past n among
// the 8 whose sums of q_w the int8 panels reduce together), and one, two and three panels, and 17 panels (a
// pass takes eight); k with a remainder group, k not a multiple of 8 (a step's last columns past k), and k
// over one or more 256-column slices of a panel.
const AmxProblem kProblems[] = {{1, 40, 256, 128}, {17, 33, 192, 64},  {32, 64, 128, 32},  {45, 70, 200, 64},
                                {70, 31, 352, 32}, {33, 40, 600, 128}, {20, 90, 202, 32},  {5, 300, 130, 32},
                                {40, 520, 300, 64}, {11, 70, 200, 32}, {13, 45, 264, 128}};

class AmxTileLoopTest : public ::testing::TestWithParam<int> {};

// The "amx" CPU path where this CPU runs it, else nullptr.
const dyq::cpu::CpuPath* amx_path() {
  for (const auto* path : dyq::cpu::runnable_cpu_paths()) {
    if (std::string(path->name) == "amx") return path;
  }
  return nullptr;
}

TEST_P(AmxTileLoopTest, EmulatedTilesMatchTheNaiveReference) {
  const int act_bits = GetParam();
  for (const AmxProblem& p : kProblems) {
    expect_matches_reference(p, act_bits, [&](const float* x, const uint8_t* qweight, const float* scales,
                                              const float* bias, float* out) {
      dyq::cpu::amx_emulated_gemm(x, qweight, scales, bias, p.m, p.n, p.k, p.group_size, act_bits, out);
    }, "emulated m " + std::to_string(p.m) + " k " + std::to_string(p.k));
  }
}

TEST_P(AmxTileLoopTest, AmxTilesMatchTheNaiveReference) {
  const dyq::cpu::CpuPath* amx = amx_path();
  if (amx == nullptr) GTEST_SKIP() << "this CPU has no AMX-INT8 and AMX-BF16 (or the OS did not grant the tile state)";
  const int act_bits = GetParam();
  for (const AmxProblem& p : kProblems) {
    expect_matches_reference(p, act_bits, [&](const float* x, const uint8_t* qweight, const float* scales,
                                              const float* bias, float* out) {
      amx->kernels->gemm(x, dyq::ScalarType::kFloat32, qweight, scales, bias, p.m, p.n, p.k, p.group_size, act_bits,
                         out);
    }, std::string(amx->kernels->gemm_kernel(p.m, p.k, p.group_size, act_bits)) + " m " + std::to_string(p.m));
  }
}

// K = 0: the loop has no slice to run, and every output must still be its bias, on 16 to 40 rows and part
// of a panel, one panel and two.
TEST_P(AmxTileLoopTest, NoColumnsGiveTheBias) {
  const int act_bits = GetParam();
  const dyq::cpu::CpuPath* amx = amx_path();
  for (const int64_t m : {16, 40}) {
    for (const int64_t n : {37, 32, 64}) {
      const auto bias = naive::random_values(n, 17u + static_cast<uint32_t>(n));
      const std::vector<float> x(1), scales(1);
      const std::vector<uint8_t> qweight(1);
      std::vector<float> out(m * n, -12345.0f);
      dyq::cpu::amx_emulated_gemm(x.data(), qweight.data(), scales.data(), bias.data(), m, n, 0, 32, act_bits,
                                  out.data());
      for (int64_t i = 0; i < m * n; ++i) ASSERT_EQ(out[i], bias[i % n]) << "emulated m " << m << " n " << n;
      if (amx == nullptr) continue;
      std::fill(out.begin(), out.end(), -12345.0f);
      amx->kernels->gemm(x.data(), dyq::ScalarType::kFloat32, qweight.data(), scales.data(), bias.data(), m, n, 0, 32,
                         act_bits, out.data());
      for (int64_t i = 0; i < m * n; ++i) ASSERT_EQ(out[i], bias[i % n]) << "amx m " << m << " n " << n;
    }
  }
}

// 2, 4 and 8 through AMX-INT8, 16 (the fallback) through AMX-BF16.
INSTANTIATE_TEST_SUITE_P(EveryWidth, AmxTileLoopTest, ::testing::Values(2, 4, 8, 16));

TEST(AmxTileLoop, RejectsAnUnregisteredWidth) {
  std::vector<float> x(2 * 64), scales(2), out(4);
  std::vector<uint8_t> qweight(2 * 32);
  EXPECT_THROW(dyq::cpu::amx_emulated_gemm(x.data(), qweight.data(), scales.data(), nullptr, 2, 2, 64, 64, 3,
                                           out.data()),
               std::invalid_argument);
}

// tdpbf16ps as the instruction defines it: bf16 denormal inputs read as 0, fp32 denormal results flushed.
TEST(AmxTileLoop, EmulatedBf16ProductFlushesDenormals) {
  dyq::cpu::portable::EmulatedTiles tiles;
  tiles.configure(64);
  for (int t = 0; t < 8; ++t) std::memset(tiles.tiles[t], 0, sizeof(tiles.tiles[t]));
  auto put = [&](int tile, int row, int word, float value) {
    const uint16_t bits = dyq::cpu::portable::bf16_bits(value);
    std::memcpy(&tiles.tiles[tile][row][2 * word], &bits, 2);
  };
  put(4, 0, 0, 3.0f);      // A[0] dword 0: (3, 2^-130: a bf16 denormal)
  put(4, 0, 1, 0x1p-130f);
  put(6, 0, 0, 5.0f);      // B row 0, output 0: (5, 1)
  put(6, 0, 1, 1.0f);
  put(4, 1, 0, 0x1p-70f);  // A[1]: 2^-70 * 2^-70 = 2^-140, an fp32 denormal
  put(6, 0, 2, 0x1p-70f);  // B row 0, output 1
  put(4, 1, 2, 0x1p-70f);  // A[1] dword 1 times B row 1, output 1
  put(6, 1, 2, 0x1p-70f);
  tiles.dpbf16ps<0, 4, 6>();
  float c00, c11;
  std::memcpy(&c00, &tiles.tiles[0][0][0], 4);
  std::memcpy(&c11, &tiles.tiles[0][1][4], 4);
  EXPECT_EQ(c00, 15.0f);  // 3 * 5 + (denormal, read as 0) * 1
  EXPECT_EQ(c11, 0.0f);   // 2^-140 + 2^-140 are denormal sums, flushed
}

// The AMX-BF16 panels' weights: q_w s_w formed in fp32, then rounded to the nearest bf16 (ties to even),
// against a rounding found by comparing distances in double; products below 2^-126 count as 0.
TEST(AmxTileLoop, DequantizedWeightsRoundToNearestBf16AndReadSubnormalsAsZero) {
  auto nearest_bf16 = [](float value) {
    uint32_t bits;
    std::memcpy(&bits, &value, 4);
    const uint32_t down = bits & 0xFFFF0000u, up = down + 0x10000u;
    float low, high;
    std::memcpy(&low, &down, 4);
    std::memcpy(&high, &up, 4);
    const double to_low = std::fabs(double{value} - low), to_high = std::fabs(double{high} - value);
    if (to_low != to_high) return static_cast<uint16_t>((to_low < to_high ? down : up) >> 16);
    return static_cast<uint16_t>(((down >> 16) & 1u) == 0 ? down >> 16 : up >> 16);
  };
  uint32_t state = 12345u;
  for (int i = 0; i < 20000; ++i) {
    state = state * 1664525u + 1013904223u;
    const int code = static_cast<int>(state >> 28) - 8;
    const float scale = std::ldexp(1.0f + static_cast<float>((state >> 4) & 0xFFFFFu) / 1048576.0f,
                                   static_cast<int>((state >> 24) & 15u) - 12);
    const float product = static_cast<float>(code) * scale;
    EXPECT_EQ(dyq::cpu::portable::dequantized_bf16_bits(code, scale), nearest_bf16(product))
        << code << " * " << scale;
  }
  EXPECT_EQ(dyq::cpu::portable::dequantized_bf16_bits(1, 0x1p-127f) & 0x7FFFu, 0u);  // 2^-127: subnormal, read as 0
  EXPECT_EQ(dyq::cpu::portable::dequantized_bf16_bits(-3, 0x1p-128f) & 0x7FFFu, 0u);
  const float smallest_kept = 7 * 0x1p-127f;  // 1.75 * 2^-125: normal
  EXPECT_EQ(dyq::cpu::portable::dequantized_bf16_bits(7, 0x1p-127f), nearest_bf16(smallest_kept));
}

}  // namespace
