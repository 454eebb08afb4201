// The W4A2 / W4A4 / W4A8 / W4A16 GEMM on the CPU (docs/numerics.md, section 3), with the activation
// quantization fused in. The mirror the CUDA kernels are tested against.
#pragma once

#include <cstdint>

#include "common/format.h"

namespace dyq::cpu {

// out[m, n] = x[m, k] * W^T (+ bias[n]) where W is the INT4 weight (qweight uint8 [n, k/2], scales fp32
// [n, ceil(k/group_size)]). x, bias (nullable) and out share `dtype`. act_bits in {2, 4, 8, 16}.
// m may be 0; k is even (the caller's precondition), and the last group of a row holds the remainder
// when group_size does not divide k.
//
// A row whose fp32 intermediates overflow although its inputs are finite is recomputed from x scaled by a
// power of two (exact; docs/numerics.md, section 4). Returns false when an output is still not finite
// for finite x, bias and scales: the product is out of the range of `dtype` (the caller reports it).
bool gemm(const void* x, ScalarType dtype, const uint8_t* qweight, const float* scales, const void* bias,
          int64_t m, int64_t n, int64_t k, int group_size, int act_bits, void* out);

}  // namespace dyq::cpu
