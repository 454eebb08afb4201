// The GEMM (dyq::cpu::gemm and every CPU path this machine can execute) against a double-precision naive
// GEMM on the codes of docs/numerics.md, section 3.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <functional>
#include <limits>
#include <string>
#include <thread>
#include <tuple>
#include <utility>
#include <random>
#include <vector>

#include "cpu/cpu_isa.h"
#include "gemm/gemm_cpu.h"
#include "naive_reference.h"
#include "parallel/parallel.h"
#include "weight/weight_pack_cpu.h"

namespace {

using dyq::ScalarType;
using GemmFn = std::function<void(const void*, ScalarType, const uint8_t*, const float*, const void*, int64_t,
                                  int64_t, int64_t, int, int, void*)>;

struct Implementation {
  std::string name;
  GemmFn run;
  const char* (*kernel)(int64_t m, int64_t k, int group_size, int act_bits);
};

const std::vector<Implementation>& implementations() {
  static const std::vector<Implementation> all = [] {
    std::vector<Implementation> list = {{"gemm", dyq::cpu::gemm, dyq::cpu::active_cpu_path().kernels->gemm_kernel}};
    for (const auto* path : dyq::cpu::runnable_cpu_paths()) {
      list.push_back({path->name, path->kernels->gemm, path->kernels->gemm_kernel});
    }
    return list;
  }();
  return all;
}

struct Problem {
  int64_t m, n, k;
  int group_size, act_bits;
  bool with_bias;
  uint32_t seed;
};

// Inputs as the kernel sees them (already rounded to the element type) and the packed weight.
struct Inputs {
  std::vector<float> x, bias;
  naive::QuantizedWeight weight;
  std::vector<uint8_t> qweight;
};

Inputs make_inputs(const Problem& p, const std::function<float(float)>& round_to_element) {
  Inputs in;
  in.x = naive::random_values(p.m * p.k, p.seed);
  for (auto& v : in.x) v = round_to_element(v);
  const auto weight = naive::random_values(p.n * p.k, p.seed + 1, 0.05f);
  in.weight = naive::quantize_weight(weight, p.n, p.k, p.group_size);
  in.qweight = naive::pack_weight(in.weight.codes);
  if (p.with_bias) {
    in.bias = naive::random_values(p.n, p.seed + 2);
    for (auto& v : in.bias) v = round_to_element(v);
  }
  return in;
}

// The error bound relative to sum |terms|: fp32 sums, and on a kernel of bf16 dot products x rounded to
// bf16 first (docs/numerics.md, section 3), up to 2^-8 of each term; 2^-7 + 2^-16 where the dequantized
// weights q_w s_w are rounded to bf16 too.
double relative_bound(const Implementation& impl, const Problem& p) {
  const std::string kernel = impl.kernel(p.m, p.k, p.group_size, p.act_bits);
  if (kernel.find("dequantized") != std::string::npos) return 1e-5 + std::ldexp(1.0, -7) + std::ldexp(1.0, -16);
  return 1e-5 + (kernel.find("bf16") != std::string::npos ? std::ldexp(1.0, -8) : 0.0);
}

// The output must be the element rounding of an fp32 value within the rounding bound of the exact sum:
// since rounding is monotonic, it lies between the roundings of the bound's two ends.
template <typename Element>
void expect_within_bound(const std::vector<Element>& out, const naive::GemmReference& ref, double rtol,
                         const std::string& what) {
  constexpr double kAtol = 1e-6;
  for (size_t i = 0; i < out.size(); ++i) {
    const double actual = static_cast<float>(out[i]);
    const double slack = kAtol + rtol * ref.magnitude[i];
    const double lo = static_cast<float>(static_cast<Element>(static_cast<float>(ref.value[i] - slack)));
    const double hi = static_cast<float>(static_cast<Element>(static_cast<float>(ref.value[i] + slack)));
    ASSERT_TRUE(actual >= lo - kAtol && actual <= hi + kAtol)
        << what << " element " << i << ": " << actual << " not in [" << lo << ", " << hi << "], exact "
        << ref.value[i];
  }
}

template <typename Element>
void check_problem(const Problem& p, ScalarType dtype) {
  const Inputs in = make_inputs(p, [](float v) { return static_cast<float>(static_cast<Element>(v)); });
  const auto x = naive::to_element<Element>(in.x);
  const auto bias = naive::to_element<Element>(in.bias);
  const auto ref = naive::gemm(in.x, in.weight, in.bias, p.m, p.n, p.k, p.group_size, p.act_bits);
  for (const auto& impl : implementations()) {
    std::vector<Element> out(p.m * p.n, static_cast<Element>(-12345.0f));
    impl.run(x.data(), dtype, in.qweight.data(), in.weight.scales.data(), p.with_bias ? bias.data() : nullptr, p.m,
             p.n, p.k, p.group_size, p.act_bits, out.data());
    expect_within_bound(out, ref, relative_bound(impl, p),
                        impl.name + " m " + std::to_string(p.m) + " n " + std::to_string(p.n) + " k " +
                            std::to_string(p.k));
  }
}

void check_problem(const Problem& p, ScalarType dtype) {
  switch (dtype) {
    case ScalarType::kFloat32:
      return check_problem<float>(p, dtype);
    case ScalarType::kBFloat16:
      return check_problem<Eigen::bfloat16>(p, dtype);
    case ScalarType::kFloat16:
      return check_problem<Eigen::half>(p, dtype);
  }
}

class GemmTest : public ::testing::TestWithParam<std::tuple<ScalarType, int, int, bool>> {};

TEST_P(GemmTest, MatchesNaiveReferenceOnSeveralShapes) {
  const auto [dtype, act_bits, group_size, with_bias] = GetParam();
  // Odd M, N not a multiple of 8, K of several groups and not always a multiple of 128.
  const std::vector<std::tuple<int64_t, int64_t, int64_t>> shapes = {
      {1, 37, group_size}, {3, 64, 3 * group_size}, {13, 133, 5 * group_size}, {40, 19, 2 * group_size}};
  uint32_t seed = 100 * act_bits + group_size;
  for (const auto& [m, n, k] : shapes) check_problem({m, n, k, group_size, act_bits, with_bias, seed++}, dtype);
}

TEST_P(GemmTest, LastGroupHoldsTheRemainderOfK) {
  const auto [dtype, act_bits, group_size, with_bias] = GetParam();
  // K not a multiple of the group size: 576 (SmolLM2's hidden size), 960 (SmolVLA's), a short even
  // remainder, a remainder straddling the 128-column blocks (in the row kernels a last group of whole and
  // partial chunks), and K shorter than one group. M = 13 and 40 take the panel path.
  const std::vector<std::tuple<int64_t, int64_t, int64_t>> shapes = {
      {1, 37, 576}, {3, 21, 960}, {2, 19, group_size + 2}, {1, 23, 2 * group_size + 46},
      {13, 40, 2 * group_size + 46}, {40, 9, 30}, {5, 7, 6}};
  uint32_t seed = 7 * act_bits + group_size;
  for (const auto& [m, n, k] : shapes) check_problem({m, n, k, group_size, act_bits, with_bias, seed++}, dtype);
}

INSTANTIATE_TEST_SUITE_P(
    AllFormats, GemmTest,
    ::testing::Combine(::testing::Values(ScalarType::kFloat32, ScalarType::kBFloat16, ScalarType::kFloat16),
                       ::testing::Values(2, 4, 8, 16), ::testing::Values(32, 64, 128), ::testing::Bool()));

class GemmEdgeTest : public ::testing::TestWithParam<int> {};

TEST_P(GemmEdgeTest, EmptyBatchWritesNothing) {
  const int act_bits = GetParam();
  const Inputs in = make_inputs({1, 8, 64, 32, act_bits, false, 1}, [](float v) { return v; });
  std::vector<float> out(1, 7.0f);
  for (const auto& impl : implementations()) {
    impl.run(in.x.data(), ScalarType::kFloat32, in.qweight.data(), in.weight.scales.data(), nullptr, 0, 8, 64, 32,
             act_bits, out.data());
    EXPECT_EQ(out[0], 7.0f) << impl.name;
  }
}

// K = 0: no column, no depth slice of a panel; every output is its bias (the row kernels and the panels of
// whole and partial column blocks alike).
TEST_P(GemmEdgeTest, EmptyRowsGiveTheBias) {
  const int act_bits = GetParam();
  std::mt19937 rng(31 + act_bits);
  std::normal_distribution<float> normal(0.0f, 1.0f);
  for (const int64_t m : {1, 3, 40}) {
    for (const int64_t n : {37, 64}) {
      std::vector<float> bias(n);
      for (float& b : bias) b = normal(rng);
      const std::vector<float> x(1, 0.0f);
      const std::vector<uint8_t> qweight(1, 0);
      const std::vector<float> scales(1, 0.0f);
      for (const auto& impl : implementations()) {
        std::vector<float> out(m * n, -12345.0f);
        impl.run(x.data(), ScalarType::kFloat32, qweight.data(), scales.data(), bias.data(), m, n, 0, 32, act_bits,
                 out.data());
        for (int64_t i = 0; i < m * n; ++i) ASSERT_EQ(out[i], bias[i % n]) << impl.name << " m " << m << " n " << n;
      }
    }
  }
}

TEST_P(GemmEdgeTest, AllZeroGroupsContributeNothing) {
  const int act_bits = GetParam();
  const Problem p{5, 21, 4 * 32, 32, act_bits, true, 9};
  Inputs in = make_inputs(p, [](float v) { return v; });
  for (int64_t row = 0; row < p.m; ++row) {
    for (int i = 0; i < 32; ++i) in.x[row * p.k + 32 + i] = 0.0f;  // activation group 1 of every row
  }
  for (int64_t col = 0; col < p.n; ++col) {
    for (int i = 0; i < 32; ++i) in.weight.codes[col * p.k + 64 + i] = 0;  // weight group 2 of every column
    in.weight.scales[col * 4 + 2] = 1.0f;
  }
  in.qweight = naive::pack_weight(in.weight.codes);
  const auto ref = naive::gemm(in.x, in.weight, in.bias, p.m, p.n, p.k, p.group_size, act_bits);
  for (const auto& impl : implementations()) {
    std::vector<float> out(p.m * p.n);
    impl.run(in.x.data(), ScalarType::kFloat32, in.qweight.data(), in.weight.scales.data(), in.bias.data(), p.m, p.n,
             p.k, p.group_size, act_bits, out.data());
    expect_within_bound(out, ref, relative_bound(impl, p), impl.name);
  }
}

TEST_P(GemmEdgeTest, NaNRowIsNaNAndOtherRowsAreUntouched) {
  const int act_bits = GetParam();
  const Problem p{6, 45, 3 * 64, 64, act_bits, false, 21};
  Inputs in = make_inputs(p, [](float v) { return v; });
  const int64_t nan_row = 4;
  in.x[nan_row * p.k + 70] = NAN;
  const auto ref = naive::gemm(in.x, in.weight, in.bias, p.m, p.n, p.k, p.group_size, act_bits);
  for (const auto& impl : implementations()) {
    std::vector<float> out(p.m * p.n);
    impl.run(in.x.data(), ScalarType::kFloat32, in.qweight.data(), in.weight.scales.data(), nullptr, p.m, p.n, p.k,
             p.group_size, act_bits, out.data());
    for (int64_t row = 0; row < p.m; ++row) {
      for (int64_t col = 0; col < p.n; ++col) {
        const double actual = out[row * p.n + col], exact = ref.value[row * p.n + col];
        if (row == nan_row) {
          ASSERT_TRUE(std::isnan(actual)) << impl.name << " column " << col;
        } else {
          ASSERT_NEAR(actual, exact, 1e-6 + relative_bound(impl, p) * ref.magnitude[row * p.n + col]) << impl.name;
        }
      }
    }
  }
}

INSTANTIATE_TEST_SUITE_P(AllActBits, GemmEdgeTest, ::testing::Values(2, 4, 8, 16));

// A bf16 or fp16 output is the fp32 output rounded exactly as from_float rounds (round half to even, a NaN
// stays NaN): x and the bias hold values exact in every element type, so the fp32 call computes the same
// sums, and only the final conversion, vectorized in the kernels, differs. Rows of either path, columns
// past the last whole vector, and a NaN row.
// With whole_blocks, 64 x 64 outputs (whole 32 x 32 blocks of the AMX loops, which convert a block's bf16
// outputs at once unless one is a NaN or a denormal): one block holds a NaN row, another a denormal output
// (row 2's x all 0, so that its outputs are the bias, 2^-130 in column 5).
template <typename Element>
void expect_outputs_rounded_from_fp32(int act_bits, int64_t m, ScalarType dtype, bool whole_blocks = false) {
  const Problem p{m, whole_blocks ? 64 : 45, 3 * 64, 64, act_bits, true, 31u + static_cast<uint32_t>(m)};
  // Multiples of 1/64 in [-4, 4): 9 significant bits at most, exact in bf16 and fp16 alike.
  Inputs in = make_inputs(p, [](float v) { return std::round(std::clamp(v, -3.9f, 3.9f) * 64.0f) / 64.0f; });
  in.x[(m - 1) * p.k + 5] = NAN;
  if (whole_blocks) {
    std::fill(in.x.begin() + 2 * p.k, in.x.begin() + 3 * p.k, 0.0f);
    in.bias[5] = 0x1p-130f;  // a denormal, exact in bf16 (fp16 flushes it to 0 in both outputs alike)
  }
  for (const auto& impl : implementations()) {
    std::vector<float> fp32_out(p.m * p.n);
    impl.run(in.x.data(), ScalarType::kFloat32, in.qweight.data(), in.weight.scales.data(), in.bias.data(), p.m, p.n,
             p.k, p.group_size, act_bits, fp32_out.data());
    const auto x = naive::to_element<Element>(in.x);
    const auto bias = naive::to_element<Element>(in.bias);
    std::vector<Element> out(p.m * p.n);
    impl.run(x.data(), dtype, in.qweight.data(), in.weight.scales.data(), bias.data(), p.m, p.n, p.k, p.group_size,
             act_bits, out.data());
    for (int64_t i = 0; i < p.m * p.n; ++i) {
      const Element expected = static_cast<Element>(fp32_out[i]);
      if (std::isnan(fp32_out[i])) {
        ASSERT_TRUE(std::isnan(static_cast<float>(out[i]))) << impl.name << " element " << i;
      } else {
        ASSERT_EQ(std::memcmp(&out[i], &expected, sizeof(Element)), 0)
            << impl.name << " element " << i << ": " << static_cast<float>(out[i]) << " for fp32 " << fp32_out[i];
      }
    }
  }
}

TEST_P(GemmEdgeTest, HalfPrecisionOutputsAreTheFp32OutputsRounded) {
  for (const int64_t m : {1, 3, 9, 40}) {
    expect_outputs_rounded_from_fp32<Eigen::bfloat16>(GetParam(), m, ScalarType::kBFloat16);
    expect_outputs_rounded_from_fp32<Eigen::half>(GetParam(), m, ScalarType::kFloat16);
  }
  expect_outputs_rounded_from_fp32<Eigen::bfloat16>(GetParam(), 64, ScalarType::kBFloat16, true);
  expect_outputs_rounded_from_fp32<Eigen::half>(GetParam(), 64, ScalarType::kFloat16, true);
}

TEST(Gemm, InfinityMakesTheQuantizedRowNaN) {
  const Problem p{3, 17, 128, 128, 4, false, 5};
  Inputs in = make_inputs(p, [](float v) { return v; });
  in.x[1 * p.k + 9] = INFINITY;
  for (const auto& impl : implementations()) {
    std::vector<float> out(p.m * p.n);
    impl.run(in.x.data(), ScalarType::kFloat32, in.qweight.data(), in.weight.scales.data(), nullptr, p.m, p.n, p.k,
             p.group_size, p.act_bits, out.data());
    for (int64_t col = 0; col < p.n; ++col) {
      EXPECT_TRUE(std::isnan(out[p.n + col])) << impl.name;
      EXPECT_TRUE(std::isfinite(out[col])) << impl.name;
    }
  }
}

// Shapes large enough for every blocking and threading path of the kernels.
class GemmLargeTest : public ::testing::TestWithParam<std::tuple<int, int>> {};

TEST_P(GemmLargeTest, MatchesNaiveReference) {
  const auto [act_bits, m] = GetParam();
  check_problem({m, 300, 640, 128, act_bits, true, 77u + m}, ScalarType::kFloat32);
  check_problem({m, 77, 352, 32, act_bits, false, 78u + m}, ScalarType::kBFloat16);
}

INSTANTIATE_TEST_SUITE_P(Shapes, GemmLargeTest,
                         ::testing::Combine(::testing::Values(2, 4, 8, 16), ::testing::Values(1, 2, 7, 33, 70)));

// The largest codes of the format (q_x at 0 and 2^b - 1, z_x at either end, q_w at 7 and -8) in every row
// of a group: the kernels' 16-bit partial sums must not saturate, and P stays exact.
TEST_P(GemmEdgeTest, ExtremeCodesStayExact) {
  const int act_bits = GetParam();
  const int64_t n = 18, k = 256;
  const int group_size = 128;
  for (const int64_t m : {1, 3, 16, 19}) {
    Inputs in;
    in.x.resize(m * k);
    for (int64_t r = 0; r < m; ++r) {
      for (int64_t c = 0; c < k; ++c) {
        const float sign = r % 3 == 0 ? 1.0f : r % 3 == 1 ? -1.0f : (c % 2 == 0 ? 1.0f : -1.0f);
        in.x[r * k + c] = sign * 3.0f;
      }
    }
    in.weight.codes.resize(n * k);
    in.weight.scales.assign(n * 2, 0.5f);
    for (int64_t j = 0; j < n; ++j) {
      for (int64_t c = 0; c < k; ++c) in.weight.codes[j * k + c] = j % 2 == 0 ? 7 : -8;
    }
    in.qweight = naive::pack_weight(in.weight.codes);
    const Problem p{m, n, k, group_size, act_bits, false, 0};
    const auto ref = naive::gemm(in.x, in.weight, in.bias, m, n, k, group_size, act_bits);
    for (const auto& impl : implementations()) {
      std::vector<float> out(m * n);
      impl.run(in.x.data(), ScalarType::kFloat32, in.qweight.data(), in.weight.scales.data(), nullptr, m, n, k,
               group_size, act_bits, out.data());
      expect_within_bound(out, ref, relative_bound(impl, p), impl.name + " m " + std::to_string(m));
    }
  }
}

// Decode of weights on either side of the AVX-512 path's switch of act_bits 2 and 4 from the centred row
// kernel to act_bits 8's (at 1 MiB of packed weights), K not a multiple of the group size.
class GemmDecodeFormTest : public ::testing::TestWithParam<int> {};

TEST_P(GemmDecodeFormTest, MatchesNaiveReferenceOnEitherSideOfTheSwitch) {
  const int act_bits = GetParam();
  constexpr int64_t k = 1058;  // 529 bytes a row: 1900 rows take 1 005 100 bytes, 2100 rows 1 110 900
  uint32_t seed = 3000u + act_bits;
  for (const int64_t n : {1900, 2100}) {
    for (const int64_t m : {1, 3, 7}) check_problem({m, n, k, 64, act_bits, m == 3, seed++}, ScalarType::kFloat32);
  }
}

INSTANTIATE_TEST_SUITE_P(IntegerWidths, GemmDecodeFormTest, ::testing::Values(2, 4, 8));

// W4A16 decode on either side of the bf16 row kernels' switches between several weight rows a call (K up to
// 4096 and above 12288) and one (in between): every activation row count of the row kernels, N leaving
// weight rows over, K not always a multiple of the 128-column blocks.
class GemmBf16DecodeColumnsTest : public ::testing::TestWithParam<int> {};

TEST_P(GemmBf16DecodeColumnsTest, MatchesNaiveReferenceOnEitherSideOfTheSwitches) {
  const int group_size = GetParam();
  uint32_t seed = 4000u + group_size;
  for (const int64_t k : {int64_t{4096}, int64_t{4096} + group_size, int64_t{12288}, int64_t{12288} + group_size + 2}) {
    for (const int64_t m : {1, 2, 3, 5}) {
      check_problem({m, 19, k, group_size, 16, m == 2, seed++}, ScalarType::kBFloat16);
    }
  }
}

INSTANTIATE_TEST_SUITE_P(GroupSizes, GemmBf16DecodeColumnsTest, ::testing::Values(32, 64, 128));

// Around the CPU's switch from the row kernels (decode) to the panel path (at 8 rows on the AVX2 and
// AVX-512 paths), with N not a multiple of the panels' 16 outputs and K not a multiple of the group size, on
// fresh random inputs for every width and group size.
class GemmPanelThresholdTest : public ::testing::TestWithParam<std::tuple<int, int>> {};

TEST_P(GemmPanelThresholdTest, MatchesNaiveReferenceOnEitherSide) {
  const auto [act_bits, group_size] = GetParam();
  uint32_t seed = 1000u + 10 * act_bits + group_size;
  for (const int64_t m : {1, 2, 4, 5, 6, 7, 8, 9, 15, 16, 17, 23}) {
    check_problem({m, 53, 4 * group_size + 34, group_size, act_bits, m % 2 == 1, seed++}, ScalarType::kFloat32);
  }
  check_problem({16, 21, 3 * group_size, group_size, act_bits, true, seed++}, ScalarType::kBFloat16);
  check_problem({17, 35, 2 * group_size + 6, group_size, act_bits, false, seed++}, ScalarType::kFloat16);
}

INSTANTIATE_TEST_SUITE_P(WidthsAndGroups, GemmPanelThresholdTest,
                         ::testing::Combine(::testing::Values(2, 4, 8, 16), ::testing::Values(32, 64, 128)));

// Around the AVX512-BF16 path's switch of W4A16 panels to the dequantized weights (from 32 rows where K is
// over 256 columns, from 256 rows at most 256): slices of 1024 columns and a last partial one, K not a
// multiple of the group size, N not a multiple of the panels' 32 weight rows, and row counts on either side
// of the switch and of the 8-row tiles. Every path runs them against the reference.
class GemmDequantizedPanelTest : public ::testing::TestWithParam<int> {};

TEST_P(GemmDequantizedPanelTest, MatchesNaiveReferenceOnEitherSideOfTheSwitch) {
  const int group_size = GetParam();
  uint32_t seed = 2000u + group_size;
  for (const int64_t m : {31, 32, 37}) {
    check_problem({m, 45, 2 * 1024 + 2 * group_size + 30, group_size, 16, m % 2 == 1, seed++}, ScalarType::kFloat32);
  }
  check_problem({33, 70, 1024, group_size, 16, true, seed++}, ScalarType::kBFloat16);
  for (const int64_t m : {255, 256, 259}) {
    check_problem({m, 37, 256, group_size, 16, m % 2 == 0, seed++}, ScalarType::kFloat32);
  }
}

INSTANTIATE_TEST_SUITE_P(GroupSizes, GemmDequantizedPanelTest, ::testing::Values(32, 64, 128));

// The AVX-VNNI path is the AVX2 one with its integer sums on vpdpbusd: both form every lane's P exactly and
// then run the same fp32 operations on it, so their outputs agree bit for bit (a check of the VNNI kernels
// beyond the reference's bound). Every row count of the row kernels and the panels' tiles, ragged N and K.
class GemmAvxVnniTest : public ::testing::TestWithParam<std::tuple<int, int>> {};

TEST_P(GemmAvxVnniTest, AgreesWithTheAvx2PathBitForBit) {
  const auto [act_bits, group_size] = GetParam();
  const Implementation *vnni = nullptr, *avx2 = nullptr;
  for (const auto& impl : implementations()) {
    if (impl.name == "avx_vnni") vnni = &impl;
    if (impl.name == "avx2") avx2 = &impl;
  }
  if (vnni == nullptr || avx2 == nullptr) GTEST_SKIP() << "this CPU runs no AVX-VNNI path";
  uint32_t seed = 5000u + 10 * act_bits + group_size;
  for (const int64_t m : {1, 2, 3, 4, 5, 6, 7, 12, 13, 19}) {
    const Problem p{m, 16 * 4 + 3, 5 * group_size + 66, group_size, act_bits, m % 2 == 0, seed++};
    const Inputs in = make_inputs(p, [](float v) { return v; });
    std::vector<float> from_vnni(p.m * p.n), from_avx2(p.m * p.n);
    for (auto [impl, out] : {std::pair{vnni, &from_vnni}, std::pair{avx2, &from_avx2}}) {
      impl->run(in.x.data(), ScalarType::kFloat32, in.qweight.data(), in.weight.scales.data(),
                p.with_bias ? in.bias.data() : nullptr, p.m, p.n, p.k, p.group_size, p.act_bits, out->data());
    }
    ASSERT_EQ(0, std::memcmp(from_vnni.data(), from_avx2.data(), from_vnni.size() * sizeof(float)))
        << "m " << m << ": " << vnni->kernel(m, p.k, group_size, act_bits) << " against "
        << avx2->kernel(m, p.k, group_size, act_bits);
  }
}

INSTANTIATE_TEST_SUITE_P(WidthsAndGroups, GemmAvxVnniTest,
                         ::testing::Combine(::testing::Values(2, 4, 8, 16), ::testing::Values(32, 64, 128)));

// Runs every chunk of a parallel_for on a thread of its own, in chunks of the grain: far more, and
// smaller, pieces of the output than the pool makes on a small machine.
void thread_per_chunk_backend(int64_t begin, int64_t end, int64_t grain_size, const dyq::RangeBody& body) {
  std::vector<std::thread> threads;
  for (int64_t chunk = begin; chunk < end; chunk += grain_size) {
    threads.emplace_back([&body, chunk, end, grain_size] { body(chunk, std::min(chunk + grain_size, end)); });
  }
  for (auto& thread : threads) thread.join();
}

class GemmManyThreadsTest : public ::testing::TestWithParam<int> {
 protected:
  void SetUp() override { dyq::set_parallel_backend(thread_per_chunk_backend); }
  void TearDown() override { dyq::set_parallel_backend(nullptr); }
};

TEST_P(GemmManyThreadsTest, MatchesNaiveReferenceWithAThreadPerChunk) {
  const int act_bits = GetParam();
  uint32_t seed = 2000u + act_bits;
  for (const int64_t m : {1, 3, 16, 29}) {
    check_problem({m, 77, 576, 64, act_bits, true, seed++}, ScalarType::kFloat32);
    check_problem({m, 40, 160, 32, act_bits, false, seed++}, ScalarType::kBFloat16);
  }
}

INSTANTIATE_TEST_SUITE_P(AllActBits, GemmManyThreadsTest, ::testing::Values(2, 4, 8, 16));

int one_thread() { return 1; }
int three_threads() { return 3; }

// Small layers split their activation rows between the threads where large ones split the weight rows
// (split_panel_rows); on one thread nothing is split. Each row's codes and sums do not depend on the other
// rows, so every path must give the same outputs bit for bit on one thread and on three (uneven shares of
// rows included), and both within the reference's bound.
class GemmThreadSplitTest : public ::testing::TestWithParam<int> {
 protected:
  void TearDown() override { dyq::set_thread_count_source(nullptr); }
};

TEST_P(GemmThreadSplitTest, OutputsDoNotDependOnTheThreadCount) {
  const int act_bits = GetParam();
  uint32_t seed = 3000u + act_bits;
  for (const auto& [m, n, k] : {std::tuple<int64_t, int64_t, int64_t>{32, 256, 256}, {45, 64, 200},
                                {70, 256, 768}, {100, 300, 256}, {256, 256, 256}}) {
    const Problem p{m, n, k, 128, act_bits, true, seed++};
    const Inputs in = make_inputs(p, [](float v) { return static_cast<float>(static_cast<Eigen::bfloat16>(v)); });
    const auto x = naive::to_element<Eigen::bfloat16>(in.x);
    const auto bias = naive::to_element<Eigen::bfloat16>(in.bias);
    const auto ref = naive::gemm(in.x, in.weight, in.bias, m, n, k, p.group_size, act_bits);
    for (const auto& impl : implementations()) {
      const std::string what = impl.name + " m " + std::to_string(m) + " n " + std::to_string(n);
      std::vector<Eigen::bfloat16> outputs[2];
      for (int threads = 0; threads < 2; ++threads) {
        dyq::set_thread_count_source(threads == 0 ? one_thread : three_threads);
        outputs[threads].assign(m * n, static_cast<Eigen::bfloat16>(-12345.0f));
        impl.run(x.data(), ScalarType::kBFloat16, in.qweight.data(), in.weight.scales.data(), bias.data(), m, n, k,
                 p.group_size, act_bits, outputs[threads].data());
        expect_within_bound(outputs[threads], ref, relative_bound(impl, p), what);
      }
      ASSERT_EQ(0, std::memcmp(outputs[0].data(), outputs[1].data(), m * n * sizeof(Eigen::bfloat16))) << what;
    }
  }
}

INSTANTIATE_TEST_SUITE_P(AllActBits, GemmThreadSplitTest, ::testing::Values(2, 4, 8, 16));

}  // namespace
