// Device building blocks of the activation quantizer, shared by the quantization kernel and the fused
// decode GEMM. One thread holds a run of 8 consecutive elements of a row; a group of G columns is G/8
// consecutive lanes of one warp (G in {32, 64, 128}: 4, 8 or 16 lanes), so group statistics are a few
// xor-shuffles. Every lane of the warp must call these together (inactive lanes pass active = false).
#pragma once

#include "common/cuda_utils.cuh"

namespace dyq::cuda {

// Parameters (s_x, z_x) of the group the calling lane's run belongs to, from all its lanes' values.
__device__ __forceinline__ ActivationGroupParams group_params_across_lanes(const float (&v)[8], bool active,
                                                                           int lanes_per_group, int act_bits) {
  // lo and hi start at 0: the range of Eq. 2 always contains 0.
  float lo = 0.0f, hi = 0.0f;
  int nonfinite = 0;
  if (active) {
#pragma unroll
    for (int i = 0; i < 8; ++i) {
      if (isfinite(v[i])) {
        lo = fminf(lo, v[i]);
        hi = fmaxf(hi, v[i]);
      } else {
        nonfinite = 1;
      }
    }
  }
  for (int offset = 1; offset < lanes_per_group; offset <<= 1) {
    lo = fminf(lo, __shfl_xor_sync(0xFFFFFFFFu, lo, offset));
    hi = fmaxf(hi, __shfl_xor_sync(0xFFFFFFFFu, hi, offset));
    nonfinite |= __shfl_xor_sync(0xFFFFFFFFu, nonfinite, offset);
  }
  return activation_group_params(lo, hi, act_bits, nonfinite != 0);
}

__device__ __forceinline__ void activation_codes8(const float (&v)[8], ActivationGroupParams params, int act_bits,
                                                  uint32_t (&codes)[8]) {
#pragma unroll
  for (int i = 0; i < 8; ++i) codes[i] = static_cast<uint32_t>(activation_code(v[i], params, act_bits));
}

// The 8 codes in the canonical packed layout (docs/numerics.md, section 2), stored at `dst`
// (act_bits bytes, aligned to them).
__device__ __forceinline__ void store_packed_codes8(const uint32_t (&c)[8], int act_bits, uint8_t* dst) {
  if (act_bits == 8) {
    *reinterpret_cast<uint2*>(dst) = make_uint2(c[0] | c[1] << 8 | c[2] << 16 | c[3] << 24,
                                                c[4] | c[5] << 8 | c[6] << 16 | c[7] << 24);
  } else if (act_bits == 4) {
    uint32_t word = 0;
#pragma unroll
    for (int i = 0; i < 8; ++i) word |= c[i] << (4 * i);
    *reinterpret_cast<uint32_t*>(dst) = word;
  } else {
    uint32_t word = 0;
#pragma unroll
    for (int i = 0; i < 8; ++i) word |= c[i] << (2 * i);
    *reinterpret_cast<uint16_t*>(dst) = static_cast<uint16_t>(word);
  }
}

// The 8 codes as bytes in the order the decode GEMM pairs them with the INT4 weights: even columns in
// the first word, odd columns in the second (see weight_even_s8x4 / weight_odd_s8x4).
__device__ __forceinline__ uint2 deinterleaved_code_bytes8(const uint32_t (&c)[8]) {
  return make_uint2(c[0] | c[2] << 8 | c[4] << 16 | c[6] << 24, c[1] | c[3] << 8 | c[5] << 16 | c[7] << 24);
}

}  // namespace dyq::cuda
