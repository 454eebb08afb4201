// The online Hadamard rotation of activation rows on CUDA: y = (x * signs) (left (x) H_p) / sqrt(p) per row
// of n = m * p, p a power of two. The formula, the layout and the CPU twin: activation/hadamard_cpu.h.
// Torch-free: raw pointers, sizes and a stream.
#pragma once

#include <cuda_runtime.h>

#include <cstdint>

#include "common/format.h"

namespace dyq::cuda {

// x and out: [rows, n] row-major of `dtype`, no alignment needed; signs fp32 [n]; left fp32 [m, m] row-major;
// all in device memory, out not overlapping x. n = m * p with p a power of two (the caller checks) and
// n <= hadamard_max_columns(device): a block holds its row in shared memory as fp32.
cudaError_t hadamard_transform(const void* x, ScalarType dtype, const float* signs, const float* left, int64_t rows,
                               int64_t n, int64_t m, void* out, cudaStream_t stream);

// The largest n whose row fits a block's shared memory on `device` (the opt-in limit: 41728 on sm_80 and
// sm_87, 25344 on sm_86 and sm_89, 58112 on sm_90).
cudaError_t hadamard_max_columns(int device, int64_t* columns);

}  // namespace dyq::cuda
