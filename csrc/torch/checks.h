// Argument checks shared by the CPU and CUDA registrations: every misuse is a clear error that names
// the argument and what was expected (docs/numerics.md, section 4).
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/util/Exception.h>

#include <optional>
#include <string>
#include <tuple>
#include <utility>
#include <vector>

#include "common/format.h"
#include "common/precision.h"

namespace dyq {

inline bool is_activation_dtype(at::ScalarType t) {
  return t == at::kFloat || t == at::kBFloat16 || t == at::kHalf;
}

inline ScalarType to_dyq_dtype(at::ScalarType t) {
  switch (t) {
    case at::kFloat: return ScalarType::kFloat32;
    case at::kBFloat16: return ScalarType::kBFloat16;
    case at::kHalf: return ScalarType::kFloat16;
    default: TORCH_CHECK(false, "dyq: unsupported dtype ", t, "; expected float32, bfloat16 or float16");
  }
}

// "2, 4, 8 or 16": the values of a registry list, for error messages.
template <int... kValues>
std::string spelled_out(IntList<kValues...>, bool skip_fallback = false) {
  std::string text;
  int remaining = 0;
  ((remaining += !(skip_fallback && kValues == kFallbackBits)), ...);
  for (const int value : {kValues...}) {
    if (skip_fallback && value == kFallbackBits) continue;
    --remaining;
    text += std::to_string(value) + (remaining > 1 ? ", " : (remaining == 1 ? " or " : ""));
  }
  return text;
}

inline std::string registered_act_bits_text(bool quantized_only = false) {
  return spelled_out(RegisteredActivationBits(), quantized_only);
}

inline void check_group_size(int64_t group_size) {
  TORCH_CHECK(is_valid_group_size(group_size), "dyq: group_size must be ", spelled_out(RegisteredGroupSizes()),
              ", got ", group_size);
}

// allow_fallback = false: only the quantized widths (the standalone activation quantizer).
inline void check_act_bits(int64_t act_bits, bool allow_fallback = true) {
  TORCH_CHECK(is_valid_act_bits(act_bits) && (allow_fallback || act_bits != kFallbackBits), "dyq: act_bits must be ",
              registered_act_bits_text(!allow_fallback), ", got ", act_bits);
}

inline void check_k_divisible(int64_t k, int64_t group_size, const char* what) {
  TORCH_CHECK(k % group_size == 0, "dyq: ", what, " has K = ", k, " columns, which is not a multiple of group_size = ",
              group_size);
}

inline void check_activation(const at::Tensor& x, const char* name) {
  TORCH_CHECK(is_activation_dtype(x.scalar_type()), "dyq: ", name, " must be float32, bfloat16 or float16, got ",
              x.scalar_type());
  TORCH_CHECK(x.dim() >= 1, "dyq: ", name, " must have at least one dimension (..., K), got a scalar");
}

// qweight uint8 [N, K/2] and scales fp32 [N, K/G], dense, on the device of `x`.
inline void check_packed_weight(const at::Tensor& qweight, const at::Tensor& scales, int64_t group_size,
                                const at::Device& device) {
  TORCH_CHECK(qweight.scalar_type() == at::kByte, "dyq: qweight must be uint8 (two INT4 codes per byte), got ",
              qweight.scalar_type());
  TORCH_CHECK(qweight.dim() == 2, "dyq: qweight must have shape [N, K/2], got ", qweight.sizes());
  TORCH_CHECK(qweight.is_contiguous(), "dyq: qweight must be contiguous (packed data is dense)");
  TORCH_CHECK(scales.scalar_type() == at::kFloat, "dyq: scales must be float32, got ", scales.scalar_type());
  TORCH_CHECK(scales.is_contiguous(), "dyq: scales must be contiguous");
  const int64_t k = qweight.size(1) * 2;
  check_k_divisible(k, group_size, "qweight");
  TORCH_CHECK(scales.dim() == 2 && scales.size(0) == qweight.size(0) && scales.size(1) == k / group_size,
              "dyq: scales must have shape [N, K/group_size] = [", qweight.size(0), ", ", k / group_size, "], got ",
              scales.sizes());
  TORCH_CHECK(qweight.device() == device, "dyq: qweight is on ", qweight.device(), " but x is on ", device);
  TORCH_CHECK(scales.device() == device, "dyq: scales is on ", scales.device(), " but x is on ", device);
}

inline void check_gemm_args(const at::Tensor& x, const at::Tensor& qweight, const at::Tensor& scales,
                            int64_t group_size, const std::optional<at::Tensor>& bias) {
  check_group_size(group_size);
  check_activation(x, "x");
  check_packed_weight(qweight, scales, group_size, x.device());
  const int64_t k = qweight.size(1) * 2;
  TORCH_CHECK(x.size(-1) == k, "dyq: x has ", x.size(-1), " features (last dimension) but the weight expects K = ",
              k);
  if (bias.has_value()) {
    TORCH_CHECK(bias->scalar_type() == x.scalar_type(), "dyq: bias must have the dtype of x (", x.scalar_type(),
                "), got ", bias->scalar_type());
    TORCH_CHECK(bias->dim() == 1 && bias->size(0) == qweight.size(0), "dyq: bias must have shape [N] = [",
                qweight.size(0), "], got ", bias->sizes());
    TORCH_CHECK(bias->device() == x.device(), "dyq: bias is on ", bias->device(), " but x is on ", x.device());
  }
}

inline void check_flag_tensor(const at::Tensor& flag) {
  TORCH_CHECK(flag.scalar_type() == at::kInt, "dyq: act_bits_flag must be an int32 tensor, got ",
              flag.scalar_type());
  TORCH_CHECK(flag.numel() == 1, "dyq: act_bits_flag must hold exactly one element, got ", flag.numel());
}

// Checks quantize_weight's arguments; returns (N, K).
inline std::pair<int64_t, int64_t> check_quantize_weight_args(const at::Tensor& weight, int64_t group_size) {
  check_group_size(group_size);
  TORCH_CHECK(weight.is_floating_point(), "dyq: weight must be a floating-point tensor, got ", weight.scalar_type());
  TORCH_CHECK(weight.dim() == 2, "dyq: weight must have shape [N, K], got ", weight.sizes());
  check_k_divisible(weight.size(1), group_size, "weight");
  return {weight.size(0), weight.size(1)};
}

// Checks quantize_activations' arguments and allocates its outputs on x's device:
// packed codes uint8 [..., K*b/8], scales fp32 [..., K/G], zero points uint8 [..., K/G].
inline std::tuple<at::Tensor, at::Tensor, at::Tensor> activation_quantization_outputs(const at::Tensor& x,
                                                                                      int64_t group_size,
                                                                                      int64_t act_bits) {
  check_group_size(group_size);
  check_act_bits(act_bits, /*allow_fallback=*/false);
  check_activation(x, "x");
  const int64_t k = x.size(-1);
  check_k_divisible(k, group_size, "x");
  std::vector<int64_t> packed_shape(x.sizes().begin(), x.sizes().end());
  std::vector<int64_t> group_shape = packed_shape;
  packed_shape.back() = packed_activation_bytes(k, static_cast<int>(act_bits));
  group_shape.back() = k / group_size;
  return {at::empty(packed_shape, x.options().dtype(at::kByte)), at::empty(group_shape, x.options().dtype(at::kFloat)),
          at::empty(group_shape, x.options().dtype(at::kByte))};
}

// Output shape: x's leading dimensions, then N.
inline std::vector<int64_t> gemm_output_shape(const at::Tensor& x, int64_t n) {
  std::vector<int64_t> shape(x.sizes().begin(), x.sizes().end());
  shape.back() = n;
  return shape;
}

}  // namespace dyq
