"""The kinematic dispatcher: picks the activation bit-width of every control step (paper Sec. IV).

Per control step the dispatcher sees the action the arm executed last (or its end-effector pose) and
returns the bit-width b*_t for the next step:

1. proxies (Sec. III-B, IV-A2): each kinematic proxy turns the motion into a normalized, windowed
   value. Motion Fineness M_t = 1 - ||a_t^xyz|| / mu_max, averaged over W_macro steps into M~_t;
   Angular Jerk J_t = ||a_t^rot - a_{t-1}^rot|| / nu_max, averaged over W_micro steps into J~_t.
   mu_max and nu_max are the ``percentile``-th percentiles of the last ``history`` samples;
2. fusion: S_t = max(0, sum_i w_i * value_i) with convex weights (lambda, 1 - lambda for the paper's pair);
3. allocation (Eq. 6), a ladder of (threshold, bits) rungs with ascending thresholds and strictly
   increasing bits: b^_t is the bits of the first rung with S_t <= threshold (Phi), and the 16-bit
   fallback above the top threshold (theta_fp);
4. hysteresis (Eq. 4 or Algorithm 1, or none): upgrades at once, downgrades after K steps of evidence.

Warm-up: until each proxy of non-zero weight is warm (its scale history holds ``warmup`` samples, its
scale is positive, its window holds a value), the target is 16 (full precision). A new width is one
rung of the ladder, a new proxy one class with ``update`` and ``value`` plus one entry of
:data:`PROXIES`. docs/dispatcher.md explains every rule in prose.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
from array import array
from bisect import bisect_left, insort
from collections import deque
from typing import Any

import numpy as np

from ..core.precision import FALLBACK_BITS, QUANTIZED_BITS, check_bits
from ..errors import FileFormatError

HYSTERESIS_MODES = ("window", "counter", "none")
INPUT_KINDS = ("action", "pose")

# Upper bounds of the sizes a config may ask for: far above any use (the paper's windows are 5 and 10
# steps, its history a few hundred), low enough that no config allocates more than a few MiB.
MAX_HISTORY = 1 << 16    # samples per percentile history (two arrays of doubles: 1 MiB)
MAX_WINDOW = 1 << 12     # steps of a proxy window or of the hysteresis delay K
MAX_ACTION_LENGTH = 1 << 12  # entries of an action or pose (the slices' bounds)


def _check_int(value, name: str, minimum: int, maximum: int | None = None) -> int:
    expected = f"an int >= {minimum}" if maximum is None else f"an int in [{minimum}, {maximum}]"
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be {expected}, got {type(value).__name__} {value!r}")
    if value < minimum or (maximum is not None and value > maximum):
        raise ValueError(f"{name} must be {expected}, got {value}")
    return int(value)


def _check_real(value, name: str) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a real number, got {type(value).__name__} {value!r}")
    try:
        value = float(value)
    except OverflowError:  # a Python int beyond float64
        raise ValueError(f"{name} must be finite, got an int beyond float64's range") from None
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    return value


def _check_slice(value, name: str) -> tuple[int, int]:
    if not isinstance(value, (tuple, list)) or len(value) != 2:
        raise TypeError(f"{name} must be a pair (start, stop) of ints, got {value!r}")
    start = _check_int(value[0], f"{name}[0]", 0, MAX_ACTION_LENGTH - 1)
    stop = _check_int(value[1], f"{name}[1]", 1, MAX_ACTION_LENGTH)
    if stop <= start:
        raise ValueError(f"{name} must satisfy 0 <= start < stop, got ({start}, {stop})")
    return (start, stop)


def _check_choice(value, name: str, choices: tuple[str, ...]) -> str:
    if value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}")
    return value


@dataclasses.dataclass(frozen=True)
class ProxyWeight:
    """One kinematic proxy in the fusion: its :data:`PROXIES` name, its weight w_i in S_t and the window
    (steps averaged into its smoothed value: W_macro for Motion Fineness, W_micro for Angular Jerk)."""

    name: str
    weight: float
    window: int

    def __post_init__(self):
        if self.name not in PROXIES:
            raise ValueError(f"proxy name must be one of {tuple(PROXIES)}, got {self.name!r}")
        object.__setattr__(self, "weight", _check_real(self.weight, f"{self.name} weight"))
        object.__setattr__(self, "window", _check_int(self.window, f"{self.name} window", 1, MAX_WINDOW))


# The paper's fusion: lambda weighs Motion Fineness over W_macro steps, 1 - lambda Angular Jerk over W_micro.
def paper_proxies(fusion_weight: float = 0.5, macro_window: int = 10, micro_window: int = 5) -> tuple[ProxyWeight, ...]:
    """(Motion Fineness, Angular Jerk) with weights (lambda, 1 - lambda) and windows (W_macro, W_micro)."""
    fusion_weight = _check_real(fusion_weight, "fusion_weight")
    if not 0.0 <= fusion_weight <= 1.0:
        raise ValueError(f"fusion_weight (lambda) must be in [0, 1], got {fusion_weight}")
    return (ProxyWeight("motion_fineness", fusion_weight, macro_window),
            ProxyWeight("angular_jerk", 1.0 - fusion_weight, micro_window))


def paper_ladder(theta_2_4: float = 0.15, theta_4_8: float = 0.3, theta_fp: float = 0.5) -> tuple[tuple[float, int], ...]:
    """The ladder of Eq. 6: 2 bits on [0, theta_2|4], 4 on (theta_2|4, theta_4|8], 8 on (theta_4|8, theta_fp]."""
    values = [_check_real(v, name) for v, name in ((theta_2_4, "theta_2_4"), (theta_4_8, "theta_4_8"), (theta_fp, "theta_fp"))]
    if not 0.0 <= values[0] <= values[1] <= values[2]:
        raise ValueError(
            "thresholds must satisfy 0 <= theta_2_4 <= theta_4_8 <= theta_fp, got "
            f"theta_2_4={values[0]}, theta_4_8={values[1]}, theta_fp={values[2]}"
        )
    return ((values[0], 2), (values[1], 4), (values[2], 8))


def _check_proxies(value) -> tuple[ProxyWeight, ...]:
    if not isinstance(value, (tuple, list)) or not value:
        raise TypeError(f"proxies must be a non-empty sequence of ProxyWeight, got {value!r}")
    proxies = tuple(p if isinstance(p, ProxyWeight) else ProxyWeight(**p) if isinstance(p, dict) else ProxyWeight(*p)
                    for p in value)
    names = [p.name for p in proxies]
    if len(set(names)) != len(names):
        raise ValueError(f"proxies must name each proxy once, got {names}")
    weights = [p.weight for p in proxies]
    if min(weights) < 0.0 or abs(sum(weights) - 1.0) > 1e-9:
        raise ValueError(f"proxy weights must be convex (each >= 0, summing to 1), got {weights}")
    return proxies


def _check_ladder(value) -> tuple[tuple[float, int], ...]:
    if not isinstance(value, (tuple, list)) or not value:
        raise TypeError(f"ladder must be a non-empty sequence of (threshold, bits) pairs, got {value!r}")
    ladder = []
    for i, rung in enumerate(value):
        if not isinstance(rung, (tuple, list)) or len(rung) != 2:
            raise TypeError(f"ladder[{i}] must be a pair (threshold, bits), got {rung!r}")
        threshold = _check_real(rung[0], f"ladder[{i}] threshold")
        bits = check_bits(rung[1], f"ladder[{i}] bits")
        if bits not in QUANTIZED_BITS:
            raise ValueError(f"ladder[{i}] bits must be a quantized width {QUANTIZED_BITS} (above the top "
                             f"threshold the {FALLBACK_BITS}-bit fallback applies), got {bits}")
        ladder.append((threshold, bits))
    thresholds, bits = [t for t, _ in ladder], [b for _, b in ladder]
    if thresholds[0] < 0.0 or any(a > b for a, b in zip(thresholds, thresholds[1:])):
        raise ValueError(f"ladder thresholds must be >= 0 and ascending, got {thresholds}")
    if any(a >= b for a, b in zip(bits, bits[1:])):
        raise ValueError(f"ladder bits must increase strictly, got {bits}")
    return tuple(ladder)


# The paper's parameters as edits of the proxies and the ladder (constructor, ``replace`` and files).
PAPER_VALUES = ("fusion_weight", "macro_window", "micro_window", "theta_2_4", "theta_4_8", "theta_fp")
_PAPER_SYMBOLS = {"lambda": "fusion_weight", "theta_2|4": "theta_2_4", "theta_4|8": "theta_4_8", "K": "delay_window",
                  "W_macro": "macro_window", "W_micro": "micro_window"}
_PAPER_PAIR = ("motion_fineness", "angular_jerk")


def _with_paper_values(proxies: tuple[ProxyWeight, ...], ladder: tuple[tuple[float, int], ...], values: dict):
    """Apply the paper's parameters: lambda and the windows to the (Motion Fineness, Angular Jerk) pair,
    theta_2|4 and theta_4|8 to the rungs of 2 and 4 bits, theta_fp to the top rung."""
    by_name = {p.name: p for p in proxies}
    if "fusion_weight" in values:
        fusion_weight = paper_proxies(values["fusion_weight"])[0].weight  # checked as lambda
        if tuple(by_name) != _PAPER_PAIR:
            raise ValueError(f"fusion_weight (lambda) weighs the proxies {_PAPER_PAIR}, got {tuple(by_name)}")
        by_name = {name: dataclasses.replace(by_name[name], weight=w) for name, w in zip(_PAPER_PAIR, (fusion_weight, 1.0 - fusion_weight))}
    for key, name in (("macro_window", "motion_fineness"), ("micro_window", "angular_jerk")):
        if key in values:
            if name not in by_name:
                raise ValueError(f"{key} is the window of {name}, which the proxies do not list")
            by_name[name] = ProxyWeight(name, by_name[name].weight, _check_int(values[key], key, 1, MAX_WINDOW))
    rungs = [list(rung) for rung in ladder]
    if {"theta_2_4", "theta_4_8", "theta_fp"} & set(values):
        for key, bits in (("theta_2_4", 2), ("theta_4_8", 4)):
            if key not in values:
                continue
            rung = next((r for r in rungs if r[1] == bits), None)
            if values[key] is None:  # no rung of this width: no S_t maps to it, not even S_t = 0
                if rung is not None:
                    rungs.remove(rung)
                continue
            if rung is None:
                raise ValueError(f"{key} is the threshold of the {bits}-bit rung, which the ladder does not have")
            rung[0] = _check_real(values[key], key)
        if "theta_fp" in values:
            rungs[-1][0] = _check_real(values["theta_fp"], "theta_fp")
        if [bits for _, bits in rungs] == [2, 4, 8]:
            paper_ladder(*(threshold for threshold, _ in rungs))  # the paper's message for a wrong order
    return tuple(by_name.values()), tuple(tuple(rung) for rung in rungs)


@dataclasses.dataclass(frozen=True, init=False)
class DispatchConfig:
    """Parameters of the kinematic dispatcher; validated on construction, saved as JSON.

    The defaults follow the paper where it gives a value (W_macro = 10, W_micro = 5, theta_fp = 0.5,
    95th percentile). lambda, K and the boundaries Theta = {theta_2|4, theta_4|8} are calibrated per
    task (Sec. IV-B2); their defaults are neutral starting points, not calibrated values.

    Attributes:
        proxies: the fused kinematic proxies, :class:`ProxyWeight` (name, weight, window) entries whose
            weights are convex; default :func:`paper_proxies` (lambda = 0.5). Weights (1, 0) or (0, 1)
            use one proxy alone, and so does a list of one.
        ladder: (threshold, bits) rungs, thresholds ascending, bits strictly increasing: S_t <= threshold
            maps to bits (the first such rung, Phi of Eq. 6), S_t above the top threshold, theta_fp, to
            the 16-bit fallback. Default :func:`paper_ladder` ((0.15, 2), (0.3, 4), (0.5, 8)).
        delay_window: K >= 1, steps of evidence a downgrade needs.
        percentile: in (0, 100], the percentile of the history that normalizes each proxy.
        history: >= 1, samples kept for each percentile (bounded memory).
        warmup: in [1, history], samples each scale history needs before leaving full precision.
        hysteresis: "counter" (Algorithm 1, the deployed form), "window" (Eq. 4) or "none" (b* = b^, the
            target taken at once; the same as K = 1 in either other mode).
        input: "action" (executed 7-D actions: deltas) or "pose" (end-effector poses; the
            dispatcher differences consecutive poses).
        xyz_slice: (start, stop) of the translation inside an action or pose.
        rot_slice: (start, stop) of the rotation inside an action or pose.

    The paper's parameters are accepted as keywords (and by :meth:`replace`) and edit the two fields:
    ``fusion_weight`` (lambda), ``macro_window`` (W_macro), ``micro_window`` (W_micro) the proxies,
    ``theta_2_4``, ``theta_4_8`` (Theta) and ``theta_fp`` the ladder; they are readable as properties.
    ``theta_2_4=None`` (or ``theta_4_8=None``) removes that width's rung: Eq. 6's interval [0, theta_2|4]
    holds S_t = 0 even when theta_2|4 = 0, so a width that calibration finds too coarse everywhere is
    dropped, not given a threshold of 0.
    """

    proxies: tuple[ProxyWeight, ...]
    ladder: tuple[tuple[float, int], ...]
    delay_window: int
    percentile: float
    history: int
    warmup: int
    hysteresis: str
    input: str
    xyz_slice: tuple[int, int]
    rot_slice: tuple[int, int]

    def __init__(self, *, proxies=None, ladder=None, delay_window: int = 3, percentile: float = 95.0,
                 history: int = 256, warmup: int = 10, hysteresis: str = "counter", input: str = "action",
                 xyz_slice: tuple[int, int] = (0, 3), rot_slice: tuple[int, int] = (3, 6), **paper_values):
        unknown = sorted(set(paper_values) - set(PAPER_VALUES))
        if unknown:
            raise TypeError(f"DispatchConfig got an unexpected keyword argument {unknown[0]!r}")
        proxies = _check_proxies(paper_proxies() if proxies is None else proxies)
        ladder = _check_ladder(paper_ladder() if ladder is None else ladder)
        proxies, ladder = _with_paper_values(proxies, ladder, paper_values)
        set_ = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731 (frozen)
        set_("proxies", _check_proxies(proxies))
        set_("ladder", _check_ladder(ladder))
        for name, value, maximum in (("delay_window", delay_window, MAX_WINDOW), ("history", history, MAX_HISTORY),
                                     ("warmup", warmup, MAX_HISTORY)):
            set_(name, _check_int(value, name, 1, maximum))
        if self.warmup > self.history:
            raise ValueError(f"warmup must be <= history ({self.history}), got {self.warmup}")
        set_("percentile", _check_real(percentile, "percentile"))
        if not 0.0 < self.percentile <= 100.0:
            raise ValueError(f"percentile must be in (0, 100], got {self.percentile}")
        set_("hysteresis", _check_choice(hysteresis, "hysteresis", HYSTERESIS_MODES))
        set_("input", _check_choice(input, "input", INPUT_KINDS))
        set_("xyz_slice", _check_slice(xyz_slice, "xyz_slice"))
        set_("rot_slice", _check_slice(rot_slice, "rot_slice"))

    def weight(self, proxy: str) -> float:
        """The fusion weight of ``proxy`` (0 when it is not in :attr:`proxies`)."""
        return next((p.weight for p in self.proxies if p.name == proxy), 0.0)

    def _window(self, proxy: str) -> int | None:
        return next((p.window for p in self.proxies if p.name == proxy), None)

    def _threshold(self, bits: int) -> float:
        return next((threshold for threshold, b in self.ladder if b == bits), math.nan)

    fusion_weight = property(lambda self: self.weight("motion_fineness"), doc="lambda, the weight of M~ in S_t.")
    macro_window = property(lambda self: self._window("motion_fineness"), doc="W_macro (None without M).")
    micro_window = property(lambda self: self._window("angular_jerk"), doc="W_micro (None without J).")
    theta_2_4 = property(lambda self: self._threshold(2), doc="theta_2|4, the 2-bit rung's threshold (NaN without).")
    theta_4_8 = property(lambda self: self._threshold(4), doc="theta_4|8, the 4-bit rung's threshold (NaN without).")
    theta_fp = property(lambda self: self.ladder[-1][0], doc="theta_fp: S_t above it forces the 16-bit fallback.")

    @property
    def is_paper_form(self) -> bool:
        """Whether the config is the paper's: the (M, J) pair with weights (lambda, 1 - lambda) and the
        rungs of 2, 4 and 8 bits, or of 8 bits and some of 2 and 4 (a missing rung's theta is None), so
        that the paper's parameters describe it completely."""
        pair = tuple(p.name for p in self.proxies) == _PAPER_PAIR
        bits = [b for _, b in self.ladder]
        return (pair and self.proxies[1].weight == 1.0 - self.proxies[0].weight
                and bits[-1] == 8 and set(bits) <= {2, 4, 8})

    @property
    def min_length(self) -> int:
        """The shortest action (or pose) the slices fit in."""
        return max(self.xyz_slice[1], self.rot_slice[1])

    def replace(self, **changes) -> "DispatchConfig":
        """A copy with some fields (or paper parameters, which edit the copy's proxies and ladder)
        changed, validated again."""
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return DispatchConfig(**{**fields, **changes})

    def to_dict(self) -> dict[str, Any]:
        """The fields as JSON values; a config of the paper's form is written with the paper's
        parameters (``fusion_weight``, ``theta_*``, the windows), as files were before the ladder."""
        out: dict[str, Any] = {}
        if self.is_paper_form:
            missing_as_none = lambda theta: None if math.isnan(theta) else theta  # noqa: E731
            out.update(fusion_weight=self.fusion_weight, theta_fp=self.theta_fp,
                       theta_2_4=missing_as_none(self.theta_2_4), theta_4_8=missing_as_none(self.theta_4_8))
        else:
            out.update(proxies=[dataclasses.asdict(p) for p in self.proxies], ladder=[list(r) for r in self.ladder])
        out["delay_window"] = self.delay_window
        if self.is_paper_form:
            out.update(macro_window=self.macro_window, micro_window=self.micro_window)
        for name in ("percentile", "history", "warmup", "hysteresis", "input"):
            out[name] = getattr(self, name)
        out["xyz_slice"] = list(self.xyz_slice)
        out["rot_slice"] = list(self.rot_slice)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "DispatchConfig":
        """Build from a mapping of field names or paper parameters (``fusion_weight``, ``theta_2_4``, ...,
        which edit the proxies and the ladder given or the defaults); the paper's symbols (``"lambda"``,
        ``"K"``, ``"W_macro"``, ``"W_micro"``, ``"theta_2|4"``, ``"theta_4|8"``) are accepted too."""
        if not isinstance(data, dict):
            raise TypeError(f"config data must be a dict, got {type(data).__name__}")
        names = {f.name for f in dataclasses.fields(cls)} | set(PAPER_VALUES)
        kwargs: dict[str, Any] = {}
        for key, value in data.items():
            name = _PAPER_SYMBOLS.get(key, key)
            if name not in names:
                raise ValueError(f"unknown config key {key!r}; expected one of {sorted(names)}")
            if name in kwargs:
                raise ValueError(f"config key {key!r} given twice (as {name!r} and a paper symbol)")
            kwargs[name] = tuple(value) if name.endswith("_slice") and isinstance(value, list) else value
        return cls(**kwargs)

    def save(self, path: str | os.PathLike) -> None:
        with open(path, "w", encoding="utf-8") as f:
            json.dump(self.to_dict(), f, indent=2)
            f.write("\n")

    @classmethod
    def load(cls, path: str | os.PathLike) -> "DispatchConfig":
        with open(path, encoding="utf-8") as f:
            try:
                data = json.load(f)
            except (json.JSONDecodeError, UnicodeDecodeError) as err:
                raise FileFormatError(f"config file {os.fspath(path)!r} is not valid JSON: {err}") from None
        try:
            return cls.from_dict(data)
        except (ValueError, TypeError) as err:
            raise FileFormatError(f"config file {os.fspath(path)!r}: {err}") from None


class RollingPercentile:
    """The p-th percentile of the last ``capacity`` samples, in O(capacity) bytes.

    A ring buffer remembers arrival order (to evict the oldest sample) and a sorted array gives the
    percentile by linear interpolation between closest ranks, the same definition as
    ``np.percentile(values, p)`` (method "linear"). A push costs one binary search and one memmove of
    at most ``capacity`` doubles.
    """

    __slots__ = ("capacity", "percentile", "_fraction", "_ring", "_sorted", "_next")

    def __init__(self, capacity: int, percentile: float):
        self.capacity = _check_int(capacity, "capacity", 1, MAX_HISTORY)
        self.percentile = _check_real(percentile, "percentile")
        if not 0.0 < self.percentile <= 100.0:
            raise ValueError(f"percentile must be in (0, 100], got {self.percentile}")
        self._fraction = self.percentile / 100.0
        self._ring = array("d", bytes(8 * self.capacity))
        self._sorted = array("d")
        self._next = 0

    def __len__(self) -> int:
        return len(self._sorted)

    def clear(self) -> None:
        del self._sorted[:]
        self._next = 0

    def push(self, value: float) -> None:
        ordered = self._sorted
        if len(ordered) == self.capacity:
            del ordered[bisect_left(ordered, self._ring[self._next])]
        self._ring[self._next] = value
        self._next = (self._next + 1) % self.capacity
        insort(ordered, value)

    def value(self) -> float:
        """The percentile of the samples held (NaN when empty)."""
        ordered = self._sorted
        n = len(ordered)
        if n == 0:
            return math.nan
        position = self._fraction * (n - 1)
        low = int(position)
        weight = position - low
        if weight == 0.0:
            return ordered[low]
        below = ordered[low]
        return below + (ordered[low + 1] - below) * weight

    @property
    def nbytes(self) -> int:
        return sys.getsizeof(self) + sys.getsizeof(self._ring) + sys.getsizeof(self._sorted)


class _NormalizedProxy:
    """A proxy whose raw sample is divided by the ``percentile`` of its recent samples and averaged over
    a window. ``update`` takes the step's translation and rotation; ``value`` is the windowed mean
    (NaN while the window is empty). A scale of 0 leaves the step's sample undefined (NaN, not averaged).

    A raw sample or a normalized one that overflows (finite motion whose norm or ratio is beyond the
    floats) enters neither the history nor the window; ``overflowed`` says so for the step, and the
    dispatcher then falls back to full precision."""

    name = ""

    def __init__(self, window: int, history: int, percentile: float, warmup: int):
        self._scale = RollingPercentile(history, percentile)
        self._window: deque[float] = deque(maxlen=window)
        self._warmup = warmup
        self.reset()

    def reset(self, *, keep_history: bool = False) -> None:
        if not keep_history:
            self._scale.clear()
        self._window.clear()
        self.sample = self.scale = math.nan  # the step's normalized value and the scale it used
        self.overflowed = False

    def _push(self, raw: float) -> None:
        self.overflowed = not math.isfinite(raw)
        if self.overflowed:
            self.sample = math.nan
            return
        self._scale.push(raw)
        scale = self.scale = self._scale.value()
        if scale > 0.0:
            sample = self._normalize(raw, scale)
            self.overflowed = not math.isfinite(sample)
            self.sample = math.nan if self.overflowed else sample
            if not self.overflowed:
                self._window.append(sample)
        else:
            self.sample = math.nan

    def value(self) -> float:
        window = self._window
        if not window:
            return math.nan
        mean = sum(window) / len(window)
        # Finite samples whose sum overflows: the mean of the quotients cannot.
        return mean if math.isfinite(mean) else sum(v / len(window) for v in window)

    @property
    def is_warm(self) -> bool:
        return len(self._scale) >= self._warmup and self.scale > 0.0 and bool(self._window)

    @property
    def nbytes(self) -> int:
        return self._scale.nbytes + sys.getsizeof(self._window) + sys.getsizeof(0.0) * len(self._window)


class MotionFineness(_NormalizedProxy):
    """M_t = 1 - ||a^xyz_t|| / mu_max (Sec. III-B): 1 for a still arm, negative above the scale."""

    name = "motion_fineness"

    def update(self, translation: list[float], rotation: list[float]) -> None:
        self._push(math.hypot(*translation))

    @staticmethod
    def _normalize(raw: float, scale: float) -> float:
        return 1.0 - raw / scale


class AngularJerk(_NormalizedProxy):
    """J_t = ||a^rot_t - a^rot_{t-1}|| / nu_max (Sec. III-B); the first sample needs two rotations."""

    name = "angular_jerk"

    def reset(self, *, keep_history: bool = False) -> None:
        super().reset(keep_history=keep_history)
        self._previous_rotation: list[float] | None = None

    def update(self, translation: list[float], rotation: list[float]) -> None:
        previous, self._previous_rotation = self._previous_rotation, rotation
        self.overflowed = False
        if previous is not None:
            self._push(math.dist(rotation, previous))

    @staticmethod
    def _normalize(raw: float, scale: float) -> float:
        return raw / scale

    @property
    def nbytes(self) -> int:
        previous = self._previous_rotation
        extra = sys.getsizeof(previous) + sys.getsizeof(0.0) * len(previous) if previous is not None else 0
        return super().nbytes + extra


PROXIES = {proxy.name: proxy for proxy in (MotionFineness, AngularJerk)}
"""The kinematic proxies a config may name: each a class with ``update(translation, rotation)`` and
``value()`` (and ``reset``, ``is_warm``, ``sample``, ``scale``)."""


def fuse_sensitivity(values, weights) -> float:
    """S_t = max(0, sum_i w_i * value_i); a term of zero weight is left out, so a missing (NaN) proxy
    of weight 0 does not poison S_t. A sum that is not finite (a NaN or overflowing term) is +inf, the
    most sensitive value: it maps to the 16-bit fallback, never to a lower precision."""
    fused = 0.0
    for value, weight in zip(values, weights):
        if weight > 0.0:
            fused += weight * value
    if not math.isfinite(fused):
        return math.inf
    return fused if fused > 0.0 else 0.0


def allocate_bits(sensitivity: float, ladder) -> int:
    """Target b^_t of Eq. 6: the bits of the first rung (threshold, bits) with S_t <= threshold (Phi),
    the 16-bit fallback above the top threshold (theta_fp)."""
    for threshold, bits in ladder:
        if sensitivity <= threshold:
            return bits
    return FALLBACK_BITS


def wrap_angle(delta: float) -> float:
    """An angle difference wrapped into [-pi, pi)."""
    return (delta + math.pi) % (2.0 * math.pi) - math.pi


def actions_from_poses(poses, xyz_slice=(0, 3), rot_slice=(3, 6)) -> np.ndarray:
    """Translation and rotation deltas between consecutive poses, shape (T - 1, 3 + n_rot).

    Rotation differences are wrapped into [-pi, pi) (right for Euler angles; harmless for other
    representations whose components stay within [-pi/2, pi/2]). The result is laid out as
    (xyz, rot), so the default slices apply to it.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 2:
        raise ValueError(f"poses must have shape (T, D), got {poses.shape}")
    for name, (start, stop) in (("xyz_slice", xyz_slice), ("rot_slice", rot_slice)):
        if not 0 <= start < stop <= poses.shape[1]:
            raise ValueError(f"{name} must be (start, stop) with 0 <= start < stop <= D = {poses.shape[1]}, "
                             f"got {(start, stop)}")
    xyz = np.diff(poses[:, slice(*xyz_slice)], axis=0)
    rot = np.diff(poses[:, slice(*rot_slice)], axis=0)
    rot = (rot + np.pi) % (2.0 * np.pi) - np.pi
    return np.concatenate([xyz, rot], axis=1)


class Hysteresis:
    """Asymmetric hysteresis on the target bit-width b^_t (paper Sec. IV-A3).

    Both forms raise the precision at once (b^_t >= b*_{t-1} gives b*_t = b^_t) and lower it only
    after ``delay_window`` (K) steps of evidence; they differ in what counts as evidence:

    * ``mode="window"``, Eq. 4: keep the last K targets; before the first step the window holds
      K - 1 targets of 16. Downgrade to b^_t when it is the largest of the last K targets.
    * ``mode="none"``: b*_t = b^_t, the target taken at once (what either form does with K = 1).
    * ``mode="counter"``, Algorithm 1: a saturating counter c in [0, K), the active b* and a
      candidate b-bar (the largest target since the run of lower targets began). The counter
      restarts at 1 whenever the candidate rises; when it reaches K, b* drops to the candidate.
      Initial state: b* = 16, c = 0.

    Example (K = 3, after a 16): targets 8, 4, 4 give 8 under the counter at the third step
    but keep 16 under the window (whose max, 8, exceeds the current 4), which drops straight to 4
    one step later; targets 4, 4, 8 give 8 under the window at the third step but keep 16 under the
    counter (the candidate rose from 4 to 8 and restarted the count).
    """

    __slots__ = ("delay_window", "mode", "_bits", "_targets", "_count", "_candidate", "_update")

    def __init__(self, delay_window: int, mode: str = "window"):
        self.delay_window = _check_int(delay_window, "delay_window (K)", 1, MAX_WINDOW)
        self.mode = _check_choice(mode, "mode", HYSTERESIS_MODES)
        self._update = {"window": self._update_window, "counter": self._update_counter, "none": self._update_none}[mode]
        self.reset()

    def reset(self) -> None:
        """Back to the initial state: b* = 16 (and the window's K - 1 leading 16s, or c = 0)."""
        self._bits = FALLBACK_BITS
        self._targets = deque([FALLBACK_BITS] * (self.delay_window - 1), maxlen=self.delay_window)
        self._count = 0
        self._candidate = FALLBACK_BITS

    @property
    def bits(self) -> int:
        """b*_t, the bit-width dispatched last (16 before the first update)."""
        return self._bits

    @property
    def counter(self) -> int:
        """c_t of Algorithm 1 (always 0 in window mode)."""
        return self._count

    @property
    def candidate(self) -> int:
        """b-bar_t of Algorithm 1 (16 in window mode)."""
        return self._candidate

    @property
    def window(self) -> tuple[int, ...]:
        """The targets Eq. 4 looks at, oldest first (empty in counter mode)."""
        return tuple(self._targets) if self.mode == "window" else ()

    def update(self, target_bits: int) -> int:
        """Feed b^_t, return b*_t."""
        return self._update(check_bits(target_bits, "target_bits"))

    def _update_window(self, target: int) -> int:
        # Eq. 4: b*_t = b^_t if b^_t >= b*_{t-1} or max(b^_{t-K+1..t}) <= b^_t, else b*_{t-1}.
        targets = self._targets
        targets.append(target)
        if target >= self._bits or max(targets) <= target:
            self._bits = target
        return self._bits

    def _update_none(self, target: int) -> int:
        self._bits = target
        return target

    def _update_counter(self, target: int) -> int:
        # Algorithm 1, lines 3-9.
        if target >= self._bits:
            self._bits, self._count, self._candidate = target, 0, target
            return target
        previous = self._candidate
        candidate = max(target, previous if self._count > 0 else 0)
        count = (self._count if candidate == previous else 0) + 1
        if count == self.delay_window:
            self._bits = candidate
        self._count = count % self.delay_window
        self._candidate = candidate
        return self._bits

    @property
    def nbytes(self) -> int:
        return sys.getsizeof(self) + (sys.getsizeof(self._targets) if self.mode == "window" else 0)


class KinematicDispatcher:
    """Chooses the activation bit-width of each control step from the arm's kinematics.

    ``step(action)`` takes what the arm executed at step t-1 (the past only) and returns b*_t, the
    bits of step t. Call ``reset()`` between episodes. After each step the intermediate quantities
    are readable: :attr:`motion_fineness` (M_t), :attr:`angular_jerk` (J_t), :attr:`smoothed_fineness`
    (M~_t), :attr:`smoothed_jerk` (J~_t), :attr:`sensitivity` (S_t), :attr:`target_bits` (b^_t),
    :attr:`bits` (b*_t), :attr:`mu_max`, :attr:`nu_max`, :attr:`is_warm` (NaN for a proxy the config
    does not list).

    Edge cases:
    * M_t is negative when the translation exceeds mu_max; S_t clamps at 0. J~_t may exceed 1.
    * A normalizer of 0 (the history is that still) leaves its metric undefined (NaN, not averaged)
      and the step's target at 16, like the warm-up; no division by zero happens.
    """

    def __init__(self, config: DispatchConfig | None = None):
        if config is None:
            config = DispatchConfig()
        if not isinstance(config, DispatchConfig):
            raise TypeError(f"config must be a DispatchConfig, got {type(config).__name__}")
        self.config = config
        self._xyz = slice(*config.xyz_slice)
        self._rot = slice(*config.rot_slice)
        self._min_length = config.min_length
        self._proxies = {p.name: PROXIES[p.name](p.window, config.history, config.percentile, config.warmup)
                         for p in config.proxies}
        self._weights = [p.weight for p in config.proxies]
        self.hysteresis = Hysteresis(config.delay_window, config.hysteresis)
        self.reset()

    def reset(self, *, keep_history: bool = False) -> None:
        """Start a new episode: clear the windows, the previous rotation/pose and the hysteresis
        (b* = 16). With ``keep_history=True`` the percentile histories (the scales mu_max, nu_max)
        survive, so a new episode of the same task skips the warm-up."""
        for proxy in self._proxies.values():
            proxy.reset(keep_history=keep_history)
        self._previous_pose: list[float] | None = None
        self.hysteresis.reset()
        self._steps = 0
        self._sensitivity = math.nan
        self._target_bits = FALLBACK_BITS
        self._warm = False

    def _values(self, action) -> list[float]:
        """Validate one action (or pose) and return it as a list of Python floats."""
        try:
            array_ = np.asarray(action)
            if array_.dtype.kind == "c":
                raise TypeError(f"complex values (dtype {array_.dtype}) are not kinematics")
            array_ = array_.astype(np.float64, copy=False)
        except OverflowError:  # a Python int beyond float64
            raise ValueError("action must be finite real numbers, got values beyond float64's range") from None
        except (TypeError, ValueError, RuntimeError) as err:
            raise TypeError(
                f"action must be a 1-D array of at least {self._min_length} real numbers "
                f"(a CPU tensor, ndarray or sequence), got {type(action).__name__}: {err}"
            ) from None
        if array_.ndim != 1 or array_.shape[0] < self._min_length:
            raise ValueError(
                f"action must be 1-D with at least {self._min_length} entries "
                f"(xyz_slice={self.config.xyz_slice}, rot_slice={self.config.rot_slice}), "
                f"got shape {array_.shape}"
            )
        values = array_.tolist()
        if not math.isfinite(sum(values)) and not all(map(math.isfinite, values)):
            raise ValueError(f"action must be finite (no NaN or Inf), got {values}")
        return values

    def step(self, action) -> int:
        """Take the executed action (or pose) of step t-1, return the bit-width b*_t of step t."""
        values = self._values(action)
        self._steps += 1
        translation = values[self._xyz]
        rotation = values[self._rot]
        if self.config.input == "pose":
            previous = self._previous_pose
            self._previous_pose = values
            if previous is None:
                return self._dispatch()
            translation = [a - b for a, b in zip(translation, previous[self._xyz])]
            rotation = [wrap_angle(a - b) for a, b in zip(rotation, previous[self._rot])]
        for proxy in self._proxies.values():
            proxy.update(translation, rotation)
        return self._dispatch()

    def _dispatch(self) -> int:
        proxies = self._proxies.values()
        weighted = [proxy for proxy, weight in zip(proxies, self._weights) if weight > 0.0]
        warm = self._warm = all(proxy.is_warm for proxy in weighted)
        if any(proxy.overflowed for proxy in weighted):
            # The step's kinematics overflowed: nothing to judge it by, so full precision.
            sensitivity = math.inf
            target = FALLBACK_BITS
        elif warm:
            sensitivity = fuse_sensitivity([proxy.value() for proxy in proxies], self._weights)
            target = self.allocate(sensitivity)
        else:
            sensitivity = math.nan
            target = FALLBACK_BITS
        self._sensitivity = sensitivity
        self._target_bits = target
        return self.hysteresis._update(target)

    def allocate(self, sensitivity: float) -> int:
        """Phi of Eq. 6: the target width b^_t of a fused sensitivity S_t, from the ladder. Controls that
        map S_t differently (a reversed ladder, in the closed-loop ablations) override it."""
        return allocate_bits(sensitivity, self.config.ladder)

    def _proxy_attribute(self, name: str, attribute: str) -> float:
        proxy = self._proxies.get(name)
        return getattr(proxy, attribute) if proxy is not None else math.nan

    @property
    def steps(self) -> int:
        """Steps taken since the last reset."""
        return self._steps

    @property
    def bits(self) -> int:
        """b*_t, the bit-width returned by the last step (16 after reset)."""
        return self.hysteresis.bits

    @property
    def target_bits(self) -> int:
        """b^_t, the target before hysteresis (16 during warm-up)."""
        return self._target_bits

    @property
    def sensitivity(self) -> float:
        """S_t (NaN while not warm)."""
        return self._sensitivity

    @property
    def motion_fineness(self) -> float:
        """M_t, the instantaneous Motion Fineness (NaN before the first motion)."""
        return self._proxy_attribute("motion_fineness", "sample")

    @property
    def angular_jerk(self) -> float:
        """J_t, the instantaneous Angular Jerk (NaN before two rotations were seen)."""
        return self._proxy_attribute("angular_jerk", "sample")

    @property
    def smoothed_fineness(self) -> float:
        """M~_t, the mean of the last W_macro values of M."""
        proxy = self._proxies.get("motion_fineness")
        return proxy.value() if proxy is not None else math.nan

    @property
    def smoothed_jerk(self) -> float:
        """J~_t, the mean of the last W_micro values of J."""
        proxy = self._proxies.get("angular_jerk")
        return proxy.value() if proxy is not None else math.nan

    @property
    def mu_max(self) -> float:
        """The translation scale: percentile of the recent ||a^xyz||."""
        return self._proxy_attribute("motion_fineness", "scale")

    @property
    def nu_max(self) -> float:
        """The jerk scale: percentile of the recent ||a^rot_t - a^rot_{t-1}||."""
        return self._proxy_attribute("angular_jerk", "scale")

    @property
    def is_warm(self) -> bool:
        """Whether the last target came from the kinematics (False: warm-up, target 16)."""
        return self._warm

    @property
    def state_bytes(self) -> int:
        """Bytes held by the dispatcher's state: proxies (histories, windows), hysteresis, the previous
        pose and the Python objects that hold them (``sys.getsizeof``, floats counted one by one)."""
        float_size = sys.getsizeof(0.0)
        previous = self._previous_pose
        previous_bytes = sys.getsizeof(previous) + float_size * len(previous) if previous is not None else 0
        return (
            sys.getsizeof(self)
            + sys.getsizeof(self.__dict__)
            + sum(sys.getsizeof(proxy) + sys.getsizeof(proxy.__dict__) + proxy.nbytes for proxy in self._proxies.values())
            + previous_bytes
            + self.hysteresis.nbytes
        )


TRACE_FIELDS = (
    "bits",
    "target_bits",
    "sensitivity",
    "smoothed_fineness",
    "smoothed_jerk",
    "motion_fineness",
    "angular_jerk",
    "mu_max",
    "nu_max",
)


def replay_trajectory(actions, dispatcher: KinematicDispatcher | DispatchConfig | None = None) -> dict[str, np.ndarray]:
    """Run a recorded trajectory (shape (T, D)) through a dispatcher from a fresh episode.

    Returns one array of length T per name in :data:`TRACE_FIELDS`; entry t is what the dispatcher
    reported after seeing row t.
    """
    if not isinstance(dispatcher, KinematicDispatcher):
        dispatcher = KinematicDispatcher(dispatcher)
    actions = np.asarray(actions, dtype=np.float64)
    if actions.ndim != 2:
        raise ValueError(f"actions must have shape (T, D), got {actions.shape}")
    dispatcher.reset()
    trace = {name: np.empty(len(actions)) for name in TRACE_FIELDS}
    for t, action in enumerate(actions):
        dispatcher.step(action)
        for name in TRACE_FIELDS:
            trace[name][t] = getattr(dispatcher, name)
    trace["bits"] = trace["bits"].astype(np.int64)
    trace["target_bits"] = trace["target_bits"].astype(np.int64)
    return trace


def synthetic_trajectory(steps: int = 240, seed: int = 0) -> np.ndarray:
    """A pick-and-place-like 7-D action trajectory (xyz delta, rotation delta, gripper) in [-1, 1].

    Phases: a coarse transit (large, smooth translations), fine rotation-heavy manipulation (small
    translations, abrupt rotation corrections, the gripper closing near its end) and a coarse
    carry. Deterministic for a given ``seed``.
    """
    steps = _check_int(steps, "steps", 10)
    rng = np.random.default_rng(seed)
    t = np.arange(steps)
    transit, manipulation = int(0.4 * steps), int(0.75 * steps)
    actions = np.zeros((steps, 7))
    heading = np.linspace(0.0, 1.5, steps)
    speed = np.where((t < transit) | (t >= manipulation), 0.7, 0.06)
    actions[:, 0] = speed * np.cos(heading)
    actions[:, 1] = speed * np.sin(heading)
    actions[:, 2] = np.where(t < transit, -0.2, np.where(t >= manipulation, 0.3, -0.02))
    actions[:, :3] += rng.normal(0.0, 0.03, (steps, 3)) * speed[:, None]
    rotation_noise = np.where((t >= transit) & (t < manipulation), 0.25, 0.01)
    actions[:, 3:6] = 0.02 + rng.normal(0.0, 1.0, (steps, 3)) * rotation_noise[:, None]
    actions[:, 6] = np.where(t >= int(0.7 * steps), 1.0, -1.0)
    return np.clip(actions, -1.0, 1.0)
