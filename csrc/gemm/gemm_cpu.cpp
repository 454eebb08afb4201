// The W4A2 / W4A4 / W4A8 / W4A16 GEMM on the CPU (every width of common/precision.h) (docs/numerics.md, section 3).
#include "gemm/gemm_cpu.h"

#include <Eigen/Core>
#include <cmath>
#include <vector>

#include "activation/act_quant_cpu_row.h"
#include "common/cpu_dtype.h"
#include "common/precision.h"
#include "gemm/gemm_cpu_avx512.h"
#include "gemm/gemm_cpu_paths.h"
#include "parallel/parallel.h"

namespace dyq::cpu {
namespace {

using RowMajorMatrix = Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
using ColMajorMatrix = Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic>;

// Output rows (weight rows) per task of the portable path.
constexpr int64_t kPortableRowsPerTask = 64;

// The left operand of every group product: the centered codes q_x - z_x (integers) with their scales
// s_x, or at the fallback width the fp32 copy of x.
struct PortableActivations {
  RowMajorMatrix values;  // [m, k]
  RowMajorMatrix scales;  // [m, groups]; empty at the fallback width
};

template <int kBits, typename Element>
PortableActivations prepare_portable_activations(const Element* x, int64_t m, int64_t k, int group_size) {
  PortableActivations prepared;
  prepared.values.resize(m, k);
  if constexpr (!ActivationTraits<kBits>::kQuantized) {
    parallel_for(0, m, 16, [&](int64_t row_begin, int64_t row_end) {
      for (int64_t row = row_begin; row < row_end; ++row) load_row_fp32(x + row * k, k, &prepared.values(row, 0));
    });
  } else {
    const int64_t groups = group_count(k, group_size);
    prepared.scales.resize(m, groups);
    parallel_for(0, m, 4, [&](int64_t row_begin, int64_t row_end) {
      std::vector<float> row_fp32(k);
      std::vector<uint8_t> codes(k);
      std::vector<ActivationGroupParams> params(groups);
      for (int64_t row = row_begin; row < row_end; ++row) {
        quantize_activation_row(x + row * k, k, group_size, kBits, row_fp32.data(), codes.data(), params.data());
        for (int64_t col = 0; col < k; ++col) {
          prepared.values(row, col) = static_cast<float>(int{codes[col]} - params[col / group_size].zero);
        }
        for (int64_t g = 0; g < groups; ++g) prepared.scales(row, g) = params[g].scale;
      }
    });
  }
  return prepared;
}

template <int kBits, typename Element>
void gemm_portable_typed(const Element* x, const uint8_t* qweight, const float* scales, const Element* bias,
                         int64_t m, int64_t n, int64_t k, int group_size, Element* out) {
  const PortableActivations activations = prepare_portable_activations<kBits>(x, m, k, group_size);
  const int64_t groups = group_count(k, group_size);
  const int64_t tasks = (n + kPortableRowsPerTask - 1) / kPortableRowsPerTask;
  parallel_for(0, tasks, 1, [&](int64_t task_begin, int64_t task_end) {
    RowMajorMatrix weight_codes;  // [rows, group_size], integer-valued
    ColMajorMatrix partial;       // [m, rows]: the group's partial sums
    ColMajorMatrix accumulator;   // [m, rows]
    Eigen::VectorXf weight_scales;
    for (int64_t task = task_begin; task < task_end; ++task) {
      const int64_t row_begin = task * kPortableRowsPerTask;
      const int64_t rows = std::min(kPortableRowsPerTask, n - row_begin);
      weight_scales.resize(rows);
      accumulator.setZero(m, rows);
      for (int64_t g = 0; g < groups; ++g) {
        const int64_t columns = group_columns(k, group_size, g);  // the remainder in the last group
        weight_codes.resize(rows, columns);
        for (int64_t r = 0; r < rows; ++r) {
          const uint8_t* packed = qweight + ((row_begin + r) * k + g * group_size) / 2;
          for (int64_t i = 0; i < columns / 2; ++i) {
            weight_codes(r, 2 * i) = static_cast<float>(sign_extend_nibble(packed[i] & 0xFu));
            weight_codes(r, 2 * i + 1) = static_cast<float>(sign_extend_nibble(packed[i] >> 4));
          }
          weight_scales(r) = scales[(row_begin + r) * groups + g];
        }
        partial.noalias() = activations.values.middleCols(g * group_size, columns) * weight_codes.transpose();
        if constexpr (!ActivationTraits<kBits>::kQuantized) {
          accumulator.noalias() += partial * weight_scales.asDiagonal();
        } else {
          accumulator.array() +=
              partial.array() * (activations.scales.col(g) * weight_scales.transpose()).array();
        }
      }
      for (int64_t row = 0; row < m; ++row) {
        for (int64_t r = 0; r < rows; ++r) {
          const int64_t col = row_begin + r;
          const float bias_value = bias != nullptr ? to_float(bias[col]) : 0.0f;
          out[row * n + col] = from_float<Element>(accumulator(row, r) + bias_value);
        }
      }
    }
  });
}

// Calls fn(element, bits) with a value of the C++ element type of `dtype` and the compile-time width.
template <typename Fn>
void dispatch_gemm(ScalarType dtype, int act_bits, Fn&& fn) {
  dispatch_element_type(dtype, [&](auto element) { dispatch_act_bits(act_bits, [&](auto bits) { fn(element, bits); }, [] {}); });
}

// Rows whose output is not finite although their x, the bias and the weight scales are: an fp32
// intermediate overflowed (x near FLT_MAX makes sum x q_w overflow at 16 bits, or groups of opposite sign
// meet as inf - inf). Such a row is computed again from x scaled by 2^-shift, which is exact: every
// quantity of the format scales with x (s_x does, the codes and P do not), so the sums are the same
// numbers times 2^-shift, then scaled back. Returns false if a value is still out of range of the dtype.
template <typename Element, typename Compute>
bool recompute_overflowed_rows(const Element* x, const uint8_t* qweight, const float* scales, const Element* bias,
                               int64_t m, int64_t n, int64_t k, int group_size, Element* out, Compute&& compute) {
  auto finite = [](const auto* values, int64_t count) {
    for (int64_t i = 0; i < count; ++i) {
      if (!std::isfinite(to_float(values[i]))) return false;
    }
    return true;
  };
  if (finite(out, m * n)) return true;
  if (!finite(scales, n * group_count(k, group_size)) || (bias != nullptr && !finite(bias, n))) return true;
  bool in_range = true;
  std::vector<Element> row(k), row_bias(bias != nullptr ? n : 0), row_out(n);
  for (int64_t r = 0; r < m; ++r) {
    if (finite(out + r * n, n) || !finite(x + r * k, k)) continue;  // a non-finite x gives NaN by the spec
    float max_abs = 0.0f;
    for (int64_t i = 0; i < k; ++i) max_abs = std::fmax(max_abs, std::fabs(to_float(x[r * k + i])));
    int exponent = 0;
    std::frexp(max_abs, &exponent);
    // Scaled to at most 2^64, no sum of at most 2^24 terms of |x q_w| <= 2^67 can overflow.
    const int shift = exponent > 64 ? exponent - 64 : 0;
    if (shift == 0) {
      in_range = false;  // x is moderate: the product itself is beyond the dtype
      continue;
    }
    for (int64_t i = 0; i < k; ++i) row[i] = from_float<Element>(std::ldexp(to_float(x[r * k + i]), -shift));
    for (int64_t j = 0; j < static_cast<int64_t>(row_bias.size()); ++j) {
      row_bias[j] = from_float<Element>(std::ldexp(to_float(bias[j]), -shift));
    }
    compute(row.data(), row_bias.empty() ? nullptr : row_bias.data(), int64_t{1}, row_out.data());
    for (int64_t j = 0; j < n; ++j) {
      const Element value = from_float<Element>(std::ldexp(to_float(row_out[j]), shift));
      in_range = in_range && std::isfinite(to_float(value));
      out[r * n + j] = value;
    }
  }
  return in_range;
}

// Runs kernel(x, bias, rows, out) for the problem, then recomputes the rows that overflowed.
template <typename Kernel>
bool gemm_with_overflow_check(const void* x, ScalarType dtype, const uint8_t* qweight, const float* scales,
                              const void* bias, int64_t m, int64_t n, int64_t k, int group_size, int act_bits,
                              void* out, Kernel&& kernel) {
  if (m == 0 || n == 0) return true;
  bool in_range = true;
  dispatch_gemm(dtype, act_bits, [&](auto element, auto bits) {
    using Element = decltype(element);
    auto compute = [&](const Element* rows_x, const Element* rows_bias, int64_t rows, Element* rows_out) {
      kernel(element, bits, rows_x, rows_bias, rows, rows_out);
    };
    const auto* typed_x = static_cast<const Element*>(x);
    const auto* typed_bias = static_cast<const Element*>(bias);
    auto* typed_out = static_cast<Element*>(out);
    compute(typed_x, typed_bias, m, typed_out);
    in_range = recompute_overflowed_rows(typed_x, qweight, scales, typed_bias, m, n, k, group_size, typed_out, compute);
  });
  return in_range;
}

}  // namespace

bool gemm_portable(const void* x, ScalarType dtype, const uint8_t* qweight, const float* scales, const void* bias,
                   int64_t m, int64_t n, int64_t k, int group_size, int act_bits, void* out) {
  return gemm_with_overflow_check(
      x, dtype, qweight, scales, bias, m, n, k, group_size, act_bits, out,
      [&](auto, auto bits, const auto* rows_x, const auto* rows_bias, int64_t rows, auto* rows_out) {
        gemm_portable_typed<decltype(bits)::value>(rows_x, qweight, scales, rows_bias, rows, n, k, group_size,
                                                   rows_out);
      });
}

bool gemm(const void* x, ScalarType dtype, const uint8_t* qweight, const float* scales, const void* bias,
          int64_t m, int64_t n, int64_t k, int group_size, int act_bits, void* out) {
#if defined(DYQ_GEMM_AVX512)
  return gemm_with_overflow_check(
      x, dtype, qweight, scales, bias, m, n, k, group_size, act_bits, out,
      [&](auto, auto bits, const auto* rows_x, const auto* rows_bias, int64_t rows, auto* rows_out) {
        avx512::gemm<decltype(bits)::value>(rows_x, qweight, scales, rows_bias, rows, n, k, group_size, rows_out);
      });
#else
  return gemm_portable(x, dtype, qweight, scales, bias, m, n, k, group_size, act_bits, out);
#endif
}

}  // namespace dyq::cpu
