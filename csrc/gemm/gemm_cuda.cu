// Routing between the decode and prefill paths by the number of activation rows (a host-side shape
// decision; the bit-width is routed on the device, inside each path).
#include "gemm/gemm_cuda.h"

namespace dyq::cuda {

cudaError_t gemm(const GemmArgs& args, cudaStream_t stream) {
  return args.m <= kDecodeMaxRows ? gemm_decode(args, stream) : gemm_prefill(args, stream);
}

}  // namespace dyq::cuda
