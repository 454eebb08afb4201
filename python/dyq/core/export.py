"""``dyq.export``: a torch.export program of a quantized model that still reads its precision flag.

``torch.export.export`` of a model whose layers are bound to a :class:`~dyq.PrecisionFlag` records the flag's
int32 as a constant of the program. The program in memory shares it with the flag, but a saved program
(``torch.export.save``) and an AOTInductor package (``torch._inductor.aoti_compile_and_package``) keep their own
copy: they run at the width the flag held at export, whatever the dispatcher writes later. ``dyq.export``
makes the flag the program's first input instead, so that each call names the int32 it reads::

    program = dyq.export(model, (input_ids,))
    runner = torch._inductor.aoti_load_package(torch._inductor.aoti_compile_and_package(program))
    flag = dyq.model_flag(model)
    flag.bits = 4
    logits = runner(flag.tensor, input_ids)          # W4A4; the next write switches the next call

On CUDA the flag stays the pinned host int32 that the kernels read without a copy.
"""
from __future__ import annotations

from typing import Any

import torch
from torch import nn

from .quantize import dyq_layers, model_flag


class _FlagInput:
    """Stands in for the layers' PrecisionFlag while the model is traced: its tensor is the program's input."""

    __slots__ = ("tensor",)

    def __init__(self, tensor: torch.Tensor):
        self.tensor = tensor


class FlagAsInput(nn.Module):
    """``model`` with its flag's int32 as the first argument: ``FlagAsInput(model)(flag.tensor, *args)`` runs
    ``model(*args)`` with every layer bound to the model's flag reading ``flag.tensor`` instead."""

    def __init__(self, model: nn.Module):
        super().__init__()
        self.model = model
        model_flag(model)  # every layer bound to one flag, or a clear error
        # A plain list, not submodules: the layers are already the model's.
        self._bound = dyq_layers(model)

    def forward(self, flag: torch.Tensor, *args: Any, **kwargs: Any):
        saved = [layer.flag for layer in self._bound]
        stand_in = _FlagInput(flag)
        try:
            for layer in self._bound:
                layer.flag = stand_in
            return self.model(*args, **kwargs)
        finally:
            for layer, original in zip(self._bound, saved):
                layer.flag = original


def export(model: nn.Module, args: tuple = (), kwargs: dict | None = None, **options: Any):
    """``torch.export.export`` of ``model(*args, **kwargs)`` with the model's precision flag as the program's
    first input (:func:`dyq.model_flag`: every DyQLinear bound to one flag). Call the program, its
    ``module()``, a loaded copy or an AOTInductor package as ``program(flag.tensor, *args, **kwargs)``.
    ``options`` go to torch.export.export; ``dynamic_shapes``, where given, in the tuple form (one entry per
    positional argument of ``args``, the flag's is added)."""
    if not isinstance(args, tuple):
        raise TypeError(f"args must be a tuple of the model's positional arguments, got {type(args).__name__}")
    flag = model_flag(model)
    shapes = options.get("dynamic_shapes")
    if shapes is not None:
        if not isinstance(shapes, (tuple, list)):
            raise TypeError("dyq.export takes dynamic_shapes in the tuple form (one entry per positional argument "
                            f"of args), got {type(shapes).__name__}")
        options["dynamic_shapes"] = (None, tuple(shapes))  # forward(flag, *args): the flag, then args as one tuple
    return torch.export.export(FlagAsInput(model), (flag.tensor, *args), kwargs, **options)
