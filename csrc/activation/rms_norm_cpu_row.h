// RMSNorm of one activation row (formula and layout: activation/rms_norm_cpu.h), compiled once per
// instruction set (cpu/isa_region.h). The conversions are the vectorized ones of the activation quantizer
// (load_row_fp32, store_row_from_fp32: exact widening, round-half-to-even narrowing); the sum of squares
// and the two products are plain loops over contiguous floats, which the compiler vectorizes with the
// region's instructions (the sum through 32 independent partial sums: two AVX-512 registers, so that the adds overlap).
#pragma once

#include <cmath>
#include <cstdint>
#include <type_traits>

#include "activation/act_quant_cpu_row.h"
#include "common/cpu_dtype.h"
#include "cpu/isa_region.h"

DYQ_ISA_BEGIN
namespace dyq::cpu::DYQ_ISA_NAMESPACE {

// sum_i v_i^2 in fp32.
inline float sum_of_squares(const float* v, int64_t n) {
  constexpr int kLanes = 32;
  float partial[kLanes] = {};
  int64_t i = 0;
  for (; i + kLanes <= n; i += kLanes) {
    for (int lane = 0; lane < kLanes; ++lane) partial[lane] += v[i + lane] * v[i + lane];
  }
  for (; i < n; ++i) partial[i % kLanes] += v[i] * v[i];
  float sum = 0.0f;
  for (int lane = 0; lane < kLanes; ++lane) sum += partial[lane];
  return sum;
}

// One row: out = dtype(weight * dtype(x r)). `weight_fp32` is the weight widened to fp32 (once per call);
// `row` is scratch of n floats.
template <typename Element>
void rms_norm_row(const Element* x, const float* weight_fp32, int64_t n, float eps, float* row, Element* out) {
  load_row_fp32(x, n, row);
  const float inverse_rms = 1.0f / std::sqrt(sum_of_squares(row, n) / static_cast<float>(n) + eps);
  for (int64_t i = 0; i < n; ++i) row[i] *= inverse_rms;
  if constexpr (!std::is_same_v<Element, float>) {
    store_row_from_fp32(row, static_cast<const Element*>(nullptr), n, out);  // h, rounded to the dtype
    load_row_fp32(out, n, row);
  }
  for (int64_t i = 0; i < n; ++i) row[i] *= weight_fp32[i];
  store_row_from_fp32(row, static_cast<const Element*>(nullptr), n, out);
}

}  // namespace dyq::cpu::DYQ_ISA_NAMESPACE
DYQ_ISA_END
