// The argument checks of every dyq operator, the one validation that the CPU and CUDA registrations
// and the fake (meta) kernels all run (python/dyq/core/ops.py calls them through dyq._C): every misuse is
// a clear error that names the argument and what was expected (docs/numerics.md, section 4).
//
// Shapes are read as SymInts, so that the fake kernels can validate tensors with symbolic sizes under
// torch.compile; a comparison guards on them as an `if` in Python would. Every check raises
// RuntimeError (c10::Error), as the ops always have.
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/core/SymInt.h>
#include <c10/util/Exception.h>

#include <cmath>
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
  TORCH_CHECK(is_valid_act_bits(act_bits) && (allow_fallback || act_bits != kFallbackBits),
                    "dyq: act_bits must be ", registered_act_bits_text(!allow_fallback), ", got ", act_bits);
}

// Dense tensors only: sparse, quantized or MKL-DNN layouts have no data pointer the kernels can walk.
inline void check_strided(const at::Tensor& t, const char* name) {
  TORCH_CHECK(t.layout() == at::kStrided, "dyq: ", name, " must be a dense (strided) tensor, got layout ", t.layout());
}

inline void check_same_device(const at::Tensor& t, const char* name, const at::Device& device) {
  TORCH_CHECK(t.device() == device, "dyq: ", name, " is on ", t.device(), " but x is on ", device,
              "; every tensor of one call must be on the same device");
}

inline void check_activation(const at::Tensor& x, const char* name) {
  check_strided(x, name);
  TORCH_CHECK(is_activation_dtype(x.scalar_type()), "dyq: ", name, " must be float32, bfloat16 or float16, got ",
                   x.scalar_type());
  TORCH_CHECK(x.dim() >= 1, "dyq: ", name, " must have at least one dimension (..., K), got a scalar");
}

// Groups of K columns: ceil(K / G), the last holding the remainder (common/format.h).
inline c10::SymInt group_count(const c10::SymInt& k, int64_t group_size) { return (k + (group_size - 1)) / group_size; }

// qweight uint8 [N, K/2] and scales fp32 [N, ceil(K/G)], dense, on `device`.
inline void check_packed_weight(const at::Tensor& qweight, const at::Tensor& scales, int64_t group_size,
                                const at::Device& device) {
  check_strided(qweight, "qweight");
  check_strided(scales, "scales");
  TORCH_CHECK(qweight.scalar_type() == at::kByte, "dyq: qweight must be uint8 (two INT4 codes per byte), got ",
                   qweight.scalar_type());
  TORCH_CHECK(qweight.dim() == 2, "dyq: qweight must have shape [N, K/2], got ", qweight.sym_sizes());
  TORCH_CHECK(qweight.is_contiguous(), "dyq: qweight must be contiguous (packed data is dense)");
  TORCH_CHECK(scales.scalar_type() == at::kFloat, "dyq: scales must be float32, got ", scales.scalar_type());
  TORCH_CHECK(scales.is_contiguous(), "dyq: scales must be contiguous");
  const c10::SymInt k = qweight.sym_size(1) * 2;
  const c10::SymInt groups = group_count(k, group_size);
  TORCH_CHECK(scales.dim() == 2 && scales.sym_size(0) == qweight.sym_size(0) && scales.sym_size(1) == groups,
                    "dyq: scales must have shape [N, ceil(K/group_size)] = [", qweight.sym_size(0), ", ", groups,
                    "] for qweight of shape ", qweight.sym_sizes(), " and group_size = ", group_size, ", got ",
                    scales.sym_sizes());
  check_same_device(qweight, "qweight", device);
  check_same_device(scales, "scales", device);
}

// The precision flag of gemm_with_flag: one int32. Its device is the backend's to check (the CPU reads a
// CPU tensor; CUDA kernels read pinned host memory or device memory).
inline void check_flag_tensor(const at::Tensor& flag) {
  check_strided(flag, "act_bits_flag");
  TORCH_CHECK(flag.scalar_type() == at::kInt, "dyq: act_bits_flag must be an int32 tensor, got ",
                   flag.scalar_type());
  TORCH_CHECK(flag.sym_numel() == 1, "dyq: act_bits_flag must hold exactly one element, got ",
                    flag.sym_numel());
}

