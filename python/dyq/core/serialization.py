"""Saving and loading quantized models: the weights as safetensors, the quantization state beside them.

A directory written by :func:`save_quantized` holds

* ``model.safetensors``: the model's state dict (INT4 ``qweight``, fp32 ``scales``, biases and every other
  parameter), written by ``safetensors.torch.save_model`` so that tied tensors are stored once;
* ``dyq_config.json``: what the weights alone do not say: the format version, the weight method, the
  rotation (``None``, or ``{"kind": "hadamard", "seed": s, "construction": c}`` after
  :func:`dyq.rotation.rotate_llama`: the folded rotations are in the weights, the online one is rebuilt from
  the seed and the Hadamard construction, 1 when a file does not say), the flag's bit-width
  and, per converted layer, its group size, activation bit-width and shape.

:func:`load_quantized` rebuilds the DyQLinear layers of a freshly built model (or of a Hugging Face
config's model) from that description, loads the tensors into them and binds them to one new
:class:`~dyq.PrecisionFlag` holding the saved bit-width.
"""
from __future__ import annotations

import json
import os
from typing import Any

import torch
from torch import nn

from ..control.flag import PrecisionFlag
from .linear import DyQLinear, as_plain_linear, is_transposed_linear, route_encoder_layers_through_modules
from .norm import fuse_rms_norms
from .precision import check_bits, check_group_size

CONFIG_NAME = "dyq_config.json"
WEIGHTS_NAME = "model.safetensors"
FORMAT_VERSION = 1
# The name each weight method (quantize_model's ``method``) is saved under; all write the symmetric INT4
# format of docs/numerics.md section 1, so any of them loads the same way.
WEIGHT_METHOD_NAMES = {"rtn": "rtn_int4_symmetric", "mse": "mse_clip_int4_symmetric", "awq": "awq_int4_symmetric",
                      "gptq": "gptq_int4_symmetric"}
WEIGHT_METHODS = tuple(WEIGHT_METHOD_NAMES.values())


def _safetensors():
    try:
        import safetensors.torch
    except ImportError as err:  # pragma: no cover - safetensors comes with transformers
        raise ImportError("dyq.save_quantized / load_quantized need the safetensors package") from err
    return safetensors.torch


def quantization_state(model: nn.Module) -> dict[str, Any]:
    """The description :func:`save_quantized` writes to ``dyq_config.json``."""
    layers, flags = {}, {}
    for name, module in model.named_modules():
        if isinstance(module, DyQLinear):
            layers[name] = {"in_features": module.in_features, "out_features": module.out_features,
                            "bias": module.bias is not None, "group_size": module.group_size,
                            "act_bits": module.act_bits}
            if module.min_act_bits > 2:
                layers[name]["min_act_bits"] = module.min_act_bits
            if module.flag is not None:
                flags[id(module.flag)] = module.flag
    if not layers:
        raise ValueError(f"{type(model).__name__} contains no DyQLinear layer; run dyq.quantize_model first")
    if len(flags) > 1:
        raise ValueError(f"the DyQLinear layers of {type(model).__name__} are bound to {len(flags)} different "
                         "flags; a saved model has one")
    flag = next(iter(flags.values()), None)
    methods = sorted({m.weight_method for m in model.modules() if isinstance(m, DyQLinear)})
    if len(methods) > 1:
        raise ValueError(f"the DyQLinear layers of {type(model).__name__} were quantized by several methods "
                         f"({methods}); a saved model has one")
    return {"format": "dyq", "version": FORMAT_VERSION, "weight_method": WEIGHT_METHOD_NAMES[methods[0]],
            "rotation": getattr(model, "dyq_rotation", None),
            "model_class": type(model).__name__, "flag_bits": flag.bits if flag is not None else None,
            "layers": layers}


