// INT4 weight quantization and packing on the CPU (docs/numerics.md, section 1).
#pragma once

#include <cstdint>

namespace dyq::cpu {

// weight: fp32 [n, k] row-major, k even. Writes qweight uint8 [n, k/2] and scales fp32 [n, ceil(k/group_size)]
// (the last group of a row holds the remainder).
// Returns false (and writes nothing useful) if the weight holds NaN or Inf.
bool quantize_weight(const float* weight, int64_t n, int64_t k, int group_size, uint8_t* qweight, float* scales);

// out: fp32 [n, k], the dequantized weight s_w * q_w.
void dequantize_weight(const uint8_t* qweight, const float* scales, int64_t n, int64_t k, int group_size,
                       float* out);

}  // namespace dyq::cpu
