"""Whole-model conversion: ``quantize_model``, ``set_precision`` and ``bind_flag``."""
from __future__ import annotations

import fnmatch
import re
import sys
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Iterable, Pattern, Union

import torch
from torch import nn

from ..control.flag import PrecisionFlag
from .linear import (DyQLinear, as_plain_linear, is_transposed_linear, route_encoder_layers_through_modules,
                     weight_readers)
from .norm import fuse_rms_norms
from .precision import check_bits, check_group_size
from . import reference
from .weight_methods import (CALIBRATED_METHODS, DEFAULT_CALIBRATION_BITS, awq_prepare, check_calibration_bits,
                             check_method, collect_hessians, gptq_weight, packed_clipped_weight)

SkipPattern = Union[str, Pattern[str]]
DEFAULT_SKIP = ("lm_head",)


def _tensor_bytes(tensors: Iterable[torch.Tensor]) -> int:
    return sum(t.numel() * t.element_size() for t in tensors)


def _module_bytes(model: nn.Module) -> int:
    return _tensor_bytes(model.parameters()) + _tensor_bytes(model.buffers())


def _matches(name: str, patterns: Iterable[SkipPattern]) -> bool:
    """A glob (``"*.lm_head"``, matched against the full name and its last component) or a compiled regex."""
    last = name.rsplit(".", 1)[-1]
    for p in patterns:
        if isinstance(p, re.Pattern):
            if p.search(name):
                return True
        elif fnmatch.fnmatchcase(name, p) or fnmatch.fnmatchcase(last, p):
            return True
    return False


def _floor_of(names: Iterable[str], floors: Mapping) -> int | None:
    """The highest of ``floors``' bits ({pattern: bits}) whose pattern matches one of a layer's ``names``."""
    return max((bits for pattern, bits in floors.items() if any(_matches(n, (pattern,)) for n in names)), default=None)


def _check_pattern(pattern, argument: str) -> None:
    if not isinstance(pattern, (str, re.Pattern)):
        raise TypeError(f"{argument} patterns must be glob strings or compiled regular expressions, got "
                        f"{type(pattern).__name__} {pattern!r}")


@dataclass
class QuantizationReport:
    """What :func:`quantize_model` converted, what it left alone and why, and the memory it saved.

    ``converted`` names each converted layer once (its first name); ``shared`` lists the other names of
    a layer that several parents hold (tied modules), all of which now hold the one DyQLinear;
    ``already_quantized`` names the DyQLinear layers found (a second call converts nothing and says so).
    ``fused_norms`` names the RMSNorm layers now run through dyq's kernel; ``norms_left`` says why the others
    were left as they are.
    """

    group_size: int
    method: str = "rtn"
    converted: list[str] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)
    shared: dict[str, list[str]] = field(default_factory=dict)
    already_quantized: list[str] = field(default_factory=list)
    min_act_bits: dict[str, int] = field(default_factory=dict)
    fused_norms: list[str] = field(default_factory=list)
    norms_left: dict[str, str] = field(default_factory=dict)
    linear_bytes_before: int = 0
    linear_bytes_after: int = 0
    model_bytes_before: int = 0
    model_bytes_after: int = 0

    @property
    def linear_ratio(self) -> float:
        return self.linear_bytes_after / self.linear_bytes_before if self.linear_bytes_before else 1.0

    @property
    def model_ratio(self) -> float:
        return self.model_bytes_after / self.model_bytes_before if self.model_bytes_before else 1.0

    def __str__(self) -> str:
        mb = 1 / 2**20
        if not self.converted and self.already_quantized:
            return (f"dyq: the model is already quantized ({len(self.already_quantized)} DyQLinear layers); "
                    f"nothing to convert" + "".join(f"\n  skipped {n}: {why}" for n, why in self.skipped.items()))
        lines = [
            f"dyq: converted {len(self.converted)} linear layers to INT4 (group_size={self.group_size}, "
            f"method={self.method}), "
            f"skipped {len(self.skipped)}",
            f"  converted layers: {self.linear_bytes_before * mb:10.2f} MiB -> {self.linear_bytes_after * mb:10.2f} MiB "
            f"({100 * self.linear_ratio:.1f} %)",
            f"  whole model:      {self.model_bytes_before * mb:10.2f} MiB -> {self.model_bytes_after * mb:10.2f} MiB "
            f"({100 * self.model_ratio:.1f} %)",
        ]
        lines += [f"  shared {name}: also held as {', '.join(others)}" for name, others in self.shared.items()]
        if self.min_act_bits:
            lines.append(f"  {len(self.min_act_bits)} layers never run below "
                         f"{', '.join(f'A{b}' for b in sorted(set(self.min_act_bits.values())))} (min_act_bits)")
        if self.already_quantized:
            lines.append(f"  {len(self.already_quantized)} layers were DyQLinear already")
        lines += [f"  skipped {name}: {why}" for name, why in self.skipped.items()]
        if self.fused_norms:
            lines.append(f"  {len(self.fused_norms)} RMSNorm layers run through dyq's fused kernel")
        lines += [f"  RMSNorm {name} left as it is: {why}" for name, why in self.norms_left.items()]
        return "\n".join(lines)


