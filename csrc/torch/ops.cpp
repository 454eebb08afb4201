// The schema of every dyq operator, declared once, and the one validation of each op's arguments.
// Backends register kernels in ops_cpu.cpp and ops_cuda.cpp; fake (meta) kernels for tracing live in
// python/dyq/core/ops.py and validate through the `_check_*` ops below, which run the C++ checks of
// checks.h that the backends run too, so a fake kernel accepts exactly what the real kernels accept.
#include <torch/library.h>

#include "torch/checks.h"

TORCH_LIBRARY(dyq, m) {
  m.def("quantize_weight(Tensor weight, int group_size) -> (Tensor qweight, Tensor scales)");
  m.def("dequantize_weight(Tensor qweight, Tensor scales, int group_size) -> Tensor");
  m.def("quantize_activations(Tensor x, int group_size, int act_bits) -> (Tensor packed, Tensor scales, Tensor zeros)");
  m.def("gemm(Tensor x, Tensor qweight, Tensor scales, int group_size, int act_bits, Tensor? bias=None) -> Tensor");
  m.def(
      "gemm_with_flag(Tensor x, Tensor qweight, Tensor scales, int group_size, Tensor act_bits_flag, "
      "Tensor? bias=None, int min_act_bits=2) -> Tensor");
  m.def("hadamard_transform(Tensor x, Tensor signs, Tensor left) -> Tensor");
  m.def("rms_norm(Tensor x, Tensor weight, float eps) -> Tensor");
  // The checks alone (metadata only: they read no data, so they work on meta and fake tensors).
  m.def("_check_quantize_weight(Tensor weight, int group_size) -> ()");
  m.def("_check_dequantize_weight(Tensor qweight, Tensor scales, int group_size) -> ()");
  m.def("_check_quantize_activations(Tensor x, int group_size, int act_bits) -> ()");
  m.def("_check_gemm(Tensor x, Tensor qweight, Tensor scales, int group_size, int act_bits, Tensor? bias=None) -> ()");
  m.def(
      "_check_gemm_with_flag(Tensor x, Tensor qweight, Tensor scales, int group_size, Tensor act_bits_flag, "
      "Tensor? bias=None, int min_act_bits=2) -> ()");
  m.def("_check_hadamard_transform(Tensor x, Tensor signs, Tensor left) -> ()");
  m.def("_check_rms_norm(Tensor x, Tensor weight, float eps) -> ()");
}

// Composite: the checks run above every backend and every tensor subclass, on the tensors as given.
TORCH_LIBRARY_IMPL(dyq, CompositeImplicitAutograd, m) {
  m.impl("_check_quantize_weight", &dyq::check_quantize_weight);
  m.impl("_check_dequantize_weight", &dyq::check_dequantize_weight);
  m.impl("_check_quantize_activations", &dyq::check_quantize_activations);
  m.impl("_check_gemm", &dyq::check_gemm);
  m.impl("_check_gemm_with_flag", &dyq::check_gemm_with_flag);
  m.impl("_check_hadamard_transform", &dyq::check_hadamard_transform);
  m.impl("_check_rms_norm", &dyq::check_rms_norm);
}

namespace {

// Sparse, compressed and MKL-DNN tensors dispatch to keys no dyq kernel is registered for; this kernel
// turns what would be torch's "could not run with arguments from the backend" into an error naming the
// argument and the layout expected.
void reject_non_strided(const c10::OperatorHandle& op, torch::jit::Stack* stack) {
  const auto& arguments = op.schema().arguments();
  const size_t first = stack->size() - arguments.size();
  for (size_t i = 0; i < arguments.size(); ++i) {
    const c10::IValue& value = (*stack)[first + i];
    if (value.isTensor()) dyq::check_strided(value.toTensor(), arguments[i].name().c_str());
  }
  TORCH_CHECK(false, "dyq: ", op.schema().name(), " has no kernel for these arguments (dense tensors expected)");
}

}  // namespace

#define DYQ_REJECT_NON_STRIDED(dispatch_key)                                                                   \
  TORCH_LIBRARY_IMPL(dyq, dispatch_key, m) {                                                                   \
    for (const char* name : {"quantize_weight", "dequantize_weight", "quantize_activations", "gemm",          \
                             "gemm_with_flag", "hadamard_transform", "rms_norm"}) {                                       \
      m.impl(name, torch::CppFunction::makeFromBoxedFunction<&reject_non_strided>());                         \
    }                                                                                                          \
  }
DYQ_REJECT_NON_STRIDED(SparseCPU)
DYQ_REJECT_NON_STRIDED(SparseCsrCPU)
DYQ_REJECT_NON_STRIDED(SparseCUDA)
DYQ_REJECT_NON_STRIDED(SparseCsrCUDA)
DYQ_REJECT_NON_STRIDED(MkldnnCPU)
