// INT4 weight quantization and packing on CUDA (docs/numerics.md, section 1). Torch-free; the CPU
// mirror is weight_pack_cpu.h. Weights are static: these run once per checkpoint, not per step.
#pragma once

#include <cuda_runtime.h>

#include <cstdint>

namespace dyq::cuda {

// weight: fp32 [n, k] row-major, k even. Writes qweight uint8 [n, k/2] and scales fp32 [n, ceil(k/group_size)].
// Sets *nonfinite (device int32, zeroed by the caller) to 1 if the weight holds NaN or Inf.
cudaError_t quantize_weight(const float* weight, int64_t n, int64_t k, int group_size, uint8_t* qweight,
                            float* scales, int32_t* nonfinite, cudaStream_t stream);

// out: fp32 [n, k], the dequantized weight s_w * q_w.
cudaError_t dequantize_weight(const uint8_t* qweight, const float* scales, int64_t n, int64_t k, int group_size,
                              float* out, cudaStream_t stream);

}  // namespace dyq::cuda
