"""Step-wise perturbation profile (paper Sec. III-A) and the kinematic proxies' correlation with it
(Sec. III-B). Definitions and rules: docs/profiling.md.

One :class:`ProfiledStep` records one perturbed episode: full precision everywhere except step t,
which ran at ``act_bits``; e_t is the local action error there and D_T the terminal deviation it
caused. The measured sensitivity is s_t = D_T / e_t; steps with e_t == 0 (the low-precision action
de-tokenized to exactly the full-precision one) have no s_t: they are counted and left out.
"""
from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple, Sequence

import numpy as np

from . import _checks
from .stats import bootstrap_ci, pearson, spearman, wilson_interval

PROFILED_BITS = (2, 4, 8)


@dataclasses.dataclass(frozen=True)
class ProfiledStep:
    """One perturbed episode: step t of episode ``episode`` ran at ``act_bits``, all others at 16.

    The kinematic fields are what the dispatcher reported when it chose step t's precision (after
    ``step(a_{t-1})``), on the unperturbed full-precision trajectory; NaN while it warms up.

    Attributes:
        episode: id of the full-precision episode (its seed).
        t: the perturbed step, >= 0.
        act_bits: the injected activation width (2, 4 or 8; weights are INT4).
        action_error: e_t = ||a_t^low - a_t^fp||_2 on the de-tokenized action, >= 0.
        terminal_deviation: D_T, distance between the final positions of the perturbed and the
            unperturbed episode, >= 0.
        success: whether the perturbed episode still succeeded.
        motion_fineness, angular_jerk: M_t and J_t (dispatcher ``motion_fineness``, ``angular_jerk``).
        smoothed_fineness, smoothed_jerk: M~_t and J~_t.
        fused_sensitivity: S_t = max(0, lambda M~_t + (1 - lambda) J~_t) (dispatcher ``sensitivity``).
    """

    episode: int
    t: int
    act_bits: int
    action_error: float
    terminal_deviation: float
    success: bool
    motion_fineness: float = math.nan
    angular_jerk: float = math.nan
    smoothed_fineness: float = math.nan
    smoothed_jerk: float = math.nan
    fused_sensitivity: float = math.nan

    def __post_init__(self):
        _checks.integer(self.episode, "episode", 0)
        _checks.integer(self.t, "t", 0)
        # An int: 4.0 and True compare equal to widths, but no layer runs at them.
        if isinstance(self.act_bits, (bool, np.bool_)) or not isinstance(self.act_bits, (int, np.integer)):
            raise TypeError(f"act_bits must be an int in {PROFILED_BITS}, got {type(self.act_bits).__name__} "
                            f"{self.act_bits!r}")
        if self.act_bits not in PROFILED_BITS:
            raise ValueError(f"act_bits must be one of {PROFILED_BITS}, got {self.act_bits!r}")
        _checks.real(self.action_error, "action_error", minimum=0.0)
        _checks.real(self.terminal_deviation, "terminal_deviation", minimum=0.0)
        if not isinstance(self.success, (bool, np.bool_)):
            raise TypeError(f"success must be a bool, got {type(self.success).__name__} {self.success!r}")
        for name in ("motion_fineness", "angular_jerk", "smoothed_fineness", "smoothed_jerk", "fused_sensitivity"):
            value = getattr(self, name)
            if not isinstance(value, (int, float, np.integer, np.floating)) or math.isinf(value):
                raise TypeError(f"{name} must be a real number (NaN while the dispatcher warms up), got {value!r}")

    @classmethod
    def from_dispatcher(cls, dispatcher, **fields) -> "ProfiledStep":
        """Take the kinematic fields from a ``dyq.KinematicDispatcher`` that has just chosen step t."""
        return cls(
            motion_fineness=dispatcher.motion_fineness,
            angular_jerk=dispatcher.angular_jerk,
            smoothed_fineness=dispatcher.smoothed_fineness,
            smoothed_jerk=dispatcher.smoothed_jerk,
            fused_sensitivity=dispatcher.sensitivity,
            **fields,
        )


