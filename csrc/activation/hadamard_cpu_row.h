// The online Hadamard rotation of one activation row (layout and formula: activation/hadamard_cpu.h),
// compiled once per instruction set (cpu/isa_region.h). The loops are plain C++ over contiguous floats,
// which the compiler vectorizes with the region's instructions: the butterfly stages with h >= 8 and the
// left factor's product (register-blocked, left_product) are runs of independent adds and multiply-adds.
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

// Eight floats as one value, loadable from any float address: GCC's vector extension, which the region's
// instructions lower to one ymm register (AVX2, AVX-512) or two xmm ones (the portable path).
typedef float Floats8 __attribute__((vector_size(32), aligned(4), may_alias));

// The left product z = scaled_left^T y, y and z viewed as [m, p] row-major: z[k p + j] = sum_i
// scaled_left[i, k] y[i p + j]. A register-blocked small GEMM whose vectors run along the longer of y's rows
// (p >= 16) or left's rows (p < 16: only construction 1's 5504 x 2 and small test sizes), the other
// operand's entries broadcast. With vectors along j, a block of 4 outputs k by 16 columns j walks i over
// the stripe of y's 16 columns (m x 64 bytes, in L1 from one block of k to the next) and 4 entries of each
// left row; left itself is read p / 16 times (473 KB for m = 344, Llama-7B's 11008 = 344 x 32).
template <int kOutputs>
inline void left_product_along_columns(const float* scaled_left, const float* y, int64_t m, int64_t p, int64_t k0,
                                       int64_t j0, float* z) {
  Floats8 acc[kOutputs][2] = {};
  for (int64_t i = 0; i < m; ++i) {
    const Floats8 low = *reinterpret_cast<const Floats8*>(y + i * p + j0);
    const Floats8 high = *reinterpret_cast<const Floats8*>(y + i * p + j0 + 8);
    const float* weights = scaled_left + i * m + k0;
    for (int o = 0; o < kOutputs; ++o) {
      acc[o][0] += low * weights[o];
      acc[o][1] += high * weights[o];
    }
  }
  for (int o = 0; o < kOutputs; ++o) {
    *reinterpret_cast<Floats8*>(z + (k0 + o) * p + j0) = acc[o][0];
    *reinterpret_cast<Floats8*>(z + (k0 + o) * p + j0 + 8) = acc[o][1];
  }
}

// With vectors along k: `width` <= 16 outputs from k0 (those past m read as 0) by kColumns columns from j0.
template <int kColumns>
inline void left_product_along_outputs(const float* scaled_left, const float* y, int64_t m, int64_t p, int64_t k0,
                                       int64_t width, int64_t j0, float* z) {
  Floats8 acc[kColumns][2] = {};
  alignas(32) float padded[16] = {};
  for (int64_t i = 0; i < m; ++i) {
    const float* weights = scaled_left + i * m + k0;
    if (width < 16) {
      for (int64_t k = 0; k < width; ++k) padded[k] = weights[k];
      weights = padded;
    }
    const Floats8 low = *reinterpret_cast<const Floats8*>(weights);
    const Floats8 high = *reinterpret_cast<const Floats8*>(weights + 8);
    for (int c = 0; c < kColumns; ++c) {
      acc[c][0] += low * y[i * p + j0 + c];
      acc[c][1] += high * y[i * p + j0 + c];
    }
  }
  for (int c = 0; c < kColumns; ++c) {
    for (int64_t k = 0; k < width; ++k) z[(k0 + k) * p + j0 + c] = acc[c][k / 8][k % 8];
  }
}

inline void left_product(const float* scaled_left, const float* y, int64_t m, int64_t p, float* z) {
  if (p >= 16) {  // p a power of two: whole blocks of 16 columns
    for (int64_t j0 = 0; j0 < p; j0 += 16) {
      int64_t k0 = 0;
      for (; k0 + 4 <= m; k0 += 4) left_product_along_columns<4>(scaled_left, y, m, p, k0, j0, z);
      for (; k0 < m; ++k0) left_product_along_columns<1>(scaled_left, y, m, p, k0, j0, z);
    }
    return;
  }
  for (int64_t k0 = 0; k0 < m; k0 += 16) {
    const int64_t width = m - k0 < 16 ? m - k0 : 16;
    int64_t j0 = 0;
    for (; j0 + 4 <= p; j0 += 4) left_product_along_outputs<4>(scaled_left, y, m, p, k0, width, j0, z);
    for (; j0 < p; ++j0) left_product_along_outputs<1>(scaled_left, y, m, p, k0, width, j0, z);
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
  if (m == 1) {  // left is the scalar 1 / sqrt(p)
    for (int64_t j = 0; j < p; ++j) z[j] = scaled_left[0] * signed_row[j];
  } else {
    left_product(scaled_left, signed_row, m, p, z);
  }
  if constexpr (!std::is_same_v<Element, float>) {
    for (int64_t i = 0; i < n; ++i) out[i] = from_float<Element>(z[i]);
  }
}

}  // namespace dyq::cpu::DYQ_ISA_NAMESPACE
DYQ_ISA_END
