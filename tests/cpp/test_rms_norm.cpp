// RMSNorm (activation/rms_norm_cpu.h), every CPU path this machine can execute, against a float64 reference
// of the same formula on fresh random rows and weights: the two roundings to the dtype applied to the
// float64 values, so that the kernel may differ only where its fp32 arithmetic moves a value across a
// rounding boundary.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <vector>

#include "activation/rms_norm_cpu.h"
#include "common/cpu_dtype.h"
#include "cpu/cpu_isa.h"
#include "naive_reference.h"

namespace {

using dyq::ScalarType;

// The formula in float64 from x and weight as the dtype holds them; `round` rounds to the dtype.
template <typename Round>
std::vector<double> reference(const std::vector<float>& x, const std::vector<float>& weight, int64_t rows, int64_t n,
                              double eps, Round round) {
  std::vector<double> out(rows * n);
  for (int64_t r = 0; r < rows; ++r) {
    double sum = 0.0;
    for (int64_t i = 0; i < n; ++i) sum += double{x[r * n + i]} * x[r * n + i];
    const double inverse_rms = 1.0 / std::sqrt(sum / n + eps);
    for (int64_t i = 0; i < n; ++i) out[r * n + i] = round(weight[i] * round(x[r * n + i] * inverse_rms));
  }
  return out;
}

template <typename Element>
std::vector<float> run(const dyq::cpu::CpuKernelSet* kernels, ScalarType dtype, const std::vector<Element>& x,
                       const std::vector<Element>& weight, int64_t rows, int64_t n, float eps) {
  std::vector<Element> out(rows * n);
  if (kernels == nullptr) {
    dyq::cpu::rms_norm(x.data(), dtype, weight.data(), rows, n, eps, out.data());
  } else {
    kernels->rms_norm(x.data(), dtype, weight.data(), rows, n, eps, out.data());
  }
  return naive::to_float(out);
}

std::vector<const dyq::cpu::CpuKernelSet*> every_table() {
  std::vector<const dyq::cpu::CpuKernelSet*> tables = {nullptr};  // nullptr: the active path
  for (const auto* path : dyq::cpu::runnable_cpu_paths()) tables.push_back(path->kernels);
  return tables;
}

// Every output within `steps` units of the dtype's rounding of the reference (relative), and at least
// `exact_share` of them equal to it. A different sum of squares may move the normalized value by one step
// where it lies near a rounding boundary, and the product with the weight then by up to two.
template <typename Element>
void expect_matches_reference(ScalarType dtype, int64_t rows, int64_t n, double relative_step, int steps,
                              double exact_share) {
  const auto x = naive::to_element<Element>(naive::random_values(rows * n, 17 + n, 3.0f));
  std::vector<float> raw_weight = naive::random_values(n, 29 + n);
  for (auto& w : raw_weight) w = 0.5f + std::fabs(w);
  const auto weight = naive::to_element<Element>(raw_weight);
  const float eps = 1e-6f;
  const auto round = [](double v) {
    return static_cast<double>(dyq::cpu::to_float(dyq::cpu::from_float<Element>(static_cast<float>(v))));
  };
  const auto expected = reference(naive::to_float(x), naive::to_float(weight), rows, n, eps, round);
  for (const auto* kernels : every_table()) {
    SCOPED_TRACE(kernels == nullptr ? "active path" : "a runnable path");
    const auto actual = run(kernels, dtype, x, weight, rows, n, eps);
    int64_t exact = 0;
    for (int64_t i = 0; i < rows * n; ++i) {
      ASSERT_NEAR(actual[i], expected[i], steps * relative_step * std::fabs(expected[i]) + 1e-30) << "element " << i;
      exact += actual[i] == expected[i];
    }
    EXPECT_GE(exact, exact_share * rows * n);
  }
}

TEST(RmsNorm, Fp32MatchesFloat64Reference) {
  for (int64_t n : {1, 7, 16, 100, 256, 4097}) expect_matches_reference<float>(ScalarType::kFloat32, 5, n, 1e-6, 1, 0.0);
}

TEST(RmsNorm, Bf16MatchesReferenceToTwoRoundingSteps) {
  for (int64_t n : {3, 33, 256, 1000}) {
    expect_matches_reference<Eigen::bfloat16>(ScalarType::kBFloat16, 9, n, 0x1p-7, 2, 0.98);
  }
}

TEST(RmsNorm, Fp16MatchesReferenceToTwoRoundingSteps) {
  for (int64_t n : {3, 33, 256, 1000}) expect_matches_reference<Eigen::half>(ScalarType::kFloat16, 9, n, 0x1p-10, 2, 0.98);
}

// Rows shared among threads give the rows one thread computes (a prefill's 256 rows of 256 are several chunks).
TEST(RmsNorm, ManyRowsMatchRowByRow) {
  const int64_t rows = 300, n = 256;
  const auto x = naive::random_values(rows * n, 5);
  const auto weight = naive::random_values(n, 6);
  const auto all = run<float>(nullptr, ScalarType::kFloat32, x, weight, rows, n, 1e-5f);
  for (int64_t r = 0; r < rows; r += 37) {
    const std::vector<float> row(x.begin() + r * n, x.begin() + (r + 1) * n);
    const auto alone = run<float>(nullptr, ScalarType::kFloat32, row, weight, 1, n, 1e-5f);
    for (int64_t i = 0; i < n; ++i) ASSERT_EQ(all[r * n + i], alone[i]) << "row " << r << " element " << i;
  }
}

// A NaN makes its row NaN; an Inf makes its own element NaN (Inf times 0) and the rest of its row 0; other
// rows are untouched.
TEST(RmsNorm, NonFiniteValuesSpreadAsInTheFormula) {
  const int64_t n = 40;
  std::vector<float> x = naive::random_values(3 * n, 8);
  const std::vector<float> weight(n, 1.0f);
  x[5] = std::numeric_limits<float>::quiet_NaN();
  x[n + 9] = std::numeric_limits<float>::infinity();
  for (const auto* kernels : every_table()) {
    const auto out = run<float>(kernels, ScalarType::kFloat32, x, weight, 3, n, 1e-6f);
    for (int64_t i = 0; i < n; ++i) EXPECT_TRUE(std::isnan(out[i])) << i;
    for (int64_t i = 0; i < n; ++i) {
      if (i == 9) {
        EXPECT_TRUE(std::isnan(out[n + i]));
      } else {
        EXPECT_EQ(out[n + i], 0.0f) << i;
      }
    }
    for (int64_t i = 0; i < n; ++i) EXPECT_TRUE(std::isfinite(out[2 * n + i])) << i;
  }
}

}  // namespace
