"""dyq: vision-language-action policies on static INT4 weights with per-step activation precision.

Quick start::

    import dyq
    report = dyq.quantize_model(model)          # nn.Linear -> DyQLinear (INT4 weights)
    dyq.set_precision(model, 4)                 # W4A4 for the next steps

Layout: ``dyq.core`` (kernel API), ``dyq.control`` (dispatcher, flag, runtime), ``dyq.apps`` (command
line, demo); every public name is importable from ``dyq`` itself.
"""
from .control.dispatch import DispatchConfig, Hysteresis, KinematicDispatcher, ProxyWeight
from .control.flag import PrecisionFlag, capture_cuda_graph
from .control.runtime import DyQRuntime, StepStats, force_precision
from .core import ops, reference
from .core.cpu import cpu_gemm_kernel, cpu_info
from .core.export import export
from .core.linear import DyQLinear
from .core.norm import DyQRMSNorm, fuse_rms_norms
from .core.precision import FALLBACK_BITS, GROUP_SIZES, VALID_BITS
from .core.quantize import QuantizationReport, bind_flag, model_flag, quantize_model, set_precision
from .core.serialization import load_quantized, save_quantized
from .errors import FileFormatError

__version__ = "0.1.0"

from .core.hf_registration import register_with_transformers as _register_with_transformers  # noqa: E402

_register_with_transformers()


def __getattr__(name):
    # The Hugging Face quantizer registers itself with transformers on first use (transformers is optional).
    if name in ("DyQConfig", "DyQHfQuantizer"):
        from .core import hf_quantizer

        return getattr(hf_quantizer, name)
    raise AttributeError(f"module 'dyq' has no attribute {name!r}")

__all__ = [
    "DispatchConfig",
    "DyQRuntime",
    "Hysteresis",
    "KinematicDispatcher",
    "StepStats",
    "force_precision",
    "DyQLinear",
    "DyQRMSNorm",
    "FALLBACK_BITS",
    "FileFormatError",
    "GROUP_SIZES",
    "ProxyWeight",
    "PrecisionFlag",
    "capture_cuda_graph",
    "QuantizationReport",
    "VALID_BITS",
    "bind_flag",
    "cpu_gemm_kernel",
    "cpu_info",
    "export",
    "fuse_rms_norms",
    "load_quantized",
    "model_flag",
    "ops",
    "quantize_model",
    "reference",
    "save_quantized",
    "set_precision",
]
