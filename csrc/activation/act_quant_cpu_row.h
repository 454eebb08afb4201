// Quantization of one activation row (docs/numerics.md, section 2): the one CPU quantizer, shared by
// the standalone op (act_quant_cpu.cpp) and every GEMM path that fuses it (gemm_cpu.cpp,
// gemm_cpu_avx512.h). Each caller only lays the codes out its own way (packed, centered, even/odd).
//
// With AVX-512 the row is converted and quantized 16 lanes at a time; vdivps and vrndscaleps (round to
// nearest even) are exact IEEE operations, so the codes are bit-identical to the scalar expressions of
// common/format.h, which the build without AVX-512 uses.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>

#include "common/cpu_dtype.h"
#include "common/format.h"

#if defined(__AVX512F__) && defined(__AVX512BW__)
#define DYQ_ACT_QUANT_AVX512 1
#include <immintrin.h>
#endif

namespace dyq::cpu {

// x converted to fp32 (any k).
template <typename Element>
void load_row_fp32(const Element* x, int64_t k, float* out) {
  if constexpr (std::is_same_v<Element, float>) {
    std::memcpy(out, x, k * sizeof(float));
  } else {
    int64_t i = 0;
#if defined(DYQ_ACT_QUANT_AVX512)
    const auto* bits = reinterpret_cast<const uint16_t*>(x);
    for (; i + 16 <= k; i += 16) {
      const __m256i halves = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(bits + i));
      __m512 values;
      if constexpr (std::is_same_v<Element, Eigen::bfloat16>) {
        values = _mm512_castsi512_ps(_mm512_slli_epi32(_mm512_cvtepu16_epi32(halves), 16));
      } else {
        values = _mm512_cvtph_ps(halves);
      }
      _mm512_storeu_ps(out + i, values);
    }
#endif
    for (; i < k; ++i) out[i] = to_float(x[i]);
  }
}

// Codes q_x of one group of `columns` fp32 values (a full group, or the remainder at the end of a row);
// returns the group's (s_x, z_x).
inline ActivationGroupParams quantize_group(const float* v, int64_t columns, int act_bits, uint8_t* codes) {
#if defined(DYQ_ACT_QUANT_AVX512)
  // Lanes past `columns` load as 0, which changes neither the range (it always holds 0) nor finiteness.
  auto lanes = [&](int64_t i) {
    const int64_t rest = columns - i;
    return rest >= 16 ? static_cast<__mmask16>(0xFFFF) : static_cast<__mmask16>((1u << rest) - 1);
  };
  const __m512 zero = _mm512_setzero_ps();
  __m512 group_min = zero, group_max = zero;
  __mmask16 nonfinite = 0;
  for (int64_t i = 0; i < columns; i += 16) {
    const __m512 values = _mm512_maskz_loadu_ps(lanes(i), v + i);
    nonfinite |= _mm512_cmp_ps_mask(_mm512_sub_ps(values, values), zero, _CMP_NEQ_UQ);  // NaN or Inf
    group_min = _mm512_min_ps(group_min, values);
    group_max = _mm512_max_ps(group_max, values);
  }
  const ActivationGroupParams params = activation_group_params(_mm512_reduce_min_ps(group_min),
                                                               _mm512_reduce_max_ps(group_max), act_bits, nonfinite != 0);
  if (nonfinite != 0) {
    std::memset(codes, 0, columns);
    return params;
  }
  const __m512 levels = _mm512_set1_ps(static_cast<float>((1 << act_bits) - 1));
  const __m512 scale = _mm512_set1_ps(params.scale);
  const __m512 zero_point = _mm512_set1_ps(static_cast<float>(params.zero));
  for (int64_t i = 0; i < columns; i += 16) {
    const __m512 ratio = _mm512_div_ps(_mm512_maskz_loadu_ps(lanes(i), v + i), scale);
    const __m512 rounded = _mm512_roundscale_ps(ratio, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    const __m512 code = _mm512_min_ps(_mm512_max_ps(_mm512_add_ps(rounded, zero_point), zero), levels);
    _mm512_mask_cvtepi32_storeu_epi8(codes + i, lanes(i), _mm512_cvtps_epi32(code));
  }
  return params;
#else
  float group_min = 0.0f;
  float group_max = 0.0f;
  bool nonfinite = false;
  for (int64_t i = 0; i < columns; ++i) {
    nonfinite |= !std::isfinite(v[i]);
    group_min = std::fmin(group_min, v[i]);
    group_max = std::fmax(group_max, v[i]);
  }
  const ActivationGroupParams params = activation_group_params(group_min, group_max, act_bits, nonfinite);
  for (int64_t i = 0; i < columns; ++i) codes[i] = static_cast<uint8_t>(activation_code(v[i], params, act_bits));
  return params;
#endif
}

// Quantizes the k values of `x`: codes[0..k) receive the unsigned codes q_x, params[0..ceil(k/group_size))
// each group's (s_x, z_x), the last group holding the remainder when group_size does not divide k.
// `row_fp32` is scratch of k floats.
template <typename Element>
void quantize_activation_row(const Element* x, int64_t k, int group_size, int act_bits, float* row_fp32,
                             uint8_t* codes, ActivationGroupParams* params) {
  load_row_fp32(x, k, row_fp32);
  for (int64_t g = 0; g < group_count(k, group_size); ++g) {
    params[g] = quantize_group(row_fp32 + g * group_size, group_columns(k, group_size, g), act_bits,
                               codes + g * group_size);
  }
}

}  // namespace dyq::cpu
