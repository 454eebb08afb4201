// Autograd of the dyq operators that carry gradients: gemm and gemm_with_flag, through the frozen INT4
// weights, hadamard_transform, the run-time rotation, and rms_norm.
//
// They are C++ rather than torch.library.register_autograd because that Python kernel runs on every call,
// with or without gradients: 4.7 us of a 256 x 256 layer's 11 us at one activation row on the AMD EPYC,
// a fifth of a small policy's control step. Here a call that records no gradient goes straight on to the
// backend's kernel.
#include <ATen/core/dispatch/Dispatcher.h>
#include <torch/csrc/autograd/custom_function.h>
#include <torch/library.h>

#include <optional>
#include <type_traits>

namespace dyq {
namespace {

using torch::autograd::AutogradContext;
using torch::autograd::variable_list;

// The operator `kName` of signature `Schema`, called below autograd: its backend's kernel.
template <typename Schema, const char* kName>
struct BelowAutograd {
  template <typename... Args>
  static at::Tensor call(Args&&... args) {
    static const auto op = c10::Dispatcher::singleton().findSchemaOrThrow(kName, "").template typed<Schema>();
    at::AutoDispatchBelowADInplaceOrView guard;
    return op.call(std::forward<Args>(args)...);
  }
};

constexpr char kGemm[] = "dyq::gemm";
constexpr char kGemmWithFlag[] = "dyq::gemm_with_flag";
constexpr char kDequantizeWeight[] = "dyq::dequantize_weight";
constexpr char kHadamardTransform[] = "dyq::hadamard_transform";
constexpr char kRmsNorm[] = "dyq::rms_norm";
using GemmOp = BelowAutograd<at::Tensor(const at::Tensor&, const at::Tensor&, const at::Tensor&, int64_t, int64_t,
                                        const std::optional<at::Tensor>&),
                             kGemm>;
using GemmWithFlagOp = BelowAutograd<at::Tensor(const at::Tensor&, const at::Tensor&, const at::Tensor&, int64_t,
                                                const at::Tensor&, const std::optional<at::Tensor>&, int64_t),
                                     kGemmWithFlag>;
using DequantizeWeightOp =
    BelowAutograd<at::Tensor(const at::Tensor&, const at::Tensor&, int64_t), kDequantizeWeight>;
using HadamardTransformOp =
    BelowAutograd<at::Tensor(const at::Tensor&, const at::Tensor&, const at::Tensor&), kHadamardTransform>;
using RmsNormOp = BelowAutograd<at::Tensor(const at::Tensor&, const at::Tensor&, double), kRmsNorm>;

// ---- gemm, gemm_with_flag ------------------------------------------------------------------------------
//
// The weights are static, so only x and the bias get gradients. The activation quantization is treated as
// the identity in the backward pass (straight-through): the gradient is that of x W^T + bias with the
// dequantized weight W = s_w q_w, grad_x = grad_y W, at every width, which is what LoRA-style adapters on
// a frozen 4-bit base need (QLoRA's backward through NF4 weights does the same).

// Whether a call records a backward: grad mode on and any argument asking for a gradient, which the
// packed weights may not do.
bool records_gemm_gradient(const at::Tensor& x, const at::Tensor& qweight, const at::Tensor& scales,
                           const std::optional<at::Tensor>& bias) {
  if (!at::GradMode::is_enabled()) return false;
  const bool weight_grad = scales.requires_grad() || qweight.requires_grad();
  if (!weight_grad && !x.requires_grad() && !(bias.has_value() && bias->requires_grad())) return false;
  TORCH_CHECK(!weight_grad, "dyq: the INT4 weights are frozen: scales (and qweight) have no gradient; train "
                            "adapters beside the layer (LoRA) or the bias instead");
  return true;
}

// forward's arguments after ctx are the operator's; `Op` is it below autograd.
template <typename Op>
struct FrozenWeightGemm : torch::autograd::Function<FrozenWeightGemm<Op>> {
  template <typename ActBits, typename... Extra>
  static at::Tensor forward(AutogradContext* ctx, const at::Tensor& x, const at::Tensor& qweight,
                            const at::Tensor& scales, int64_t group_size, const ActBits& act_bits,
                            const std::optional<at::Tensor>& bias, Extra... extra) {
    // No sizes of x are saved: its gradient takes them from the output's (x.sizes() would also fix a size that
    // torch.export traces as symbolic to the one example's).
    ctx->saved_data["group_size"] = group_size;
    ctx->saved_data["x_dtype"] = x.scalar_type();
    ctx->saved_data["arguments"] = static_cast<int64_t>(6 + sizeof...(Extra));
    // needs_input_grad counts the tensor arguments only: x, qweight, scales, and the flag where it is one.
    if (bias.has_value()) ctx->saved_data["bias_edge"] = int64_t{std::is_same_v<ActBits, at::Tensor> ? 4 : 3};
    ctx->save_for_backward({qweight, scales});
    return Op::call(x, qweight, scales, group_size, act_bits, bias, extra...);
  }

