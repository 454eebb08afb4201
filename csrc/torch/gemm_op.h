// The one path of dyq::gemm and dyq::gemm_with_flag, shared by the CPU and CUDA registrations: the
// argument checks, where the activation width comes from (the fixed act_bits or the precision flag),
// the width counter, the empty and K = 0 cases, then the backend's kernel.
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>

#include <optional>
#include <utility>

#include "torch/checks.h"
#include "torch/width_counts.h"

namespace dyq {

// The width of one call: `fixed_bits` (dyq::gemm) or, when `flag` is set, the flag's value raised to at
// least `min_bits` where it is read (dyq::gemm_with_flag; on CUDA in the kernel, so that a captured graph
// keeps the floor under every later flag value).
struct ActBitsSource {
  int64_t fixed_bits;
  const at::Tensor* flag;
  int64_t min_bits;
};

inline ActBitsSource fixed_act_bits(int64_t act_bits) { return {act_bits, nullptr, 0}; }
inline ActBitsSource flag_act_bits(const at::Tensor& flag, int64_t min_bits) { return {0, &flag, min_bits}; }

// A Backend provides
//   using Precision = ...;                                         what its kernels take
//   static Precision fixed(int64_t act_bits);                      act_bits already checked
//   static std::pair<Precision, int64_t> from_flag(flag, x, min_bits);   checks the flag; the width to
//                                                                  count, floor applied (any unregistered
//                                                                  value when the host cannot know it)
//   static void run(x, qweight, scales, group_size, precision, bias, out);   out non-empty, K > 0; raises
//                                                                  when the product is out of range
template <typename Backend>
at::Tensor gemm_op(const at::Tensor& x, const at::Tensor& qweight, const at::Tensor& scales, int64_t group_size,
                   const ActBitsSource& act_bits, const std::optional<at::Tensor>& bias) {
  typename Backend::Precision precision;
  int64_t counted_bits = act_bits.fixed_bits;
  if (act_bits.flag != nullptr) {
    check_gemm_with_flag(x, qweight, scales, group_size, *act_bits.flag, bias, act_bits.min_bits);
    std::tie(precision, counted_bits) = Backend::from_flag(*act_bits.flag, x, act_bits.min_bits);
  } else {
    check_gemm(x, qweight, scales, group_size, act_bits.fixed_bits, bias);
    precision = Backend::fixed(act_bits.fixed_bits);
  }
  count_gemm_call(counted_bits);

  const int64_t n = qweight.size(0), k = qweight.size(1) * 2;
  at::Tensor out = at::empty(gemm_output_shape(x, n), x.options());
  if (out.numel() == 0) return out;
  if (k == 0) {  // an empty sum: the bias alone
    return bias.has_value() ? out.copy_(bias->expand_as(out)) : out.zero_();
  }
  Backend::run(x, qweight, scales, group_size, precision, bias, out);
  return out;
}

}  // namespace dyq
