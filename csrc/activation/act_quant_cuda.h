// Dynamic per-token, per-group activation quantization on CUDA (docs/numerics.md, section 2).
// Torch-free: raw pointers, sizes and a stream. The CPU mirror is act_quant_cpu.h.
#pragma once

#include <cuda_runtime.h>

#include <cstdint>

#include "common/cuda_precision.cuh"
#include "common/format.h"

namespace dyq::cuda {

// x: [m, k] row-major of `dtype` (16-byte aligned), k a multiple of 32. act_bits in {2, 4, 8}. Writes the
// canonical packed codes uint8 [m, k*act_bits/8], scales fp32 [m, groups] and zero points uint8 [m, groups],
// groups = ceil(k/group_size) (the last group holds the remainder).
cudaError_t quantize_activations(const void* x, ScalarType dtype, int64_t m, int64_t k, int group_size, int act_bits,
                                 uint8_t* packed, float* scales, uint8_t* zeros, cudaStream_t stream);

// The activation operand of the prefill GEMM, written by `prepare_activations` into a workspace.
struct PreparedActivations {
  int32_t* bits_used;  // the bit-width read from the flag, for the GEMM launched next to reuse
  uint8_t* codes;      // b in {2,4,8}: packed codes, rows padded to 16 bytes; b = 16: bf16 copy of x
  float* scales;       // [m, ceil(k/group_size)]
  uint8_t* zeros;      // [m, ceil(k/group_size)]
};

// Row pitch in bytes of PreparedActivations::codes: cp.async moves 16-byte chunks, so rows start 16-byte
// aligned (the padding is never read as data).
DYQ_HOST_DEVICE int64_t prepared_row_bytes(int64_t k, int act_bits) {
  return act_bits == kFallbackBits ? 2 * k : (k * act_bits / 8 + 15) / 16 * 16;
}

// Reads the precision once on the device and prepares the activations at that bit-width: codes, scales
// and zeros for 2, 4 and 8 bits; for 16 a bf16 copy of x, except when x is already bf16 (the GEMM then
// reads x). Writes the bit-width it read to `out.bits_used`.
cudaError_t prepare_activations(const void* x, ScalarType dtype, int64_t m, int64_t k, int group_size,
                                Precision precision, PreparedActivations out, cudaStream_t stream);

}  // namespace dyq::cuda
