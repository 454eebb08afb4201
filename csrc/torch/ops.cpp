// The schema of every dyq operator, declared once. Backends register kernels in ops_cpu.cpp and
// ops_cuda.cpp; fake (meta) kernels for tracing live in python/dyq/ops.py.
#include <torch/library.h>

TORCH_LIBRARY(dyq, m) {
  m.def("quantize_weight(Tensor weight, int group_size) -> (Tensor qweight, Tensor scales)");
  m.def("dequantize_weight(Tensor qweight, Tensor scales, int group_size) -> Tensor");
  m.def("quantize_activations(Tensor x, int group_size, int act_bits) -> (Tensor packed, Tensor scales, Tensor zeros)");
  m.def("gemm(Tensor x, Tensor qweight, Tensor scales, int group_size, int act_bits, Tensor? bias=None) -> Tensor");
  m.def(
      "gemm_with_flag(Tensor x, Tensor qweight, Tensor scales, int group_size, Tensor act_bits_flag, "
      "Tensor? bias=None) -> Tensor");
}
