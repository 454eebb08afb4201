"""``DyQRMSNorm``: a model's RMSNorm layers through dyq's fused kernel, and :func:`fuse_rms_norms`, which
converts them.

A Llama decoder layer runs two RMSNorms, each seven framework operations in ``LlamaRMSNorm.forward`` (a
dispatch and a pass over the row apiece); ``torch.ops.dyq.rms_norm`` computes the same in one pass per row
(docs/numerics.md, section 2a). During a control step's decoding the rows are single tokens, so the
operations' dispatch is most of a norm's time: on the Xeon with AMX a 256-wide norm at one row took 20 to
30 us through the framework.

A layer is converted only where dyq's kernel reproduces it: every module whose class name ends in
``RMSNorm``, with a one-dimensional weight and a numeric epsilon, is run on a probe input beside the kernel
first, and converted if the two agree to the rounding of its dtype. A norm of another formula (Gemma's
``1 + weight``, one that returns float32 for bfloat16 input) disagrees and stays as it is, with the reason.
"""
from __future__ import annotations

import torch
from torch import nn

from . import reference
from .linear import ACTIVATION_DTYPES

_RMS_NORM = torch.ops.dyq.rms_norm.default
_EPSILON_NAMES = ("variance_epsilon", "eps")  # transformers' name, then torch's and most others'


class DyQRMSNorm(nn.Module):
    """``weight * (x / sqrt(mean(x^2) + eps))`` over the last dimension, in float32 with the result of the
    normalization and the product each rounded to x's dtype (transformers' ``LlamaRMSNorm``), through
    ``torch.ops.dyq.rms_norm``. The parameter is ``weight`` ``[hidden_size]``, so a state dict of the layer it
    replaces loads as it is. An input of another dtype than the weight's goes through the plain PyTorch
    reference of the same formula (:func:`dyq.reference.rms_norm`), with the type promotion of ``LlamaRMSNorm``.
    """

    def __init__(self, hidden_size: int, eps: float = 1e-6, device=None, dtype: torch.dtype | None = None) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.ones(hidden_size, device=device, dtype=dtype))
        self.eps = _checked_eps(eps)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        weight = self._parameters["weight"]
        if x.dtype == weight.dtype:
            return _RMS_NORM(x, weight, self.eps)
        return reference.rms_norm(x, weight, self.eps)  # the kernel takes one dtype; the formula promotes

    def extra_repr(self) -> str:
        return f"{self.weight.shape[0]}, eps={self.eps}, kernel=dyq.rms_norm"


def _checked_eps(eps) -> float:
    if isinstance(eps, bool) or not isinstance(eps, (int, float)) or not (0 <= eps < float("inf")):
        raise ValueError(f"eps must be a finite number >= 0, got {eps!r}")
    return float(eps)


def _epsilon(module: nn.Module) -> float | None:
    for name in _EPSILON_NAMES:
        value = getattr(module, name, None)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    return None


def _probe(weight: torch.Tensor) -> torch.Tensor:
    """Rows of the weight's width at magnitudes from 1e-2 to 1e3, on its device and in its dtype."""
    generator = torch.Generator().manual_seed(0)
    rows = torch.randn(4, weight.shape[0], generator=generator)
    rows = rows * torch.tensor([[1e-2], [1.0], [30.0], [1e3]])
    return rows.to(device=weight.device, dtype=weight.dtype)


def _agrees(expected: torch.Tensor, actual: torch.Tensor) -> bool:
    """Equal to the rounding of the dtype: the two sum the squares in different orders, which may move a
    rounded value by one step of its dtype."""
    if expected.dtype != actual.dtype or expected.shape != actual.shape:
        return False
    step = {torch.float32: 2.0 ** -20, torch.bfloat16: 2.0 ** -7, torch.float16: 2.0 ** -10}[expected.dtype]
    expected, actual = expected.double(), actual.double()
    return bool(((expected - actual).abs() <= step * torch.maximum(expected.abs(), actual.abs()) + 1e-30).all())


def unfusable_reason(module: nn.Module) -> str | None:
    """Why ``module`` (an RMSNorm by its class name) cannot run through dyq's kernel, or None if it can."""
    weight = module._parameters.get("weight")
    if not isinstance(weight, torch.Tensor) or weight.dim() != 1:
        return "it has no one-dimensional weight"
    if len(module._parameters) != 1 or module._buffers or module._modules:
        return "it holds more than its weight"
    if weight.is_meta:
        return "its weight is on the meta device"
    if weight.dtype not in ACTIVATION_DTYPES:
        return f"its weight is {weight.dtype}"
    if weight.device.type not in ("cpu", "cuda"):
        return f"its weight is on {weight.device}"
    eps = _epsilon(module)
    if eps is None or not 0 <= eps < float("inf"):
        return f"it has no finite epsilon >= 0 ({' or '.join(_EPSILON_NAMES)})"
    probe = _probe(weight)
    with torch.no_grad():
        expected = module(probe)
        try:
            actual = _RMS_NORM(probe, weight.detach(), eps)
        except (NotImplementedError, RuntimeError) as error:  # a dyq built without its kernels for that device
            return f"dyq's rms_norm does not run on {weight.device}: {str(error).splitlines()[0]}"
    if not isinstance(expected, torch.Tensor) or not _agrees(expected, actual):
        return "its output differs from the kernel's formula (weight * x / rms(x), rounded as LlamaRMSNorm rounds)"
    return None


def fuse_rms_norms(model: nn.Module) -> tuple[list[str], dict[str, str]]:
    """Convert, in place, every RMSNorm of ``model`` that dyq's kernel reproduces (module docstring) to a
    :class:`DyQRMSNorm` (its class changes; its weight and everything else stay), so that every reference to
    it sees the fused layer. Returns the names converted and ``{name: why}`` for the RMSNorms left alone. A
    norm several parents share is converted once, under its first name; one already converted is not listed."""
    if not isinstance(model, nn.Module):
        raise TypeError(f"model must be a torch.nn.Module, got {type(model).__name__}")
    fused, left = [], {}
    seen: set[int] = set()
    for name, module in model.named_modules():
        if id(module) in seen or isinstance(module, DyQRMSNorm) or not type(module).__name__.endswith("RMSNorm"):
            continue
        seen.add(id(module))
        label = name or type(module).__name__  # the model itself, by its class
        reason = unfusable_reason(module)
        if reason is not None:
            left[label] = reason
            continue
        eps = _epsilon(module)
        module.__class__ = DyQRMSNorm
        module.eps = eps
        fused.append(label)
    return fused, left