// gemm and gemm_with_flag: x [..., K], the packed weight, an optional bias [N] of x's dtype, all on x's
// device; then a registered act_bits (gemm) or a valid flag tensor (gemm_with_flag, whose value only the
// backend can read).
inline void check_gemm_args(const at::Tensor& x, const at::Tensor& qweight, const at::Tensor& scales,
                            int64_t group_size, const std::optional<at::Tensor>& bias) {
  check_group_size(group_size);
  check_activation(x, "x");
  check_packed_weight(qweight, scales, group_size, x.device());
  const c10::SymInt k = qweight.sym_size(1) * 2;
  TORCH_CHECK(x.sym_size(-1) == k, "dyq: x has ", x.sym_size(-1),
                    " features (last dimension) but the weight expects K = ", k);
  if (bias.has_value()) {
    check_strided(*bias, "bias");
    TORCH_CHECK(bias->scalar_type() == x.scalar_type(), "dyq: bias must have the dtype of x (", x.scalar_type(),
                     "), got ", bias->scalar_type());
    TORCH_CHECK(bias->dim() == 1 && bias->sym_size(0) == qweight.sym_size(0), "dyq: bias must have shape [N] = [",
                      qweight.sym_size(0), "], got ", bias->sym_sizes());
    check_same_device(*bias, "bias", x.device());
  }
}

inline void check_gemm(const at::Tensor& x, const at::Tensor& qweight, const at::Tensor& scales, int64_t group_size,
                       int64_t act_bits, const std::optional<at::Tensor>& bias) {
  check_gemm_args(x, qweight, scales, group_size, bias);
  check_act_bits(act_bits);
}

// min_act_bits: a registered width, the floor applied to the flag's value where it is read.
inline void check_gemm_with_flag(const at::Tensor& x, const at::Tensor& qweight, const at::Tensor& scales,
                                 int64_t group_size, const at::Tensor& flag, const std::optional<at::Tensor>& bias,
                                 int64_t min_act_bits) {
  check_gemm_args(x, qweight, scales, group_size, bias);
  check_flag_tensor(flag);
  // The host's flag (pinned on CUDA) or one on x's own device; any other device (meta with real inputs)
  // would leave the output to a kernel that does not compute it.
  TORCH_CHECK(flag.device().is_cpu() || flag.device() == x.device(),
              "dyq: act_bits_flag must be a CPU (host) tensor or on x's device (", x.device(), "), got ",
              flag.device());
  TORCH_CHECK(is_valid_act_bits(min_act_bits), "dyq: min_act_bits must be ", registered_act_bits_text(), ", got ",
              min_act_bits);
}

// Why quantize_weight found a weight its fp32 copy cannot hold finitely: NaN or Inf in the weight itself, or
// (float64) finite values beyond fp32's range, which the fp32 scales could not hold either. Only on that error.
inline std::string non_finite_weight_message(const at::Tensor& weight) {
  const bool finite = weight.isfinite().all().item<bool>();
  return finite ? std::string("dyq: weight has values beyond float32's range (|w| above 3.4e38), which the fp32 "
                              "scales of static INT4 weights cannot hold")
                : std::string("dyq: weight contains NaN or Inf; static INT4 weights must be finite");
}

// quantize_weight: a floating-point [N, K] with K even (two INT4 codes per byte).
inline void check_quantize_weight(const at::Tensor& weight, int64_t group_size) {
  check_group_size(group_size);
  check_strided(weight, "weight");
  TORCH_CHECK(weight.is_floating_point(), "dyq: weight must be a floating-point tensor, got ",
                   weight.scalar_type());
  TORCH_CHECK(weight.dim() == 2, "dyq: weight must have shape [N, K], got ", weight.sym_sizes());
  TORCH_CHECK(weight.sym_size(1) % 2 == 0, "dyq: weight has K = ", weight.sym_size(1),
                    " columns; K must be even (two INT4 codes per byte)");
}

inline void check_dequantize_weight(const at::Tensor& qweight, const at::Tensor& scales, int64_t group_size) {
  check_group_size(group_size);
  check_packed_weight(qweight, scales, group_size, qweight.device());
}

// quantize_activations: x [..., K] at a quantized width, with K * act_bits a multiple of 8 (whole bytes of
// packed codes: K a multiple of 4 at 2 bits, of 2 at 4 bits).
inline void check_quantize_activations(const at::Tensor& x, int64_t group_size, int64_t act_bits) {
  check_group_size(group_size);
  check_act_bits(act_bits, /*allow_fallback=*/false);
  check_activation(x, "x");
  TORCH_CHECK(x.sym_size(-1) * act_bits % 8 == 0, "dyq: x has K = ", x.sym_size(-1), " columns; at act_bits = ",
                    act_bits, " K must be a multiple of ", 8 / act_bits, " (whole bytes of packed codes)");
}

