// The quantization format of docs/numerics.md, shared by the CPU and CUDA kernels.
//
// Everything here is header-only, torch-free and usable from host and device code, so that both
// backends round, clamp and pack with the same expressions and produce the same integer codes.
#pragma once

#include <cmath>
#include <cstdint>

#if defined(__CUDACC__)
#define DYQ_HOST_DEVICE __host__ __device__ __forceinline__
#else
#define DYQ_HOST_DEVICE inline
#endif

namespace dyq {

// Element type of activations and outputs. Weights scales are always fp32.
enum class ScalarType : int { kFloat32 = 0, kBFloat16 = 1, kFloat16 = 2 };

constexpr int kWeightBits = 4;
constexpr int kWeightQMin = -8;
constexpr int kWeightQMax = 7;
constexpr int kFallbackBits = 16;  // act_bits == 16: the unquantized (BF16) fallback path

// Bytes of packed activation codes for k columns at a quantized act_bits (common/precision.h); k * act_bits
// is a multiple of 8 (the op checks it).
DYQ_HOST_DEVICE int64_t packed_activation_bytes(int64_t k, int act_bits) { return k * act_bits / 8; }

// Groups of a row of k columns: ceil(k / group_size). When group_size does not divide k, the last group
// holds the remainder, k - (groups - 1) * group_size columns (docs/numerics.md, section 4).
DYQ_HOST_DEVICE int64_t group_count(int64_t k, int64_t group_size) { return (k + group_size - 1) / group_size; }

// Columns of group g of a row of k columns.
DYQ_HOST_DEVICE int64_t group_columns(int64_t k, int64_t group_size, int64_t g) {
  const int64_t rest = k - g * group_size;
  return rest < group_size ? rest : group_size;
}

// Round half to even, the rounding of every quantizer in dyq.
DYQ_HOST_DEVICE float round_half_even(float v) {
#if defined(__CUDA_ARCH__)
  return rintf(v);
#else
  return std::nearbyint(v);
#endif
}

DYQ_HOST_DEVICE float clampf(float v, float lo, float hi) { return v < lo ? lo : (v > hi ? hi : v); }

// ---- weights: symmetric INT4 -------------------------------------------------------------------

// Scale of a weight group from its absolute maximum; 0 means "store as scale 1, codes 0".
DYQ_HOST_DEVICE float weight_scale_from_absmax(float absmax) { return absmax / 7.0f; }

DYQ_HOST_DEVICE int weight_code(float w, float scale) {
  return static_cast<int>(clampf(round_half_even(w / scale), kWeightQMin, kWeightQMax));
}

// Two's-complement nibble -> signed value in [-8, 7].
DYQ_HOST_DEVICE int sign_extend_nibble(uint32_t nibble) { return static_cast<int>((nibble ^ 8u)) - 8; }

DYQ_HOST_DEVICE uint8_t pack_weight_pair(int even_code, int odd_code) {
  return static_cast<uint8_t>((even_code & 0xF) | ((odd_code & 0xF) << 4));
}

// ---- activations: asymmetric b-bit, per token and group (Eq. 2) --------------------------------

struct ActivationGroupParams {
  float scale;   // s_x; NaN for a group with NaN or Inf
  int zero;      // z_x in [0, 2^b - 1]
};

// From the group's min and max (non-finite groups are handled by the caller with `nonfinite`).
DYQ_HOST_DEVICE ActivationGroupParams activation_group_params(float group_min, float group_max, int act_bits,
                                                              bool nonfinite) {
  const float levels = static_cast<float>((1 << act_bits) - 1);
  if (nonfinite) return {NAN, 0};
  const float lo = group_min < 0.0f ? group_min : 0.0f;
  const float hi = group_max > 0.0f ? group_max : 0.0f;
  float scale = (hi - lo) / levels;
  // hi - lo overflows only when the range exceeds FLT_MAX; halving both ends is exact there (they are far
  // from the subnormals), so this is the value fp32 with a wider exponent would give, and it is finite.
  if (scale > 3.4028235e38f) scale = ((0.5f * hi - 0.5f * lo) / levels) * 2.0f;
  if (scale == 0.0f) return {1.0f, 0};
  const int zero = static_cast<int>(clampf(round_half_even(-lo / scale), 0.0f, levels));
  return {scale, zero};
}

DYQ_HOST_DEVICE int activation_code(float x, ActivationGroupParams p, int act_bits) {
  const float levels = static_cast<float>((1 << act_bits) - 1);
  if (!(p.scale == p.scale)) return 0;  // NaN scale: non-finite group, codes 0
  return static_cast<int>(clampf(round_half_even(x / p.scale) + static_cast<float>(p.zero), 0.0f, levels));
}

}  // namespace dyq
