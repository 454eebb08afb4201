"""The Python view of the precision registry (``csrc/common/precision.h``).

The activation bit-widths and group sizes are read from the compiled extension, so that the flag, the
dispatcher, the command line and the benchmarks iterate over exactly the widths the kernels implement.
:mod:`dyq.core.reference` keeps formulas of its own (it is the spec the registry is tested against).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch  # noqa: F401  (loads the libraries _C links against)

from .. import _C


class ActivationTraits(NamedTuple):
    """What one registered activation width is: ``bits``, ``quantized`` (False for the BF16 fallback),
    ``codes_per_byte`` and ``levels`` (2^b - 1 of Eq. 2; both 0 for the fallback)."""

    bits: int
    quantized: bool
    codes_per_byte: int
    levels: int


VALID_BITS: tuple[int, ...] = tuple(_C.ACTIVATION_BITS)
"""Activation bit-widths, ascending: every one but :data:`FALLBACK_BITS` quantizes activations."""

FALLBACK_BITS: int = _C.FALLBACK_BITS
"""The unquantized (BF16) fallback width, the paper's 16."""

QUANTIZED_BITS: tuple[int, ...] = tuple(b for b in VALID_BITS if b != FALLBACK_BITS)

GROUP_SIZES: tuple[int, ...] = tuple(_C.GROUP_SIZES)
"""Group sizes along K of the INT4 weights and of the activation quantization."""

TRAITS: dict[int, ActivationTraits] = {
    bits: ActivationTraits(bits, bits != FALLBACK_BITS, codes_per_byte, levels)
    for bits, codes_per_byte, levels in _C.ACTIVATION_TRAITS
}


def spelled_out(values) -> str:
    """``(2, 4, 8, 16)`` -> ``"2, 4, 8 or 16"``, as the extension's error messages write lists."""
    values = [str(v) for v in values]
    return values[0] if len(values) == 1 else ", ".join(values[:-1]) + " or " + values[-1]


def check_bits(bits, name: str = "bits") -> int:
    """Return ``bits`` as an int if it is one of :data:`VALID_BITS`, else raise naming ``name``."""
    if isinstance(bits, (bool, np.bool_)) or not isinstance(bits, (int, np.integer)):
        raise TypeError(f"{name} must be an int in {VALID_BITS}, got {type(bits).__name__} {bits!r}")
    bits = int(bits)
    if bits not in VALID_BITS:
        raise ValueError(f"{name} must be one of {VALID_BITS}, got {bits}")
    return bits


def check_group_size(group_size) -> int:
    """Return ``group_size`` as an int if it is one of :data:`GROUP_SIZES`, else raise naming it (a float such
    as 64.0 compares equal to 64, but no tensor shape takes it)."""
    if isinstance(group_size, (bool, np.bool_)) or not isinstance(group_size, (int, np.integer)):
        raise TypeError(f"group_size must be an int in {GROUP_SIZES}, got {type(group_size).__name__} {group_size!r}")
    if group_size not in GROUP_SIZES:
        raise ValueError(f"group_size must be one of {GROUP_SIZES}, got {group_size!r}")
    return int(group_size)
