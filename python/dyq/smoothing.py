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
* down reads ``silu(gate(x)) * up(x)``: the rows of ``up`` are divided by s (the product is linear in it),
  unless :func:`dyq.rotation.rotate_llama` rotates down's input at run time (then it is not smoothed);
* o reads the attention output, which is linear in ``v``: the rows of ``v_proj`` are divided by s (only
  when every query head has its own key/value head, so that each channel of v feeds one channel of o).

The float model after :func:`smooth_llama` computes the same function up to fp32 rounding; only the
quantized model changes. ``alpha`` moves difficulty from activations (alpha -> 1) to weights (alpha -> 0).
The activation maxima are calibrated on inputs the caller passes (for the closed-loop policies, training
observations, never evaluation episodes).
"""
from __future__ import annotations

from dataclasses import dataclass
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


@dataclass
class ScaleGroup:
    """Linear layers that read one activation, and how to divide that activation by per-channel scales
    where it is produced (an RMSNorm weight or a producing layer's rows)."""

    readers: list[nn.Linear]
    divide_producer: Callable[[torch.Tensor], None]

    @torch.no_grad()
    def fold(self, scales: torch.Tensor) -> None:
        """x / s at the producer, W diag(s) in every reader: the float function is unchanged."""
        self.divide_producer(scales)
        for reader in self.readers:
            reader.weight.mul_(scales.to(reader.weight.device, reader.weight.dtype))


def _divide_norm(norm):
    def divide(s):
        norm.weight.div_(s.to(norm.weight.device, norm.weight.dtype))
    return divide


def _divide_rows(linear):
    def divide(s):
        linear.weight.div_(s.to(linear.weight.device, linear.weight.dtype)[:, None])
        if linear.bias is not None:
            linear.bias.div_(s.to(linear.bias.device, linear.bias.dtype))
    return divide


def llama_scale_groups(model: nn.Module, strict: bool = True) -> list[ScaleGroup]:
    """The scale groups of every decoder layer of a Llama-style model (module docstring); ``strict``: an
    error if the model has no such layer, else an empty list."""
    layers = [m for m in model.modules() if hasattr(m, "self_attn") and hasattr(m, "mlp")]
    if not layers and strict:
        raise ValueError("smooth_llama needs decoder layers with self_attn and mlp (a Llama-style model)")
    groups = []
    for layer in layers:
        attn, mlp = layer.self_attn, layer.mlp
        groups.append(ScaleGroup([attn.q_proj, attn.k_proj, attn.v_proj], _divide_norm(layer.input_layernorm)))
        groups.append(ScaleGroup([mlp.gate_proj, mlp.up_proj], _divide_norm(layer.post_attention_layernorm)))
        # After rotate_llama, down_proj reads (silu(gate) * up) R, rotated at run time: a scale on up's rows
        # no longer lines up with down_proj's input channels, so that group is left unscaled.
        if getattr(mlp, "down_proj_rotation", None) is None:
            groups.append(ScaleGroup([mlp.down_proj], _divide_rows(mlp.up_proj)))
        if attn.v_proj.out_features == attn.o_proj.in_features:
            groups.append(ScaleGroup([attn.o_proj], _divide_rows(attn.v_proj)))
    return groups


@torch.no_grad()
def smooth_llama(model: nn.Module, maxima: dict[str, torch.Tensor], alpha: float = 0.5) -> int:
    """Folds SmoothQuant scales into every decoder layer of a Hugging Face Llama-style model in place.

    ``maxima`` comes from :func:`activation_maxima` on the unsmoothed model. Returns the number of
    linear layers whose input was smoothed.
    """
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be in [0, 1], got {alpha}")
    names = {module: name for name, module in model.named_modules()}
    smoothed = 0
    for group in llama_scale_groups(model):
        key = names[group.readers[0]]
        if key not in maxima:
            raise ValueError(f"no activation maximum for {key}: calibrate on the same model")
        scales = smoothing_scales(maxima[key].to(group.readers[0].weight.device),
                                  [r.weight for r in group.readers], alpha)
        group.fold(scales)
        smoothed += len(group.readers)
    return smoothed
