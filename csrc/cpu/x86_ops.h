// Helpers of the x86 paths (AVX2 and AVX-512), compiled in each one's target region (cpu/isa_region.h).
#pragma once

#include <cstdint>

#include "cpu/isa_region.h"

#if defined(DYQ_ISA_TARGET)
DYQ_ISA_BEGIN
namespace dyq::cpu::DYQ_ISA_NAMESPACE {

// The elementwise operations that reduce_lanes folds with, on 4 and on 8 fp32 lanes, and on 16 where the path
// has AVX-512 (the quantizer's fold of 16 groups at once, act_quant_cpu_row.h; the zero-masking forms for
// the reason given at kAll16 below).
struct AddLanes {
  __m128 operator()(__m128 a, __m128 b) const { return _mm_add_ps(a, b); }
  __m256 operator()(__m256 a, __m256 b) const { return _mm256_add_ps(a, b); }
#if defined(DYQ_CPU_ISA_AVX512)
  __m512 operator()(__m512 a, __m512 b) const { return _mm512_add_ps(a, b); }
#endif
};
struct MinLanes {
  __m128 operator()(__m128 a, __m128 b) const { return _mm_min_ps(a, b); }
  __m256 operator()(__m256 a, __m256 b) const { return _mm256_min_ps(a, b); }
#if defined(DYQ_CPU_ISA_AVX512)
  __m512 operator()(__m512 a, __m512 b) const { return _mm512_maskz_min_ps(__mmask16{0xFFFF}, a, b); }
#endif
};
struct MaxLanes {
  __m128 operator()(__m128 a, __m128 b) const { return _mm_max_ps(a, b); }
  __m256 operator()(__m256 a, __m256 b) const { return _mm256_max_ps(a, b); }
#if defined(DYQ_CPU_ISA_AVX512)
  __m512 operator()(__m512 a, __m512 b) const { return _mm512_maskz_max_ps(__mmask16{0xFFFF}, a, b); }
#endif
};

// Op folded over the 8 lanes of v (AddLanes: their sum).
template <typename Op>
float reduce_lanes(__m256 v) {
  const Op op;
  __m128 half = op(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
  half = op(half, _mm_movehl_ps(half, half));
  return _mm_cvtss_f32(op(half, _mm_movehdup_ps(half)));
}

// A prefetch of the line at `address` (which may lie past the data: a prefetch does not fault). kInOrder
// writes it as a volatile asm statement, which the compiler keeps in its place among the kernel's other
// volatile statements rather than gathering the prefetches of a loop's iteration at its top, as GCC 12 did
// with W4A16's row kernel over four weight rows (bf16_decode_kernel in gemm/gemm_cpu_avx512.h says what
// that cost).
template <_mm_hint kHint, bool kInOrder = false>
[[gnu::always_inline]] inline void prefetch_line(uintptr_t address) {
  if constexpr (!kInOrder) {
    _mm_prefetch(reinterpret_cast<const char*>(address), kHint);
  } else if constexpr (kHint == _MM_HINT_T0) {
    asm volatile("prefetcht0 %0" ::"m"(*reinterpret_cast<const char*>(address)));
  } else {
    static_assert(kHint == _MM_HINT_T1, "in-order prefetches go to L1 or L2");
    asm volatile("prefetcht1 %0" ::"m"(*reinterpret_cast<const char*>(address)));
  }
}

// The prefetch of a row kernel over several weight rows at once, which read them as that many streams
// k / 2 bytes apart: the prefetchers lose them, and each prefetched ahead on its own, the AVX-512 kernels'
// cold decode of 4096 x 4096 fell from 21 to 12 GB/s on the AMD EPYC. Instead one sweep over the next
// rows' bytes in memory order, as fast as the call reads its own, so that they have all arrived when it
// ends (21 to 24 GB/s there, at the streaming read's speed): the line `read_bytes` into the rows after
// the call's `rows_bytes`, or, where those are fewer than kMinAheadBytes, into the bytes that far past the
// call's first (further ahead still paid on one thread; each path says how far). Past the end of the weights
// it touches nothing (a prefetch does not fault).
template <_mm_hint kHint, int64_t kMinAheadBytes = 0, bool kInOrder = false>
[[gnu::always_inline]] inline void prefetch_next_rows(const uint8_t* weight_rows, int64_t rows_bytes,
                                                     int64_t read_bytes) {
  const int64_t ahead = rows_bytes > kMinAheadBytes ? rows_bytes : kMinAheadBytes;
  prefetch_line<kHint, kInOrder>(reinterpret_cast<uintptr_t>(weight_rows) + ahead + read_bytes);
}

#if defined(DYQ_CPU_ISA_AVX512)
// The AVX-512 intrinsics dyq uses whose unmasked forms GCC 12 writes with an uninitialized
// `_mm512_undefined_*()` merge source, which -Wmaybe-uninitialized reports at every inlined call (GCC
// PR 105593). Each is the same instruction through its zero-masking form with every lane selected, whose
// merge source is a defined zero vector.

constexpr __mmask16 kAll16 = 0xFFFF;

inline __m512 min_ps(__m512 a, __m512 b) { return _mm512_maskz_min_ps(kAll16, a, b); }
inline __m512 max_ps(__m512 a, __m512 b) { return _mm512_maskz_max_ps(kAll16, a, b); }
inline __m512 cvtepi32_ps(__m512i a) { return _mm512_maskz_cvtepi32_ps(kAll16, a); }
inline __m512i cvtps_epi32(__m512 a) { return _mm512_maskz_cvtps_epi32(kAll16, a); }
inline __m512 cvtph_ps(__m256i a) { return _mm512_maskz_cvtph_ps(kAll16, a); }
inline __m512i cvtepu8_epi32(__m128i a) { return _mm512_maskz_cvtepu8_epi32(kAll16, a); }
inline __m512i cvtepu16_epi32(__m256i a) { return _mm512_maskz_cvtepu16_epi32(kAll16, a); }
inline __m128i cvtepi32_epi8(__m512i a) { return _mm512_maskz_cvtepi32_epi8(kAll16, a); }
inline __m512i broadcast_i32x4(__m128i a) { return _mm512_maskz_broadcast_i32x4(kAll16, a); }
inline __m512 permutexvar_ps(__m512i index, __m512 a) { return _mm512_maskz_permutexvar_ps(kAll16, index, a); }
inline __m512i permutexvar_epi8(__m512i index, __m512i a) {
  return _mm512_maskz_permutexvar_epi8(~__mmask64{0}, index, a);
}
inline __m512i unpacklo_epi64(__m512i a, __m512i b) { return _mm512_maskz_unpacklo_epi64(0xFF, a, b); }
inline __m512i unpackhi_epi64(__m512i a, __m512i b) { return _mm512_maskz_unpackhi_epi64(0xFF, a, b); }
template <int kLanes>
__m512i shuffle_i64x2(__m512i a, __m512i b) {
  return _mm512_maskz_shuffle_i64x2(0xFF, a, b, kLanes);
}
template <int kHalf>
__m256i extracti64x4(__m512i a) {
  return _mm512_maskz_extracti64x4_epi64(0xF, a, kHalf);
}
inline __m512i slli_epi32(__m512i a, unsigned int count) { return _mm512_maskz_slli_epi32(kAll16, a, count); }
inline __m512i srli_epi32(__m512i a, unsigned int count) { return _mm512_maskz_srli_epi32(kAll16, a, count); }
inline __m512i srai_epi32(__m512i a, unsigned int count) { return _mm512_maskz_srai_epi32(kAll16, a, count); }
inline __m512i min_epi32(__m512i a, __m512i b) { return _mm512_maskz_min_epi32(kAll16, a, b); }
inline __m512i max_epi32(__m512i a, __m512i b) { return _mm512_maskz_max_epi32(kAll16, a, b); }
// int32 of each lane rounded to nearest even, whatever MXCSR's rounding mode.
#define DYQ_AVX512_ROUND_NEAREST (_MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC)
inline __m512i cvt_nearest_epi32(__m512 a) { return _mm512_maskz_cvt_roundps_epi32(kAll16, a, DYQ_AVX512_ROUND_NEAREST); }
#undef DYQ_AVX512_ROUND_NEAREST
inline __m512i i32gather_epi32(__m512i index, const void* base) {
  return _mm512_mask_i32gather_epi32(_mm512_setzero_si512(), kAll16, index, base, 1);
}

// rows[i] (dwords 0..15 of row i) becomes rows[q] = dword q of rows 0..15 (vector lane i).
inline void transpose_16x16_dwords(__m512i rows[16]) {
  __m512i t[16], u[16];
  for (int i = 0; i < 8; ++i) {
    t[2 * i] = _mm512_maskz_unpacklo_epi32(kAll16, rows[2 * i], rows[2 * i + 1]);
    t[2 * i + 1] = _mm512_maskz_unpackhi_epi32(kAll16, rows[2 * i], rows[2 * i + 1]);
  }
  // u[4i + j], 128-bit lane L: column 4L + j of rows 4i..4i+3.
  for (int i = 0; i < 4; ++i) {
    u[4 * i] = _mm512_maskz_unpacklo_epi64(0xFF, t[4 * i], t[4 * i + 2]);
    u[4 * i + 1] = _mm512_maskz_unpackhi_epi64(0xFF, t[4 * i], t[4 * i + 2]);
    u[4 * i + 2] = _mm512_maskz_unpacklo_epi64(0xFF, t[4 * i + 1], t[4 * i + 3]);
    u[4 * i + 3] = _mm512_maskz_unpackhi_epi64(0xFF, t[4 * i + 1], t[4 * i + 3]);
  }
  for (int j = 0; j < 4; ++j) {
    const __m512i s0 = _mm512_maskz_shuffle_i32x4(kAll16, u[j], u[4 + j], 0x44);
    const __m512i s1 = _mm512_maskz_shuffle_i32x4(kAll16, u[j], u[4 + j], 0xEE);
    const __m512i s2 = _mm512_maskz_shuffle_i32x4(kAll16, u[8 + j], u[12 + j], 0x44);
    const __m512i s3 = _mm512_maskz_shuffle_i32x4(kAll16, u[8 + j], u[12 + j], 0xEE);
    rows[j] = _mm512_maskz_shuffle_i32x4(kAll16, s0, s2, 0x88);
    rows[4 + j] = _mm512_maskz_shuffle_i32x4(kAll16, s0, s2, 0xDD);
    rows[8 + j] = _mm512_maskz_shuffle_i32x4(kAll16, s1, s3, 0x88);
    rows[12 + j] = _mm512_maskz_shuffle_i32x4(kAll16, s1, s3, 0xDD);
  }
}

// Op folded over the 16 lanes of v. The header's _mm512_reduce_* and _mm512_castps512_ps256 split the
// vector with the unmasked extract.
template <typename Op>
float reduce_lanes(__m512 v) {
  return reduce_lanes<Op>(Op()(_mm512_maskz_extractf32x8_ps(0xFF, v, 0), _mm512_maskz_extractf32x8_ps(0xFF, v, 1)));
}
#endif

}  // namespace dyq::cpu::DYQ_ISA_NAMESPACE
DYQ_ISA_END
#endif
