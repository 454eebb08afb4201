"""Registers dyq's quantizer with transformers as soon as both are imported, in either order, without
importing transformers with dyq: ``from_pretrained`` of a dyq checkpoint needs the "dyq" quantization method
registered, and a program that imported dyq and then loads one must not get float layers of random weights
(transformers skips a quantization method it does not know, with a warning)."""
from __future__ import annotations

import importlib.abc
import importlib.util
import sys


def _register() -> None:
    try:
        from . import hf_quantizer  # noqa: F401  (registers DyQConfig and DyQHfQuantizer on import)
    except ImportError:
        pass  # a transformers without custom-quantizer hooks: dyq.DyQConfig says so where it is used


class _RegisterAfterTransformers(importlib.abc.MetaPathFinder):
    """Finds transformers through the other finders, and registers dyq once its module has run."""

    def find_spec(self, name, path=None, target=None):
        if name != "transformers":
            return None
        sys.meta_path.remove(self)  # once: the other finders locate the package
        spec = importlib.util.find_spec(name)
        if spec is not None and spec.loader is not None and hasattr(spec.loader, "exec_module"):
            exec_module = spec.loader.exec_module

            def exec_then_register(module):
                exec_module(module)
                _register()

            spec.loader.exec_module = exec_then_register
        return spec


def register_with_transformers() -> None:
    if "transformers" in sys.modules:
        _register()
    elif not any(isinstance(finder, _RegisterAfterTransformers) for finder in sys.meta_path):
        sys.meta_path.insert(0, _RegisterAfterTransformers())
