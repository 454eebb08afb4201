"""Typed wrappers and fake (meta) kernels of the ``torch.ops.dyq`` operators.

The schemas are declared once, in ``csrc/torch/ops.cpp``; the kernels are registered per backend in
C++. The fake kernels here give every op its output shapes without running it, so the ops work with
meta tensors, ``torch.compile`` and ``torch.library.opcheck``. The numerics are in docs/numerics.md.
"""
from __future__ import annotations

import torch

from . import _C  # noqa: F401  (loads the library that registers the ops)
from .reference import ACT_BITS, GROUP_SIZES  # noqa: F401  (re-exported)


def _check_fake_gemm(x: torch.Tensor, qweight: torch.Tensor, scales: torch.Tensor, group_size: int) -> None:
    torch._check(group_size in GROUP_SIZES, lambda: f"dyq: group_size must be 32, 64 or 128, got {group_size}")
    torch._check(qweight.dim() == 2, lambda: f"dyq: qweight must have shape [N, K/2], got {tuple(qweight.shape)}")
    torch._check(x.shape[-1] == qweight.shape[1] * 2,
                 lambda: f"dyq: x has {x.shape[-1]} features but the weight expects K = {qweight.shape[1] * 2}")


@torch.library.register_fake("dyq::quantize_weight")
def _quantize_weight_fake(weight, group_size):
    n, k = weight.shape
    return (weight.new_empty((n, k // 2), dtype=torch.uint8),
            weight.new_empty((n, k // group_size), dtype=torch.float32))


@torch.library.register_fake("dyq::dequantize_weight")
def _dequantize_weight_fake(qweight, scales, group_size):
    return scales.new_empty((qweight.shape[0], qweight.shape[1] * 2), dtype=torch.float32)


@torch.library.register_fake("dyq::quantize_activations")
def _quantize_activations_fake(x, group_size, act_bits):
    k = x.shape[-1]
    lead = tuple(x.shape[:-1])
    return (x.new_empty(lead + (k * act_bits // 8,), dtype=torch.uint8),
            x.new_empty(lead + (k // group_size,), dtype=torch.float32),
            x.new_empty(lead + (k // group_size,), dtype=torch.uint8))


@torch.library.register_fake("dyq::gemm")
def _gemm_fake(x, qweight, scales, group_size, act_bits, bias=None):
    _check_fake_gemm(x, qweight, scales, group_size)
    return x.new_empty(tuple(x.shape[:-1]) + (qweight.shape[0],))


@torch.library.register_fake("dyq::gemm_with_flag")
def _gemm_with_flag_fake(x, qweight, scales, group_size, act_bits_flag, bias=None):
    _check_fake_gemm(x, qweight, scales, group_size)
    return x.new_empty(tuple(x.shape[:-1]) + (qweight.shape[0],))


def quantize_weight(weight: torch.Tensor, group_size: int = 128) -> tuple[torch.Tensor, torch.Tensor]:
    """Static symmetric INT4 quantization of ``weight [N, K]``: returns (qweight uint8 [N, K/2],
    scales float32 [N, K/group_size])."""
    return torch.ops.dyq.quantize_weight(weight, group_size)


def dequantize_weight(qweight: torch.Tensor, scales: torch.Tensor, group_size: int = 128) -> torch.Tensor:
    """The float32 weight [N, K] that the INT4 codes represent (s_w * q_w)."""
    return torch.ops.dyq.dequantize_weight(qweight, scales, group_size)


def quantize_activations(x: torch.Tensor, group_size: int, act_bits: int):
    """Per-token, per-group ``act_bits``-bit codes of ``x [..., K]`` (Eq. 2): returns (packed uint8
    [..., K*act_bits/8], scales float32 [..., K/G], zero points uint8 [..., K/G])."""
    return torch.ops.dyq.quantize_activations(x, group_size, act_bits)


def gemm(x: torch.Tensor, qweight: torch.Tensor, scales: torch.Tensor, group_size: int, act_bits: int,
         bias: torch.Tensor | None = None) -> torch.Tensor:
    """``x [..., K] @ W^T (+ bias)`` with INT4 weights and ``act_bits``-bit activations (16: unquantized)."""
    return torch.ops.dyq.gemm(x, qweight, scales, group_size, act_bits, bias)


def gemm_with_flag(x: torch.Tensor, qweight: torch.Tensor, scales: torch.Tensor, group_size: int,
                   act_bits_flag: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
    """As :func:`gemm`, with the bit-width read at run time from a one-element int32 tensor."""
    return torch.ops.dyq.gemm_with_flag(x, qweight, scales, group_size, act_bits_flag, bias)
