"""dyq: vision-language-action policies on static INT4 weights with per-step activation precision.

Quick start::

    import dyq
    report = dyq.quantize_model(model)          # nn.Linear -> DyQLinear (INT4 weights)
    dyq.set_precision(model, 4)                 # W4A4 for the next steps
"""
from . import ops, reference
from .dispatch import DispatchConfig, Hysteresis, KinematicDispatcher
from .flag import VALID_BITS, PrecisionFlag
from .linear import DyQLinear
from .quantize import QuantizationReport, bind_flag, quantize_model, set_precision
from .runtime import DyQRuntime, StepStats, force_precision

__version__ = "0.1.0"

__all__ = [
    "DispatchConfig",
    "DyQRuntime",
    "Hysteresis",
    "KinematicDispatcher",
    "StepStats",
    "force_precision",
    "DyQLinear",
    "PrecisionFlag",
    "QuantizationReport",
    "VALID_BITS",
    "bind_flag",
    "ops",
    "quantize_model",
    "reference",
    "set_precision",
]
