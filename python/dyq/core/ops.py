"""Typed wrappers and fake (meta) kernels of the ``torch.ops.dyq`` operators.

The schemas are declared once, in ``csrc/torch/ops.cpp``; the kernels are registered per backend in
C++. The fake kernels here give every op its output shapes without running it, so the ops work with
meta tensors, ``torch.compile`` and ``torch.library.opcheck``. The numerics are in docs/numerics.md.
"""
from __future__ import annotations

import torch

from .. import _C
from .precision import VALID_BITS, check_bits


# Every fake kernel first runs the op's C++ validation (csrc/torch/checks.h, through the ``_check_*`` ops),
# the same that the CPU and CUDA kernels run: a traced or meta call fails exactly where a real one would.
@torch.library.register_fake("dyq::quantize_weight")
def _quantize_weight_fake(weight, group_size):
    torch.ops.dyq._check_quantize_weight(weight, group_size)
    n, k = weight.shape
    return (weight.new_empty((n, k // 2), dtype=torch.uint8),
            weight.new_empty((n, _groups(k, group_size)), dtype=torch.float32))


@torch.library.register_fake("dyq::dequantize_weight")
def _dequantize_weight_fake(qweight, scales, group_size):
    torch.ops.dyq._check_dequantize_weight(qweight, scales, group_size)
    return scales.new_empty((qweight.shape[0], qweight.shape[1] * 2), dtype=torch.float32)


@torch.library.register_fake("dyq::quantize_activations")
def _quantize_activations_fake(x, group_size, act_bits):
    torch.ops.dyq._check_quantize_activations(x, group_size, act_bits)
    k = x.shape[-1]
    lead = tuple(x.shape[:-1])
    return (x.new_empty(lead + (k * act_bits // 8,), dtype=torch.uint8),
            x.new_empty(lead + (_groups(k, group_size),), dtype=torch.float32),
            x.new_empty(lead + (_groups(k, group_size),), dtype=torch.uint8))


@torch.library.register_fake("dyq::gemm")
def _gemm_fake(x, qweight, scales, group_size, act_bits, bias=None):
    torch.ops.dyq._check_gemm(x, qweight, scales, group_size, act_bits, bias)
    return x.new_empty(tuple(x.shape[:-1]) + (qweight.shape[0],))


@torch.library.register_fake("dyq::gemm_with_flag")
def _gemm_with_flag_fake(x, qweight, scales, group_size, act_bits_flag, bias=None, min_act_bits=2):
    torch.ops.dyq._check_gemm_with_flag(x, qweight, scales, group_size, act_bits_flag, bias, min_act_bits)
    return x.new_empty(tuple(x.shape[:-1]) + (qweight.shape[0],))


@torch.library.register_fake("dyq::hadamard_transform")
def _hadamard_transform_fake(x, signs, left):
    torch.ops.dyq._check_hadamard_transform(x, signs, left)
    return x.new_empty(x.shape)


@torch.library.register_fake("dyq::rms_norm")
def _rms_norm_fake(x, weight, eps):
    torch.ops.dyq._check_rms_norm(x, weight, eps)
    return x.new_empty(x.shape)


# Autograd (gemm and gemm_with_flag through the frozen INT4 weights, hadamard_transform, rms_norm) is
# registered in C++, csrc/torch/autograd.cpp: a Python autograd kernel would run on every call, gradients or
# not.


def _groups(k, group_size: int):
    """ceil(K / G): groups per row, the last holding the remainder when G does not divide K."""
    return (k + group_size - 1) // group_size


def quantize_weight(weight: torch.Tensor, group_size: int = 128) -> tuple[torch.Tensor, torch.Tensor]:
    """Static symmetric INT4 quantization of ``weight [N, K]`` (K even): returns (qweight uint8 [N, K/2],
    scales float32 [N, ceil(K/group_size)]); the last group of a row holds the remainder."""
    return torch.ops.dyq.quantize_weight(weight, group_size)


def dequantize_weight(qweight: torch.Tensor, scales: torch.Tensor, group_size: int = 128) -> torch.Tensor:
    """The float32 weight [N, K] that the INT4 codes represent (s_w * q_w)."""
    return torch.ops.dyq.dequantize_weight(qweight, scales, group_size)


def quantize_activations(x: torch.Tensor, group_size: int, act_bits: int):
    """Per-token, per-group ``act_bits``-bit codes of ``x [..., K]`` (Eq. 2): returns (packed uint8
    [..., K*act_bits/8], scales float32 [..., K/G], zero points uint8 [..., K/G])."""
    return torch.ops.dyq.quantize_activations(x, group_size, act_bits)


def gemm(x: torch.Tensor, qweight: torch.Tensor, scales: torch.Tensor, group_size: int,
         act_bits: int | torch.Tensor, bias: torch.Tensor | None = None, min_act_bits: int = 2) -> torch.Tensor:
    """``x [..., K] @ W^T (+ bias)`` with INT4 weights and ``act_bits``-bit activations (16: unquantized).

    ``act_bits`` is a width of :data:`VALID_BITS`, or a precision flag (a one-element int32 tensor such as
    ``PrecisionFlag.tensor``) that the kernel reads when it runs (``torch.ops.dyq.gemm_with_flag``), then
    raises to at least ``min_act_bits``: the floor is applied where the flag is read (on CUDA in the
    kernel), so a captured CUDA graph keeps it under every later flag value. With a fixed width the floor
    applies likewise.
    """
    if isinstance(act_bits, torch.Tensor):
        return torch.ops.dyq.gemm_with_flag(x, qweight, scales, group_size, act_bits, bias, min_act_bits)
    if min_act_bits != 2:
        check_bits(min_act_bits, "min_act_bits")
        act_bits = max(check_bits(act_bits, "act_bits"), min_act_bits)
    return torch.ops.dyq.gemm(x, qweight, scales, group_size, act_bits, bias)


def hadamard_transform(x: torch.Tensor, signs: torch.Tensor, left: torch.Tensor) -> torch.Tensor:
    """``(x * signs) R`` over the last dimension n of ``x``, ``R = left (x) H_p / sqrt(p)``: ``left`` float32
    [m, m], ``H_p`` Sylvester's +-1 Hadamard matrix of order ``p = n / m`` (a power of two), ``signs``
    float32 [n]. The output has x's shape and dtype (computed in float32). This is the run-time rotation of
    :class:`dyq.rotation.OnlineRotation`; the kernel applies ``H_p`` by the fast Walsh-Hadamard butterfly,
    ``n (log2 p + m)`` operations per row instead of ``n^2`` (docs/numerics.md, section 1a)."""
    return torch.ops.dyq.hadamard_transform(x, signs, left)


def rms_norm(x: torch.Tensor, weight: torch.Tensor, eps: float) -> torch.Tensor:
    """RMSNorm over the last dimension n of ``x``: ``dtype(weight * dtype(x / sqrt(mean(x^2) + eps)))``, computed
    in float32 with those two roundings to x's dtype, as transformers' ``LlamaRMSNorm`` computes it, in one
    pass per row (docs/numerics.md, section 2a). ``weight`` is ``[n]`` of x's dtype; eps a number >= 0."""
    return torch.ops.dyq.rms_norm(x, weight, eps)


def width_counts() -> dict[int, int]:
    """GEMM calls of this process by the activation width each ran at, one key per width of
    :data:`VALID_BITS`. Counted in C++ where the width is resolved: for a flag, the value read at the
    call (on CUDA the host's read of the pinned flag at launch; see docs/cuda.md). A child process
    starts at zero."""
    return dict(zip(VALID_BITS, _C.gemm_width_counts()))


def reset_width_counts() -> None:
    """Set every count of :func:`width_counts` to zero."""
    _C.reset_gemm_width_counts()
