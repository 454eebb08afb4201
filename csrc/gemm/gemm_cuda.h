// The W4A2 / W4A4 / W4A8 / W4A16 GEMM on CUDA (docs/numerics.md, section 3; design in docs/cuda.md).
// Torch-free: raw pointers, sizes and a stream. The CPU mirror is gemm_cpu.h.
#pragma once

#include <cuda_runtime.h>

#include <cstdint>

#include "common/cuda_precision.cuh"
#include "common/format.h"

namespace dyq::cuda {

struct GemmArgs {
  const void* x;            // [m, k] row-major, `dtype`, 16-byte aligned
  ScalarType dtype;         // of x, bias and out
  const uint8_t* qweight;   // [n, k/2], canonical packed INT4, 16-byte aligned
  const float* scales;      // [n, ceil(k/group_size)]: the last group holds the remainder
  const void* bias;         // [n] or null
  int64_t m, n, k;          // k % 32 == 0 (16-byte rows of packed weights); group_size need not divide k
  int group_size;           // 32, 64 or 128
  Precision precision;      // act_bits (2, 4, 8, 16), fixed or read on the device
  void* workspace;          // gemm_workspace_bytes(m, k, group_size, flag routed) bytes, 256-byte aligned
  void* out;                // [m, n], `dtype`
};

// Rows up to this many take the decode path (a GEMV that streams the weights once, with the activation
// quantization fused); more take the prefill path (quantize once, then a tiled tensor-core GEMM). The
// decode path re-quantizes all m rows in every block, so its time grows with m; on an H200 it is faster
// than the prefill path up to m = 4 on every Llama-7B shape and slower from m = 16 on (bench_cuda.py).
constexpr int64_t kDecodeMaxRows = 8;

// Bytes of scratch the GEMM needs: the prefill path's prepared activations; and, when the width comes
// from a flag (`flag_routed`), a device-resident copy of it.
int64_t gemm_workspace_bytes(int64_t m, int64_t k, int group_size, bool flag_routed);

// out = x W^T (+ bias). Enqueues one kernel (decode) or two (prefill) on `stream`, plus, when the width
// comes from a flag, a one-thread kernel before them that reads the flag once: every block reading
// mapped host memory would cost one PCIe round trip each. Never synchronizes.
cudaError_t gemm(const GemmArgs& args, cudaStream_t stream);

// Enqueues a one-thread kernel that writes read_precision(precision) (flag read once, floor applied)
// to `device_bits`, and returns the precision to hand the kernels after it: that device copy, no floor.
Precision snapshot_precision(const Precision& precision, int32_t* device_bits, cudaStream_t stream);

// The two paths, called by gemm(); exposed so that the benchmark and tests can name them.
cudaError_t gemm_decode(const GemmArgs& args, cudaStream_t stream);
cudaError_t gemm_prefill(const GemmArgs& args, cudaStream_t stream);

}  // namespace dyq::cuda
