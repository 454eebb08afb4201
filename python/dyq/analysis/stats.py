"""Statistics for the closed-loop tables and the proxy study, in numpy only.

Success rates get Wilson score intervals; two methods run on the same seeds are compared with the
exact McNemar test on their discordant seeds; correlations (Pearson, Spearman with average ranks for
ties) get percentile bootstrap intervals that resample (x, y) pairs.
"""
from __future__ import annotations

import math
from typing import Callable, NamedTuple

import numpy as np

from . import _checks


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval of a success rate successes / n (z = 1.96: 95 %)."""
    n = _checks.integer(n, "n", 1)
    successes = _checks.integer(successes, "successes", 0)
    if successes > n:
        raise ValueError(f"successes must be <= n ({n}), got {successes}")
    z = _checks.real(z, "z", minimum=0.0, strict=True)
    p = successes / n
    denominator = 1.0 + z * z / n
    center = (p + z * z / (2 * n)) / denominator
    half_width = z / denominator * math.sqrt(p * (1.0 - p) / n + z * z / (4 * n * n))
    # At 0 or n successes the end is exactly 0 or 1; the formula leaves rounding residue there.
    low = 0.0 if successes == 0 else center - half_width
    high = 1.0 if successes == n else center + half_width
    return low, high


def _successes(value, name: str) -> np.ndarray:
    array = np.asarray(value)
    if array.ndim != 1 or array.size == 0:
        raise ValueError(f"{name} must be a non-empty 1-D array of per-seed successes, got shape {array.shape}")
    if array.dtype != np.bool_:
        if not np.issubdtype(array.dtype, np.number) or not np.all((array == 0) | (array == 1)):
            raise ValueError(f"{name} must hold booleans (or 0/1), got {array}")
        array = array.astype(bool)
    return array


EXACT_MCNEMAR_MAX = 2000  # discordant seeds up to which the p-value is summed in exact integers


def mcnemar_exact(a_only: int, b_only: int) -> float:
    """Two-sided exact McNemar p-value: under the null each discordant seed favours A with
    probability 1/2, p = min(1, 2 P[Binomial(m, 1/2) <= min(a_only, b_only)]); 1 with no discordant seeds."""
    a_only = _checks.integer(a_only, "a_only", 0)
    b_only = _checks.integer(b_only, "b_only", 0)
    m, k = a_only + b_only, min(a_only, b_only)
    if m <= EXACT_MCNEMAR_MAX:
        tail = sum(math.comb(m, i) for i in range(k + 1))
        return min(1.0, 2 * tail / 2**m)  # exact integers; one rounding in the division
    # Beyond, the exact sum of big integers takes seconds to minutes: the terms C(m, i) / 2^m in logarithms,
    # each from the one before (C(m, i + 1) = C(m, i) (m - i) / (i + 1)), summed from the largest.
    i = np.arange(k, dtype=np.float64)
    logs = np.concatenate([[0.0], np.cumsum(np.log((m - i) / (i + 1)))]) - m * math.log(2.0)
    top = float(logs.max())
    return min(1.0, 2.0 * math.exp(top) * float(np.exp(logs - top).sum()))


def paired_comparison(a, b, alpha: float = 0.05) -> dict:
    """Compare two methods' per-seed successes on the same seeds (a[i], b[i]: seed i).

    Returns n, successes_a, successes_b, a_only (seeds only A solved), b_only, p_value (exact
    McNemar) and verdict: "resolved: A better", "resolved: B better" (p < alpha) or "not resolved".
    """
    a, b = _successes(a, "a"), _successes(b, "b")
    n = _checks.same_length({"a": a, "b": b})
    alpha = _checks.real(alpha, "alpha", minimum=0.0, strict=True)
    if alpha >= 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    a_only, b_only = int(np.sum(a & ~b)), int(np.sum(b & ~a))
    p_value = mcnemar_exact(a_only, b_only)
    if p_value < alpha:
        verdict = "resolved: A better" if a_only > b_only else "resolved: B better"
    else:
        verdict = "not resolved"
    return {
        "n": n,
        "successes_a": int(a.sum()),
        "successes_b": int(b.sum()),
        "a_only": a_only,
        "b_only": b_only,
        "p_value": p_value,
        "verdict": verdict,
    }


def _pair(x, y) -> tuple[np.ndarray, np.ndarray]:
    x = _checks.vector(x, "x", min_length=2)
    y = _checks.vector(y, "y", min_length=2)
    _checks.same_length({"x": x, "y": y})
    return x, y


def _unit_deviations(x: np.ndarray) -> np.ndarray | None:
    """x's deviations from its mean over their largest magnitude, or None when x is constant. Scaled before
    and after centring, so that values near float64's range neither overflow the sums nor underflow them."""
    largest = float(np.abs(x).max())
    if largest == 0.0:
        return None
    d = x / largest
    d = d - d.mean()
    spread = float(np.abs(d).max())
    return None if spread == 0.0 else d / spread


def _correlation(x: np.ndarray, y: np.ndarray) -> float:
    dx, dy = _unit_deviations(x), _unit_deviations(y)
    if dx is None or dy is None:
        return math.nan
    return max(-1.0, min(1.0, float(dx @ dy) / math.sqrt(float(dx @ dx) * float(dy @ dy))))


def pearson(x, y) -> float:
    """Pearson r; NaN when x or y is constant (the correlation is undefined)."""
    return _correlation(*_pair(x, y))


def average_ranks(x: np.ndarray) -> np.ndarray:
    """Ranks 1..n, tied values sharing the mean of their ranks."""
    order = np.argsort(x, kind="stable")
    ordered = x[order]
    starts_group = np.r_[True, ordered[1:] != ordered[:-1]]
    starts = np.flatnonzero(starts_group)
    ends = np.r_[starts[1:], x.size]
    ranks = np.empty(x.size)
    ranks[order] = ((starts + ends + 1) / 2.0)[np.cumsum(starts_group) - 1]
    return ranks


def spearman(x, y) -> float:
    """Spearman rho: Pearson r of the average ranks; NaN when x or y is constant."""
    x, y = _pair(x, y)
    return _correlation(average_ranks(x), average_ranks(y))


class BootstrapInterval(NamedTuple):
    low: float
    high: float
    level: float
    resamples: int  # resamples whose statistic was defined
    skipped: int  # degenerate resamples (statistic NaN, e.g. a constant x), left out


def bootstrap_ci(x, y, statistic: Callable[[np.ndarray, np.ndarray], float], n_boot: int = 2000,
                 seed: int = 0, level: float = 0.95) -> BootstrapInterval:
    """Percentile bootstrap interval of statistic(x, y), resampling (x_i, y_i) pairs with replacement.

    Resamples where the statistic is undefined (NaN) are skipped and counted; with none defined the
    interval is (NaN, NaN). Deterministic for a given seed.
    """
    x, y = _pair(x, y)
    n_boot = _checks.integer(n_boot, "n_boot", 1)
    seed = _checks.integer(seed, "seed", 0)
    level = _checks.real(level, "level")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    indices = np.random.default_rng(seed).integers(0, x.size, size=(n_boot, x.size))
    values = np.array([statistic(x[i], y[i]) for i in indices], dtype=np.float64)
    defined = values[np.isfinite(values)]
    if defined.size == 0:
        return BootstrapInterval(math.nan, math.nan, level, 0, n_boot)
    low, high = np.quantile(defined, [(1.0 - level) / 2.0, (1.0 + level) / 2.0])
    return BootstrapInterval(float(low), float(high), level, int(defined.size), n_boot - int(defined.size))