def save_quantized(model: nn.Module, directory: str | os.PathLike) -> None:
    """Write a quantized model to ``directory`` (created if needed): ``model.safetensors`` and
    ``dyq_config.json``."""
    state = quantization_state(model)
    os.makedirs(directory, exist_ok=True)
    _safetensors().save_model(model, os.fspath(os.path.join(directory, WEIGHTS_NAME)))
    with open(os.path.join(directory, CONFIG_NAME), "w", encoding="utf-8") as f:
        json.dump(state, f, indent=2)
        f.write("\n")


def read_quantization_state(directory: str | os.PathLike) -> dict[str, Any]:
    """``dyq_config.json`` of ``directory``, checked."""
    path = os.path.join(directory, CONFIG_NAME)
    try:
        with open(path, encoding="utf-8") as f:
            state = json.load(f)
    except FileNotFoundError:
        raise FileNotFoundError(f"{os.fspath(directory)!r} holds no {CONFIG_NAME}; was it written by "
                                "dyq.save_quantized?") from None
    except json.JSONDecodeError as err:
        raise ValueError(f"{path!r} is not valid JSON: {err}") from None
    if not isinstance(state, dict) or state.get("format") != "dyq":
        raise ValueError(f"{path!r} is not a dyq quantization config")
    if state.get("version") != FORMAT_VERSION:
        raise ValueError(f"{path!r} has format version {state.get('version')!r}; this dyq reads {FORMAT_VERSION}")
    if state.get("weight_method") not in WEIGHT_METHODS:
        raise ValueError(f"{path!r} uses weight method {state.get('weight_method')!r}; this dyq knows {WEIGHT_METHODS}")
    rotation = state.get("rotation")
    if rotation is not None:
        from ..rotation import HADAMARD_CONSTRUCTIONS

        if not (isinstance(rotation, dict) and rotation.get("kind") == "hadamard"
                and isinstance(rotation.get("seed"), int) and rotation["seed"] >= 0
                and rotation.get("construction", 1) in HADAMARD_CONSTRUCTIONS):
            raise ValueError(f"{path!r} uses rotation {rotation!r}; this dyq knows None and "
                             "{'kind': 'hadamard', 'seed': <int >= 0>, 'construction': "
                             f"{' or '.join(map(str, HADAMARD_CONSTRUCTIONS))}}} (dyq.rotation.rotate_llama)")
    for name, layer in state["layers"].items():
        check_group_size(layer["group_size"])
        check_bits(layer["act_bits"], f"layers[{name!r}].act_bits")
        check_bits(layer.get("min_act_bits", 2), f"layers[{name!r}].min_act_bits")
    if state["flag_bits"] is not None:
        check_bits(state["flag_bits"], "flag_bits")
    return state


def transformers_model_class(config, *fallbacks: str):
    """The transformers class that ``config.architectures`` names, else the first of ``fallbacks`` that
    transformers has; None if neither."""
    import transformers

    names = [*(getattr(config, "architectures", None) or []), *fallbacks]
    return next((getattr(transformers, name) for name in names if name and hasattr(transformers, name)), None)


def from_pretrained_dtype(dtype) -> dict[str, Any]:
    """``from_pretrained``'s dtype argument (a torch dtype or "auto", the checkpoint's own) under the name the
    installed transformers takes: ``dtype`` from 4.56, ``torch_dtype`` before."""
    import transformers
    from packaging.version import Version

    return {"dtype" if Version(transformers.__version__) >= Version("4.56") else "torch_dtype": dtype}


def _model_from_config(config, state: dict[str, Any]) -> nn.Module:
    """A Hugging Face model built from its config (no download): the class its ``architectures`` names,
    or else the class the saved model had; in eval mode, as ``from_pretrained`` returns it (a model built
    from a config trains, and GPT-2's dropout would then change every output)."""
    architectures = (getattr(config, "architectures", None) or []) + [state.get("model_class") or ""]
    cls = transformers_model_class(config, state.get("model_class") or "")
    if cls is None:
        raise ValueError("load_quantized got a config whose `architectures` names no transformers class "
                         f"({architectures!r}); pass the model built from it instead")
    return cls(config).eval()


