"""The kinematic dispatcher: picks the activation bit-width of every control step (paper Sec. IV).

Per control step the dispatcher sees the action the arm executed last (or its end-effector pose) and
returns the bit-width b*_t in {2, 4, 8, 16} for the next step:

1. kinematics (Sec. III-B): Motion Fineness M_t = 1 - ||a_t^xyz|| / mu_max and Angular Jerk
   J_t = ||a_t^rot - a_{t-1}^rot|| / nu_max, with mu_max and nu_max the ``percentile``-th
   percentiles of the last ``history`` magnitudes and jerks (current sample included);
2. windows (Sec. IV-A2): M~_t is the mean of the last W_macro values of M, J~_t the mean of the last
   W_micro values of J;
3. fusion: S_t = max(0, lambda * M~_t + (1 - lambda) * J~_t);
4. allocation (Eq. 6): b^_t = 16 if S_t > theta_fp, else Phi(S_t) in {2, 4, 8};
5. hysteresis (Eq. 4 or Algorithm 1): upgrades at once, downgrades after K steps of evidence.

Warm-up: until each scale history used by the fusion holds ``warmup`` samples and its percentile is
positive, the target is 16 (full precision). docs/dispatcher.md explains every rule in prose.
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

from .flag import check_bits

FULL_PRECISION = 16
HYSTERESIS_MODES = ("window", "counter")
INPUT_KINDS = ("action", "pose")

# Paper symbols accepted as keys in configuration files, next to the readable field names.
_PAPER_SYMBOLS = {
    "lambda": "fusion_weight",
    "theta_2|4": "theta_2_4",
    "theta_4|8": "theta_4_8",
    "K": "delay_window",
    "W_macro": "macro_window",
    "W_micro": "micro_window",
}


def _check_int(value, name: str, minimum: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an int >= {minimum}, got {type(value).__name__} {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {value}")
    return int(value)


def _check_real(value, name: str) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a real number, got {type(value).__name__} {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    return value


def _check_slice(value, name: str) -> tuple[int, int]:
    if not isinstance(value, (tuple, list)) or len(value) != 2:
        raise TypeError(f"{name} must be a pair (start, stop) of ints, got {value!r}")
    start = _check_int(value[0], f"{name}[0]", 0)
    stop = _check_int(value[1], f"{name}[1]", 1)
    if stop <= start:
        raise ValueError(f"{name} must satisfy 0 <= start < stop, got ({start}, {stop})")
    return (start, stop)


def _check_choice(value, name: str, choices: tuple[str, ...]) -> str:
    if value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}")
    return value


@dataclasses.dataclass(frozen=True)
class DispatchConfig:
    """Parameters of the kinematic dispatcher; validated on construction, saved as JSON.

    The defaults follow the paper where it gives a value (W_macro = 10, W_micro = 5, theta_fp = 0.5,
    95th percentile). lambda, K and the boundaries Theta = {theta_2|4, theta_4|8} are calibrated per
    task (Sec. IV-B2); their defaults are neutral starting points, not calibrated values.

    Attributes:
        fusion_weight: lambda in [0, 1], the weight of M~ in S_t (1 - lambda weighs J~).
        theta_fp: theta_fp, S_t above it forces the BF16 fallback (16 bits).
        theta_2_4: theta_2|4, S_t in [0, theta_2|4] maps to 2 bits.
        theta_4_8: theta_4|8, S_t in (theta_2|4, theta_4|8] maps to 4 bits, (theta_4|8, theta_fp] to 8.
        delay_window: K >= 1, steps of evidence a downgrade needs.
        macro_window: W_macro >= 1, steps averaged into M~_t.
        micro_window: W_micro >= 1, steps averaged into J~_t.
        percentile: in (0, 100], the percentile of the history that normalizes M_t and J_t.
        history: >= 1, samples kept for each percentile (bounded memory).
        warmup: in [1, history], samples each scale history needs before leaving full precision.
        hysteresis: "counter" (Algorithm 1, the deployed form) or "window" (Eq. 4).
        input: "action" (executed 7-D actions: deltas) or "pose" (end-effector poses; the
            dispatcher differences consecutive poses).
        xyz_slice: (start, stop) of the translation inside an action or pose.
        rot_slice: (start, stop) of the rotation inside an action or pose.
    """

    fusion_weight: float = 0.5
    theta_fp: float = 0.5
    theta_2_4: float = 0.15
    theta_4_8: float = 0.3
    delay_window: int = 3
    macro_window: int = 10
    micro_window: int = 5
    percentile: float = 95.0
    history: int = 256
    warmup: int = 10
    hysteresis: str = "counter"
    input: str = "action"
    xyz_slice: tuple[int, int] = (0, 3)
    rot_slice: tuple[int, int] = (3, 6)

    def __post_init__(self):
        set_ = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731 (frozen)
        set_("fusion_weight", _check_real(self.fusion_weight, "fusion_weight"))
        if not 0.0 <= self.fusion_weight <= 1.0:
            raise ValueError(f"fusion_weight (lambda) must be in [0, 1], got {self.fusion_weight}")
        for name in ("theta_2_4", "theta_4_8", "theta_fp"):
            set_(name, _check_real(getattr(self, name), name))
        if not 0.0 <= self.theta_2_4 <= self.theta_4_8 <= self.theta_fp:
            raise ValueError(
                "thresholds must satisfy 0 <= theta_2_4 <= theta_4_8 <= theta_fp, got "
                f"theta_2_4={self.theta_2_4}, theta_4_8={self.theta_4_8}, theta_fp={self.theta_fp}"
            )
        for name in ("delay_window", "macro_window", "micro_window", "history", "warmup"):
            set_(name, _check_int(getattr(self, name), name, 1))
        if self.warmup > self.history:
            raise ValueError(f"warmup must be <= history ({self.history}), got {self.warmup}")
        set_("percentile", _check_real(self.percentile, "percentile"))
        if not 0.0 < self.percentile <= 100.0:
            raise ValueError(f"percentile must be in (0, 100], got {self.percentile}")
        _check_choice(self.hysteresis, "hysteresis", HYSTERESIS_MODES)
        _check_choice(self.input, "input", INPUT_KINDS)
        set_("xyz_slice", _check_slice(self.xyz_slice, "xyz_slice"))
        set_("rot_slice", _check_slice(self.rot_slice, "rot_slice"))

    @property
    def min_length(self) -> int:
        """The shortest action (or pose) the slices fit in."""
        return max(self.xyz_slice[1], self.rot_slice[1])

    def replace(self, **changes) -> "DispatchConfig":
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        out["xyz_slice"] = list(self.xyz_slice)
        out["rot_slice"] = list(self.rot_slice)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "DispatchConfig":
        """Build from a mapping of field names; the paper's symbols (``"lambda"``, ``"K"``,
        ``"W_macro"``, ``"W_micro"``, ``"theta_2|4"``, ``"theta_4|8"``) are accepted too."""
        if not isinstance(data, dict):
            raise TypeError(f"config data must be a dict, got {type(data).__name__}")
        fields = {f.name for f in dataclasses.fields(cls)}
        kwargs: dict[str, Any] = {}
        for key, value in data.items():
            name = _PAPER_SYMBOLS.get(key, key)
            if name not in fields:
                raise ValueError(f"unknown config key {key!r}; expected one of {sorted(fields)}")
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
            except json.JSONDecodeError as err:
                raise ValueError(f"config file {os.fspath(path)!r} is not valid JSON: {err}") from None
        return cls.from_dict(data)


class RollingPercentile:
    """The p-th percentile of the last ``capacity`` samples, in O(capacity) bytes.

    A ring buffer remembers arrival order (to evict the oldest sample) and a sorted array gives the
    percentile by linear interpolation between closest ranks, the same definition as
    ``np.percentile(values, p)`` (method "linear"). A push costs one binary search and one memmove of
    at most ``capacity`` doubles.
    """

    __slots__ = ("capacity", "percentile", "_fraction", "_ring", "_sorted", "_next")

    def __init__(self, capacity: int, percentile: float):
        self.capacity = _check_int(capacity, "capacity", 1)
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


def fuse_sensitivity(smoothed_fineness: float, smoothed_jerk: float, fusion_weight: float) -> float:
    """S_t = max(0, lambda * M~_t + (1 - lambda) * J~_t); a term of zero weight is left out, so a
    missing (NaN) metric of weight 0 does not poison S_t."""
    fused = 0.0
    if fusion_weight > 0.0:
        fused += fusion_weight * smoothed_fineness
    if fusion_weight < 1.0:
        fused += (1.0 - fusion_weight) * smoothed_jerk
    return fused if fused > 0.0 else 0.0


def allocate_bits(sensitivity: float, theta_2_4: float, theta_4_8: float, theta_fp: float) -> int:
    """Target b^_t: 16 if S_t > theta_fp, else Phi(S_t) of Eq. 6 (2 on [0, theta_2|4], 4 on
    (theta_2|4, theta_4|8], 8 on (theta_4|8, theta_fp])."""
    if sensitivity > theta_fp:
        return FULL_PRECISION
    if sensitivity > theta_4_8:
        return 8
    if sensitivity > theta_2_4:
        return 4
    return 2


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
        self.delay_window = _check_int(delay_window, "delay_window (K)", 1)
        self.mode = _check_choice(mode, "mode", HYSTERESIS_MODES)
        self._update = self._update_window if mode == "window" else self._update_counter
        self.reset()

    def reset(self) -> None:
        """Back to the initial state: b* = 16 (and the window's K - 1 leading 16s, or c = 0)."""
        self._bits = FULL_PRECISION
        self._targets = deque([FULL_PRECISION] * (self.delay_window - 1), maxlen=self.delay_window)
        self._count = 0
        self._candidate = FULL_PRECISION

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
    :attr:`bits` (b*_t), :attr:`mu_max`, :attr:`nu_max`, :attr:`is_warm`.

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
        self._uses_fineness = config.fusion_weight > 0.0
        self._uses_jerk = config.fusion_weight < 1.0
        self._translation_scale = RollingPercentile(config.history, config.percentile)
        self._jerk_scale = RollingPercentile(config.history, config.percentile)
        self._fineness_window: deque[float] = deque(maxlen=config.macro_window)
        self._jerk_window: deque[float] = deque(maxlen=config.micro_window)
        self.hysteresis = Hysteresis(config.delay_window, config.hysteresis)
        self.reset()

    def reset(self, *, keep_history: bool = False) -> None:
        """Start a new episode: clear the windows, the previous rotation/pose and the hysteresis
        (b* = 16). With ``keep_history=True`` the percentile histories (the scales mu_max, nu_max)
        survive, so a new episode of the same task skips the warm-up."""
        if not keep_history:
            self._translation_scale.clear()
            self._jerk_scale.clear()
        self._fineness_window.clear()
        self._jerk_window.clear()
        self._previous_rotation: list[float] | None = None
        self._previous_pose: list[float] | None = None
        self.hysteresis.reset()
        self._steps = 0
        nan = math.nan
        self._motion_fineness = self._angular_jerk = nan
        self._smoothed_fineness = self._smoothed_jerk = self._sensitivity = nan
        self._mu_max = self._nu_max = nan
        self._target_bits = FULL_PRECISION
        self._warm = False

    def _values(self, action) -> list[float]:
        """Validate one action (or pose) and return it as a list of Python floats."""
        try:
            array_ = np.asarray(action, dtype=np.float64)
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

        magnitude = math.hypot(*translation)
        scale = self._translation_scale
        scale.push(magnitude)
        mu_max = self._mu_max = scale.value()
        if mu_max > 0.0:
            fineness = 1.0 - magnitude / mu_max
            self._fineness_window.append(fineness)
        else:
            fineness = math.nan
        self._motion_fineness = fineness

        previous_rotation = self._previous_rotation
        self._previous_rotation = rotation
        if previous_rotation is not None:
            jerk = math.dist(rotation, previous_rotation)
            scale = self._jerk_scale
            scale.push(jerk)
            nu_max = self._nu_max = scale.value()
            if nu_max > 0.0:
                jerk /= nu_max
                self._jerk_window.append(jerk)
            else:
                jerk = math.nan
            self._angular_jerk = jerk
        return self._dispatch()

    def _dispatch(self) -> int:
        config = self.config
        fineness_window = self._fineness_window
        jerk_window = self._jerk_window
        smoothed_fineness = sum(fineness_window) / len(fineness_window) if fineness_window else math.nan
        smoothed_jerk = sum(jerk_window) / len(jerk_window) if jerk_window else math.nan
        self._smoothed_fineness = smoothed_fineness
        self._smoothed_jerk = smoothed_jerk
        warm = True
        if self._uses_fineness:
            warm = len(self._translation_scale) >= config.warmup and self._mu_max > 0.0 and bool(fineness_window)
        if warm and self._uses_jerk:
            warm = len(self._jerk_scale) >= config.warmup and self._nu_max > 0.0 and bool(jerk_window)
        self._warm = warm
        if warm:
            sensitivity = fuse_sensitivity(smoothed_fineness, smoothed_jerk, config.fusion_weight)
            target = allocate_bits(sensitivity, config.theta_2_4, config.theta_4_8, config.theta_fp)
        else:
            sensitivity = math.nan
            target = FULL_PRECISION
        self._sensitivity = sensitivity
        self._target_bits = target
        return self.hysteresis._update(target)

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
        return self._motion_fineness

    @property
    def angular_jerk(self) -> float:
        """J_t, the instantaneous Angular Jerk (NaN before two rotations were seen)."""
        return self._angular_jerk

    @property
    def smoothed_fineness(self) -> float:
        """M~_t, the mean of the last W_macro values of M."""
        return self._smoothed_fineness

    @property
    def smoothed_jerk(self) -> float:
        """J~_t, the mean of the last W_micro values of J."""
        return self._smoothed_jerk

    @property
    def mu_max(self) -> float:
        """The translation scale: percentile of the recent ||a^xyz||."""
        return self._mu_max

    @property
    def nu_max(self) -> float:
        """The jerk scale: percentile of the recent ||a^rot_t - a^rot_{t-1}||."""
        return self._nu_max

    @property
    def is_warm(self) -> bool:
        """Whether the last target came from the kinematics (False: warm-up, target 16)."""
        return self._warm

    @property
    def state_bytes(self) -> int:
        """Bytes held by the dispatcher's state: buffers, windows, hysteresis and the Python objects
        that hold them (``sys.getsizeof``, floats in the windows counted one by one)."""
        float_size = sys.getsizeof(0.0)
        windows = sum(
            sys.getsizeof(window) + float_size * len(window)
            for window in (self._fineness_window, self._jerk_window)
        )
        previous = sum(
            sys.getsizeof(values) + float_size * len(values)
            for values in (self._previous_rotation, self._previous_pose)
            if values is not None
        )
        return (
            sys.getsizeof(self)
            + sys.getsizeof(self.__dict__)
            + self._translation_scale.nbytes
            + self._jerk_scale.nbytes
            + windows
            + previous
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