// hadamard_transform: x [..., n] (n its last dimension), signs float32 [n], left float32 [m, m] with
// n = m * p, p a power of two; signs and left contiguous and on x's device (activation/hadamard_cpu.h).
inline void check_hadamard_transform(const at::Tensor& x, const at::Tensor& signs, const at::Tensor& left) {
  check_activation(x, "x");
  check_strided(signs, "signs");
  check_strided(left, "left");
  TORCH_CHECK(signs.scalar_type() == at::kFloat, "dyq: signs must be float32, got ", signs.scalar_type());
  TORCH_CHECK(left.scalar_type() == at::kFloat, "dyq: left must be float32, got ", left.scalar_type());
  const c10::SymInt n = x.sym_size(-1);
  TORCH_CHECK(signs.dim() == 1 && signs.sym_size(0) == n, "dyq: signs must have shape [n] = [", n,
              "] (x's last dimension), got ", signs.sym_sizes());
  TORCH_CHECK(left.dim() == 2 && left.sym_size(0) == left.sym_size(1) && left.sym_size(0) >= 1,
              "dyq: left must be a square matrix [m, m], got ", left.sym_sizes());
  const c10::SymInt m = left.sym_size(0);
  TORCH_CHECK(n % m == 0, "dyq: x has n = ", n, " features, not a multiple of left's order m = ", m);
  const int64_t p = (n / m).guard_int(__FILE__, __LINE__);
  TORCH_CHECK(p >= 1 && (p & (p - 1)) == 0, "dyq: x has n = ", n, " features and left has order m = ", m,
              "; n / m = ", p, " must be a power of two (the order of the Walsh-Hadamard factor)");
  TORCH_CHECK(signs.is_contiguous(), "dyq: signs must be contiguous");
  TORCH_CHECK(left.is_contiguous(), "dyq: left must be contiguous (row-major [m, m])");
  check_same_device(signs, "signs", x.device());
  check_same_device(left, "left", x.device());
}

// Checks hadamard_transform's arguments and allocates its output: x's shape and dtype, contiguous.
inline at::Tensor hadamard_transform_output(const at::Tensor& x, const at::Tensor& signs, const at::Tensor& left) {
  check_hadamard_transform(x, signs, left);
  return at::empty(x.sizes(), x.options());
}

// rms_norm: x [..., n] (n >= 1 its last dimension), weight [n] of x's dtype on x's device, eps a finite
// number >= 0 (activation/rms_norm_cpu.h).
inline void check_rms_norm(const at::Tensor& x, const at::Tensor& weight, double eps) {
  check_activation(x, "x");
  check_strided(weight, "weight");
  const c10::SymInt n = x.sym_size(-1);
  TORCH_CHECK(n >= 1, "dyq: x must have at least one feature (..., n >= 1), got shape ", x.sym_sizes());
  TORCH_CHECK(weight.dim() == 1 && weight.sym_size(0) == n, "dyq: weight must have shape [n] = [", n,
              "] (x's last dimension), got ", weight.sym_sizes());
  TORCH_CHECK(weight.scalar_type() == x.scalar_type(), "dyq: weight must have x's dtype ", x.scalar_type(),
              ", got ", weight.scalar_type());
  TORCH_CHECK(std::isfinite(eps) && eps >= 0, "dyq: eps must be a finite number >= 0, got ", eps);
  check_same_device(weight, "weight", x.device());
}

// Checks rms_norm's arguments and allocates its output: x's shape and dtype, contiguous.
inline at::Tensor rms_norm_output(const at::Tensor& x, const at::Tensor& weight, double eps) {
  check_rms_norm(x, weight, eps);
  return at::empty(x.sizes(), x.options());
}

// Checks quantize_weight's arguments; returns (N, K).
inline std::pair<int64_t, int64_t> check_quantize_weight_args(const at::Tensor& weight, int64_t group_size) {
  check_quantize_weight(weight, group_size);
  return {weight.size(0), weight.size(1)};
}

// Checks quantize_activations' arguments and allocates its outputs on x's device:
// packed codes uint8 [..., K*b/8], scales fp32 [..., groups], zero points uint8 [..., groups].
inline std::tuple<at::Tensor, at::Tensor, at::Tensor> activation_quantization_outputs(const at::Tensor& x,
                                                                                      int64_t group_size,
                                                                                      int64_t act_bits) {
  check_quantize_activations(x, group_size, act_bits);
  const int64_t k = x.size(-1);
  std::vector<int64_t> packed_shape(x.sizes().begin(), x.sizes().end());
  std::vector<int64_t> group_shape = packed_shape;
  packed_shape.back() = packed_activation_bytes(k, static_cast<int>(act_bits));
  group_shape.back() = dyq::group_count(k, group_size);
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
