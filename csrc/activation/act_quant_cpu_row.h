// Quantization of one activation row (docs/numerics.md, section 2): the one CPU quantizer, shared by
// the standalone op and every GEMM path that fuses it (cpu/kernel_entries.h, gemm/gemm_cpu_*.h). Each
// caller only lays the codes out its own way (packed, centered, even/odd).
//
// It is compiled once per instruction set (cpu/isa_region.h): AVX-512 converts and quantizes 16 lanes at
// a time, AVX2 8, the portable path one. vdivps and vroundps / vrndscaleps (round to nearest even) are
// exact IEEE operations, so every path gives codes bit-identical to the scalar expressions of
// common/format.h.
#pragma once

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <type_traits>

#include "common/cpu_dtype.h"
#include "common/format.h"
#include "cpu/isa_region.h"
#include "cpu/x86_ops.h"

DYQ_ISA_BEGIN
namespace dyq::cpu::DYQ_ISA_NAMESPACE {

#if defined(DYQ_CPU_ISA_AVX512)
inline __m512 load_fp32_lanes(const float* x) { return _mm512_loadu_ps(x); }
template <typename Element>
__m512 load_fp32_lanes(const Element* x) {
  const __m256i halves = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(x));
  if constexpr (std::is_same_v<Element, Eigen::bfloat16>) {
    return _mm512_castsi512_ps(slli_epi32(cvtepu16_epi32(halves), 16));
  } else {
    return cvtph_ps(halves);
  }
}
#elif defined(DYQ_CPU_ISA_AVX2)
inline __m256 load_fp32_lanes(const float* x) { return _mm256_loadu_ps(x); }
template <typename Element>
__m256 load_fp32_lanes(const Element* x) {
  const __m128i halves = _mm_loadu_si128(reinterpret_cast<const __m128i*>(x));
  if constexpr (std::is_same_v<Element, Eigen::bfloat16>) {
    return _mm256_castsi256_ps(_mm256_slli_epi32(_mm256_cvtepu16_epi32(halves), 16));
  } else {
    return _mm256_cvtph_ps(halves);
  }
}
#endif

// x converted to fp32 (any k: the vector loop covers whole lanes, the rest is converted one by one).
template <typename Element>
void load_row_fp32(const Element* x, int64_t k, float* out) {
  if constexpr (std::is_same_v<Element, float>) {
    std::memcpy(out, x, k * sizeof(float));
  } else {
    int64_t i = 0;
#if defined(DYQ_CPU_ISA_AVX512)
    for (; i + 16 <= k; i += 16) _mm512_storeu_ps(out + i, load_fp32_lanes(x + i));
#elif defined(DYQ_CPU_ISA_AVX2)
    for (; i + 8 <= k; i += 8) _mm256_storeu_ps(out + i, load_fp32_lanes(x + i));
#endif
    for (; i < k; ++i) out[i] = to_float(x[i]);
  }
}

// Row x (k values) in fp32: x itself where it is fp32 already, else converted into `scratch` (k floats).
template <typename Element>
const float* row_as_fp32(const Element* x, int64_t k, float* scratch) {
  if constexpr (std::is_same_v<Element, float>) {
    return x;
  } else {
    load_row_fp32(x, k, scratch);
    return scratch;
  }
}

// out[i] = values[i] + bias[i] (bias nullable) converted to Element exactly as from_float does (round half
// to even; a NaN becomes Eigen's quiet NaN of its sign for bf16), a vector at a time: written one by one,
// the outputs of a 256-row GEMM of a 256 x 256 layer took a fifth of its time in bf16. store_lanes returns
// the lanes whose stored value is inf or NaN (its exponent all ones), tested in the register it stores.
#if defined(DYQ_CPU_ISA_AVX512)
#if defined(DYQ_AVX512_HAS_BF16)
// vfpclassps: quiet NaN, denormal, signalling NaN, the values that vcvtneps2bf16 and vcvtne2ps2bf16 read
// otherwise than from_float (a denormal as 0, a NaN with its payload kept).
constexpr int kFpclassNanOrDenormal = 0xA1;
#endif