def quantize_model(model: nn.Module, group_size: int = 128, skip: Iterable[SkipPattern] = DEFAULT_SKIP,
                   act_bits: int = 16, flag: PrecisionFlag | None = None, method: str = "rtn", calibration=None,
                   calibration_bits=DEFAULT_CALIBRATION_BITS, min_act_bits=None,
                   fuse_norms: bool = True) -> QuantizationReport:
    """Convert every ``nn.Linear`` of ``model`` in place to a :class:`DyQLinear` with INT4 weights (and
    every transformers ``Conv1D``, the transposed linear layer of GPT-2 and the models built on it). The
    out_proj of an ``nn.MultiheadAttention``, whose weight the attention reads without calling the layer,
    stays as it is (the report says why); ``nn.TransformerEncoderLayer``'s feed-forward layers are converted
    and the layer run through them instead of its fused inference kernel.

    Args:
        model: any module, e.g. a Hugging Face ``LlamaForCausalLM`` or a BERT encoder, or an ``nn.Linear``.
        group_size: INT4 group size along the input features (32, 64 or 128). Any in_features works: the
            last group of each row holds the remainder.
        skip: layer names to leave in full precision: globs matched against the full name and its last
            component (``"lm_head"``, ``"*.attn.*"``) or compiled regular expressions. The LM head is skipped
            by default (it scores the action tokens; pass ``skip=()`` to convert it too). A layer held under
            several names is skipped if any of them matches. A pattern passed here that matches no linear
            layer is warned about (a misspelt name would convert the layer it meant to keep).
        act_bits: the initial activation bit-width of the converted layers (16 = unquantized).
        flag: a :class:`PrecisionFlag` that every converted layer reads at run time, so that one write
            switches the whole model (the dispatcher's b*_t).
        method: how the INT4 codes and scales are chosen (``dyq.core.weight_methods``, docs/numerics.md
            section 1a): ``"rtn"`` (round-to-nearest from the absmax), ``"mse"`` (per-group clipping
            search), ``"awq"`` (activation-aware scaling folded into the float model, then clipping weighted
            by the activations; needs ``calibration``) or ``"gptq"`` (error-compensating rounding from each
            layer's Hessian over the float model's calibration inputs; needs ``calibration``). Every method
            writes the same format.
        calibration: for ``"awq"`` and ``"gptq"``, what the model is run on to observe its activations: a tensor
            (``model(t)``, e.g. token ids ``[batch, seq]``), a dict of keyword arguments, a list of those, or a
            callable. Keep it disjoint from the data the quantized model is evaluated on.
        calibration_bits: the activation widths the ``"awq"`` search weighs equally (by relative error): one
            weight set serves every width, so by default all of them, (16, 8, 4, 2).
        min_act_bits: ``{pattern: bits}``, patterns as in ``skip``: the matching converted layers never run
            below ``bits`` (a floor on the flag, :class:`DyQLinear`), e.g. ``{"gate_proj": 8, "up_proj": 8}``
            (docs/quantization.md: where a Llama's A4 error comes from).
        fuse_norms: also run the model's RMSNorm layers through dyq's fused kernel (:class:`DyQRMSNorm`,
            ``torch.ops.dyq.rms_norm``): one pass per row instead of seven framework operations, the same
            numerics but for the order of a sum. Only the norms the kernel reproduces on a probe input are
            converted; the report lists them (``fused_norms``) and why others stay (``norms_left``).

    Each Linear is converted in place (its class becomes DyQLinear), so a layer that several parents
    share stays one layer, and a bare ``nn.Linear`` passed as ``model`` is itself converted.
    """
    if not isinstance(model, nn.Module):
        raise TypeError(f"model must be a torch.nn.Module, got {type(model).__name__}")
    check_group_size(group_size)
    check_bits(act_bits, "act_bits")
    if flag is not None and not isinstance(flag, PrecisionFlag):
        raise TypeError(f"flag must be a dyq.PrecisionFlag or None, got {type(flag).__name__}")
    check_method(method)
    calibration_bits = check_calibration_bits(calibration_bits)
    if method in CALIBRATED_METHODS and calibration is None:
        raise ValueError(f"method={method!r} needs calibration: a small batch of inputs (e.g. token ids "
                         "[batch, seq]) disjoint from the evaluation data")
    if method not in CALIBRATED_METHODS and calibration is not None:
        raise ValueError(f"calibration is only used by methods {CALIBRATED_METHODS}; method={method!r} takes none")
    if min_act_bits is not None and not isinstance(min_act_bits, Mapping):
        raise TypeError(f"min_act_bits must be a dict {{pattern: bits}}, e.g. {{'gate_proj': 8}}, got "
                        f"{type(min_act_bits).__name__} {min_act_bits!r}")
    floors = dict(min_act_bits or {})
    for pattern, bits in floors.items():
        _check_pattern(pattern, "min_act_bits")
        check_bits(bits, f"min_act_bits[{pattern!r}]")
    if not isinstance(fuse_norms, bool):
        raise TypeError(f"fuse_norms must be True or False, got {fuse_norms!r}")
    if skip is None:
        raise TypeError("skip must be layer-name patterns (a glob, a compiled regular expression, or a tuple of "
                        "them); pass skip=() to convert every layer, got None")
    skip = tuple(skip) if not isinstance(skip, (str, re.Pattern)) else (skip,)
    for pattern in skip:
        _check_pattern(pattern, "skip")
    # (the parameter itself: reading `weight` would run a spectral norm's power iteration)
    lazy = [name for name, module in model.named_modules()
            if isinstance(module._parameters.get("weight"), nn.parameter.UninitializedParameter)]
    if lazy:
        raise ValueError(f"{lazy[0]} is a lazy layer whose weight is not initialized yet: run one forward pass "
                         "with a sample input before quantize_model")
    report = QuantizationReport(group_size=group_size, method=method, model_bytes_before=_module_bytes(model))

    names: dict[int, list[str]] = {}
    modules: dict[int, nn.Module] = {}
    for name, module in model.named_modules(remove_duplicate=False):
        if isinstance(module, DyQLinear):
            if name not in report.already_quantized:
                report.already_quantized.append(name)
        elif isinstance(module, nn.Linear) or is_transposed_linear(module):
            names.setdefault(id(module), []).append(name)
            modules[id(module)] = module

    if not modules and not report.already_quantized:
        warnings.warn(f"dyq.quantize_model: {type(model).__name__} holds no nn.Linear; nothing to convert",
                      stacklevel=2)
    # A skip pattern of the caller's that names no linear layer quantizes what it was meant to keep (a
    # misspelt name); warned rather than refused, as one skip list may serve several architectures. The
    # default ("lm_head") is quiet on models without one (an encoder).
    all_names = [n for key in modules for n in names[key]] + report.already_quantized
    unused_skip = [p for p in skip if skip != DEFAULT_SKIP and not any(_matches(n, (p,)) for n in all_names)]
    if unused_skip and all_names:
        warnings.warn(f"dyq.quantize_model: skip patterns {[getattr(p, 'pattern', p) for p in unused_skip]} match no "
                      f"linear layer (such as {all_names[0]!r}); patterns are globs against each layer's full name "
                      "and its last component, or compiled regular expressions", stacklevel=2)

    coupled = weight_readers(model)

    def skip_reason(key: int) -> str | None:
        """Why the layer ``key`` stays as it is, or None to convert it."""
        if key in coupled:
            return f"its parent {coupled[key]} reads its weight without calling it"
        matched = next((n for n in names[key] if _matches(n, skip)), None)
        if matched is None:
            return None
        return "matches a skip pattern" + (f" (as {matched})" if matched != names[key][0] else "")

    # A floor whose pattern reaches no converted layer would do nothing, silently (a misspelt name): refused
    # here, before any method changes the model.
    converted_names = [n for key in modules if skip_reason(key) is None for n in names[key]]
    idle = [pattern for pattern in floors if not any(_matches(n, (pattern,)) for n in converted_names)]
    if idle:
        example = f" (such as {converted_names[0]!r})" if converted_names else ""
        raise ValueError(f"min_act_bits: {idle} match no layer that is converted{example}; patterns are matched "
                         "like skip's, against each layer's full name and its last component")

    # What is converted becomes a plain nn.Linear first (the weight methods read and change its weight): a
    # Conv1D the nn.Linear it computes, a weight computed on access (weight_norm, spectral_norm) its value.
    for key, module in modules.items():
        if skip_reason(key) is None:
            as_plain_linear(module)

    # Every weight to convert is checked before any method changes the model or a layer is converted: an
    # error from the middle of the loop below would name no layer and leave the model half converted.
    non_finite = [names[key][0] for key, module in modules.items() if skip_reason(key) is None
                  and not module.weight.is_meta and not torch.isfinite(module.weight).all()]
    if non_finite:
        raise ValueError(f"layers {non_finite} have NaN or Inf weights: static INT4 weights must be finite (fix the "
                         "checkpoint, or keep those layers in float with skip=...); no layer was converted")

    channel_weight: dict[int, torch.Tensor | None] = {}
    hessians: dict[int, torch.Tensor] = {}
    if method == "awq":
        channel_weight = awq_prepare(model, calibration, group_size, calibration_bits,
                                     targets=lambda linear: id(linear) in modules and skip_reason(id(linear)) is None)
    elif method == "gptq":
        hessians = collect_hessians(model, calibration)

    for key, linear in modules.items():
        first, *others = names[key]
        reason = skip_reason(key)
        if reason is not None:
            report.skipped[first] = reason
            continue
        report.linear_bytes_before += _tensor_bytes(linear.parameters())
        if method == "rtn":
            DyQLinear.convert_in_place(linear, group_size=group_size, act_bits=act_bits, flag=flag)
        else:
            weight = linear.weight.detach()
            if key in hessians:
                codes, scales = gptq_weight(weight, hessians.pop(key), group_size)
                qweight = reference.pack_int4(_even_columns(codes))
            else:  # "mse", "awq", and a "gptq" layer the calibration never reached: the clipping search
                qweight, scales = packed_clipped_weight(_even_columns(weight), group_size,
                                                        _even_columns(channel_weight.get(key)))
            DyQLinear.convert_in_place(linear, group_size=group_size, act_bits=act_bits, flag=flag, quantize=False)
            linear.qweight.copy_(qweight)
            linear.scales.copy_(scales)
        linear.weight_method = method
        floor = _floor_of(names[key], floors)
        if floor is not None:
            linear.set_min_act_bits(floor)
            report.min_act_bits[first] = floor
        report.linear_bytes_after += linear.weight_bytes()
        report.converted.append(first)
        if others:
            report.shared[first] = others

    route_encoder_layers_through_modules(model)
    if fuse_norms:
        report.fused_norms, report.norms_left = fuse_rms_norms(model)
    # A converted LM head no longer shares the input embedding's float weight: a Hugging Face config that
    # still ties them would make save_pretrained's checkpoint tie them again when it is loaded, onto an INT4
    # head that has no weight to tie.
    head = model.get_output_embeddings() if callable(getattr(model, "get_output_embeddings", None)) else None
    config = getattr(model, "config", None)
    if isinstance(head, DyQLinear) and getattr(config, "tie_word_embeddings", False):
        config.tie_word_embeddings = False
    report.model_bytes_after = _module_bytes(model)
    _describe_for_save_pretrained(model, skip, floors)
    return report


