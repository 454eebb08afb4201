// The entry points of one path's kernels. Each cpu/kernels_<isa>.cpp includes this last, after the
// header that defines the path's gemm_typed and gemm_kernel (and, through it, quantize_activation_row), and so defines
// dyq::cpu::<isa>::kernels, the entry of the dispatch table (cpu/cpu_isa.cpp). The entry points are
// baseline code outside the target region: they only choose the element type and width, then call in.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>
#include <vector>

#include "activation/hadamard_cpu_row.h"
#include "activation/rms_norm_cpu_row.h"
#include "common/cpu_dtype.h"
#include "common/precision.h"
#include "cpu/cpu_isa.h"
#include "cpu/isa_region.h"
#include "parallel/parallel.h"

namespace dyq::cpu::DYQ_ISA_NAMESPACE {
namespace {

// The canonical packed layout: code i of each byte in bits [i * b, (i + 1) * b).
template <int kBits>
void pack_codes(const uint8_t* codes, int64_t count, uint8_t* packed) {
  constexpr int kCodesPerByte = ActivationTraits<kBits>::kCodesPerByte;
  for (int64_t byte = 0; byte < count / kCodesPerByte; ++byte) {
    uint32_t packed_byte = 0;
    for (int i = 0; i < kCodesPerByte; ++i) packed_byte |= uint32_t{codes[byte * kCodesPerByte + i]} << (i * kBits);
    packed[byte] = static_cast<uint8_t>(packed_byte);
  }
}

template <int kBits, typename Element>
void quantize_rows(const Element* x, int64_t m, int64_t k, int group_size, uint8_t* packed, float* scales,
                   uint8_t* zeros) {
  const int64_t groups = group_count(k, group_size);
  const int64_t packed_row_bytes = packed_activation_bytes(k, kBits);
  parallel_for(0, m, 4, [&](int64_t row_begin, int64_t row_end) {
    std::vector<float> row_fp32(k);
    std::vector<uint8_t> codes(k);
    std::vector<ActivationGroupParams> params(groups);
    for (int64_t row = row_begin; row < row_end; ++row) {
      quantize_activation_row(x + row * k, k, group_size, kBits, row_fp32.data(), codes.data(), params.data());
      pack_codes<kBits>(codes.data(), k, packed + row * packed_row_bytes);
      for (int64_t g = 0; g < groups; ++g) {
        scales[row * groups + g] = params[g].scale;
        zeros[row * groups + g] = static_cast<uint8_t>(params[g].zero);
      }
    }
  });
}

void quantize_activations(const void* x, ScalarType dtype, int64_t m, int64_t k, int group_size, int act_bits,
                          uint8_t* packed, float* scales, uint8_t* zeros) {
  dispatch_element_type(dtype, [&](auto element) {
    using Element = decltype(element);
    dispatch_act_bits(
        act_bits,
        [&](auto bits) {
          constexpr int kBits = decltype(bits)::value;
          if constexpr (ActivationTraits<kBits>::kQuantized) {
            quantize_rows<kBits>(static_cast<const Element*>(x), m, k, group_size, packed, scales, zeros);
          }
        },
        [] {});
  });
}

// The online Hadamard rotation (activation/hadamard_cpu.h): left / sqrt(p) computed once, then rows in
// parallel, each with its own scratch.
template <typename Element>
void hadamard_rows(const Element* x, const float* signs, const float* left, int64_t rows, int64_t n, int64_t m,
                   Element* out) {
  const int64_t p = n / m;
  const double norm = 1.0 / std::sqrt(static_cast<double>(p));
  std::vector<float> scaled_left(m * m);
  for (int64_t i = 0; i < m * m; ++i) scaled_left[i] = static_cast<float>(left[i] * norm);
  // A chunk of rows is at least ~64K elements of work, so that small calls stay on one thread.
  const int64_t grain = std::max<int64_t>(1, (int64_t{1} << 16) / n);
  parallel_for(0, rows, grain, [&](int64_t row_begin, int64_t row_end) {
    std::vector<float> signed_row(n), product(std::is_same_v<Element, float> ? 0 : n);
    for (int64_t row = row_begin; row < row_end; ++row) {
      hadamard_transform_row(x + row * n, signs, scaled_left.data(), m, p, signed_row.data(), product.data(),
                             out + row * n);
    }
  });
}

void hadamard_transform(const void* x, ScalarType dtype, const float* signs, const float* left, int64_t rows,
                        int64_t n, int64_t m, void* out) {
  if (rows == 0 || n == 0) return;
  dispatch_element_type(dtype, [&](auto element) {
    using Element = decltype(element);
    hadamard_rows(static_cast<const Element*>(x), signs, left, rows, n, m, static_cast<Element*>(out));
  });
}

// RMSNorm (activation/rms_norm_cpu.h): the weight widened once, then rows in parallel, each with its own
// scratch. A chunk is at least 16K elements (about 10 us on one core), so that a decode step's rows stay on
// the calling thread and a prefill's are shared.
template <typename Element>
void rms_norm_rows(const Element* x, const Element* weight, int64_t rows, int64_t n, float eps, Element* out) {
  std::vector<float> weight_fp32(n);
  load_row_fp32(weight, n, weight_fp32.data());
  const int64_t grain = std::max<int64_t>(1, (int64_t{1} << 14) / n);
  parallel_for(0, rows, grain, [&](int64_t row_begin, int64_t row_end) {
    std::vector<float> row(n);
    for (int64_t r = row_begin; r < row_end; ++r) {
      rms_norm_row(x + r * n, weight_fp32.data(), n, eps, row.data(), out + r * n);
    }
  });
}

void rms_norm(const void* x, ScalarType dtype, const void* weight, int64_t rows, int64_t n, float eps, void* out) {
  if (rows == 0 || n == 0) return;
  dispatch_element_type(dtype, [&](auto element) {
    using Element = decltype(element);
    rms_norm_rows(static_cast<const Element*>(x), static_cast<const Element*>(weight), rows, n, eps,
                  static_cast<Element*>(out));
  });
}

// After a GEMM whose outputs were not all finite (gemm_typed said so), the rows whose output is not finite
// although their x, the bias and the weight scales are: an fp32 intermediate overflowed (x near FLT_MAX
// makes sum x q_w overflow at 16 bits, or groups of opposite sign meet as inf - inf). Such a row is
// computed again from x scaled by 2^-shift, which is exact: every quantity of the format scales with x (s_x
// does, the codes and P do not), so the sums are the same numbers times 2^-shift, then scaled back. Returns false if a value is still out of range of the dtype.
// Baseline code, as every entry point, so the rescue is the same on every path.
template <typename Element, typename Compute>
bool recompute_overflowed_rows(const Element* x, const float* scales, const Element* bias, int64_t m, int64_t n,
                               int64_t k, int group_size, Element* out, Compute&& compute) {
  auto finite = [](const auto* values, int64_t count) { return all_finite(values, count); };
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

// The path's GEMM, then the rows that overflowed recomputed (dyq::cpu::gemm's contract, gemm/gemm_cpu.h).
bool gemm(const void* x, ScalarType dtype, const uint8_t* qweight, const float* scales, const void* bias, int64_t m,
          int64_t n, int64_t k, int group_size, int act_bits, void* out) {
  if (m == 0 || n == 0) return true;
  // Below about 128 thousand multiply-adds one thread finishes sooner than two: the second thread's share is
  // smaller than the cost of handing it over. On the AMD EPYC in torch (its OpenMP threads, alternating
  // builds), two threads took 768 x 256 at M = 1 in 11 to 13 us against 14 on one, at M = 4 in 14 against
  // 17, and 256 x 256 at M = 8 in 11 against 11.6; 256 x 256 at M = 1 (65536) was no faster on two. The
  // threshold had been a million (a 256 x 256 layer at 16 rows). On the Xeon with AMX (torch, the thread
  // counts alternating in one process, W4A8) it holds: two threads took 768 x 256 at M = 1 in 17.7 against
  // 21.7 us, 256 x 768 at M = 1 tied (15.9 and 15.7), and 256 x 256 at M = 2 and 4, just above it, were 4 %
  // to 6 % slower on two.
  constexpr int64_t kMinParallelWork = int64_t{1} << 17;
  const SerialScope serial(m * n * k < kMinParallelWork);
  bool in_range = true;
  dispatch_element_type(dtype, [&](auto element) {
    using Element = decltype(element);
    dispatch_act_bits(
        act_bits,
        [&](auto bits) {
          // Returns whether every output is finite (gemm_typed checks them as its threads write them).
          auto compute = [&](const Element* rows_x, const Element* rows_bias, int64_t rows, Element* rows_out) {
            return gemm_typed<decltype(bits)::value>(rows_x, qweight, scales, rows_bias, rows, n, k, group_size,
                                                     rows_out);
          };
          const auto* typed_x = static_cast<const Element*>(x);
          const auto* typed_bias = static_cast<const Element*>(bias);
          auto* typed_out = static_cast<Element*>(out);
          in_range = compute(typed_x, typed_bias, m, typed_out) ||
                     recompute_overflowed_rows(typed_x, scales, typed_bias, m, n, k, group_size, typed_out, compute);
        },
        [] {});
  });
  return in_range;
}

}  // namespace

extern const CpuKernelSet kernels = {gemm, quantize_activations, gemm_kernel, hadamard_transform, rms_norm};

}  // namespace dyq::cpu::DYQ_ISA_NAMESPACE
