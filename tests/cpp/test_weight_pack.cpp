// INT4 weight quantization against the naive loops of docs/numerics.md, section 1.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "naive_reference.h"
#include "weight/weight_pack_cpu.h"

namespace {

struct Packed {
  std::vector<uint8_t> qweight;
  std::vector<float> scales;
  bool ok;
};

Packed quantize(const std::vector<float>& weight, int64_t n, int64_t k, int group_size) {
  Packed p{std::vector<uint8_t>(n * k / 2), std::vector<float>(n * k / group_size), false};
  p.ok = dyq::cpu::quantize_weight(weight.data(), n, k, group_size, p.qweight.data(), p.scales.data());
  return p;
}

class WeightPackTest : public ::testing::TestWithParam<int> {};

TEST_P(WeightPackTest, MatchesNaiveCodesAndScalesExactly) {
  const int group_size = GetParam();
  for (auto [n, k] : {std::pair<int64_t, int64_t>{1, group_size}, {37, 3 * group_size}, {130, 4 * group_size}}) {
    const auto weight = naive::random_values(n * k, 7 + n, 0.05f);
    const Packed packed = quantize(weight, n, k, group_size);
    ASSERT_TRUE(packed.ok);
    const auto expected = naive::quantize_weight(weight, n, k, group_size);
    EXPECT_EQ(packed.qweight, naive::pack_weight(expected.codes)) << "n " << n << " k " << k;
    EXPECT_EQ(packed.scales, expected.scales);
  }
}

TEST_P(WeightPackTest, DequantizesToScaleTimesCode) {
  const int group_size = GetParam();
  const int64_t n = 19, k = 2 * group_size;
  const auto weight = naive::random_values(n * k, 3);
  const Packed packed = quantize(weight, n, k, group_size);
  std::vector<float> dequantized(n * k);
  dyq::cpu::dequantize_weight(packed.qweight.data(), packed.scales.data(), n, k, group_size, dequantized.data());
  const auto expected = naive::quantize_weight(weight, n, k, group_size);
  for (int64_t i = 0; i < n * k; ++i) {
    ASSERT_EQ(dequantized[i], expected.scales[i / group_size] * static_cast<float>(expected.codes[i])) << i;
  }
}

INSTANTIATE_TEST_SUITE_P(GroupSizes, WeightPackTest, ::testing::Values(32, 64, 128));

TEST(WeightPack, RoundsHalfToEven) {
  // absmax 7 gives scale 1, so each value is its own ratio: 0.5 -> 0, 1.5 -> 2, 2.5 -> 2, -0.5 -> 0, -1.5 -> -2.
  std::vector<float> weight(32, 0.0f);
  weight[0] = 7.0f;
  weight[1] = 0.5f;
  weight[2] = 1.5f;
  weight[3] = 2.5f;
  weight[4] = -0.5f;
  weight[5] = -1.5f;
  const Packed packed = quantize(weight, 1, 32, 32);
  EXPECT_EQ(packed.scales[0], 1.0f);
  EXPECT_EQ(packed.qweight[0], 0x07);  // 7, 0
  EXPECT_EQ(packed.qweight[1], 0x22);  // 2, 2
  EXPECT_EQ(packed.qweight[2], 0xE0);  // 0, -2
}

TEST(WeightPack, NegativeCodesAreTwosComplementNibbles) {
  std::vector<float> weight(32, 0.0f);
  weight[0] = -7.0f;
  weight[1] = -1.0f;
  const Packed packed = quantize(weight, 1, 32, 32);
  EXPECT_EQ(packed.qweight[0], 0xF9);  // -7 = 0x9 low, -1 = 0xF high
}

TEST(WeightPack, AllZeroGroupGetsScaleOneAndZeroCodes) {
  const int64_t k = 64;
  auto weight = naive::random_values(k, 5);
  for (int i = 0; i < 32; ++i) weight[32 + i] = 0.0f;
  const Packed packed = quantize(weight, 1, k, 32);
  EXPECT_EQ(packed.scales[1], 1.0f);
  for (int j = 16; j < 32; ++j) EXPECT_EQ(packed.qweight[j], 0);
}

TEST(WeightPack, UnderflowingScaleGetsScaleOneAndZeroCodes) {
  std::vector<float> weight(32, 0.0f);
  weight[3] = std::numeric_limits<float>::denorm_min();
  const Packed packed = quantize(weight, 1, 32, 32);
  EXPECT_EQ(packed.scales[0], 1.0f);
  for (uint8_t byte : packed.qweight) EXPECT_EQ(byte, 0);
}

TEST(WeightPack, RejectsNaN) {
  auto weight = naive::random_values(8 * 128, 1);
  weight[5 * 128 + 17] = NAN;
  EXPECT_FALSE(quantize(weight, 8, 128, 64).ok);
}

TEST(WeightPack, RejectsInfinity) {
  auto weight = naive::random_values(8 * 128, 1);
  weight[7 * 128 + 127] = -INFINITY;
  EXPECT_FALSE(quantize(weight, 8, 128, 32).ok);
}

}  // namespace
