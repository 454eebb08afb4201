// The online Hadamard rotation (activation/hadamard_cpu.h), every CPU path this machine can execute,
// against the float64 dense reference of naive_reference.h on fresh random rows, signs and left factors.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <vector>

#include "activation/hadamard_cpu.h"
#include "cpu/cpu_isa.h"
#include "naive_reference.h"

namespace {

using dyq::ScalarType;

struct Problem {
  std::vector<float> x, signs, left;
  int64_t rows, m, p;
};

// Rows of N(0, 1), signs +-1 and a left factor of N(0, 1/m) entries (the kernel applies any [m, m] matrix;
// the reference does not assume it orthogonal either).
Problem random_problem(int64_t rows, int64_t m, int64_t p, uint32_t seed) {
  const int64_t n = m * p;
  std::mt19937 rng(seed);
  std::vector<float> signs(n);
  for (auto& s : signs) s = rng() % 2 ? 1.0f : -1.0f;
  return {naive::random_values(rows * n, seed + 1), signs,
          naive::random_values(m * m, seed + 2, 1.0f / std::sqrt(static_cast<float>(m))), rows, m, p};
}

// Runs `kernels` (a path's table, or nullptr for the active path) on x rounded to Element.
template <typename Element>
std::vector<float> transform(const Problem& problem, ScalarType dtype, const dyq::cpu::CpuKernelSet* kernels) {
  const int64_t n = problem.m * problem.p;
  const auto x = naive::to_element<Element>(problem.x);
  std::vector<Element> out(problem.rows * n);
  if (kernels == nullptr) {
    dyq::cpu::hadamard_transform(x.data(), dtype, problem.signs.data(), problem.left.data(), problem.rows, n,
                                 problem.m, out.data());
  } else {
    kernels->hadamard_transform(x.data(), dtype, problem.signs.data(), problem.left.data(), problem.rows, n,
                                problem.m, out.data());
  }
  return naive::to_float(out);
}

// fp32: within 1e-5 of the reference times the row's scale (unit-variance rows stay unit-variance when
// left is near orthogonal); fp32 rounding of log2(p) butterfly adds and m multiply-adds is far below it.
// bf16 / fp16: the reference of the rounded input, within two units in the last place of the output.
template <typename Element>
void expect_matches_reference(const Problem& problem, ScalarType dtype, double relative) {
  const auto rounded_x = naive::to_float(naive::to_element<Element>(problem.x));
  const auto expected =
      naive::hadamard_transform(rounded_x, problem.signs, problem.left, problem.rows, problem.m, problem.p);
  std::vector<const dyq::cpu::CpuKernelSet*> tables = {nullptr};
  for (const auto* path : dyq::cpu::runnable_cpu_paths()) tables.push_back(path->kernels);
  for (size_t t = 0; t < tables.size(); ++t) {
    SCOPED_TRACE(t == 0 ? "active path" : dyq::cpu::runnable_cpu_paths()[t - 1]->name);
    const auto got = transform<Element>(problem, dtype, tables[t]);
    for (size_t i = 0; i < got.size(); ++i) {
      const double tolerance = relative * std::fmax(1.0, std::fabs(expected[i]));
      ASSERT_NEAR(got[i], expected[i], tolerance) << "element " << i;
    }
  }
}

uint32_t fresh_seed() { return std::random_device{}(); }

class HadamardShapes : public ::testing::TestWithParam<std::tuple<int64_t, int64_t>> {};

TEST_P(HadamardShapes, Fp32MatchesDenseReference) {
  const auto [m, p] = GetParam();
  const uint32_t seed = fresh_seed();
  SCOPED_TRACE("seed " + std::to_string(seed));
  expect_matches_reference<float>(random_problem(3, m, p, seed), ScalarType::kFloat32, 1e-5);
}

// The left orders of dyq's Paley matrices and the trivial one, with every power of two up to 1024.
INSTANTIATE_TEST_SUITE_P(LeftOrdersAndPowersOfTwo, HadamardShapes,
                         ::testing::Combine(::testing::Values(1, 12, 36, 60),
                                            ::testing::Values(1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024)));

// The left product's blocks: 16 outputs by 4 columns, with outputs (17, 344 = 21 x 16 + 8) and columns
// (p = 1, 2; 6 = 4 + 2) left over; 344 x 32 is Llama-7B's 11008.
INSTANTIATE_TEST_SUITE_P(LeftProductBlocks, HadamardShapes,
                         ::testing::Combine(::testing::Values(17, 344), ::testing::Values(1, 2, 4, 32)));

TEST(Hadamard, HalfPrecisionRoundsTheFp32ResultOnce) {
  const uint32_t seed = fresh_seed();
  SCOPED_TRACE("seed " + std::to_string(seed));
  expect_matches_reference<Eigen::bfloat16>(random_problem(4, 12, 64, seed), ScalarType::kBFloat16, 2.0 / 256);
  expect_matches_reference<Eigen::half>(random_problem(4, 12, 64, seed), ScalarType::kFloat16, 2.0 / 2048);
}

TEST(Hadamard, ManyRowsRunInParallelLikeOne) {
  const uint32_t seed = fresh_seed();
  SCOPED_TRACE("seed " + std::to_string(seed));
  const Problem problem = random_problem(257, 20, 32, seed);
  const auto all = transform<float>(problem, ScalarType::kFloat32, nullptr);
  const int64_t n = problem.m * problem.p;
  for (const int64_t row : {int64_t{0}, int64_t{128}, int64_t{256}}) {
    Problem one = problem;
    one.rows = 1;
    one.x.assign(problem.x.begin() + row * n, problem.x.begin() + (row + 1) * n);
    const auto single = transform<float>(one, ScalarType::kFloat32, nullptr);
    for (int64_t i = 0; i < n; ++i) ASSERT_EQ(all[row * n + i], single[i]) << "row " << row << " element " << i;
  }
}

TEST(Hadamard, NoRowsWritesNothing) {
  const Problem problem = random_problem(0, 12, 8, 7);
  float untouched = 3.0f;
  dyq::cpu::hadamard_transform(nullptr, ScalarType::kFloat32, problem.signs.data(), problem.left.data(), 0, 96, 12,
                               &untouched);
  EXPECT_EQ(untouched, 3.0f);
}

}  // namespace
