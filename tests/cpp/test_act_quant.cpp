// Activation quantization (every CPU path this machine can execute) against the naive loops of
// docs/numerics.md, section 2.
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <random>
#include <tuple>

#include "activation/act_quant_cpu.h"
#include "cpu/cpu_isa.h"
#include "naive_reference.h"

namespace {

using dyq::ScalarType;

struct Quantized {
  std::vector<uint8_t> packed;
  std::vector<float> scales;
  std::vector<uint8_t> zeros;
};

template <typename Element>
Quantized quantize(const std::vector<Element>& x, ScalarType dtype, int64_t m, int64_t k, int group_size,
                   int act_bits) {
  Quantized q{std::vector<uint8_t>(m * k * act_bits / 8), std::vector<float>(m * k / group_size),
              std::vector<uint8_t>(m * k / group_size)};
  dyq::cpu::quantize_activations(x.data(), dtype, m, k, group_size, act_bits, q.packed.data(), q.scales.data(),
                                 q.zeros.data());
  // Every path quantizes bit for bit alike.
  for (const auto* path : dyq::cpu::runnable_cpu_paths()) {
    Quantized other{std::vector<uint8_t>(q.packed.size()), std::vector<float>(q.scales.size()),
                    std::vector<uint8_t>(q.zeros.size())};
    path->kernels->quantize_activations(x.data(), dtype, m, k, group_size, act_bits, other.packed.data(),
                                        other.scales.data(), other.zeros.data());
    EXPECT_EQ(other.packed, q.packed) << path->name;
    EXPECT_EQ(std::memcmp(other.scales.data(), q.scales.data(), q.scales.size() * sizeof(float)), 0) << path->name;
    EXPECT_EQ(other.zeros, q.zeros) << path->name;
  }
  return q;
}

// Scales compared bit for bit (NaN included).
void expect_same_bits(const std::vector<float>& actual, const std::vector<float>& expected) {
  ASSERT_EQ(actual.size(), expected.size());
  for (size_t i = 0; i < actual.size(); ++i) {
    EXPECT_EQ(std::memcmp(&actual[i], &expected[i], sizeof(float)), 0)
        << "scale " << i << ": " << actual[i] << " vs " << expected[i];
  }
}

template <typename Element>
void check_against_naive(ScalarType dtype, const std::vector<float>& values, int64_t m, int64_t k, int group_size,
                         int act_bits) {
  const auto x = naive::to_element<Element>(values);
  const Quantized q = quantize(x, dtype, m, k, group_size, act_bits);
  const auto expected = naive::quantize_activations(naive::to_float(x), m, k, group_size, act_bits);
  EXPECT_EQ(q.packed, naive::pack_activations(expected.codes, act_bits));
  expect_same_bits(q.scales, expected.scales);
  EXPECT_EQ(std::vector<int>(q.zeros.begin(), q.zeros.end()), expected.zeros);
}

void check_dtype(ScalarType dtype, const std::vector<float>& values, int64_t m, int64_t k, int group_size,
                 int act_bits) {
  switch (dtype) {
    case ScalarType::kFloat32:
      return check_against_naive<float>(dtype, values, m, k, group_size, act_bits);
    case ScalarType::kBFloat16:
      return check_against_naive<Eigen::bfloat16>(dtype, values, m, k, group_size, act_bits);
    case ScalarType::kFloat16:
      return check_against_naive<Eigen::half>(dtype, values, m, k, group_size, act_bits);
  }
}

class ActQuantTest : public ::testing::TestWithParam<std::tuple<ScalarType, int, int>> {};

TEST_P(ActQuantTest, MatchesNaiveCodesScalesAndZerosExactly) {
  const auto [dtype, act_bits, group_size] = GetParam();
  const int64_t m = 9, k = 3 * group_size;
  auto values = naive::random_values(m * k, 11 + act_bits);
  // Row 1 positive only (zero point 0), row 2 negative only (zero point 2^b - 1), row 3 one all-zero group.
  for (int64_t i = 0; i < k; ++i) {
    values[k + i] = std::abs(values[k + i]);
    values[2 * k + i] = -std::abs(values[2 * k + i]) - 0.25f;
  }
  for (int i = 0; i < group_size; ++i) values[3 * k + group_size + i] = 0.0f;
  check_dtype(dtype, values, m, k, group_size, act_bits);
}

TEST_P(ActQuantTest, NonFiniteGroupGetsNaNScaleZeroPointAndCodesZero) {
  const auto [dtype, act_bits, group_size] = GetParam();
  const int64_t m = 3, k = 2 * group_size;
  auto values = naive::random_values(m * k, 5);
  values[k + 3] = NAN;                       // row 1, group 0
  values[2 * k + group_size + 1] = INFINITY;  // row 2, group 1
  check_dtype(dtype, values, m, k, group_size, act_bits);
  const auto x = naive::to_element<float>(values);
  const Quantized q = quantize(x, ScalarType::kFloat32, m, k, group_size, act_bits);
  EXPECT_TRUE(std::isnan(q.scales[2]));
  EXPECT_TRUE(std::isnan(q.scales[5]));
  EXPECT_FALSE(std::isnan(q.scales[3]));
}

INSTANTIATE_TEST_SUITE_P(
    AllFormats, ActQuantTest,
    ::testing::Combine(::testing::Values(ScalarType::kFloat32, ScalarType::kBFloat16, ScalarType::kFloat16),
                       ::testing::Values(2, 4, 8), ::testing::Values(32, 64, 128)));

TEST(ActQuant, PacksLowBitsFirst) {
  // Range [-1, 2] at 2 bits: scale 1, zero point 1, codes x + 1.
  std::vector<float> x(32, 0.0f);
  x[0] = -1.0f;
  x[1] = 0.0f;
  x[2] = 1.0f;
  x[3] = 2.0f;
  const Quantized q = quantize(x, ScalarType::kFloat32, 1, 32, 32, 2);
  EXPECT_EQ(q.scales[0], 1.0f);
  EXPECT_EQ(q.zeros[0], 1);
  EXPECT_EQ(q.packed[0], 0b11100100);  // codes 0, 1, 2, 3
  EXPECT_EQ(q.packed[1], 0b01010101);  // four zeros -> code 1
}

TEST(ActQuant, RoundsHalfToEven) {
  // Range [0, 15] at 4 bits: scale 1, zero point 0; 0.5 -> 0, 1.5 -> 2, 2.5 -> 2.
  std::vector<float> x(32, 0.0f);
  x[0] = 15.0f;
  x[1] = 0.5f;
  x[2] = 1.5f;
  x[3] = 2.5f;
  const Quantized q = quantize(x, ScalarType::kFloat32, 1, 32, 32, 4);
  EXPECT_EQ(q.packed[0], 0x0F);
  EXPECT_EQ(q.packed[1], 0x22);
}

TEST(ActQuant, AllZeroGroupGetsScaleOne) {
  std::vector<float> x(64, 0.0f);
  const Quantized q = quantize(x, ScalarType::kFloat32, 1, 64, 64, 8);
  EXPECT_EQ(q.scales[0], 1.0f);
  EXPECT_EQ(q.zeros[0], 0);
  for (uint8_t byte : q.packed) EXPECT_EQ(byte, 0);
}

// The SIMD paths derive the parameters of 16 groups at once, in the lanes of one vector
// (act_quant_cpu_row.h, activation_group_params_lanes): every special case of activation_group_params side by
// side in one row of 20 groups (two batches, the second partial), each group's codes and parameters its own.
TEST(ActQuant, GroupsQuantizedSideBySideKeepTheirOwnSpecialCases) {
  for (int group_size : {32, 64, 128}) {
    for (int act_bits : {2, 4, 8}) {
      constexpr int64_t kGroups = 20;
      const int64_t k = kGroups * group_size;
      std::vector<float> values = naive::random_values(k, 40 + act_bits);
      auto group = [&](int64_t g) { return values.begin() + g * group_size; };
      std::fill(group(1), group(2), 0.0f);                                          // no range: s_x = 1
      group(2)[5] = NAN;                                                            // non-finite
      group(3)[0] = INFINITY;
      group(4)[group_size - 1] = -INFINITY;
      for (int i = 0; i < group_size; ++i) group(5)[i] = i % 2 == 0 ? 3.0e38f : -3.0e38f;  // range past FLT_MAX
      for (int i = 0; i < group_size; ++i) group(6)[i] = std::ldexp(static_cast<float>(i % 7) - 3.0f, -140);
      for (int i = 0; i < group_size; ++i) group(7)[i] = std::abs(group(7)[i]);     // z_x = 0
      for (int i = 0; i < group_size; ++i) group(8)[i] = -std::abs(group(8)[i]);    // z_x = L
      std::fill(group(9), group(10), 0.75f);                                        // one value
      for (int i = 0; i < group_size; ++i) group(10)[i] = static_cast<float>(i % 16) * 0.5f;  // halfway points
      group(17)[1] = NAN;                                                           // in the second batch
      std::fill(group(18), group(19), -0.0f);
      check_dtype(ScalarType::kFloat32, values, 1, k, group_size, act_bits);
      check_dtype(ScalarType::kFloat32, values, 2, k / 2, group_size, act_bits);  // 10 groups a row
    }
  }
}

TEST(ActQuant, EmptyBatchWritesNothing) {
  const std::vector<float> x;
  Quantized q{std::vector<uint8_t>(1, 0xAB), std::vector<float>(1, 3.0f), std::vector<uint8_t>(1, 0xAB)};
  dyq::cpu::quantize_activations(x.data(), ScalarType::kFloat32, 0, 128, 128, 4, q.packed.data(), q.scales.data(),
                                 q.zeros.data());
  EXPECT_EQ(q.packed[0], 0xAB);
  EXPECT_EQ(q.scales[0], 3.0f);
}

}  // namespace

