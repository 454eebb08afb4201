// CUDA registrations of the dyq operators: validation (checks.h), pointer extraction, the current
// stream, then the torch-free kernels of csrc/*/*_cuda.h. Built only against a CUDA build of torch
// (cmake/cuda_glue.cmake). Nothing here synchronizes with the device except quantize_weight, which
// must report non-finite weights as an error.
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include <algorithm>
#include <limits>

#include "activation/act_quant_cuda.h"
#include "activation/hadamard_cuda.h"
#include "activation/rms_norm_cuda.h"
#include "gemm/gemm_cuda.h"
#include "torch/checks.h"
#include "torch/gemm_op.h"
#include "weight/weight_pack_cuda.h"

namespace dyq {
namespace {

void check_launch(cudaError_t err, const char* what) {
  TORCH_CHECK(err == cudaSuccess, "dyq: CUDA ", what, " failed: ", cudaGetErrorString(err));
}

// The kernels read 16-byte vectors. A tensor from the caching allocator is aligned; a view with an odd
// storage offset is copied (once per call) rather than refused.
at::Tensor aligned_contiguous(const at::Tensor& t) {
  at::Tensor c = t.contiguous();
  return reinterpret_cast<uintptr_t>(c.const_data_ptr()) % 16 == 0 ? c : c.clone();
}

// The CUDA kernels move 16-byte vectors of packed weights (32 columns) and runs of 8 activations, so K
// must be a multiple of 32 here (the CPU takes any even K); the group size need not divide it.
void check_cuda_k(int64_t k, const char* name) {
  TORCH_CHECK(k % 32 == 0, "dyq: ", name, " has K = ", k, " columns; CUDA kernels need K a multiple of 32");
}

void check_on_cuda(const at::Tensor& x, const char* name) {
  TORCH_CHECK(x.is_cuda(), "dyq: ", name, " must be a CUDA tensor here, got one on ", x.device());
}

std::tuple<at::Tensor, at::Tensor> quantize_weight_cuda(const at::Tensor& weight, int64_t group_size) {
  const auto [n, k] = check_quantize_weight_args(weight, group_size);
  check_cuda_k(k, "weight");
  const c10::cuda::CUDAGuard guard(weight.device());
  const at::Tensor w = weight.to(at::kFloat).contiguous();
  at::Tensor qweight = at::empty({n, k / 2}, weight.options().dtype(at::kByte));
  at::Tensor scales = at::empty({n, group_count(k, group_size)}, weight.options().dtype(at::kFloat));
  at::Tensor nonfinite = at::zeros({1}, weight.options().dtype(at::kInt));
  check_launch(cuda::quantize_weight(w.const_data_ptr<float>(), n, k, static_cast<int>(group_size),
                                     qweight.mutable_data_ptr<uint8_t>(), scales.mutable_data_ptr<float>(),
                                     nonfinite.mutable_data_ptr<int32_t>(), at::cuda::getCurrentCUDAStream()),
               "quantize_weight");
  TORCH_CHECK(nonfinite.item<int32_t>() == 0, non_finite_weight_message(weight));
  return {qweight, scales};
}

at::Tensor dequantize_weight_cuda(const at::Tensor& qweight, const at::Tensor& scales, int64_t group_size) {
  check_dequantize_weight(qweight, scales, group_size);
  const c10::cuda::CUDAGuard guard(qweight.device());
  const int64_t n = qweight.size(0), k = qweight.size(1) * 2;
  at::Tensor out = at::empty({n, k}, scales.options());
  check_launch(cuda::dequantize_weight(qweight.const_data_ptr<uint8_t>(), scales.const_data_ptr<float>(), n, k,
                                       static_cast<int>(group_size), out.mutable_data_ptr<float>(),
                                       at::cuda::getCurrentCUDAStream()),
               "dequantize_weight");
  return out;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> quantize_activations_cuda(const at::Tensor& x, int64_t group_size,
                                                                         int64_t act_bits) {
  auto [packed, scales, zeros] = activation_quantization_outputs(x, group_size, act_bits);
  const c10::cuda::CUDAGuard guard(x.device());
  const int64_t k = x.size(-1);
  check_cuda_k(k, "x");
  const at::Tensor xc = aligned_contiguous(x);
  const int64_t m = k == 0 ? 0 : xc.numel() / k;
  check_launch(cuda::quantize_activations(xc.const_data_ptr(), to_dyq_dtype(x.scalar_type()), m, k,
                                          static_cast<int>(group_size), static_cast<int>(act_bits),
                                          packed.mutable_data_ptr<uint8_t>(), scales.mutable_data_ptr<float>(),
                                          zeros.mutable_data_ptr<uint8_t>(), at::cuda::getCurrentCUDAStream()),
               "quantize_activations");
  return {packed, scales, zeros};
}

// One block holds a row in shared memory, so n is bounded by the device's opt-in limit per block.
at::Tensor hadamard_transform_cuda(const at::Tensor& x, const at::Tensor& signs, const at::Tensor& left) {
  at::Tensor out = hadamard_transform_output(x, signs, left);
  const c10::cuda::CUDAGuard guard(x.device());
  const int64_t n = x.size(-1);
  int64_t max_columns = 0;
  check_launch(cuda::hadamard_max_columns(x.device().index(), &max_columns), "shared memory query");
  TORCH_CHECK(n <= max_columns, "dyq: x has n = ", n, " features; hadamard_transform on ", x.device(),
              " holds a row in shared memory, at most ", max_columns, " features");
  const at::Tensor xc = x.contiguous();
  check_launch(cuda::hadamard_transform(xc.const_data_ptr(), to_dyq_dtype(x.scalar_type()),
                                        signs.const_data_ptr<float>(), left.const_data_ptr<float>(), xc.numel() / n,
                                        n, left.size(0), out.mutable_data_ptr(), at::cuda::getCurrentCUDAStream()),
               "hadamard_transform");
  return out;
}

at::Tensor rms_norm_cuda(const at::Tensor& x, const at::Tensor& weight, double eps) {
  at::Tensor out = rms_norm_output(x, weight, eps);
  const c10::cuda::CUDAGuard guard(x.device());
  const int64_t n = x.size(-1);
  TORCH_CHECK(n <= std::numeric_limits<int>::max(), "dyq: x has n = ", n, " features; rms_norm on CUDA takes at most ",
              std::numeric_limits<int>::max());
  const at::Tensor xc = x.contiguous();
  const at::Tensor weight_c = weight.contiguous();
  check_launch(cuda::rms_norm(xc.const_data_ptr(), to_dyq_dtype(x.scalar_type()), weight_c.const_data_ptr(),
                              xc.numel() / n, n, static_cast<float>(eps), out.mutable_data_ptr(),
                              at::cuda::getCurrentCUDAStream()),
               "rms_norm");
  return out;
}

// The address the kernels read the flag at. Pinned host memory is mapped into the device's address
// space (unified addressing), so the kernel reads the host's latest write with no copy; a CUDA int32
// on x's device is read in place.
const int32_t* device_visible_flag(const at::Tensor& flag, const at::Device& device) {
  if (flag.is_cuda()) {
    TORCH_CHECK(flag.device() == device, "dyq: act_bits_flag is on ", flag.device(), " but x is on ", device);
    return flag.const_data_ptr<int32_t>();
  }
  TORCH_CHECK(flag.is_cpu() && flag.is_pinned(),
              "dyq: for CUDA inputs act_bits_flag must live in pinned host memory (torch.empty(1, dtype=torch.int32, "
              "pin_memory=True), as dyq.PrecisionFlag allocates it) or on the GPU; a pageable CPU tensor cannot be "
              "read by the kernel");
  void* device_ptr = nullptr;
  const cudaError_t err = cudaHostGetDevicePointer(&device_ptr, const_cast<void*>(flag.const_data_ptr()), 0);
  TORCH_CHECK(err == cudaSuccess, "dyq: act_bits_flag is pinned but not mapped into the device address space: ",
              cudaGetErrorString(err));
  return static_cast<const int32_t*>(device_ptr);
}

struct CudaGemm {
  using Precision = cuda::Precision;

  static Precision fixed(int64_t act_bits) { return cuda::fixed_precision(static_cast<int>(act_bits)); }

  // The value is not validated here: the kernels read it when they run (a NaN output marks an invalid
  // one). The width counted is the host's read of a pinned flag at launch (no synchronization); a flag
  // in device memory, or a launch replayed from a CUDA graph, is not counted (docs/cuda.md).
  static std::pair<Precision, int64_t> from_flag(const at::Tensor& flag, const at::Tensor& x, int64_t min_bits) {
    check_on_cuda(x, "x");
    const c10::cuda::CUDAGuard guard(x.device());
    const int64_t host_bits = flag.is_cuda() ? 0 : *static_cast<const volatile int32_t*>(flag.const_data_ptr());
    const int64_t counted = is_valid_act_bits(host_bits) ? std::max(host_bits, min_bits) : host_bits;
    return {cuda::flag_precision(device_visible_flag(flag, x.device()), static_cast<int>(min_bits)), counted};
  }

  static void run(const at::Tensor& x, const at::Tensor& qweight, const at::Tensor& scales, int64_t group_size,
                  Precision precision, const std::optional<at::Tensor>& bias, at::Tensor& out) {
    const c10::cuda::CUDAGuard guard(x.device());
    const int64_t n = qweight.size(0), k = qweight.size(1) * 2, m = out.numel() / n;
    check_cuda_k(k, "qweight");
    const at::Tensor xc = aligned_contiguous(x);
    const at::Tensor qweight_c = aligned_contiguous(qweight);
    const at::Tensor bias_c = bias.has_value() ? bias->contiguous() : at::Tensor();
    // Scratch from the caching allocator: stream-ordered, and drawn from the graph's pool under capture.
    const int64_t workspace_bytes =
        cuda::gemm_workspace_bytes(m, k, static_cast<int>(group_size), precision.flag != nullptr);
    const at::Tensor workspace =
        workspace_bytes > 0 ? at::empty({workspace_bytes}, x.options().dtype(at::kByte)) : at::Tensor();
    cuda::GemmArgs args{};
    args.x = xc.const_data_ptr();
    args.dtype = to_dyq_dtype(x.scalar_type());
    args.qweight = qweight_c.const_data_ptr<uint8_t>();
    args.scales = scales.const_data_ptr<float>();
    args.bias = bias_c.defined() ? bias_c.const_data_ptr() : nullptr;
    args.m = m;
    args.n = n;
    args.k = k;
    args.group_size = static_cast<int>(group_size);
    args.precision = precision;
    args.workspace = workspace.defined() ? workspace.mutable_data_ptr() : nullptr;
    args.out = out.mutable_data_ptr();
    check_launch(cuda::gemm(args, at::cuda::getCurrentCUDAStream()), "gemm");
  }
};

at::Tensor gemm_cuda(const at::Tensor& x, const at::Tensor& qweight, const at::Tensor& scales, int64_t group_size,
                     int64_t act_bits, const std::optional<at::Tensor>& bias) {
  return gemm_op<CudaGemm>(x, qweight, scales, group_size, fixed_act_bits(act_bits), bias);
}

at::Tensor gemm_with_flag_cuda(const at::Tensor& x, const at::Tensor& qweight, const at::Tensor& scales,
                               int64_t group_size, const at::Tensor& act_bits_flag,
                               const std::optional<at::Tensor>& bias, int64_t min_act_bits) {
  return gemm_op<CudaGemm>(x, qweight, scales, group_size, flag_act_bits(act_bits_flag, min_act_bits), bias);
}

}  // namespace
}  // namespace dyq

TORCH_LIBRARY_IMPL(dyq, CUDA, m) {
  m.impl("quantize_weight", &dyq::quantize_weight_cuda);
  m.impl("dequantize_weight", &dyq::dequantize_weight_cuda);
  m.impl("quantize_activations", &dyq::quantize_activations_cuda);
  m.impl("gemm", &dyq::gemm_cuda);
  m.impl("gemm_with_flag", &dyq::gemm_with_flag_cuda);
  m.impl("hadamard_transform", &dyq::hadamard_transform_cuda);
  m.impl("rms_norm", &dyq::rms_norm_cuda);
}