  static variable_list backward(AutogradContext* ctx, variable_list grad_outputs) {
    const variable_list saved = ctx->get_saved_variables();
    const at::Tensor& qweight = saved[0];
    const at::Tensor& scales = saved[1];
    const at::Tensor& grad_out = grad_outputs[0];  // [..., N]: x's leading dimensions
    variable_list grads(ctx->saved_data["arguments"].toInt());  // one per argument; x is 0, the bias 5
    if (ctx->needs_input_grad(0)) {
      const at::Tensor weight = DequantizeWeightOp::call(qweight, scales, ctx->saved_data["group_size"].toInt());
      // [..., N] x [N, K]: x's shape.
      grads[0] = grad_out.to(at::kFloat).matmul(weight).to(ctx->saved_data["x_dtype"].toScalarType());
    }
    const auto bias_edge = ctx->saved_data.find("bias_edge");
    if (bias_edge != ctx->saved_data.end() && ctx->needs_input_grad(bias_edge->second.toInt())) {
      grads[5] = grad_out.reshape({-1, qweight.size(0)}).sum(0);
    }
    return grads;
  }
};

at::Tensor gemm_autograd(const at::Tensor& x, const at::Tensor& qweight, const at::Tensor& scales, int64_t group_size,
                         int64_t act_bits, const std::optional<at::Tensor>& bias) {
  if (!records_gemm_gradient(x, qweight, scales, bias)) return GemmOp::call(x, qweight, scales, group_size, act_bits, bias);
  return FrozenWeightGemm<GemmOp>::apply(x, qweight, scales, group_size, act_bits, bias);
}

at::Tensor gemm_with_flag_autograd(const at::Tensor& x, const at::Tensor& qweight, const at::Tensor& scales,
                                   int64_t group_size, const at::Tensor& act_bits_flag,
                                   const std::optional<at::Tensor>& bias, int64_t min_act_bits) {
  if (!records_gemm_gradient(x, qweight, scales, bias)) {
    return GemmWithFlagOp::call(x, qweight, scales, group_size, act_bits_flag, bias, min_act_bits);
  }
  return FrozenWeightGemm<GemmWithFlagOp>::apply(x, qweight, scales, group_size, act_bits_flag, bias, min_act_bits);
}

// ---- hadamard_transform ----------------------------------------------------------------------------------
//
// The rotation is linear: with R = diag(signs) (left (x) H_p) / sqrt(p) and H_p symmetric,
// grad_x = grad_y R^T = (grad_y (left^T (x) H_p) / sqrt(p)) * signs, the op itself with unit signs and
// left^T. signs and left are constants of the rotation (no gradient).
struct Rotation : torch::autograd::Function<Rotation> {
  static at::Tensor forward(AutogradContext* ctx, const at::Tensor& x, const at::Tensor& signs, const at::Tensor& left) {
    ctx->save_for_backward({signs, left});
    return HadamardTransformOp::call(x, signs, left);
  }

