// The portable GEMM (docs/numerics.md, section 3): per-group Eigen products of integer-valued fp32
// matrices, exact because every partial sum is an integer below 2^24. The path for CPUs without AVX2,
// and on aarch64.
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <vector>

#include "activation/act_quant_cpu_row.h"
#include "common/cpu_dtype.h"
#include "common/precision.h"
#include "parallel/parallel.h"

namespace dyq::cpu::portable {

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

// out = x W^T (+ bias) at kBits; returns whether every output is finite.
template <int kBits, typename Element>
bool gemm_typed(const Element* x, const uint8_t* qweight, const float* scales, const Element* bias,
                int64_t m, int64_t n, int64_t k, int group_size, Element* out) {
  const PortableActivations activations = prepare_portable_activations<kBits>(x, m, k, group_size);
  const int64_t groups = group_count(k, group_size);
  const int64_t tasks = (n + kPortableRowsPerTask - 1) / kPortableRowsPerTask;
  FiniteOutputs finite;
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
        finite.check(out + row * n + row_begin, rows);
      }
    }
  });
  return finite.all();
}

inline const char* gemm_kernel(int64_t, int64_t, int, int act_bits) {
  return act_bits == kFallbackBits ? "portable/eigen-fp32" : "portable/eigen-integer-fp32";
}

}  // namespace dyq::cpu::portable
