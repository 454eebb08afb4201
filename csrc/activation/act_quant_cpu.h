// Dynamic per-token, per-group activation quantization on the CPU (docs/numerics.md, section 2).
#pragma once

#include <cstdint>

#include "common/format.h"

namespace dyq::cpu {

// x: [m, k] row-major of `dtype`. act_bits: a quantized width of common/precision.h (the caller checks it).
// Writes packed codes uint8 [m, k*act_bits/8] (k*act_bits a multiple of 8), scales fp32 [m, groups] and zeros
// uint8 [m, groups], groups = ceil(k/group_size) (the last group holds the remainder).
void quantize_activations(const void* x, ScalarType dtype, int64_t m, int64_t k, int group_size, int act_bits,
                          uint8_t* packed, float* scales, uint8_t* zeros);

}  // namespace dyq::cpu
