// The AMX tile loop (gemm/gemm_cpu_amx.h) against the double-precision naive GEMM: through scalar tile
// operations on every CPU, and through the AMX instructions where the CPU has them.
#include <gtest/gtest.h>

#include <cmath>
#include <string>
#include <tuple>
#include <vector>

#include "cpu/cpu_isa.h"
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
  for (size_t i = 0; i < out.size(); ++i) {
    ASSERT_NEAR(out[i], ref.value[i], 1e-6 + 1e-5 * ref.magnitude[i]) << what << " element " << i;
  }
}

// m below, at and above the 32 rows of a pass; n not a multiple of a 32-column panel; k with a remainder group.
const AmxProblem kProblems[] = {{1, 40, 256, 128}, {17, 33, 192, 64}, {32, 64, 128, 32}, {45, 70, 200, 64},
                                {70, 31, 352, 32}};

class AmxTileLoopTest : public ::testing::TestWithParam<int> {};

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
  const dyq::cpu::CpuPath* amx = nullptr;
  for (const auto* path : dyq::cpu::runnable_cpu_paths()) {
    if (std::string(path->name) == "amx") amx = path;
  }
  if (amx == nullptr) GTEST_SKIP() << "this CPU has no AMX-INT8 (or the OS did not grant the tile state)";
  const int act_bits = GetParam();
  for (const AmxProblem& p : kProblems) {
    expect_matches_reference(p, act_bits, [&](const float* x, const uint8_t* qweight, const float* scales,
                                              const float* bias, float* out) {
      amx->kernels->gemm(x, dyq::ScalarType::kFloat32, qweight, scales, bias, p.m, p.n, p.k, p.group_size, act_bits,
                         out);
    }, std::string(amx->kernels->gemm_kernel(p.m, p.k, p.group_size, act_bits)) + " m " + std::to_string(p.m));
  }
}

INSTANTIATE_TEST_SUITE_P(QuantizedWidths, AmxTileLoopTest, ::testing::Values(2, 4, 8));

TEST(AmxTileLoop, RejectsTheFallbackWidth) {
  std::vector<float> x(2 * 64), scales(2), out(4);
  std::vector<uint8_t> qweight(2 * 32);
  EXPECT_THROW(dyq::cpu::amx_emulated_gemm(x.data(), qweight.data(), scales.data(), nullptr, 2, 2, 64, 64, 16,
                                           out.data()),
               std::invalid_argument);
}

}  // namespace