def prepare_quantized_layers(model: nn.Module, state: dict[str, Any], flag: PrecisionFlag | None) -> None:
    """Turn the Linear layers that ``state`` lists into DyQLinear layers of the saved geometry (their
    contents are overwritten by the load that follows). A layer that is a DyQLinear already (a model
    quantized before the load) must have the saved geometry, and takes the saved precision like the others:
    its act_bits, the load's flag and its floor."""
    found = dict(model.named_modules())
    method = next(m for m, saved in WEIGHT_METHOD_NAMES.items() if saved == state["weight_method"])
    for name, layer in state["layers"].items():
        module = found.get(name)
        if isinstance(module, DyQLinear):
            here = (module.in_features, module.out_features, module.bias is not None, module.group_size)
            saved = (layer["in_features"], layer["out_features"], layer["bias"], layer["group_size"])
            if here != saved:
                raise ValueError(f"layer {name!r} is a DyQLinear of (in_features, out_features, bias, group_size) "
                                 f"{here} here but was saved as {saved}")
            module.act_bits = layer["act_bits"]
            module.bind_flag(flag)
            module.weight_method = method
            module.set_min_act_bits(layer.get("min_act_bits", 2))
            continue
        if is_transposed_linear(module):  # its nn.Linear shape, for the check below
            as_plain_linear(module)
        if not isinstance(module, nn.Linear):
            raise ValueError(f"the saved model has a DyQLinear at {name!r}, but this model has "
                             f"{type(module).__name__ if module is not None else 'nothing'} there")
        if (module.in_features, module.out_features, module.bias is not None) != (
                layer["in_features"], layer["out_features"], layer["bias"]):
            raise ValueError(f"layer {name!r} is Linear({module.in_features}, {module.out_features}, "
                             f"bias={module.bias is not None}) here but was saved as Linear({layer['in_features']}, "
                             f"{layer['out_features']}, bias={layer['bias']})")
        DyQLinear.convert_in_place(module, group_size=layer["group_size"], act_bits=layer["act_bits"], flag=flag,
                                   quantize=False)
        module.weight_method = method
        module.set_min_act_bits(layer.get("min_act_bits", 2))
    route_encoder_layers_through_modules(model)


def load_quantized(model_or_config, directory: str | os.PathLike) -> nn.Module:
    """Load what :func:`save_quantized` wrote into ``model_or_config`` (a model of the same architecture,
    freshly built, or a Hugging Face config to build it from) and return the model: its quantized layers
    are rebuilt, their tensors loaded, and all of them bound to one new PrecisionFlag at the saved bits."""
    state = read_quantization_state(directory)
    model = model_or_config if isinstance(model_or_config, nn.Module) else _model_from_config(model_or_config, state)
    flag = PrecisionFlag(state["flag_bits"]) if state["flag_bits"] is not None else None
    with torch.no_grad():
        prepare_quantized_layers(model, state, flag)
        if state["rotation"] is not None:
            # The rotation is in the saved weights but for down_proj's run-time input rotation, rebuilt from
            # its seed; the rotated LM head differs from the embedding, so they are untied first.
            from ..rotation import attach_online_rotations, untie_lm_head

            untie_lm_head(model)
            # A file from before the construction was recorded used construction 1 (prime fields only).
            attach_online_rotations(model, state["rotation"]["seed"], state["rotation"].get("construction", 1))
            model.dyq_rotation = dict(state["rotation"])
    missing, unexpected = _safetensors().load_model(model, os.path.join(directory, WEIGHTS_NAME), strict=False)
    if missing or unexpected:
        raise ValueError(f"the saved weights do not fit this model: missing {sorted(missing)[:5]}, "
                         f"unexpected {sorted(unexpected)[:5]}")
    fuse_rms_norms(model)  # as quantize_model does (its norms' weights are loaded now)
    return model