def _transformers_model(model: nn.Module) -> bool:
    """Whether ``model`` is a transformers ``PreTrainedModel`` (without importing transformers for it)."""
    transformers = sys.modules.get("transformers")
    base = getattr(transformers, "PreTrainedModel", None) if transformers is not None else None
    return base is not None and isinstance(model, base)


def _describe_for_save_pretrained(model: nn.Module, skip: tuple = DEFAULT_SKIP, floors: Mapping | None = None) -> None:
    """Set a transformers model's ``config.quantization_config`` to the :class:`dyq.DyQConfig` that
    ``from_pretrained`` rebuilds its DyQLinear layers from, so that ``save_pretrained`` writes a checkpoint
    that loads back (without one, ``from_pretrained`` gives the INT4 layers float weights of random values,
    with only a load report to say so). ``skip`` and ``floors`` (patterns, as ``quantize_model`` took them)
    stand in the config where they select exactly the layers that are in float and the floors each layer has;
    otherwise the layers' full names do. Where one config cannot describe the model (DyQLinear layers of
    several group sizes or weight methods), a dyq config already there is removed, with a
    warning that says how to save it instead. Other models, and transformers without dyq's quantizer
    (before 4.49), are left as they are."""
    config = getattr(model, "config", None)
    if config is None or not _transformers_model(model):
        return
    try:
        from .hf_quantizer import DyQConfig
        from .serialization import WEIGHT_METHOD_NAMES
    except ImportError:
        return
    from .linear import weight_readers

    layers = {name: module for name, module in model.named_modules() if isinstance(module, DyQLinear)}
    if not layers:
        return
    group_sizes = {layer.group_size for layer in layers.values()}
    methods = {getattr(layer, "weight_method", "rtn") for layer in layers.values()}
    obstacle = None
    if len(group_sizes) > 1:
        obstacle = f"its DyQLinear layers have group sizes {sorted(group_sizes)}"
    elif len(methods) > 1:
        obstacle = f"its DyQLinear layers were quantized by methods {sorted(methods)}"
    if obstacle is not None:
        if isinstance(getattr(config, "quantization_config", None), DyQConfig):
            del config.quantization_config
        warnings.warn(f"dyq.quantize_model: {type(model).__name__}.save_pretrained cannot describe this model "
                      f"({obstacle}) in one quantization_config; save it with dyq.save_quantized(model, dir) and "
                      "load it with dyq.load_quantized(model, dir)", stacklevel=3)
        return
    readers = weight_readers(model)
    in_float = [name for name, module in model.named_modules()
                if (type(module) is nn.Linear or is_transposed_linear(module)) and id(module) not in readers]
    patterns = list(skip) if all(isinstance(p, str) for p in skip) else None
    if patterns is None or any(_matches(name, tuple(patterns)) for name in layers) \
            or not all(_matches(name, tuple(patterns)) for name in in_float):
        patterns = in_float
    no_floor = DyQLinear.min_act_bits

    def floor_by_layer(patterns: Mapping) -> dict[str, int]:
        """Each layer's floor as ``patterns`` give it, where it has one."""
        found = {name: _floor_of((name,), patterns) for name in layers}
        return {name: bits for name, bits in found.items() if bits is not None and bits > no_floor}

    actual = {name: layer.min_act_bits for name, layer in layers.items() if layer.min_act_bits > no_floor}
    given = dict(floors or {})
    exact = all(isinstance(p, str) for p in given) and floor_by_layer(given) == actual
    min_act_bits = given if exact else actual
    flag = next((layer.flag for layer in layers.values() if layer.flag is not None), None)
    act_bits = flag.bits if flag is not None else next(iter(layers.values())).act_bits
    if len({id(layer.flag) if layer.flag is not None else layer.act_bits for layer in layers.values()}) > 1:
        warnings.warn(f"dyq.quantize_model: the DyQLinear layers of {type(model).__name__} read different flags (or "
                      f"none): from_pretrained of what save_pretrained writes binds them all to one flag at {act_bits} "
                      "bits, as dyq.bind_flag(model, flag) would here", stacklevel=3)
    config.quantization_config = DyQConfig(group_size=group_sizes.pop(), act_bits=act_bits,
                                           modules_to_not_convert=patterns,
                                           weight_method=WEIGHT_METHOD_NAMES[methods.pop()],
                                           min_act_bits=min_act_bits or None,
                                           rotation=getattr(model, "dyq_rotation", None))


