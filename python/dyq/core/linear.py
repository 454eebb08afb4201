"""``DyQLinear``: a drop-in ``nn.Linear`` with static INT4 weights and a switchable activation precision."""
from __future__ import annotations

import warnings

import torch
from torch import nn

from ..control.flag import PrecisionFlag
from . import ops
from .host_memory import on_huge_pages
from .precision import check_bits, check_group_size

ACTIVATION_DTYPES = (torch.float32, torch.bfloat16, torch.float16)
_EXPORTED_FLAG_WARNING = (
    "torch.export records a DyQLinear's precision flag as a constant: a saved program or an AOTInductor package "
    "keeps its own copy and runs at the width the flag holds now, whatever is written to the flag later. "
    "dyq.export(model, args) makes the flag the program's first input instead (program(flag.tensor, *args)).")
# The ops' overloads themselves: resolving torch.ops.dyq.gemm on every call costs time a small layer notices.
_GEMM = torch.ops.dyq.gemm.default
_GEMM_WITH_FLAG = torch.ops.dyq.gemm_with_flag.default


def _check_features(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be an int >= 1, got {value!r}")
    return value


def _packed_columns(in_features: int) -> int:
    """K of the packed weight: in_features, plus one zero column when it is odd (two codes per byte)."""
    return in_features + in_features % 2


def _quantized_weight(linear: nn.Linear, group_size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(qweight, scales) of ``linear.weight`` on its device; an odd in_features gets a zero column, which
    changes no group's scale and no product."""
    weight = linear.weight.detach()
    if weight.is_meta:
        raise ValueError("linear.weight is on the meta device and holds no values to quantize: load the float "
                         "weights first, or make an empty layer for a quantized state dict with "
                         "DyQLinear.convert_in_place(linear, quantize=False)")
    if weight.shape[1] % 2:
        weight = nn.functional.pad(weight, (0, 1))
    qweight, scales = ops.quantize_weight(weight.to("cpu"), group_size)
    return qweight.to(linear.weight.device), scales.to(linear.weight.device)


def _bias_dtype(linear: nn.Linear) -> torch.dtype:
    return linear.weight.dtype if linear.weight.dtype in ACTIVATION_DTYPES else torch.float32


class DyQLinear(nn.Module):
    """``y = x W^T + b`` with W stored as grouped INT4 and x quantized per step to ``act_bits``.

    The activation bit-width (the paper's b*_t in {2, 4, 8, 16}, 16 being the BF16 fallback) comes from the
    module's own ``act_bits``, or, when the module is bound to a :class:`dyq.PrecisionFlag`, from that flag
    at run time, so that one write switches every layer of a model without re-tracing.

    Buffers (and so the ``state_dict``): ``qweight`` uint8 ``[N, K/2]``, ``scales`` float32
    ``[N, ceil(K/group_size)]`` and the optional ``bias`` ``[N]``; the layout is in docs/numerics.md. Any
    ``in_features`` works: the last group of a row holds the remainder when group_size does not divide it,
    and an odd ``in_features`` is stored with one zero column (K = in_features + 1) that the forward pads x
    with.

    Gradients: ``x.grad`` is that of ``x W^T + b`` with the dequantized weight (straight-through over the
    activation quantization), so adapters trained beside a frozen DyQLinear (LoRA) learn; the INT4 weights
    themselves have no gradient.

    ``weight_method`` names how the codes were chosen (``quantize_model``'s ``method``); every method writes
    the same format, so it is a record, not a switch.

    ``min_act_bits`` (default 2: none) is a floor on the width: a layer whose flag asks for fewer bits runs
    at ``min_act_bits`` instead (``quantize_model(min_act_bits=...)`` keeps, for example, gate/up at A8 while
    the rest of the model runs at A4). The floor goes to the kernel with the flag and is applied where the
    flag is read (on CUDA, in the kernel), so a captured CUDA graph keeps it under every later flag value.
    """

    weight_method = "rtn"
    min_act_bits = 2

    def __init__(self, in_features: int, out_features: int, bias: bool = True, *, group_size: int = 128,
                 act_bits: int = 16, flag: PrecisionFlag | None = None, device=None,
                 dtype: torch.dtype | None = None) -> None:
        super().__init__()
        _check_features(in_features, "in_features")
        _check_features(out_features, "out_features")
        check_group_size(group_size)
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
        k = _packed_columns(in_features)
        self.register_buffer("qweight", torch.zeros(out_features, k // 2, dtype=torch.uint8, device=device))
        self.register_buffer("scales", torch.ones(out_features, -(-k // group_size), dtype=torch.float32,
                                                  device=device))
        self.place_packed_weights()
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
        module = cls(linear.in_features, linear.out_features, bias=linear.bias is not None, group_size=group_size,
                     act_bits=act_bits, flag=flag, device=linear.weight.device, dtype=_bias_dtype(linear))
        qweight, scales = _quantized_weight(linear, group_size)
        module.qweight.copy_(qweight)
        module.scales.copy_(scales)
        if linear.bias is not None:
            module.bias.data.copy_(linear.bias.detach())
        return module

    @classmethod
    def convert_in_place(cls, linear: nn.Linear, group_size: int = 128, act_bits: int = 16,
                         flag: PrecisionFlag | None = None, *, quantize: bool = True) -> "DyQLinear":
        """Turn ``linear`` itself into a DyQLinear (its class changes; its weight becomes INT4), so that
        every reference to it, in any parent or in the caller's hands, sees the quantized layer. Returns it.
        ``quantize=False`` leaves empty INT4 buffers of the right shape (on the weight's device, meta
        included) for a state dict to be loaded into. A transformers ``Conv1D``, or a weight computed on
        access, first becomes the plain ``nn.Linear`` it computes (:func:`as_plain_linear`)."""
        if not (isinstance(linear, nn.Linear) or is_transposed_linear(linear)):
            raise TypeError(f"linear must be a torch.nn.Linear, got {type(linear).__name__}")
        check_group_size(group_size)
        act_bits = check_bits(act_bits, "act_bits")
        as_plain_linear(linear)
        if quantize:
            qweight, scales = _quantized_weight(linear, group_size)
        else:
            k, device = _packed_columns(linear.in_features), linear.weight.device
            qweight = torch.zeros(linear.out_features, k // 2, dtype=torch.uint8, device=device)
            scales = torch.ones(linear.out_features, -(-k // group_size), dtype=torch.float32, device=device)
        bias = linear.bias
        if bias is not None:
            bias = nn.Parameter(bias.detach().to(_bias_dtype(linear)), requires_grad=False)
        del linear._parameters["weight"]
        del linear._parameters["bias"]
        linear.__class__ = cls
        linear.group_size, linear.act_bits, linear.flag = group_size, act_bits, None
        linear.bind_flag(flag)
        linear.register_buffer("qweight", qweight)
        linear.register_buffer("scales", scales)
        linear.place_packed_weights()
        linear.register_parameter("bias", bias)
        return linear

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
        bits = self.flag.bits if self.flag is not None else self.act_bits
        return max(bits, self.min_act_bits)

    def set_min_act_bits(self, bits: int) -> None:
        """Run at ``bits`` or more whatever the flag says (2: no floor)."""
        self.min_act_bits = check_bits(bits, "min_act_bits")

    # -- forward -----------------------------------------------------------------------------------------------
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not isinstance(x, torch.Tensor):
            raise TypeError(f"DyQLinear input must be a torch.Tensor, got {type(x).__name__}")
        if x.dtype not in ACTIVATION_DTYPES:
            raise TypeError(f"DyQLinear input must be one of {ACTIVATION_DTYPES}, got {x.dtype}")
        if x.dim() < 1 or x.shape[-1] != self.in_features:
            raise ValueError(f"DyQLinear input must have shape [..., in_features = {self.in_features}], "
                             f"got {tuple(x.shape)}")
        if self.in_features % 2:
            x = nn.functional.pad(x, (0, 1))  # the zero column of the packed weight
        # The tensors straight from the module's dicts: nn.Module.__getattr__ costs about 1 us a name, a
        # sixth of a small layer's call at one activation row.
        bias = self._parameters["bias"]
        if bias is not None and bias.dtype != x.dtype:
            bias = bias.to(x.dtype)
        qweight, scales = self._buffers["qweight"], self._buffers["scales"]
        if self.flag is None:
            return _GEMM(x, qweight, scales, self.group_size, max(self.act_bits, self.min_act_bits), bias)
        if torch.compiler.is_exporting() and isinstance(self.flag, PrecisionFlag):
            warnings.warn(_EXPORTED_FLAG_WARNING, stacklevel=2)
        return _GEMM_WITH_FLAG(x, qweight, scales, self.group_size, self.flag.tensor, bias, self.min_act_bits)

    # -- module plumbing ---------------------------------------------------------------------------------------
    def place_packed_weights(self) -> None:
        """Move ``qweight`` and ``scales`` onto huge pages where they are CPU tensors of one huge page or
        more (:mod:`dyq.core.host_memory`: a CPU decode streams them). Conversion and loading do it; a deep
        copy or an unpickled module does it again, since copies land in ordinary memory."""
        for name in ("qweight", "scales"):
            if self._buffers.get(name) is not None:
                self._buffers[name] = on_huge_pages(self._buffers[name])

    def __setstate__(self, state):
        super().__setstate__(state)
        self.place_packed_weights()

    def _apply(self, fn, recurse=True):
        # model.half() / .to(bf16) must not round the fp32 group scales; moving devices is fine.
        before = {name: self._buffers.get(name) for name in ("qweight", "scales")}
        super()._apply(fn, recurse)
        if self.scales.dtype != torch.float32:
            self._buffers["scales"] = before["scales"].to(self.scales.device)
        # Buffers that fn replaced by new CPU tensors (a model moved back from the GPU, to_empty(device="cpu"))
        # are copies in ordinary memory: they go onto huge pages as conversion puts them. Those fn returned
        # as they were (.float() leaves the uint8 codes alone, .cpu() on the CPU, share_memory() moves the
        # storage in place) stay where they are, so no _apply copies the weights again.
        for name, old in before.items():
            new = self._buffers.get(name)
            if new is not None and new is not old:
                self._buffers[name] = on_huge_pages(new)
        return self

    def dequantized_weight(self) -> torch.Tensor:
        """The float32 weight ``[N, in_features]`` the INT4 codes represent (for inspection and tests)."""
        return ops.dequantize_weight(self.qweight, self.scales, self.group_size)[:, :self.in_features]

    def weight_bytes(self) -> int:
        """Bytes of the packed weight, its scales and the bias."""
        n = self.qweight.numel() * self.qweight.element_size() + self.scales.numel() * self.scales.element_size()
        if self.bias is not None:
            n += self.bias.numel() * self.bias.element_size()
        return n

    def extra_repr(self) -> str:
        precision = f"flag={self.flag.bits}" if self.flag is not None else f"act_bits={self.act_bits}"
        if self.min_act_bits > 2:
            precision += f", min_act_bits={self.min_act_bits}"
        return (f"in_features={self.in_features}, out_features={self.out_features}, bias={self.bias is not None}, "
                f"weight=int4, group_size={self.group_size}, {precision}")


# -- transformers' Conv1D --------------------------------------------------------------------------------------
# GPT-2 and the models built on it (DecisionTransformer, ImageGPT) keep their linear layers as
# transformers.pytorch_utils.Conv1D: y = x W + b with W stored [in, out], the transpose of nn.Linear's.
def is_transposed_linear(module: nn.Module) -> bool:
    """Whether ``module`` is a transformers ``Conv1D`` (a linear layer whose weight is stored [in, out])."""
    kind = type(module)
    return (kind.__name__ == "Conv1D" and kind.__module__.startswith("transformers.")
            and isinstance(getattr(module, "weight", None), torch.Tensor) and module.weight.dim() == 2)


def _transposed_linear_to_linear(module: nn.Module) -> None:
    """Turn a transformers ``Conv1D`` itself into the ``nn.Linear`` it computes (its class changes, its weight
    is transposed), so that every reference to it sees the new layer."""
    weight = module.weight
    in_features, out_features = weight.shape
    module.__class__ = nn.Linear
    module.weight = nn.Parameter(weight.detach().t().contiguous(), requires_grad=weight.requires_grad)
    module.in_features, module.out_features = in_features, out_features
    for name in ("nf", "nx"):
        module.__dict__.pop(name, None)


# -- the layer a DyQLinear replaces ------------------------------------------------------------------------------
def as_plain_linear(linear: nn.Module) -> nn.Linear:
    """Make ``linear`` itself the plain ``nn.Linear`` it computes, ready for conversion, and return it: a
    transformers ``Conv1D`` is transposed, and a weight computed on every access
    (``torch.nn.utils.parametrizations.weight_norm`` / ``spectral_norm``, the older hook-based ``weight_norm``)
    becomes a parameter holding its current value, as static INT4 weights fix it anyway. A plain layer is
    left as it is."""
    from torch.nn.utils import parametrize

    if is_transposed_linear(linear):
        _transposed_linear_to_linear(linear)
    if parametrize.is_parametrized(linear, "weight"):
        parametrize.remove_parametrizations(linear, "weight", leave_parametrized=True)
    elif "weight" not in linear._parameters and hasattr(linear, "weight_g") and hasattr(linear, "weight_v"):
        torch.nn.utils.remove_weight_norm(linear)
    return linear


# -- layers their parents read ----------------------------------------------------------------------------------
def weight_readers(model: nn.Module) -> dict[int, str]:
    """{id(linear): its parent's class} for the linear layers whose parent always reads their weight
    instead of calling them, which a DyQLinear (INT4 codes, no ``weight``) would break:
    ``nn.MultiheadAttention``'s out_proj (``F.multi_head_attention_forward`` takes the weight)."""
    return {id(parent.out_proj): type(parent).__name__ for parent in model.modules()
            if isinstance(parent, nn.MultiheadAttention) and isinstance(parent.out_proj, nn.Linear)}


def route_encoder_layers_through_modules(model: nn.Module) -> None:
    """``nn.TransformerEncoderLayer`` (and ``nn.TransformerEncoder`` on its first layer) runs inference
    through a fused kernel that reads linear1's and linear2's weights; its other path calls them. For an
    encoder layer whose feed-forward layers are DyQLinear, the fused path is turned off by the attribute it
    checks (``activation_relu_or_gelu``, which nothing else reads), so that the layers run dyq's GEMMs."""
    for layer in model.modules():
        if isinstance(layer, nn.TransformerEncoderLayer) and (
                isinstance(layer.linear1, DyQLinear) or isinstance(layer.linear2, DyQLinear)):
            layer.activation_relu_or_gelu = 0
