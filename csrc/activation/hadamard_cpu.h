// The online Hadamard rotation of activation rows on the CPU (docs/numerics.md, section 1a): the run-time
// rotation of down_proj's input (python/dyq/rotation.py, OnlineRotation). The CUDA twin is
// activation/hadamard_cuda.h; both compute in fp32.
//
// What it computes. For n = m * p, p a power of two, each row x [n] becomes
//
//   y = (x * signs) R,   R = left (x) H_p / sqrt(p)   (Kronecker product, (x) ),
//
// H_p Sylvester's +-1 Hadamard matrix of order p (H_1 = [1], H_2p = [[H_p, H_p], [H_p, -H_p]]) and left any
// [m, m] matrix; dyq passes Paley's Hadamard matrix of order m (or [1]) scaled by 1/sqrt(m), so that R is
// orthogonal with every entry +-1/sqrt(n). Element (i p + j) of a row is entry [i, j] of the row viewed as a
// row-major [m, p] matrix Y, and with that view
//
//   y = left^T Y H_p / sqrt(p),
//
// which is how it is computed: Y = x * signs; each of Y's m rows in place through the fast Walsh-Hadamard
// butterfly (log2 p stages of (a, b) -> (a + b, a - b), n log2(p) adds, no matrix H_p anywhere); then the
// small dense product with left^T, the 1/sqrt(p) folded into left: m n multiply-adds. So a row costs
// n (log2 p + m) operations instead of the n^2 of y = x R.
//
// Layout. x and out: [rows, n] row-major, of `dtype` (fp32, bf16 or fp16; out rounded once from fp32).
// signs: fp32 [n] (+-1, but any values are applied as given). left: fp32 [m, m] row-major. NaN and Inf are
// not special: they spread over their row as in x R.
#pragma once

#include <cstdint>

#include "common/format.h"

namespace dyq::cpu {

// n = m * p with p a power of two, m >= 1 (the caller checks). out must not overlap x. Rows run in parallel
// (dyq::parallel_for), each on the path that cpu/cpu_isa.h chose for this CPU.
void hadamard_transform(const void* x, ScalarType dtype, const float* signs, const float* left, int64_t rows,
                        int64_t n, int64_t m, void* out);

}  // namespace dyq::cpu
