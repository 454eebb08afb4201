"""``DyQLinear``: a drop-in ``nn.Linear`` with static INT4 weights and a switchable activation precision."""
from __future__ import annotations

import torch
from torch import nn

from ..control.flag import PrecisionFlag
from . import ops
from .precision import check_bits, check_group_size

ACTIVATION_DTYPES = (torch.float32, torch.bfloat16, torch.float16)


def _check_group_size(in_features: int, group_size: int) -> None:
    check_group_size(group_size)
    if in_features % group_size != 0:
        raise ValueError(f"in_features = {in_features} is not a multiple of group_size = {group_size}")


class DyQLinear(nn.Module):
    """``y = x W^T + b`` with W stored as grouped INT4 and x quantized per step to ``act_bits``.

    The activation bit-width (the paper's b*_t in {2, 4, 8, 16}, 16 being the BF16 fallback) comes from the
    module's own ``act_bits``, or, when the module is bound to a :class:`dyq.PrecisionFlag`, from that flag
    at run time, so that one write switches every layer of a model without re-tracing.

    Buffers (and so the ``state_dict``): ``qweight`` uint8 ``[N, K/2]``, ``scales`` float32
    ``[N, K/group_size]`` and the optional ``bias`` ``[N]``; the layout is in docs/numerics.md.
    """

    def __init__(self, in_features: int, out_features: int, bias: bool = True, *, group_size: int = 128,
                 act_bits: int = 16, flag: PrecisionFlag | None = None, device=None,
                 dtype: torch.dtype | None = None) -> None:
        super().__init__()
        _check_group_size(in_features, group_size)
        dtype = dtype or torch.get_default_dtype()
        if dtype not in ACTIVATION_DTYPES:
            raise TypeError(f"dtype must be one of {ACTIVATION_DTYPES}, got {dtype}")
        self.in_features = in_features
        self.out_features = out_features
        self.group_size = group_size
        self.act_bits = check_bits(act_bits, "act_bits")
        self.flag = None
        if flag is not None:
            self.bind_flag(flag)
        self.register_buffer("qweight", torch.zeros(out_features, in_features // 2, dtype=torch.uint8, device=device))
        self.register_buffer("scales", torch.ones(out_features, in_features // group_size, dtype=torch.float32,
                                                  device=device))
        if bias:
            self.bias = nn.Parameter(torch.zeros(out_features, dtype=dtype, device=device), requires_grad=False)
        else:
            self.register_parameter("bias", None)

    @classmethod
    def from_linear(cls, linear: nn.Linear, group_size: int = 128, act_bits: int = 16,
                    flag: PrecisionFlag | None = None) -> "DyQLinear":
        """Quantize an ``nn.Linear`` (its weight becomes INT4; its bias keeps its dtype)."""
        if not isinstance(linear, nn.Linear):
            raise TypeError(f"linear must be a torch.nn.Linear, got {type(linear).__name__}")
        weight = linear.weight.detach()
        dtype = weight.dtype if weight.dtype in ACTIVATION_DTYPES else torch.float32
        module = cls(linear.in_features, linear.out_features, bias=linear.bias is not None, group_size=group_size,
                     act_bits=act_bits, flag=flag, device=weight.device, dtype=dtype)
        qweight, scales = ops.quantize_weight(weight.to("cpu"), group_size)
        module.qweight.copy_(qweight)
        module.scales.copy_(scales)
        if linear.bias is not None:
            module.bias.data.copy_(linear.bias.detach())
        return module

    # -- precision ---------------------------------------------------------------------------------------------
    def bind_flag(self, flag: PrecisionFlag | None) -> None:
        """Read the bit-width from ``flag`` at run time (``None`` goes back to ``act_bits``)."""
        if flag is not None and not isinstance(flag, PrecisionFlag):
            raise TypeError(f"flag must be a dyq.PrecisionFlag or None, got {type(flag).__name__}")
        self.flag = flag

    def set_precision(self, bits: int) -> None:
        """Set the activation bit-width: writes the bound flag if there is one, else ``act_bits``."""
        bits = check_bits(bits)
        if self.flag is not None:
            self.flag.bits = bits
        else:
            self.act_bits = bits

    @property
    def precision(self) -> int:
        """The bit-width the next forward will use."""
        return self.flag.bits if self.flag is not None else self.act_bits

    # -- forward -----------------------------------------------------------------------------------------------
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dtype not in ACTIVATION_DTYPES:
            raise TypeError(f"DyQLinear input must be one of {ACTIVATION_DTYPES}, got {x.dtype}")
        bias = self.bias
        if bias is not None and bias.dtype != x.dtype:
            bias = bias.to(x.dtype)
        act_bits = self.flag.tensor if self.flag is not None else self.act_bits
        return ops.gemm(x, self.qweight, self.scales, self.group_size, act_bits, bias)

    # -- module plumbing ---------------------------------------------------------------------------------------
    def _apply(self, fn, recurse=True):
        # model.half() / .to(bf16) must not round the fp32 group scales; moving devices is fine.
        scales = self.scales
        super()._apply(fn, recurse)
        if self.scales.dtype != torch.float32:
            self._buffers["scales"] = scales.to(self.scales.device)
        return self

    def dequantized_weight(self) -> torch.Tensor:
        """The float32 weight ``[N, K]`` the INT4 codes represent (for inspection and tests)."""
        return ops.dequantize_weight(self.qweight, self.scales, self.group_size)

    def weight_bytes(self) -> int:
        """Bytes of the packed weight, its scales and the bias."""
        n = self.qweight.numel() * self.qweight.element_size() + self.scales.numel() * self.scales.element_size()
        if self.bias is not None:
            n += self.bias.numel() * self.bias.element_size()
        return n

    def extra_repr(self) -> str:
        precision = f"flag={self.flag.bits}" if self.flag is not None else f"act_bits={self.act_bits}"
        return (f"in_features={self.in_features}, out_features={self.out_features}, bias={self.bias is not None}, "
                f"weight=int4, group_size={self.group_size}, {precision}")