class Sensitivity(NamedTuple):
    values: np.ndarray  # s_t = D_T / e_t, NaN where e_t == 0
    zero_error_steps: int  # steps with e_t == 0, left out of s_t


def sensitivity(action_error, terminal_deviation) -> Sensitivity:
    """s_t = D_T / e_t (Sec. III-A), aligned with the inputs; zero-error steps are NaN and counted."""
    e = _checks.vector(action_error, "action_error", nonnegative=True)
    d = _checks.vector(terminal_deviation, "terminal_deviation", nonnegative=True)
    _checks.same_length({"action_error": e, "terminal_deviation": d})
    zero = e == 0.0
    values = np.full(e.size, np.nan)
    values[~zero] = d[~zero] / e[~zero]
    return Sensitivity(values, int(zero.sum()))


def _records(records: Sequence[ProfiledStep]) -> list[ProfiledStep]:
    records = list(records)
    if not records:
        raise ValueError("records must hold at least one ProfiledStep, got none")
    for record in records:
        if not isinstance(record, ProfiledStep):
            raise TypeError(f"records must hold ProfiledStep, got {type(record).__name__}")
    return records


def _json_number(value: float) -> float | None:
    return None if math.isnan(value) else value


def proxy_correlations(records: Sequence[ProfiledStep], n_boot: int = 2000, seed: int = 0,
                       level: float = 0.95) -> dict:
    """Pearson and Spearman r of M_t, J_t and S_t with s_t over the pooled steps of one task.

    Steps enter when s_t is defined (e_t > 0) and all three proxies are (the dispatcher was warm).
    Keys: ``pearson_<proxy>``, ``spearman_<proxy>`` and ``<key>_ci`` ([low, high], percentile
    bootstrap over steps) for proxy in motion_fineness, angular_jerk, fused; ``episodes`` and
    ``steps`` (what entered), ``zero_error_steps``, ``undefined_proxy_steps`` (left out) and
    ``bootstrap`` (n_boot, level, seed, skipped resamples per key). Undefined values (a constant
    series) are None.
    """
    records = _records(records)
    s, zero_error_steps = sensitivity([r.action_error for r in records], [r.terminal_deviation for r in records])
    proxies = {
        "motion_fineness": np.array([r.motion_fineness for r in records], dtype=np.float64),
        "angular_jerk": np.array([r.angular_jerk for r in records], dtype=np.float64),
        "fused": np.array([r.fused_sensitivity for r in records], dtype=np.float64),
    }
    proxies_defined = np.logical_and.reduce([np.isfinite(v) for v in proxies.values()])
    used = np.isfinite(s) & proxies_defined
    undefined_proxy_steps = int((np.isfinite(s) & ~proxies_defined).sum())
    if used.sum() < 2:
        raise ValueError(
            f"records must hold at least 2 steps with e_t > 0 and defined M_t, J_t, S_t, got {int(used.sum())} "
            f"({zero_error_steps} zero-error, {undefined_proxy_steps} undefined proxies)"
        )
    result = {}
    skipped = {}
    for statistic in (pearson, spearman):
        for proxy, values in proxies.items():
            key = f"{statistic.__name__}_{proxy}"
            interval = bootstrap_ci(values[used], s[used], statistic, n_boot=n_boot, seed=seed, level=level)
            result[key] = _json_number(statistic(values[used], s[used]))
            result[f"{key}_ci"] = [_json_number(interval.low), _json_number(interval.high)]
            skipped[key] = interval.skipped
    result["episodes"] = len({r.episode for r, u in zip(records, used) if u})
    result["steps"] = int(used.sum())
    result["zero_error_steps"] = zero_error_steps
    result["undefined_proxy_steps"] = undefined_proxy_steps
    result["bootstrap"] = {"n_boot": n_boot, "level": level, "seed": seed, "skipped": skipped}
    return result