template <typename Element>
__mmask16 store_lanes(__m512 v, Element* out) {
  constexpr int kNanOrInf = 0x99;  // vfpclassps: quiet NaN, +inf, -inf, signalling NaN
  if constexpr (std::is_same_v<Element, float>) {
    _mm512_storeu_ps(out, v);
    return _mm512_fpclass_ps_mask(v, kNanOrInf);
  } else if constexpr (std::is_same_v<Element, Eigen::bfloat16>) {
#if defined(DYQ_AVX512_HAS_BF16)
    // vcvtneps2bf16 rounds half to even as from_float does, but reads a denormal as 0 and keeps a NaN's
    // payload: vectors holding either take the integer rounding below. In one instruction rather than a
    // dozen, W4A8 calls of 256 rows of the policy's 256 x 256 and 768 x 256 layers, bf16 in and out, ran
    // 1.02x to 1.36x faster (one thread, alternating in one process, as the machine's state moved).
    if (_mm512_fpclass_ps_mask(v, kFpclassNanOrDenormal) == 0) {
      const __m256i words = reinterpret_cast<__m256i>(_mm512_cvtneps_pbh(v));
      _mm256_storeu_si256(reinterpret_cast<__m256i*>(out), words);
      const __m256i exponent = _mm256_set1_epi16(0x7F80);
      return _mm256_cmpeq_epi16_mask(_mm256_and_si256(words, exponent), exponent);
    }
#endif
    const __m512i bits = _mm512_castps_si512(v);
    const __m512i one = _mm512_set1_epi32(1);
    const __m512i rounding =
        _mm512_add_epi32(_mm512_set1_epi32(0x7FFF), _mm512_and_si512(srli_epi32(bits, 16), one));
    const __m512i rounded = srli_epi32(_mm512_add_epi32(bits, rounding), 16);
    const __m512i quiet_nan = _mm512_or_si512(_mm512_and_si512(srli_epi32(bits, 16), _mm512_set1_epi32(0x8000)),
                                              _mm512_set1_epi32(0x7FC0));
    const __mmask16 nan = _mm512_cmp_ps_mask(v, v, _CMP_UNORD_Q);
    const __m512i words = _mm512_mask_blend_epi32(nan, rounded, quiet_nan);
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(out), _mm512_maskz_cvtepi32_epi16(kAll16, words));
    const __m512i exponent = _mm512_set1_epi32(0x7F80);
    return _mm512_cmpeq_epi32_mask(_mm512_and_si512(words, exponent), exponent);
  } else {
    const __m256i halves = _mm512_maskz_cvtps_ph(kAll16, v, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(out), halves);
    const __m256i exponent = _mm256_set1_epi16(0x7C00);
    return _mm256_cmpeq_epi16_mask(_mm256_and_si256(halves, exponent), exponent);
  }
}
#elif defined(DYQ_CPU_ISA_AVX2)
template <typename Element>
int store_lanes(__m256 v, Element* out) {
  if constexpr (std::is_same_v<Element, float>) {
    _mm256_storeu_ps(out, v);
    return _mm256_movemask_ps(_mm256_cmp_ps(_mm256_sub_ps(v, v), _mm256_setzero_ps(), _CMP_NEQ_UQ));
  } else if constexpr (std::is_same_v<Element, Eigen::bfloat16>) {
    const __m256i bits = _mm256_castps_si256(v);
    const __m256i rounding = _mm256_add_epi32(_mm256_set1_epi32(0x7FFF),
                                              _mm256_and_si256(_mm256_srli_epi32(bits, 16), _mm256_set1_epi32(1)));
    const __m256i rounded = _mm256_srli_epi32(_mm256_add_epi32(bits, rounding), 16);
    const __m256i quiet_nan = _mm256_or_si256(_mm256_and_si256(_mm256_srli_epi32(bits, 16), _mm256_set1_epi32(0x8000)),
                                              _mm256_set1_epi32(0x7FC0));
    const __m256i nan = _mm256_castps_si256(_mm256_cmp_ps(v, v, _CMP_UNORD_Q));
    const __m256i words = _mm256_blendv_epi8(rounded, quiet_nan, nan);  // each below 2^16
    const __m128i packed = _mm_packus_epi32(_mm256_castsi256_si128(words), _mm256_extracti128_si256(words, 1));
    _mm_storeu_si128(reinterpret_cast<__m128i*>(out), packed);
    const __m256i exponent = _mm256_set1_epi32(0x7F80);
    return _mm256_movemask_epi8(_mm256_cmpeq_epi32(_mm256_and_si256(words, exponent), exponent));
  } else {
    const __m128i halves = _mm256_cvtps_ph(v, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    _mm_storeu_si128(reinterpret_cast<__m128i*>(out), halves);
    const __m128i exponent = _mm_set1_epi16(0x7C00);
    return _mm_movemask_epi8(_mm_cmpeq_epi16(_mm_and_si128(halves, exponent), exponent));
  }
}
#endif

// Whether no value is inf or NaN (no exponent all ones), in chunks without an early exit inside, which the
// compiler vectorizes at the path's width (at the baseline's 4 lanes a scan of a GEMM's whole output had cost
// a tenth of an AMX GEMM of 256 rows of a 256 x 256 layer). The 16-bit types are tested on their own bits:
// widened to fp32 one by one, a scan of 65536 bf16 outputs took 67 us, half of the GEMM that wrote them.
// For the writers' shares that store_row_from_fp32 does not cover, and the overflow rescue's inputs.
template <typename Value>
bool all_finite(const Value* values, int64_t count) {
  using Bits = std::conditional_t<sizeof(Value) == 2, uint16_t, uint32_t>;
  static_assert(sizeof(Value) == sizeof(Bits), "fp32, bf16 or fp16");
  constexpr Bits kExponent = std::is_same_v<Value, Eigen::half> ? Bits{0x7C00}
                             : std::is_same_v<Value, Eigen::bfloat16> ? Bits{0x7F80}
                                                                        : static_cast<Bits>(0x7F800000u);
  constexpr int64_t kChunk = 256;
  for (int64_t begin = 0; begin < count; begin += kChunk) {
    const int64_t end = std::min(count, begin + kChunk);
    Bits exponent_all_ones = 0;
    for (int64_t i = begin; i < end; ++i) {
      Bits bits;
      std::memcpy(&bits, values + i, sizeof(bits));
      exponent_all_ones |= (bits & kExponent) == kExponent ? Bits{1} : Bits{0};
    }
    if (exponent_all_ones != 0) return false;
  }
  return true;
}

// Whether every output of a GEMM came out finite, which its gemm_typed returns (dyq::cpu::gemm recomputes
// the rows that did not: cpu/kernel_entries.h). Each thread notes the outputs it has just written
// (store_row_from_fp32 tests them in the registers it stores). The calling thread used to scan the whole
// output afterwards, reading the rows the other thread had written; the next call's writes to those rows
// then had to take their cache lines back from the other core. On the 2-core AMD EPYC virtual machine,
// in torch, two-thread GEMMs of 256 rows of the closed-loop policy's layers took as long as on one thread
// for long stretches (256 x 256: 107 us, against 75 with the outputs checked by their writers; 768 x 256:
// 275 against 180), and 1 % to 3 % longer in others.
class FiniteOutputs {
 public:
  void note(bool finite) {
    if (!finite) nonfinite_.store(true, std::memory_order_relaxed);
  }
  // Notes all_finite over `count` outputs from `out`.
  template <typename Element>
  void check(const Element* out, int64_t count) {
    note(all_finite(out, count));
  }
  bool all() const { return !nonfinite_.load(std::memory_order_relaxed); }

 private:
  std::atomic<bool> nonfinite_{false};
};

// Returns whether every output it wrote is finite. Always inlined: the AMX tile loops write a block's outputs
// 32 at a time, a row per call, and the calls' own cost had been a seventh of a W4A8 GEMM of 256 rows of the
// policy's 768 x 256 layer.
template <typename Element>
[[gnu::always_inline]] inline bool store_row_from_fp32(const float* values, const Element* bias, int64_t count, Element* out) {
  int64_t i = 0;
  unsigned nonfinite = 0;  // lanes of store_lanes, ORed
#if defined(DYQ_CPU_ISA_AVX512)
  for (; i + 16 <= count; i += 16) {
    __m512 v = _mm512_loadu_ps(values + i);
    if (bias != nullptr) v = _mm512_add_ps(v, load_fp32_lanes(bias + i));
    nonfinite |= store_lanes(v, out + i);
  }
#elif defined(DYQ_CPU_ISA_AVX2)
  for (; i + 8 <= count; i += 8) {
    __m256 v = _mm256_loadu_ps(values + i);
    if (bias != nullptr) v = _mm256_add_ps(v, load_fp32_lanes(bias + i));
    nonfinite |= static_cast<unsigned>(store_lanes(v, out + i));
  }
#endif
  const int64_t tail = i;
  for (; i < count; ++i) out[i] = from_float<Element>(values[i] + (bias != nullptr ? to_float(bias[i]) : 0.0f));
  return nonfinite == 0 && all_finite(out + tail, count - tail);
}

// A group's quantization in two halves, so that a row can run each over several groups before the next
// (quantize_values): its range, then, from the parameters that activation_group_params derives from it,
// its codes.
struct GroupRange {
  float min, max;  // of the values and 0
  bool nonfinite;  // a NaN or Inf among the values
};

// x / s for the codes by its reciprocal: q = x r with r = 1 / s, then q + (x - q s) r with the residual
// x - q s exact in one FMA. With r correctly rounded and q within an ulp of x / s, that is the correctly
// rounded quotient (Markstein's theorem), bit for bit the division, for every normal x as long as nothing
// underflows: s in [2^-100, 2^100] here, and other groups divide. A subnormal x may come out an ulp off, but
// |x / s| < 2^-26 there, so its code is the group's zero point all the same. (Checked against vdivps on 10^9
// pairs, x at and around half-integer multiples of s included: no normal x differed, nor any code.) vdivps
// issues once every several cycles: without it, W4A8 and W4A4 calls of 256 rows of the policy's 768 x 256
// and 256 x 256 layers ran 3 % to 8 % faster (one thread, C++ loop, alternating builds).
// quotient_by_reciprocal(s): whether x / s may go through the reciprocal.
inline bool quotient_by_reciprocal(float scale) { return scale >= 0x1p-100f && scale <= 0x1p100f; }

#if defined(DYQ_CPU_ISA_AVX512)
// Over `columns` fp32 values (a full group, or the remainder at the end of a row). Lanes past `columns` load
// as 0, which changes neither the range (it always holds 0) nor finiteness, and are not stored.
inline __mmask16 group_lanes(int64_t columns, int64_t i) {
  const int64_t rest = columns - i;
  return rest >= 16 ? kAll16 : static_cast<__mmask16>((1u << rest) - 1);
}

// The range of a group as vectors, to be folded 16 groups at once (quantize_values): the lanes' minimum and
// maximum with 0, and `poison`, the sum of x * 0 over the values, which is 0 unless a value is NaN or
// infinite (one multiply-add a vector where a compare and a mask OR took three).
inline void group_range_lanes(const float* v, int64_t columns, __m512& group_min, __m512& group_max, __m512& poison) {
  const __m512 zero = _mm512_setzero_ps();
  __m512 lo = zero, hi = zero, nonfinite = zero;
  auto take = [&](__m512 values) {
    nonfinite = _mm512_fmadd_ps(values, zero, nonfinite);
    lo = min_ps(lo, values);
    hi = max_ps(hi, values);
  };
  int64_t i = 0;
  for (; i + 16 <= columns; i += 16) take(_mm512_loadu_ps(v + i));
  if (i < columns) take(_mm512_maskz_loadu_ps(group_lanes(columns, i), v + i));
  group_min = lo;
  group_max = hi;
  poison = nonfinite;
}

// Lane g of the result: `op` folded over the 16 lanes of v[g]. Four levels, each halving both the vectors and
// the lanes still to fold (45 shuffles and operations for 16 vectors, where one horizontal fold each took 160).
template <typename Op>
__m512 fold_each_lanes(__m512 (&v)[16], Op op) {
  __m512 halves[8], quarters[4], eighths[2];
  // Lanes 0..7: v[2p] folded to 8 lanes, 8..15: v[2p + 1].
  for (int p = 0; p < 8; ++p) {
    halves[p] = op(_mm512_maskz_shuffle_f32x4(kAll16, v[2 * p], v[2 * p + 1], 0x44),
                   _mm512_maskz_shuffle_f32x4(kAll16, v[2 * p], v[2 * p + 1], 0xEE));
  }
  // 128-bit lane i: v[4p + i] folded to 4 lanes.
  for (int p = 0; p < 4; ++p) {
    quarters[p] = op(_mm512_maskz_shuffle_f32x4(kAll16, halves[2 * p], halves[2 * p + 1], 0x88),
                     _mm512_maskz_shuffle_f32x4(kAll16, halves[2 * p], halves[2 * p + 1], 0xDD));
  }
  // 128-bit lane i: v[8p + i] in elements 0 and 1, v[8p + 4 + i] in 2 and 3.
  for (int p = 0; p < 2; ++p) {
    eighths[p] = op(_mm512_maskz_shuffle_ps(kAll16, quarters[2 * p], quarters[2 * p + 1], 0x44),
                    _mm512_maskz_shuffle_ps(kAll16, quarters[2 * p], quarters[2 * p + 1], 0xEE));
  }
  // Lane 4 i + e: v[4 e + i]; the permute puts v[g] at lane g.
  const __m512 folded = op(_mm512_maskz_shuffle_ps(kAll16, eighths[0], eighths[1], 0x88),
                           _mm512_maskz_shuffle_ps(kAll16, eighths[0], eighths[1], 0xDD));
  return permutexvar_ps(_mm512_setr_epi32(0, 4, 8, 12, 1, 5, 9, 13, 2, 6, 10, 14, 3, 7, 11, 15), folded);
}

// activation_group_params (common/format.h) of 16 groups at once, lane by lane the same values: the division
// and the rounding are the IEEE operations of the scalar expressions, and the special cases (non-finite
// groups, a range past FLT_MAX, a zero range) are blended in the order the scalar code tests them.
// Returns s_x and writes z_x and 1 / s_x.
inline __m512 activation_group_params_lanes(__m512 group_min, __m512 group_max, __m512 poison, int act_bits,
                                            __m512i& zero_points, __m512& reciprocals) {
  const __m512 zero = _mm512_setzero_ps();
  const __m512 levels = _mm512_set1_ps(static_cast<float>((1 << act_bits) - 1));
  const __m512 lo = min_ps(group_min, zero), hi = max_ps(group_max, zero);
  __m512 scale = _mm512_div_ps(_mm512_sub_ps(hi, lo), levels);
  const __mmask16 overflow = _mm512_cmp_ps_mask(scale, _mm512_set1_ps(3.4028235e38f), _CMP_GT_OQ);
  if (overflow != 0) {
    const __m512 half = _mm512_set1_ps(0.5f);
    const __m512 halved = _mm512_div_ps(_mm512_sub_ps(_mm512_mul_ps(half, hi), _mm512_mul_ps(half, lo)), levels);
    scale = _mm512_mask_mul_ps(scale, overflow, halved, _mm512_set1_ps(2.0f));
  }
  const __mmask16 nonfinite = _mm512_cmp_ps_mask(poison, poison, _CMP_UNORD_Q);
  const __mmask16 no_range = _mm512_cmp_ps_mask(scale, zero, _CMP_EQ_OQ);
  const __m512 point = _mm512_maskz_roundscale_ps(kAll16, _mm512_div_ps(_mm512_sub_ps(zero, lo), scale),
                                                  _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  zero_points = _mm512_maskz_cvttps_epi32(static_cast<__mmask16>(~(nonfinite | no_range)),
                                          min_ps(max_ps(point, zero), levels));
  scale = _mm512_mask_blend_ps(no_range, scale, _mm512_set1_ps(1.0f));
  scale = _mm512_mask_blend_ps(nonfinite, scale, _mm512_set1_ps(std::numeric_limits<float>::quiet_NaN()));
  reciprocals = _mm512_div_ps(_mm512_set1_ps(1.0f), scale);
  return scale;
}

// rne(x / s_x) of 16 values as int32, x / s_x through the reciprocal (kByReciprocal) or the division, and
// the codes clamp(rne(x / s_x) + z_x, 0, L) (code_lanes). The quotient is converted to int32 rounding to
// nearest even, then z_x added and the clamp taken on integers: the codes of rounding in fp32 and converting
// last, since a group's range sets its s_x, so that |x / s_x| is at most about L, far inside int32. One
// conversion in place of a round and a conversion, both on one port of Intel's cores: 256 rows of the
// policy's 256 x 256 and 256 x 768 layers (W4A8, W4A4, W4A2 on the AMX tiles) 1.03x faster, one thread,
// alternating in one process.
template <bool kByReciprocal>
[[gnu::always_inline]] inline __m512i quotient_nearest(__m512 values, __m512 scale, __m512 reciprocal) {
  __m512 quotient;
  if constexpr (kByReciprocal) {
    const __m512 estimate = _mm512_mul_ps(values, reciprocal);
    quotient = _mm512_fmadd_ps(_mm512_fnmadd_ps(estimate, scale, values), reciprocal, estimate);
  } else {
    quotient = _mm512_div_ps(values, scale);
  }
  return cvt_nearest_epi32(quotient);
}

template <bool kByReciprocal>
[[gnu::always_inline]] inline __m512i code_lanes(__m512 values, __m512 scale, __m512 reciprocal, __m512i zero_point,
                                                 __m512i levels) {
  return min_epi32(max_epi32(_mm512_add_epi32(quotient_nearest<kByReciprocal>(values, scale, reciprocal), zero_point),
                             _mm512_setzero_si512()),
                   levels);
}

// The group's constants are passed by value, so that they stay in registers: captured by reference in a
// lambda, they were loaded again after every byte store (which may alias anything), and W4A8 calls of 256
// rows of the policy's layers took 1.05x to 1.17x as long (one thread, alternating in one process).
// 64 values at a time, rne(x / s_x) + z_x of four vectors go to bytes through two saturating packs, to int16
// and then to u8, which clamp to [0, 255] on the way, then a dword permute that undoes the packs' order within
// 128-bit lanes, and a byte minimum with L below 8 bits: six instructions where a clamp and a narrowing store
// of each vector took sixteen.
template <bool kByReciprocal>
void store_group_codes(const float* v, int64_t columns, __m512 scale, __m512 reciprocal, __m512i zero_point,
                       int max_code, uint8_t* codes) {
  const __m512i levels = _mm512_set1_epi32(max_code);
  int64_t i = 0;
  if (columns >= 64) {
    // Dword 4 L + c of the packed bytes holds codes 4 L..4 L + 3 of vector c; they belong at dword 4 c + L.
    const __m512i pack_order = _mm512_setr_epi32(0, 4, 8, 12, 1, 5, 9, 13, 2, 6, 10, 14, 3, 7, 11, 15);
    const __m512i level_bytes = _mm512_set1_epi8(static_cast<char>(max_code));
    for (; i + 64 <= columns; i += 64) {
      __m512i shifted[4];
      for (int c = 0; c < 4; ++c) {
        shifted[c] = _mm512_add_epi32(quotient_nearest<kByReciprocal>(_mm512_loadu_ps(v + i + 16 * c), scale, reciprocal),
                                      zero_point);
      }
      const __m512i low_words = _mm512_maskz_packs_epi32(~__mmask32{0}, shifted[0], shifted[1]);
      const __m512i high_words = _mm512_maskz_packs_epi32(~__mmask32{0}, shifted[2], shifted[3]);
      __m512i bytes = _mm512_maskz_permutexvar_epi32(
          kAll16, pack_order, _mm512_maskz_packus_epi16(~__mmask64{0}, low_words, high_words));
      if (max_code < 255) bytes = _mm512_maskz_min_epu8(~__mmask64{0}, bytes, level_bytes);
      _mm512_storeu_si512(codes + i, bytes);
    }
  }
  for (; i + 16 <= columns; i += 16) {
    // vpmovdb to a register then a plain store: its masked store form is the slower one on Zen 4.
    const __m512i lanes = code_lanes<kByReciprocal>(_mm512_loadu_ps(v + i), scale, reciprocal, zero_point, levels);
    _mm_storeu_si128(reinterpret_cast<__m128i*>(codes + i), _mm512_maskz_cvtepi32_epi8(kAll16, lanes));
  }
  if (i < columns) {
    const __mmask16 mask = group_lanes(columns, i);
    const __m512i lanes =
        code_lanes<kByReciprocal>(_mm512_maskz_loadu_ps(mask, v + i), scale, reciprocal, zero_point, levels);
    _mm512_mask_cvtepi32_storeu_epi8(codes + i, mask, lanes);
  }
}

// codes[0..columns) = q_x, given s_x, z_x and 1 / s_x (activation_group_params_lanes); all 0 for a non-finite
// group (NaN scale), as activation_code gives.
inline void group_codes(const float* v, int64_t columns, ActivationGroupParams params, float reciprocal_scale,
                        int act_bits, uint8_t* codes) {
  if (params.scale != params.scale) {
    std::memset(codes, 0, columns);
    return;
  }
  const __m512 scale = _mm512_set1_ps(params.scale);
  const __m512 reciprocal = _mm512_set1_ps(reciprocal_scale);
  const __m512i zero_point = _mm512_set1_epi32(static_cast<int>(params.zero));
  if (quotient_by_reciprocal(params.scale)) {
    store_group_codes<true>(v, columns, scale, reciprocal, zero_point, (1 << act_bits) - 1, codes);
  } else {
    store_group_codes<false>(v, columns, scale, reciprocal, zero_point, (1 << act_bits) - 1, codes);
  }
}
#elif defined(DYQ_CPU_ISA_AVX2)
// As above, 8 lanes at a time; the lanes past `columns` load as 0 (vmaskmovps) and are not stored.
inline __m256 load_group_lanes(const float* v, int64_t columns, int64_t i) {
  const int64_t rest = columns - i;
  if (rest >= 8) return _mm256_loadu_ps(v + i);
  const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
  return _mm256_maskload_ps(v + i, _mm256_cmpgt_epi32(_mm256_set1_epi32(static_cast<int>(rest)), lane));
}

inline GroupRange group_range(const float* v, int64_t columns) {
  const __m256 zero = _mm256_setzero_ps();
  __m256 group_min = zero, group_max = zero, nonfinite = zero;
  for (int64_t i = 0; i < columns; i += 8) {
    const __m256 values = load_group_lanes(v, columns, i);
    nonfinite = _mm256_or_ps(nonfinite, _mm256_cmp_ps(_mm256_sub_ps(values, values), zero, _CMP_NEQ_UQ));
    group_min = _mm256_min_ps(group_min, values);
    group_max = _mm256_max_ps(group_max, values);
  }
  return {reduce_lanes<MinLanes>(group_min), reduce_lanes<MaxLanes>(group_max), _mm256_movemask_ps(nonfinite) != 0};
}

// As the AVX-512 store_group_codes, 8 lanes at a time.
template <bool kByReciprocal>
void store_group_codes(const float* v, int64_t columns, __m256 scale, __m256 reciprocal, __m256 zero_point,
                       __m256 levels, uint8_t* codes) {
  for (int64_t i = 0; i < columns; i += 8) {
    const __m256 values = load_group_lanes(v, columns, i);
    __m256 ratio;
    if constexpr (kByReciprocal) {
      const __m256 estimate = _mm256_mul_ps(values, reciprocal);
      ratio = _mm256_fmadd_ps(_mm256_fnmadd_ps(estimate, scale, values), reciprocal, estimate);
    } else {
      ratio = _mm256_div_ps(values, scale);
    }
    const __m256 rounded = _mm256_round_ps(ratio, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    const __m256i code =
        _mm256_cvtps_epi32(_mm256_min_ps(_mm256_max_ps(_mm256_add_ps(rounded, zero_point), _mm256_setzero_ps()), levels));
    const __m128i words = _mm_packus_epi32(_mm256_castsi256_si128(code), _mm256_extracti128_si256(code, 1));
    const __m128i bytes = _mm_packus_epi16(words, words);
    if (columns - i >= 8) {
      _mm_storel_epi64(reinterpret_cast<__m128i*>(codes + i), bytes);
    } else {
      alignas(16) uint8_t tail[16];
      _mm_store_si128(reinterpret_cast<__m128i*>(tail), bytes);
      std::memcpy(codes + i, tail, columns - i);
    }
  }
}

inline void group_codes(const float* v, int64_t columns, ActivationGroupParams params, int act_bits, uint8_t* codes) {
  if (params.scale != params.scale) {
    std::memset(codes, 0, columns);
    return;
  }
  const __m256 scale = _mm256_set1_ps(params.scale);
  const __m256 reciprocal = _mm256_set1_ps(1.0f / params.scale);
  const __m256 zero_point = _mm256_set1_ps(static_cast<float>(params.zero));
  const __m256 levels = _mm256_set1_ps(static_cast<float>((1 << act_bits) - 1));
  if (quotient_by_reciprocal(params.scale)) {
    store_group_codes<true>(v, columns, scale, reciprocal, zero_point, levels, codes);
  } else {
    store_group_codes<false>(v, columns, scale, reciprocal, zero_point, levels, codes);
  }
}
#else
inline GroupRange group_range(const float* v, int64_t columns) {
  GroupRange range{0.0f, 0.0f, false};
  for (int64_t i = 0; i < columns; ++i) {
    range.nonfinite |= !std::isfinite(v[i]);
    range.min = std::fmin(range.min, v[i]);
    range.max = std::fmax(range.max, v[i]);
  }
  return range;
}

inline void group_codes(const float* v, int64_t columns, ActivationGroupParams params, int act_bits, uint8_t* codes) {
  for (int64_t i = 0; i < columns; ++i) codes[i] = static_cast<uint8_t>(activation_code(v[i], params, act_bits));
}
#endif

// The codes and parameters of the groups of `rows` rows of k fp32 values (row r at v + r * k, its codes at
// codes + r * codes_pitch, its parameters at params + r * groups), a phase over up to 16 groups at a time,
// across the rows: each group's reduction and scalar parameters form a chain of dependent instructions,
// which chains of other groups overlap (one group after another, a row of 4096 values took 1.18 us on the
// AMD EPYC, 0.80 so; rows of 256, two groups each, quantized one row at a time left little to overlap).
inline void quantize_values(const float* v, int64_t rows, int64_t k, int group_size, int act_bits, uint8_t* codes,
                            int64_t codes_pitch, ActivationGroupParams* params) {
  constexpr int64_t kGroupsAtOnce = 16;
  const int64_t groups = group_count(k, group_size);
  const int64_t total = rows * groups;
  for (int64_t first = 0; first < total; first += kGroupsAtOnce) {
    const int64_t last = std::min(first + kGroupsAtOnce, total);
#if defined(DYQ_CPU_ISA_AVX512)
    // The 16 groups' ranges as vectors, folded together into one vector of each (fold_each_lanes), and their
    // parameters computed in those vectors' lanes.
    __m512 group_min[kGroupsAtOnce], group_max[kGroupsAtOnce], poison[kGroupsAtOnce];
    for (int64_t j = first; j < kGroupsAtOnce + first; ++j) {
      const int64_t lane = j - first;
      if (j < last) {
        const int64_t r = j / groups, g = j % groups;
        group_range_lanes(v + r * k + g * group_size, group_columns(k, group_size, g), group_min[lane], group_max[lane],
                          poison[lane]);
      } else {
        group_min[lane] = group_max[lane] = poison[lane] = _mm512_setzero_ps();
      }
    }
    __m512i zero_points;
    __m512 reciprocals;
    const __m512 scales =
        activation_group_params_lanes(fold_each_lanes(group_min, MinLanes{}), fold_each_lanes(group_max, MaxLanes{}),
                                      fold_each_lanes(poison, AddLanes{}), act_bits, zero_points, reciprocals);
    alignas(64) float lane_scales[kGroupsAtOnce], lane_reciprocals[kGroupsAtOnce];
    alignas(64) int32_t lane_zeros[kGroupsAtOnce];
    _mm512_store_ps(lane_scales, scales);
    _mm512_store_ps(lane_reciprocals, reciprocals);
    _mm512_store_si512(lane_zeros, zero_points);
    for (int64_t j = first; j < last; ++j) {
      const int64_t r = j / groups, g = j % groups;
      params[j] = {lane_scales[j - first], lane_zeros[j - first]};
      group_codes(v + r * k + g * group_size, group_columns(k, group_size, g), params[j], lane_reciprocals[j - first],
                  act_bits, codes + r * codes_pitch + g * group_size);
    }
#else
    GroupRange ranges[kGroupsAtOnce];
    for (int64_t j = first; j < last; ++j) {
      const int64_t r = j / groups, g = j % groups;
      ranges[j - first] = group_range(v + r * k + g * group_size, group_columns(k, group_size, g));
    }
    for (int64_t j = first; j < last; ++j) {
      const GroupRange& range = ranges[j - first];
      params[j] = activation_group_params(range.min, range.max, act_bits, range.nonfinite);
    }
    for (int64_t j = first; j < last; ++j) {
      const int64_t r = j / groups, g = j % groups;
      group_codes(v + r * k + g * group_size, group_columns(k, group_size, g), params[j], act_bits,
                  codes + r * codes_pitch + g * group_size);
    }
#endif
  }
}

// The 16-bit rows that quantize_activation_rows widens to fp32 at once: as many as fit 16 KiB, so that their
// values are still in L1 when quantize_values reads them, twice. Widened all at once, the AMX tiles' 16 rows
// of 768 columns (48 KiB) left L1, and `perf` put most of the widening's time on its stores; five rows at a
// time, 256 rows of a 256 x 768 layer at W4A8 ran about 1.04x faster (one thread, the two builds alternating).
inline int64_t rows_widened_at_once(int64_t k) {
  constexpr int64_t kRowsFp32Floats = 4096;
  return std::max<int64_t>(1, kRowsFp32Floats / std::max<int64_t>(k, 1));
}

// The floats of `rows_fp32` that quantize_activation_rows uses for `rows` rows of k 16-bit values.
inline int64_t rows_fp32_floats(int64_t rows, int64_t k) { return std::min(rows, rows_widened_at_once(k)) * k; }

// Quantizes the k values of each of the `rows` rows of `x` (contiguous): codes + r * codes_pitch receives
// row r's unsigned codes q_x, params + r * ceil(k/group_size) its groups' (s_x, z_x), the last group of a
// row holding the remainder when group_size does not divide k. `rows_fp32` is scratch of
// rows_fp32_floats(rows, k) floats, for 16-bit inputs; fp32 rows are read where they are (copied first, they
// took a fifth of the AVX-512 panel path's quantization of 256 rows of 4096 on the AMD EPYC).
template <typename Element>
void quantize_activation_rows(const Element* x, int64_t rows, int64_t k, int group_size, int act_bits,
                              float* rows_fp32, uint8_t* codes, int64_t codes_pitch, ActivationGroupParams* params) {
  if constexpr (std::is_same_v<Element, float>) {
    quantize_values(x, rows, k, group_size, act_bits, codes, codes_pitch, params);
  } else {
    const int64_t rows_at_once = rows_widened_at_once(k);
    const int64_t groups = group_count(k, group_size);
    for (int64_t first = 0; first < rows; first += rows_at_once) {
      const int64_t count = std::min(rows_at_once, rows - first);
      load_row_fp32(x + first * k, count * k, rows_fp32);
      quantize_values(rows_fp32, count, k, group_size, act_bits, codes + first * codes_pitch, codes_pitch,
                      params + first * groups);
    }
  }
}

// One row: codes[0..k), params[0..ceil(k/group_size)); `row_fp32` is scratch of k floats.
template <typename Element>
void quantize_activation_row(const Element* x, int64_t k, int group_size, int act_bits, float* row_fp32,
                             uint8_t* codes, ActivationGroupParams* params) {
  quantize_activation_rows(x, 1, k, group_size, act_bits, row_fp32, codes, 0, params);
}

}  // namespace dyq::cpu::DYQ_ISA_NAMESPACE
DYQ_ISA_END
