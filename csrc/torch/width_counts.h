// Per-process counts of GEMM calls by the activation width each ran at, for the closed-loop evaluation
// (which share of a policy's GEMMs ran at 2, 4, 8 or 16 bits). Counted by the op path (gemm_op.h) where
// the width is resolved; read and reset from Python (dyq.ops.width_counts). Thread-safe.
#pragma once

#include <array>
#include <cstdint>

#include "common/precision.h"

namespace dyq {

// One call at `act_bits`; a value outside the registry (a width the host cannot know) is not counted.
void count_gemm_call(int64_t act_bits);

// Calls per registered width, in the order of RegisteredActivationBits.
std::array<int64_t, kNumActivationWidths> gemm_width_counts();

void reset_gemm_width_counts();

}  // namespace dyq