def _even_columns(t: torch.Tensor | None) -> torch.Tensor | None:
    """An odd in_features gets the one zero column that DyQLinear stores (docs/numerics.md section 4)."""
    if t is None or t.shape[-1] % 2 == 0:
        return t
    return nn.functional.pad(t, (0, 1))


def model_flag(model: nn.Module) -> PrecisionFlag:
    """The one :class:`PrecisionFlag` the DyQLinear layers of ``model`` read (after ``copy.deepcopy`` or
    ``torch.load`` of a whole model, the copy's own flag); an error if the layers have none or several."""
    flags = {id(layer.flag): layer.flag for layer in dyq_layers(model)}
    if None in (f for f in flags.values()) or len(flags) != 1:
        unbound = sum(layer.flag is None for layer in dyq_layers(model))
        raise ValueError(f"the DyQLinear layers of {type(model).__name__} are bound to {len(flags) - (unbound > 0)} "
                         f"flags ({unbound} layers to none); bind one with dyq.bind_flag(model, flag)")
    return next(iter(flags.values()))


def dyq_layers(model: nn.Module) -> list[DyQLinear]:
    """The DyQLinear layers of ``model``; an error if there are none (a forgotten quantize_model)."""
    layers = [m for m in model.modules() if isinstance(m, DyQLinear)]
    if not layers:
        raise ValueError(f"{type(model).__name__} contains no DyQLinear layer; run dyq.quantize_model first")
    return layers


def set_precision(module_or_model: nn.Module, bits: int) -> int:
    """Set the activation bit-width of every DyQLinear in ``module_or_model``; returns how many layers.

    Layers bound to a PrecisionFlag get the value through their flag (one write per distinct flag).
    """
    bits = check_bits(bits)
    layers = dyq_layers(module_or_model)
    for layer in layers:
        layer.set_precision(bits)
    return len(layers)


def bind_flag(module_or_model: nn.Module, flag: PrecisionFlag | None) -> int:
    """Make every DyQLinear read its bit-width from ``flag`` (``None`` unbinds); returns how many layers."""
    layers = dyq_layers(module_or_model)
    for layer in layers:
        layer.bind_flag(flag)
    return len(layers)
