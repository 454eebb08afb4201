// RMSNorm of activation rows on the CPU (docs/numerics.md, section 2a): the norm before a transformer block's
// linear layers (Llama's RMSNorm, and those of the models built like it), fused into one pass per row where
// the framework's own takes seven operations, each a dispatch and a pass over the row. The CUDA twin is
// activation/rms_norm_cuda.h.
//
// What it computes, for each row x [n] of `dtype` with weight w [n] of the same dtype:
//
//   r   = 1 / sqrt(sum_i x_i^2 / n + eps)      in fp32 (x widened exactly)
//   h_i = dtype(x_i r)                         rounded once to dtype
//   y_i = dtype(w_i h_i)                       the product of the two dtype values in fp32, rounded again
//
// which is transformers' LlamaRMSNorm, `weight * (x.float() * rsqrt(x.float().pow(2).mean(-1) + eps)).to(dtype)`,
// operation by operation, except the order in which the squares are summed. For fp32 both roundings are
// exact. NaN and Inf are not special: a NaN makes its row NaN, an Inf its own element NaN and the rest 0, as
// the framework's operations give.
//
// Layout. x and out: [rows, n] row-major, of `dtype` (fp32, bf16 or fp16); weight: [n] of `dtype`.
#pragma once

#include <cstdint>

#include "common/format.h"

namespace dyq::cpu {

// n >= 1, eps >= 0 (the caller checks). out may not overlap x. Rows run in parallel (dyq::parallel_for),
// each on the path that cpu/cpu_isa.h chose for this CPU.
void rms_norm(const void* x, ScalarType dtype, const void* weight, int64_t rows, int64_t n, float eps, void* out);

}  // namespace dyq::cpu
