// Device helpers shared by the CUDA kernels: element loads and stores for the three activation dtypes,
// the precision flag, and the bit manipulations that widen packed codes in registers.
#pragma once

#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <cuda_runtime.h>

#include <cstdint>

#include "common/cuda_precision.cuh"
#include "common/format.h"
#include "common/precision.h"

namespace dyq::cuda {

// The flag may change between launches (a captured graph replays under new values), so it is read
// with an uncached load, once per block, by the caller's thread 0, and the floor applied here, on the
// device, for the same reason. An invalid value stays as read (the caller writes NaN).
__device__ __forceinline__ int read_precision(const Precision& precision) {
  if (precision.flag == nullptr) return precision.bits;
  const int flag_bits = __ldcv(precision.flag);
  return is_valid_act_bits(flag_bits) && flag_bits < precision.bits ? precision.bits : flag_bits;
}

// ---- activations: 8 consecutive elements as fp32 -----------------------------------------------
// `src` points at element 0 of the run and is 16-byte aligned (K is a multiple of 32 and the glue hands
// over 16-byte aligned tensors).
__device__ __forceinline__ void load8_as_float(const void* src, ScalarType dtype, float (&v)[8]) {
  if (dtype == ScalarType::kFloat32) {
    const float4 a = __ldg(static_cast<const float4*>(src));
    const float4 b = __ldg(static_cast<const float4*>(src) + 1);
    v[0] = a.x; v[1] = a.y; v[2] = a.z; v[3] = a.w;
    v[4] = b.x; v[5] = b.y; v[6] = b.z; v[7] = b.w;
  } else {
    const uint4 raw = __ldg(static_cast<const uint4*>(src));
    const uint32_t words[4] = {raw.x, raw.y, raw.z, raw.w};
#pragma unroll
    for (int i = 0; i < 4; ++i) {
      if (dtype == ScalarType::kBFloat16) {
        const __nv_bfloat162 pair = *reinterpret_cast<const __nv_bfloat162*>(&words[i]);
        const float2 f = __bfloat1622float2(pair);
        v[2 * i] = f.x; v[2 * i + 1] = f.y;
      } else {
        const __half2 pair = *reinterpret_cast<const __half2*>(&words[i]);
        const float2 f = __half22float2(pair);
        v[2 * i] = f.x; v[2 * i + 1] = f.y;
      }
    }
  }
}

__device__ __forceinline__ float load_as_float(const void* base, int64_t index, ScalarType dtype) {
  switch (dtype) {
    case ScalarType::kFloat32: return static_cast<const float*>(base)[index];
    case ScalarType::kBFloat16: return __bfloat162float(static_cast<const __nv_bfloat16*>(base)[index]);
    default: return __half2float(static_cast<const __half*>(base)[index]);
  }
}

// The one rounding of the fp32 accumulator to the output dtype.
__device__ __forceinline__ void store_from_float(void* base, int64_t index, ScalarType dtype, float value) {
  switch (dtype) {
    case ScalarType::kFloat32: static_cast<float*>(base)[index] = value; break;
    case ScalarType::kBFloat16: static_cast<__nv_bfloat16*>(base)[index] = __float2bfloat16_rn(value); break;
    default: static_cast<__half*>(base)[index] = __float2half_rn(value); break;
  }
}

// Two floats rounded to bf16 and packed, the first in the low half.
__device__ __forceinline__ uint32_t pack_bf16x2(float lo, float hi) {
  const __nv_bfloat162 pair = __floats2bfloat162_rn(lo, hi);
  return *reinterpret_cast<const uint32_t*>(&pair);
}

__device__ __forceinline__ float bf16_low_as_float(uint32_t pair) { return __uint_as_float(pair << 16); }
__device__ __forceinline__ float bf16_high_as_float(uint32_t pair) { return __uint_as_float(pair & 0xFFFF0000u); }

// ---- packed integer codes ----------------------------------------------------------------------

// Four bytes, each a two's-complement nibble value in [0, 15], sign-extended to int8 in place:
// (u ^ 8) maps the nibble to u - 8 + 16 [mod 16]; adding 0x78 and flipping bit 7 subtracts 8 without a
// carry leaving the byte (the sum stays below 136).
__device__ __forceinline__ uint32_t sign_extend_nibble_bytes(uint32_t nibble_bytes) {
  return (((nibble_bytes ^ 0x08080808u) + 0x78787878u) ^ 0x80808080u);
}

// A word of 8 packed INT4 weights (column c + i in nibble i) as two s8x4 words: the even columns
// (c, c+2, c+4, c+6) and the odd columns (c+1, c+3, c+5, c+7), byte i holding the i-th of each.
__device__ __forceinline__ uint32_t weight_even_s8x4(uint32_t word) {
  return sign_extend_nibble_bytes(word & 0x0F0F0F0Fu);
}
__device__ __forceinline__ uint32_t weight_odd_s8x4(uint32_t word) {
  return sign_extend_nibble_bytes((word >> 4) & 0x0F0F0F0Fu);
}

// 8 unsigned 2-bit codes (code i in bits 2i) spread into 8 nibbles (code i in bits 4i).
__device__ __forceinline__ uint32_t spread_2bit_to_nibbles(uint32_t codes16) {
  uint32_t v = codes16 & 0xFFFFu;
  v = (v | (v << 8)) & 0x00FF00FFu;
  v = (v | (v << 4)) & 0x0F0F0F0Fu;
  v = (v | (v << 2)) & 0x33333333u;
  return v;
}

// Sum of the four signed bytes of `s8x4` added to `acc`.
__device__ __forceinline__ int dp4a_sum_s8(uint32_t s8x4, int acc) {
  return __dp4a(static_cast<int>(s8x4), 0x01010101, acc);
}

// acc + sum_i u8(a)[i] * s8(b)[i]: unsigned activation codes against signed weight codes.
__device__ __forceinline__ int dp4a_u8_s8(uint32_t a_u8x4, uint32_t b_s8x4, int acc) {
  int d;
  asm("dp4a.u32.s32 %0, %1, %2, %3;" : "=r"(d) : "r"(a_u8x4), "r"(b_s8x4), "r"(acc));
  return d;
}

// An INT4 weight nibble (two's complement, in bits 0..3 of `nibble`; higher bits ignored) as an exact
// fp32: 2^23 + (nibble ^ 8) built from its bit pattern, minus 2^23 + 8. No int-to-float conversion unit.
__device__ __forceinline__ float weight_nibble_as_float(uint32_t nibble) {
  return __uint_as_float(0x4B000000u | ((nibble ^ 8u) & 0xFu)) - 8388616.0f;
}

// Exact int32 -> fp32 for |v| < 2^22 with one integer and one float add (the conversion unit is slow).
__device__ __forceinline__ float small_int_as_float(int v) {
  return __int_as_float(v + 0x4B400000) - 12582912.0f;
}

__device__ __forceinline__ float warp_sum(float v) {
#pragma unroll
  for (int offset = 16; offset > 0; offset >>= 1) v += __shfl_xor_sync(0xFFFFFFFFu, v, offset);
  return v;
}

}  // namespace dyq::cuda
