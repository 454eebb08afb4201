// Naive loops written from docs/numerics.md, independent of the kernels, that the C++ tests compare
// the kernels against. Clarity over speed; the GEMM reference accumulates in double.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include <Eigen/Core>

namespace naive {

inline float rne(float v) { return std::nearbyint(v); }

// Groups of a row: ceil(k / group_size); the last one holds the remainder when group_size does not divide k.
inline int64_t groups_of(int64_t k, int group_size) { return (k + group_size - 1) / group_size; }
inline int64_t columns_of(int64_t k, int group_size, int64_t g) { return std::min<int64_t>(group_size, k - g * group_size); }

struct QuantizedWeight {
  std::vector<int> codes;     // [n, k], in [-8, 7]
  std::vector<float> scales;  // [n, groups]
};

inline QuantizedWeight quantize_weight(const std::vector<float>& weight, int64_t n, int64_t k, int group_size) {
  const int64_t groups = groups_of(k, group_size);
  QuantizedWeight q{std::vector<int>(n * k), std::vector<float>(n * groups)};
  for (int64_t row = 0; row < n; ++row) {
    for (int64_t g = 0; g < groups; ++g) {
      const int64_t columns = columns_of(k, group_size, g);
      float absmax = 0.0f;
      for (int64_t i = 0; i < columns; ++i) absmax = std::max(absmax, std::abs(weight[row * k + g * group_size + i]));
      float scale = absmax / 7.0f;
      const bool empty = scale == 0.0f;
      if (empty) scale = 1.0f;
      q.scales[row * groups + g] = scale;
      for (int64_t i = 0; i < columns; ++i) {
        const int64_t at = row * k + g * group_size + i;
        q.codes[at] = empty ? 0 : static_cast<int>(std::clamp(rne(weight[at] / scale), -8.0f, 7.0f));
      }
    }
  }
  return q;
}

// Column 2j in the low nibble of byte j, column 2j+1 in the high nibble, two's complement.
inline std::vector<uint8_t> pack_weight(const std::vector<int>& codes) {
  std::vector<uint8_t> packed(codes.size() / 2);
  for (size_t j = 0; j < packed.size(); ++j) {
    packed[j] = static_cast<uint8_t>((codes[2 * j] & 0xF) | ((codes[2 * j + 1] & 0xF) << 4));
  }
  return packed;
}

struct QuantizedActivations {
  std::vector<int> codes;     // [m, k], in [0, 2^b - 1]
  std::vector<float> scales;  // [m, groups]
  std::vector<int> zeros;     // [m, groups]
};

inline QuantizedActivations quantize_activations(const std::vector<float>& x, int64_t m, int64_t k, int group_size,
                                                 int act_bits) {
  const float levels = static_cast<float>((1 << act_bits) - 1);
  const int64_t groups = groups_of(k, group_size);
  QuantizedActivations q{std::vector<int>(m * k), std::vector<float>(m * groups), std::vector<int>(m * groups)};
  for (int64_t row = 0; row < m; ++row) {
    for (int64_t g = 0; g < groups; ++g) {
      const int64_t columns = columns_of(k, group_size, g);
      const float* v = &x[row * k + g * group_size];
      bool finite = true;
      float lo = 0.0f, hi = 0.0f;
      for (int64_t i = 0; i < columns; ++i) {
        if (!std::isfinite(v[i])) {
          finite = false;
          continue;
        }
        lo = std::min(lo, v[i]);
        hi = std::max(hi, v[i]);
      }
      // A range beyond FLT_MAX: both ends halved (exact), so the scale is the wide-exponent value.
      float scale = std::isinf(hi - lo) ? ((0.5f * hi - 0.5f * lo) / levels) * 2.0f : (hi - lo) / levels;
      const bool empty = scale == 0.0f;
      if (empty) scale = 1.0f;
      int zero = static_cast<int>(std::clamp(rne(-lo / scale), 0.0f, levels));
      if (empty || !finite) zero = 0;
      q.scales[row * groups + g] = finite ? scale : NAN;
      q.zeros[row * groups + g] = zero;
      for (int64_t i = 0; i < columns; ++i) {
        q.codes[row * k + g * group_size + i] =
            (empty || !finite) ? 0 : static_cast<int>(std::clamp(rne(v[i] / scale) + zero, 0.0f, levels));
      }
    }
  }
  return q;
}

// 8 / b codes per byte, the lowest bits first.
inline std::vector<uint8_t> pack_activations(const std::vector<int>& codes, int act_bits) {
  const int per_byte = 8 / act_bits;
  std::vector<uint8_t> packed(codes.size() / per_byte, 0);
  for (size_t i = 0; i < codes.size(); ++i) {
    packed[i / per_byte] = static_cast<uint8_t>(packed[i / per_byte] | (codes[i] << ((i % per_byte) * act_bits)));
  }
  return packed;
}

// y = x W^T (+ bias) in double, and the sum of |terms| that bounds an fp32 implementation's rounding.
struct GemmReference {
  std::vector<double> value;      // [m, n]
  std::vector<double> magnitude;  // [m, n]
};

inline GemmReference gemm(const std::vector<float>& x, const QuantizedWeight& weight, const std::vector<float>& bias,
                          int64_t m, int64_t n, int64_t k, int group_size, int act_bits) {
  const int64_t groups = groups_of(k, group_size);
  GemmReference ref{std::vector<double>(m * n), std::vector<double>(m * n)};
  QuantizedActivations act;
  if (act_bits != 16) act = quantize_activations(x, m, k, group_size, act_bits);
  for (int64_t row = 0; row < m; ++row) {
    for (int64_t col = 0; col < n; ++col) {
      double value = 0.0, magnitude = 0.0;
      for (int64_t g = 0; g < groups; ++g) {
        double partial = 0.0, partial_magnitude = 0.0;
        for (int64_t i = 0; i < columns_of(k, group_size, g); ++i) {
          const int64_t kk = g * group_size + i;
          const double a = act_bits == 16 ? double{x[row * k + kk]}
                                          : double(act.codes[row * k + kk] - act.zeros[row * groups + g]);
          partial += a * weight.codes[col * k + kk];
          partial_magnitude += std::abs(a * weight.codes[col * k + kk]);
        }
        const double scale = double{weight.scales[col * groups + g]} *
                             (act_bits == 16 ? 1.0 : double{act.scales[row * groups + g]});
        value += scale * partial;
        magnitude += std::abs(scale) * partial_magnitude;
      }
      if (!bias.empty()) {
        value += bias[col];
        magnitude += std::abs(bias[col]);
      }
      ref.value[row * n + col] = value;
      ref.magnitude[row * n + col] = magnitude;
    }
  }
  return ref;
}

// The online Hadamard rotation of activation/hadamard_cpu.h in float64, from its definition: each row times
// diag(signs) (left (x) H_p) / sqrt(p), H_p[j, l] = (-1)^popcount(j & l) (Sylvester's matrix entry by entry,
// no butterfly). Applied as the two dense factors, (m^2 p + m p^2) per row rather than n^2.
inline std::vector<double> hadamard_transform(const std::vector<float>& x, const std::vector<float>& signs,
                                              const std::vector<float>& left, int64_t rows, int64_t m, int64_t p) {
  const int64_t n = m * p;
  std::vector<double> out(rows * n), mixed(n);
  for (int64_t row = 0; row < rows; ++row) {
    for (int64_t k = 0; k < m; ++k) {  // mixed = left^T (x * signs), x viewed as [m, p]
      for (int64_t j = 0; j < p; ++j) {
        double sum = 0.0;
        for (int64_t i = 0; i < m; ++i) sum += double{left[i * m + k]} * x[row * n + i * p + j] * signs[i * p + j];
        mixed[k * p + j] = sum;
      }
    }
    for (int64_t k = 0; k < m; ++k) {  // out = mixed H_p / sqrt(p)
      for (int64_t l = 0; l < p; ++l) {
        double sum = 0.0;
        for (int64_t j = 0; j < p; ++j) sum += (__builtin_popcountll(j & l) % 2 ? -1.0 : 1.0) * mixed[k * p + j];
        out[row * n + k * p + l] = sum / std::sqrt(static_cast<double>(p));
      }
    }
  }
  return out;
}

// Random normal values with a few exact zeros, seeded.
inline std::vector<float> random_values(size_t count, uint32_t seed, float stddev = 1.0f) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> normal(0.0f, stddev);
  std::vector<float> values(count);
  for (auto& v : values) v = (rng() % 16 == 0) ? 0.0f : normal(rng);
  return values;
}

// Rounds fp32 values to Element (fp32, Eigen::bfloat16, Eigen::half) and back.
template <typename Element>
std::vector<Element> to_element(const std::vector<float>& values) {
  std::vector<Element> out(values.size());
  for (size_t i = 0; i < values.size(); ++i) out[i] = static_cast<Element>(values[i]);
  return out;
}

template <typename Element>
std::vector<float> to_float(const std::vector<Element>& values) {
  std::vector<float> out(values.size());
  for (size_t i = 0; i < values.size(); ++i) out[i] = static_cast<float>(values[i]);
  return out;
}

}  // namespace naive
