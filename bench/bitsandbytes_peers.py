"""bitsandbytes' quantized linear layers as benchmark peers: the two that Hugging Face users load with
``load_in_4bit`` (NF4, blocks of 64, bf16 compute) and ``load_in_8bit`` (LLM.int8(), outliers above 6.0 kept in
16 bits), built from one bf16 weight on its device. bitsandbytes is optional: without it, or where it cannot
build a layer, the benchmark goes on without these columns and records why.
"""
from __future__ import annotations

import os
from typing import Callable

import torch

PEERS = ("bnb_nf4", "bnb_int8")
# Each peer's own input dtype: NF4 computes in bf16 here; LLM.int8() quantizes fp16 (it casts a bf16 input).
INPUT_DTYPES = {"bnb_nf4": torch.bfloat16, "bnb_int8": torch.float16}
INT8_OUTLIER_THRESHOLD = 6.0  # transformers' BitsAndBytesConfig default (llm_int8_threshold)


def bitsandbytes_version() -> str | None:
    try:
        import bitsandbytes
    except Exception:  # noqa: BLE001  (not installed, or not importable here)
        return None
    return bitsandbytes.__version__


def bitsandbytes_layers(weight: torch.Tensor,
                        peers=PEERS) -> dict[str, Callable[[torch.Tensor], torch.Tensor]] | str:
    """{peer: layer} of each of ``peers`` for ``weight`` ([N, K], bf16) on ``weight``'s device, or why
    there are none."""
    # No downloads at run time: bitsandbytes' CPU backend would otherwise ask the Hub for a kernel.
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    # A peer that cannot run here (not installed, or built for another CUDA) leaves the benchmark going: any
    # error becomes the reason recorded in its JSON.
    try:
        import bitsandbytes as bnb
    except ImportError:
        return "bitsandbytes is not installed"
    except Exception as error:  # noqa: BLE001
        return f"bitsandbytes does not import: {type(error).__name__}: {error}"
    n, k = weight.shape
    device = weight.device
    def nf4():
        layer = bnb.nn.Linear4bit(k, n, bias=False, compute_dtype=torch.bfloat16, quant_type="nf4")
        layer.weight = bnb.nn.Params4bit(weight.detach().to("cpu", torch.bfloat16).clone(), requires_grad=False,
                                         quant_type="nf4")
        return layer

    def int8():
        layer = bnb.nn.Linear8bitLt(k, n, bias=False, has_fp16_weights=False, threshold=INT8_OUTLIER_THRESHOLD)
        layer.weight = bnb.nn.Int8Params(weight.detach().to("cpu", torch.bfloat16).clone(), requires_grad=False,
                                         has_fp16_weights=False)
        return layer

    builders = {"bnb_nf4": nf4, "bnb_int8": int8}
    try:  # moving a layer to its device quantizes its weight
        layers = {peer: builders[peer]().to(device).eval() for peer in peers}
    except Exception as error:  # noqa: BLE001
        return f"bitsandbytes {bnb.__version__} cannot build its layers on {device.type}: {type(error).__name__}: {error}"
    return layers


def statistics_bytes(layer: torch.nn.Module) -> int:
    """Bytes a bitsandbytes layer holds beside its weight parameter, which are no parameter or buffer of
    the module: NF4's block absmax (itself quantized, with a state of its own), LLM.int8()'s row scales."""
    weight = layer.weight
    state = getattr(weight, "quant_state", None)
    tensors = [getattr(weight, "SCB", None)]
    if state is not None:
        tensors += [state.absmax, getattr(getattr(state, "state2", None), "absmax", None)]
    return sum(t.nbytes for t in tensors if isinstance(t, torch.Tensor))


def model_bytes(model: torch.nn.Module) -> int:
    """Bytes of the model's parameters and buffers, each tensor once (a tied weight is one), and of the
    statistics of its bitsandbytes layers."""
    tensors = {id(t): t for t in [*model.parameters(), *model.buffers()]}
    peers = [m for m in model.modules() if type(m).__module__.startswith("bitsandbytes")]
    return sum(t.numel() * t.element_size() for t in tensors.values()) + sum(statistics_bytes(m) for m in peers)


def replace_linear_layers(model: torch.nn.Module, peer: str, skip: tuple[str, ...] = ("lm_head",)) -> int:
    """Put the ``peer`` layer in place of every bias-free ``nn.Linear`` of ``model`` whose name does not end
    in one of ``skip``, as transformers' ``load_in_4bit`` / ``load_in_8bit`` do (the LM head kept); returns
    how many. Raises RuntimeError where bitsandbytes cannot build its layers."""
    targets = [(name, module) for name, module in model.named_modules()
               if type(module) is torch.nn.Linear and not name.endswith(skip)]
    for name, linear in targets:
        if linear.bias is not None:
            raise ValueError(f"{name} has a bias, which these peers are built without")
        layers = bitsandbytes_layers(linear.weight.detach().to(torch.bfloat16), (peer,))
        if isinstance(layers, str):
            raise RuntimeError(layers)
        parent_name, _, child = name.rpartition(".")
        setattr(model.get_submodule(parent_name) if parent_name else model, child, layers[peer])
    return len(targets)
