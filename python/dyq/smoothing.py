"""SmoothQuant-style activation smoothing for Llama models, folded into the weights before INT4 conversion.

Per-token activation quantization suffers from a few input channels with large magnitudes: they set
the group's scale, and every other channel of the group loses resolution. SmoothQuant (Xiao et al.,
2023) divides each input channel j of a linear layer's activation by s_j and multiplies the matching
weight column by s_j, which leaves the float product unchanged::

    y = x W^T = (x / s) (W diag(s))^T,     s_j = max|x_j|^alpha / max|W_{:,j}|^(1 - alpha)

The division ``x / s`` costs nothing at run time when it is folded into the operation that produces
``x``. In a Llama decoder layer:

* q, k, v read ``input_layernorm(h)``: the RMSNorm weight is divided by s (one s shared by the three);
* gate and up read ``post_attention_layernorm(h)``: likewise;
* down reads ``silu(gate(x)) * up(x)``: the rows of ``up`` are divided by s (the product is linear in it);
* o reads the attention output, which is linear in ``v``: the rows of ``v_proj`` are divided by s (only
  when every query head has its own key/value head, so that each channel of v feeds one channel of o).

The float model after :func:`smooth_llama` computes the same function up to fp32 rounding; only the
quantized model changes. ``alpha`` moves difficulty from activations (alpha -> 1) to weights (alpha -> 0).
The activation maxima are calibrated on inputs the caller passes (for the closed-loop policies, training
observations, never evaluation episodes).
"""
from __future__ import annotations

from typing import Callable, Iterable

import torch
from torch import nn


@torch.no_grad()
def activation_maxima(model: nn.Module, run_calibration: Callable[[], None]) -> dict[str, torch.Tensor]:
    """Per-input-channel max |x| of every ``nn.Linear`` of ``model`` over what ``run_calibration()`` runs."""
    maxima: dict[str, torch.Tensor] = {}
    hooks = []

    def observe(name):
        def hook(_module, inputs):
            x = inputs[0].detach().reshape(-1, inputs[0].shape[-1]).abs().amax(dim=0).float()
            maxima[name] = torch.maximum(maxima[name], x) if name in maxima else x
        return hook

    for name, module in model.named_modules():
        if isinstance(module, nn.Linear):
            hooks.append(module.register_forward_pre_hook(observe(name)))
    try:
        run_calibration()
    finally:
        for hook in hooks:
            hook.remove()
    if not maxima:
        raise ValueError("run_calibration ran no nn.Linear of the model: nothing to calibrate")
    return maxima


def smoothing_scales(activation_max: torch.Tensor, weights: Iterable[torch.Tensor], alpha: float) -> torch.Tensor:
    """s_j = max|x_j|^alpha / max_W |W_{:,j}|^(1 - alpha), over all layers that read the same x."""
    weight_max = torch.stack([w.detach().abs().amax(dim=0).float() for w in weights]).amax(dim=0)
    scales = activation_max.clamp(min=1e-5).pow(alpha) / weight_max.clamp(min=1e-5).pow(1 - alpha)
    return scales.clamp(min=1e-5)


@torch.no_grad()
def smooth_llama(model: nn.Module, maxima: dict[str, torch.Tensor], alpha: float = 0.5) -> int:
    """Folds SmoothQuant scales into every decoder layer of a Hugging Face Llama-style model in place.

    ``maxima`` comes from :func:`activation_maxima` on the unsmoothed model. Returns the number of
    linear layers whose input was smoothed.
    """
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be in [0, 1], got {alpha}")
    names = {module: name for name, module in model.named_modules()}
    layers = [m for m in model.modules() if hasattr(m, "self_attn") and hasattr(m, "mlp")]
    if not layers:
        raise ValueError("smooth_llama needs decoder layers with self_attn and mlp (a Llama-style model)")
    smoothed = 0

    def fold(readers: list[nn.Linear], divide: Callable[[torch.Tensor], None]) -> int:
        key = names[readers[0]]
        if key not in maxima:
            raise ValueError(f"no activation maximum for {key}: calibrate on the same model")
        scales = smoothing_scales(maxima[key].to(readers[0].weight.device), [r.weight for r in readers], alpha)
        divide(scales)
        for reader in readers:
            reader.weight.mul_(scales.to(reader.weight.dtype))
        return len(readers)

    def divide_norm(norm):
        return lambda s: norm.weight.div_(s.to(norm.weight.dtype))

    def divide_rows(linear):
        def divide(s):
            linear.weight.div_(s.to(linear.weight.dtype)[:, None])
            if linear.bias is not None:
                linear.bias.div_(s.to(linear.bias.dtype))
        return divide

    for layer in layers:
        attn, mlp = layer.self_attn, layer.mlp
        smoothed += fold([attn.q_proj, attn.k_proj, attn.v_proj], divide_norm(layer.input_layernorm))
        smoothed += fold([mlp.gate_proj, mlp.up_proj], divide_norm(layer.post_attention_layernorm))
        smoothed += fold([mlp.down_proj], divide_rows(mlp.up_proj))
        if attn.v_proj.out_features == attn.o_proj.in_features:
            smoothed += fold([attn.o_proj], divide_rows(attn.v_proj))
    return smoothed