// The SIMD paths divide by the group's scale through its reciprocal and one correction (act_quant_cpu_row.h,
// with_quotient_form); their codes must be the division's where it matters most: values at and a few ulps
// around the half-integer multiples of the scale, where the rounding to a code turns, over scales from the
// subnormal range to near FLT_MAX (outside [2^-100, 2^100] the paths divide), and subnormal values.
TEST(ActQuant, CodesAtHalfwayPointsMatchTheDivisionAtEveryScale) {
  constexpr int kGroup = 32;
  std::mt19937 rng(2024);
  for (int act_bits : {2, 4, 8}) {
    const int levels = (1 << act_bits) - 1;
    std::vector<float> values;
    for (int exponent : {-149, -140, -126, -110, -101, -100, -99, -60, -20, 0, 20, 60, 99, 100, 101, 120, 127}) {
      for (int variant = 0; variant < 24; ++variant) {
        // A group of range [0, top] (or [-top, 0]): scale top / levels, as activation_group_params forms it.
        const float mantissa = 1.0f + static_cast<float>(rng() % (1u << 23)) / static_cast<float>(1u << 23);
        const float top = std::ldexp(mantissa, exponent);
        if (!(top > 0.0f) || !std::isfinite(top)) continue;
        const float scale = top / static_cast<float>(levels);
        const float sign = variant % 2 == 0 ? 1.0f : -1.0f;
        values.push_back(sign * top);
        for (int i = 1; i < kGroup; ++i) {
          const float halfway = (static_cast<float>(rng() % levels) + 0.5f) * scale;
          float value = halfway;
          uint32_t bits;
          std::memcpy(&bits, &value, sizeof(bits));
          bits += static_cast<uint32_t>(static_cast<int>(rng() % 7) - 3);  // up to 3 ulps either side
          std::memcpy(&value, &bits, sizeof(bits));
          if (i % 8 == 0) value = std::ldexp(static_cast<float>(rng() % 1000), -149);  // subnormal (or 0)
          if (!std::isfinite(value) || std::abs(value) > top) value = halfway;
          values.push_back(sign * value);
        }
      }
    }
    const int64_t k = kGroup;
    check_dtype(ScalarType::kFloat32, values, static_cast<int64_t>(values.size()) / k, k, kGroup, act_bits);
  }
}
