// The online Hadamard rotation of one activation row (layout and formula: activation/hadamard_cpu.h),
// compiled once per instruction set (cpu/isa_region.h). The loops are plain C++ over contiguous floats,
// which the compiler vectorizes with the region's instructions: the butterfly stages with h >= 8 and the
// left factor's row updates are runs of independent adds and multiply-adds.
#pragma once

#include <cstdint>
#include <type_traits>

#include "activation/act_quant_cpu_row.h"
#include "common/cpu_dtype.h"
#include "cpu/isa_region.h"

DYQ_ISA_BEGIN
namespace dyq::cpu::DYQ_ISA_NAMESPACE {

// y <- H_p y in place, H_p Sylvester's +-1 matrix of order p (a power of two): log2(p) stages of butterflies
// (a, b) -> (a + b, a - b) on the elements h apart, h = 1, 2, ..., p/2.
inline void walsh_hadamard_in_place(float* y, int64_t p) {
  for (int64_t h = 1; h < p; h *= 2) {
    for (int64_t block = 0; block < p; block += 2 * h) {
      float* low = y + block;
      float* high = low + h;
      for (int64_t j = 0; j < h; ++j) {
        const float a = low[j], b = high[j];
        low[j] = a + b;
        high[j] = a - b;
      }
    }
  }
}

// One row: y = (x * signs) viewed as [m, p], each of its m rows through the butterfly, then
// out = scaled_left^T y, scaled_left = left / sqrt(p) ([m, m] row-major). `signed_row` is scratch of
// m * p floats; `product` too, unless Element is float (the product is then written to out directly).
template <typename Element>
void hadamard_transform_row(const Element* x, const float* signs, const float* scaled_left, int64_t m, int64_t p,
                            float* signed_row, float* product, Element* out) {
  const int64_t n = m * p;
  load_row_fp32(x, n, signed_row);
  for (int64_t i = 0; i < n; ++i) signed_row[i] *= signs[i];
  for (int64_t i = 0; i < m; ++i) walsh_hadamard_in_place(signed_row + i * p, p);
  float* z = product;
  if constexpr (std::is_same_v<Element, float>) z = out;
  // z = sum_i outer(scaled_left[i, :], y[i, :]): left is read row by row, once per row of x. (For
  // n = 11008 = 5504 x 2 left is 5504^2 floats and this product is nearly the whole cost.)
  for (int64_t i = 0; i < m; ++i) {
    const float* weights = scaled_left + i * m;
    const float* y_row = signed_row + i * p;
    for (int64_t k = 0; k < m; ++k) {
      float* z_row = z + k * p;
      const float weight = weights[k];
      if (i == 0) {
        for (int64_t j = 0; j < p; ++j) z_row[j] = weight * y_row[j];
      } else {
        for (int64_t j = 0; j < p; ++j) z_row[j] += weight * y_row[j];
      }
    }
  }
  if constexpr (!std::is_same_v<Element, float>) {
    for (int64_t i = 0; i < n; ++i) out[i] = from_float<Element>(z[i]);
  }
}

}  // namespace dyq::cpu::DYQ_ISA_NAMESPACE
DYQ_ISA_END
