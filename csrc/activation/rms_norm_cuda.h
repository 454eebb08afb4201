// RMSNorm of activation rows on CUDA: y = dtype(w * dtype(x / sqrt(mean(x^2) + eps))) per row. The formula,
// the layout and the CPU twin: activation/rms_norm_cpu.h. Torch-free: raw pointers, sizes and a stream.
#pragma once

#include <cuda_runtime.h>

#include <cstdint>

#include "common/format.h"

namespace dyq::cuda {

// x and out: [rows, n] row-major of `dtype`, no alignment needed; weight: [n] of `dtype`; all in device
// memory, out not overlapping x. n >= 1 and eps >= 0 (the caller checks).
cudaError_t rms_norm(const void* x, ScalarType dtype, const void* weight, int64_t rows, int64_t n, float eps,
                     void* out, cudaStream_t stream);

}  // namespace dyq::cuda
