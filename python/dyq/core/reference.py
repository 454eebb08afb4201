"""Plain PyTorch reference of dyq's numerics (docs/numerics.md).

This module is the executable specification: it is written for clarity, not speed, and the tests compare
the C++ and CUDA kernels against it. It never calls a dyq kernel.
"""
from __future__ import annotations

import math
import numbers

import torch

GROUP_SIZES = (32, 64, 128)
ACT_BITS = (2, 4, 8, 16)
WEIGHT_QMIN, WEIGHT_QMAX = -8, 7


def _check_group_size(group_size) -> None:
    if isinstance(group_size, bool) or not isinstance(group_size, numbers.Integral) or group_size not in GROUP_SIZES:
        raise ValueError(f"group_size must be an int in {GROUP_SIZES}, got {group_size!r}")


def _check_act_bits(act_bits) -> None:
    if isinstance(act_bits, bool) or not isinstance(act_bits, numbers.Integral) or act_bits not in ACT_BITS:
        raise ValueError(f"act_bits must be an int in {ACT_BITS}, got {act_bits!r}")


def _check_packed_weight(qweight: torch.Tensor, scales: torch.Tensor, group_size: int, k: int | None = None) -> None:
    """qweight [N, K/2] and scales [N, ceil(K/G)]; K, where given, the activations' own."""
    n, columns = qweight.shape[0], qweight.shape[-1] * 2
    if k is not None and k != columns:
        raise ValueError(f"x has K = {k} columns but qweight packs K = {columns}")
    expected = (n, -(-columns // group_size))
    if tuple(scales.shape) != expected:
        raise ValueError(f"scales must have shape {expected} for K = {columns} at group_size {group_size}, got "
                         f"{tuple(scales.shape)}")


def _grouped(t: torch.Tensor, group_size: int) -> torch.Tensor:
    """[..., K] as [..., ceil(K/G), G]. When G does not divide K the last group holds the remainder,
    padded here with zeros: a zero changes neither a group's range (which always contains 0), nor its
    absolute maximum, nor its sums, so the padding is never visible in a result."""
    _check_group_size(group_size)
    pad = -t.shape[-1] % group_size
    if pad:
        t = torch.nn.functional.pad(t, (0, pad))
    return t.reshape(*t.shape[:-1], t.shape[-1] // group_size, group_size)


def _ungrouped(t: torch.Tensor, k: int) -> torch.Tensor:
    """Inverse of _grouped: [..., groups, G] back to [..., K], the padding dropped."""
    return t.reshape(*t.shape[:-2], t.shape[-2] * t.shape[-1])[..., :k]


def quantize_weight(weight: torch.Tensor, group_size: int = 128):
    """Symmetric INT4 codes and scales: returns (q_w int8 [N, K], s_w float32 [N, K/G])."""
    w = _grouped(weight.float(), group_size)
    scales = w.abs().amax(dim=-1) / 7
    empty = scales == 0
    scales = torch.where(empty, torch.ones_like(scales), scales)
    codes = torch.round(w / scales.unsqueeze(-1)).clamp(WEIGHT_QMIN, WEIGHT_QMAX)
    codes = torch.where(empty.unsqueeze(-1), torch.zeros_like(codes), codes)
    return _ungrouped(codes, weight.shape[-1]).to(torch.int8), scales


def pack_int4(codes: torch.Tensor) -> torch.Tensor:
    """Pack signed 4-bit codes [..., K] into uint8 [..., K/2]: column 2j low nibble, 2j+1 high."""
    nibbles = codes.to(torch.int16) & 0xF
    return (nibbles[..., 0::2] | (nibbles[..., 1::2] << 4)).to(torch.uint8)


def unpack_int4(packed: torch.Tensor) -> torch.Tensor:
    """Inverse of pack_int4: uint8 [..., K/2] -> int8 [..., K] in [-8, 7]."""
    p = packed.to(torch.int16)
    low, high = p & 0xF, (p >> 4) & 0xF
    codes = torch.stack((low, high), dim=-1).reshape(*packed.shape[:-1], packed.shape[-1] * 2)
    return torch.where(codes >= 8, codes - 16, codes).to(torch.int8)


def dequantize_weight(qweight: torch.Tensor, scales: torch.Tensor, group_size: int = 128) -> torch.Tensor:
    _check_group_size(group_size)
    _check_packed_weight(qweight, scales, group_size)
    codes = _grouped(unpack_int4(qweight).float(), group_size)
    return _ungrouped(codes * scales.unsqueeze(-1), qweight.shape[-1] * 2)


def quantize_activations(x: torch.Tensor, group_size: int, act_bits: int):
    """Per-token, per-group asymmetric codes (Eq. 2 with rne).

    Returns (q_x uint8 [..., K] unpacked codes, s_x float32 [..., K/G], z_x uint8 [..., K/G]).
    """
    _check_act_bits(act_bits)
    if act_bits == 16:
        raise ValueError("act_bits 16 is not quantized: quantize_activations takes 2, 4 or 8")
    levels = 2**act_bits - 1
    xg = _grouped(x.float(), group_size)
    finite = torch.isfinite(xg).all(dim=-1)
    safe = torch.where(torch.isfinite(xg), xg, torch.zeros_like(xg))
    lo = safe.amin(dim=-1).clamp(max=0)
    hi = safe.amax(dim=-1).clamp(min=0)
    scales = (hi - lo) / levels
    # A range beyond FLT_MAX (hi - lo overflows): halve both ends, which is exact, and double the result:
    # the value an fp32 with a wider exponent would give, and finite.
    wide = torch.isinf(scales)
    scales = torch.where(wide, ((0.5 * hi - 0.5 * lo) / levels) * 2, scales)
    empty = scales == 0
    scales = torch.where(empty, torch.ones_like(scales), scales)
    zeros = torch.round(-lo / scales).clamp(0, levels)
    codes = (torch.round(safe / scales.unsqueeze(-1)) + zeros.unsqueeze(-1)).clamp(0, levels)
    # Codes 0 and zero point 0 for empty and non-finite groups; NaN scale for the non-finite ones.
    zero_group = (empty | ~finite)
    zeros = torch.where(zero_group, torch.zeros_like(zeros), zeros)
    codes = torch.where(zero_group.unsqueeze(-1), torch.zeros_like(codes), codes)
    scales = torch.where(finite, scales, torch.full_like(scales, float("nan")))
    return _ungrouped(codes, x.shape[-1]).to(torch.uint8), scales, zeros.to(torch.uint8)


def pack_activations(codes: torch.Tensor, act_bits: int) -> torch.Tensor:
    """Pack unsigned b-bit codes [..., K] into uint8 [..., K*b/8], lowest bits first."""
    if act_bits == 8:
        return codes.to(torch.uint8).clone()
    per_byte = 8 // act_bits
    c = codes.to(torch.int32).reshape(*codes.shape[:-1], codes.shape[-1] // per_byte, per_byte)
    shifts = torch.arange(per_byte, dtype=torch.int32) * act_bits
    return (c << shifts).sum(dim=-1).to(torch.uint8)


def unpack_activations(packed: torch.Tensor, act_bits: int) -> torch.Tensor:
    if act_bits == 8:
        return packed.clone()
    per_byte = 8 // act_bits
    shifts = torch.arange(per_byte, dtype=torch.int32) * act_bits
    c = (packed.to(torch.int32).unsqueeze(-1) >> shifts) & (2**act_bits - 1)
    return c.reshape(*packed.shape[:-1], packed.shape[-1] * per_byte).to(torch.uint8)


def gemm(x: torch.Tensor, qweight: torch.Tensor, scales: torch.Tensor, group_size: int, act_bits: int,
         bias: torch.Tensor | None = None, accumulate_dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """y = x W^T (+ bias) in the numerics of docs/numerics.md, accumulated in ``accumulate_dtype``.

    Returns the accumulator (float64 by default), not rounded to the input dtype, so that tests can
    measure a kernel's rounding against it.
    """
    k = x.shape[-1]
    n = qweight.shape[0]
    _check_group_size(group_size)
    _check_act_bits(act_bits)
    _check_packed_weight(qweight, scales, group_size, k)
    x2 = x.reshape(math.prod(x.shape[:-1]), k)
    w_codes = _grouped(unpack_int4(qweight).to(accumulate_dtype), group_size)        # [N, Gs, G]
    s_w = scales.to(accumulate_dtype)                                                  # [N, Gs]
    if act_bits == 16:
        xg = _grouped(x2.float().to(accumulate_dtype), group_size)                     # [M, Gs, G]
        partial = torch.einsum("mgk,ngk->mng", xg, w_codes)
        y = (partial * s_w.unsqueeze(0)).sum(dim=-1)
    else:
        q_x, s_x, z_x = quantize_activations(x2, group_size, act_bits)
        centered = _grouped(q_x.to(torch.int64), group_size) - z_x.to(torch.int64).unsqueeze(-1)
        partial = torch.einsum("mgk,ngk->mng", centered.to(accumulate_dtype), w_codes)  # exact integers
        y = (partial * s_x.to(accumulate_dtype).unsqueeze(1) * s_w.unsqueeze(0)).sum(dim=-1)
    if bias is not None:
        y = y + bias.to(accumulate_dtype)
    return y.reshape(*x.shape[:-1], n)


def gemm_error_bound(x: torch.Tensor, qweight: torch.Tensor, scales: torch.Tensor, group_size: int,
                     act_bits: int, bias: torch.Tensor | None = None) -> torch.Tensor:
    """sum of |terms| of the fp32 sums in ``gemm``: the scale of the rounding error a kernel may make."""
    k = x.shape[-1]
    x2 = x.reshape(math.prod(x.shape[:-1]), k)
    w_codes = _grouped(unpack_int4(qweight).double().abs(), group_size)
    s_w = scales.double().abs()
    if act_bits == 16:
        xg = _grouped(x2.double().abs(), group_size)
        y = (torch.einsum("mgk,ngk->mng", xg, w_codes) * s_w.unsqueeze(0)).sum(dim=-1)
    else:
        q_x, s_x, z_x = quantize_activations(x2, group_size, act_bits)
        centered = (_grouped(q_x.double(), group_size) - z_x.double().unsqueeze(-1)).abs()
        y = (torch.einsum("mgk,ngk->mng", centered, w_codes) * s_x.double().abs().unsqueeze(1)
             * s_w.unsqueeze(0)).sum(dim=-1)
    if bias is not None:
        y = y + bias.double().abs()
    return y.reshape(*x.shape[:-1], qweight.shape[0])


def rms_norm(x: torch.Tensor, weight: torch.Tensor, eps: float) -> torch.Tensor:
    """RMSNorm over the last dimension (docs/numerics.md, section 2a): x widened to float32, scaled by
    1 / sqrt(mean(x^2) + eps), rounded to x's dtype, then multiplied by ``weight`` in that dtype (the product
    of two values of the dtype, computed in float32 and rounded once, as torch multiplies them)."""
    h = x.float()
    h = h * torch.rsqrt(h.pow(2).mean(-1, keepdim=True) + eps)
    return weight * h.to(x.dtype)
