// The implementations behind dyq::cpu::gemm, exposed so that tests can check each one. They all take
// gemm's arguments and compute the same numbers (docs/numerics.md, section 3).
#pragma once

#include <cstdint>

#include "common/format.h"

namespace dyq::cpu {

// Portable: per-group Eigen products of integer-valued fp32 matrices (exact, see numerics.md section 3).
bool gemm_portable(const void* x, ScalarType dtype, const uint8_t* qweight, const float* scales, const void* bias,
                   int64_t m, int64_t n, int64_t k, int group_size, int act_bits, void* out);

}  // namespace dyq::cpu
