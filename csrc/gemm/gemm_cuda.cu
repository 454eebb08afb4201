// Routing between the decode and prefill paths by the number of activation rows (a host-side shape
// decision; the bit-width is routed on the device, inside each path).
#include "gemm/gemm_cuda.h"

#include "common/cuda_utils.cuh"

namespace dyq::cuda {
namespace {

__global__ void snapshot_precision_kernel(const Precision precision, int32_t* device_bits) {
  *device_bits = read_precision(precision);
}

}  // namespace

Precision snapshot_precision(const Precision& precision, int32_t* device_bits, cudaStream_t stream) {
  snapshot_precision_kernel<<<1, 1, 0, stream>>>(precision, device_bits);
  return flag_precision(device_bits, 2);
}

cudaError_t gemm(const GemmArgs& args, cudaStream_t stream) {
  return args.m <= kDecodeMaxRows ? gemm_decode(args, stream) : gemm_prefill(args, stream);
}

}  // namespace dyq::cuda
