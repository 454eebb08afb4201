"""Argument checks shared by the analysis modules: every error names the argument and what was expected."""
from __future__ import annotations

import math

import numpy as np


def real(value, name: str, *, minimum: float | None = None, strict: bool = False) -> float:
    """A finite real number, optionally >= minimum (> minimum with strict)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a real number, got {type(value).__name__} {value!r}")
    try:
        value = float(value)
    except OverflowError:  # a Python int beyond float64
        raise ValueError(f"{name} must be finite, got an int beyond float64's range") from None
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    if minimum is not None and (value <= minimum if strict else value < minimum):
        raise ValueError(f"{name} must be {'>' if strict else '>='} {minimum}, got {value}")
    return value


def integer(value, name: str, minimum: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an int >= {minimum}, got {type(value).__name__} {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {value}")
    return int(value)


def vector(value, name: str, *, min_length: int = 1, nonnegative: bool = False, allow_nan: bool = False) -> np.ndarray:
    """A 1-D float64 array of at least min_length finite entries (NaN allowed with allow_nan)."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a 1-D sequence of real numbers, got {type(value).__name__}") from None
    if array.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {array.shape}")
    if array.size < min_length:
        raise ValueError(f"{name} must have at least {min_length} entries, got {array.size}")
    checked = array[~np.isnan(array)] if allow_nan else array
    if not np.all(np.isfinite(checked)):
        raise ValueError(f"{name} must be finite{' (NaN marks undefined)' if allow_nan else ''}, got {array}")
    if nonnegative and np.any(checked < 0):
        raise ValueError(f"{name} must be >= 0, got minimum {checked.min()}")
    return array


def same_length(arrays: dict[str, np.ndarray]) -> int:
    lengths = {name: len(array) for name, array in arrays.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(f"{' and '.join(lengths)} must have the same length, got {lengths}")
    return next(iter(lengths.values()))