def _pyplot():
    try:
        import matplotlib
    except ImportError:
        raise ImportError("plotting needs matplotlib: pip install 'dyq[plot]'") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_perturbation_profile(records: Sequence[ProfiledStep], bins: int = 10):
    """Figure 2: (a) success rate (Wilson 95 % bars) against e_t in quantile bins, per width;
    (b) s_t over t, one line per episode and width (log scale). Returns the matplotlib Figure."""
    records = _records(records)
    bins = _checks.integer(bins, "bins", 1)
    plt = _pyplot()
    fig, (ax_success, ax_sensitivity) = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    for bits in sorted({r.act_bits for r in records}):
        subset = [r for r in records if r.act_bits == bits]
        error = np.array([r.action_error for r in subset])
        success = np.array([r.success for r in subset])
        edges = np.unique(np.quantile(error, np.linspace(0, 1, bins + 1)))
        which = np.clip(np.searchsorted(edges, error, side="right") - 1, 0, max(edges.size - 2, 0))
        centers, rates, low, high = [], [], [], []
        for b in np.unique(which):
            in_bin = which == b
            n, k = int(in_bin.sum()), int(success[in_bin].sum())
            lo, hi = wilson_interval(k, n)
            centers.append(error[in_bin].mean())
            rates.append(k / n)
            low.append(k / n - lo)
            high.append(hi - k / n)
        ax_success.errorbar(centers, rates, yerr=[low, high], marker="o", capsize=3, label=f"W4A{bits}")
        for episode in sorted({r.episode for r in subset}):
            steps = sorted((r for r in subset if r.episode == episode), key=lambda r: r.t)
            s = sensitivity([r.action_error for r in steps], [r.terminal_deviation for r in steps]).values
            ax_sensitivity.plot([r.t for r in steps], s, lw=0.8, alpha=0.7)
    ax_success.set(xlabel="local action error e_t", ylabel="success rate", ylim=(-0.05, 1.05))
    ax_success.legend()
    ax_sensitivity.set(xlabel="step t", ylabel="s_t = D_T / e_t", yscale="log")
    return fig


def _normalized(values: np.ndarray) -> np.ndarray:
    finite = values[np.isfinite(values)]
    if finite.size == 0 or finite.max() == finite.min():
        return np.full(values.size, np.nan)
    return (values - finite.min()) / (finite.max() - finite.min())


def plot_proxy_trajectories(records: Sequence[ProfiledStep], episode: int, act_bits: int = 4):
    """Figure 3: M_t, J_t and log10 s_t of one episode, each min-max normalized to [0, 1], over t.
    Returns the matplotlib Figure."""
    steps = sorted((r for r in _records(records) if r.episode == episode and r.act_bits == act_bits),
                   key=lambda r: r.t)
    if not steps:
        raise ValueError(f"records hold no step of episode {episode!r} at act_bits {act_bits!r}")
    plt = _pyplot()
    t = [r.t for r in steps]
    s = sensitivity([r.action_error for r in steps], [r.terminal_deviation for r in steps]).values
    with np.errstate(divide="ignore"):
        log_s = np.log10(s)
    fig, axes = plt.subplots(2, 1, figsize=(10, 5), sharex=True, constrained_layout=True)
    for ax, proxy, symbol in ((axes[0], "motion_fineness", "M_t"), (axes[1], "angular_jerk", "J_t")):
        ax.plot(t, _normalized(np.array([getattr(r, proxy) for r in steps])), label=f"{symbol} (normalized)")
        ax.plot(t, _normalized(log_s), color="k", lw=1.0, label="log10 s_t (normalized)")
        ax.set_ylabel(symbol)
        ax.legend(loc="upper left")
    axes[1].set_xlabel("step t")
    return fig