  static variable_list backward(AutogradContext* ctx, variable_list grad_outputs) {
    if (!ctx->needs_input_grad(0)) return {at::Tensor(), at::Tensor(), at::Tensor()};
    const variable_list saved = ctx->get_saved_variables();
    const at::Tensor& signs = saved[0];
    const at::Tensor& left = saved[1];
    const at::Tensor rotated = HadamardTransformOp::call(grad_outputs[0], at::ones_like(signs), left.t().contiguous());
    return {rotated.mul(signs.to(rotated.scalar_type())), at::Tensor(), at::Tensor()};
  }
};

at::Tensor hadamard_transform_autograd(const at::Tensor& x, const at::Tensor& signs, const at::Tensor& left) {
  if (!at::GradMode::is_enabled() || !x.requires_grad()) return HadamardTransformOp::call(x, signs, left);
  return Rotation::apply(x, signs, left);
}

// ---- rms_norm -------------------------------------------------------------------------------------------
//
// With r = (mean(x^2) + eps)^(-1/2) and the roundings to the dtype taken as the identity (as the framework's
// backward through .to(dtype) takes them), y = w * x r gives, per row,
//   grad_x = r (grad_y w) - x r^3 mean(x grad_y w),   grad_w = the sum over rows of grad_y x r,
// computed in fp32 and returned in the inputs' dtype.
struct RootMeanSquareNorm : torch::autograd::Function<RootMeanSquareNorm> {
  static at::Tensor forward(AutogradContext* ctx, const at::Tensor& x, const at::Tensor& weight, double eps) {
    ctx->save_for_backward({x, weight});
    ctx->saved_data["eps"] = eps;
    return RmsNormOp::call(x, weight, eps);
  }

  static variable_list backward(AutogradContext* ctx, variable_list grad_outputs) {
    const variable_list saved = ctx->get_saved_variables();
    const at::Tensor x = saved[0].to(at::kFloat);
    const at::Tensor weight = saved[1].to(at::kFloat);
    const at::Tensor grad = grad_outputs[0].to(at::kFloat);
    const double eps = ctx->saved_data["eps"].toDouble();
    const at::Tensor inverse_rms = x.pow(2).mean(-1, /*keepdim=*/true).add(eps).rsqrt();
    at::Tensor grad_x, grad_weight;
    if (ctx->needs_input_grad(0)) {
      const at::Tensor grad_h = grad.mul(weight);
      const at::Tensor projection = x.mul(grad_h).mean(-1, /*keepdim=*/true).mul(inverse_rms.pow(2));
      grad_x = grad_h.sub(x.mul(projection)).mul(inverse_rms).to(saved[0].scalar_type());
    }
    if (ctx->needs_input_grad(1)) {
      grad_weight = grad.mul(x).mul(inverse_rms).reshape({-1, x.size(-1)}).sum(0).to(saved[1].scalar_type());
    }
    return {grad_x, grad_weight, at::Tensor()};
  }
};

at::Tensor rms_norm_autograd(const at::Tensor& x, const at::Tensor& weight, double eps) {
  if (!at::GradMode::is_enabled() || !(x.requires_grad() || weight.requires_grad())) {
    return RmsNormOp::call(x, weight, eps);
  }
  return RootMeanSquareNorm::apply(x, weight, eps);
}

}  // namespace
}  // namespace dyq

TORCH_LIBRARY_IMPL(dyq, Autograd, m) {
  m.impl("gemm", &dyq::gemm_autograd);
  m.impl("gemm_with_flag", &dyq::gemm_with_flag_autograd);
  m.impl("hadamard_transform", &dyq::hadamard_transform_autograd);
  m.impl("rms_norm", &dyq::rms_norm_autograd);
}
