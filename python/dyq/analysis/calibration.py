"""Offline calibration of the dispatcher (paper Sec. IV-B, Eq. 5 and 6; Sec. VI-D, Figure 7).

On calibration episodes (successful full-precision episodes, seeds disjoint from evaluation), in
this order:

1. lambda: :func:`choose_fusion_weight`, the lambda whose S_t ranks the measured s_t best;
2. D_acc, eta: :func:`bound_parameters`, from the task's tolerance and a line fit of s_t on S_t;
3. Theta = {theta_2|4, theta_4|8}: :func:`calibrate_thresholds`, where the binned mean error of the
   lower width consistently exceeds eps_a(S_t) = D_acc / (S_t + eta);
4. K: :func:`choose_delay`, the smallest delay that keeps downgrade errors rare;
5. theta_fp: :func:`choose_theta_fp`, the knee of a closed-loop sweep;
6. :func:`write_config`: the file ``dyq.DispatchConfig.load`` reads.

The rules are stated in each docstring and in docs/profiling.md.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path
from typing import Sequence

import numpy as np

import dyq

from . import _checks
from .stats import spearman, wilson_interval

QUANTIZED_BITS = (2, 4, 8)
FULL_PRECISION = 16


def error_bound(sensitivity_state, d_acc: float, eta: float):
    """eps_a(S_t) = D_acc / (S_t + eta), the largest single-step action error allowed at S_t (Sec. IV-B1).

    ``sensitivity_state`` is a scalar or 1-D array of S_t >= 0; D_acc > 0, eta >= 0. At S_t + eta = 0
    the bound is infinite (any error is allowed).
    """
    d_acc = _checks.real(d_acc, "d_acc", minimum=0.0, strict=True)
    eta = _checks.real(eta, "eta", minimum=0.0)
    scalar = np.ndim(sensitivity_state) == 0
    s = _checks.vector(np.atleast_1d(sensitivity_state), "sensitivity_state", nonnegative=True)
    with np.errstate(divide="ignore"):
        bound = d_acc / (s + eta)
    return float(bound[0]) if scalar else bound


def bound_parameters(sensitivity_state, measured_sensitivity, tolerance: float) -> tuple[float, float]:
    """(D_acc, eta) by the stated rule: fit s_t ~ alpha S_t + beta (least squares over steps where both
    are defined), then D_acc = tolerance / alpha and eta = max(beta, 0) / alpha.

    So eps_a(S_t) = tolerance / (alpha S_t + beta): the largest error whose predicted terminal
    deviation s_t e_t stays within ``tolerance``, the task's success tolerance in the units of D_T.
    Nothing here looks at bit-widths or at how many steps end up at low precision.
    """
    tolerance = _checks.real(tolerance, "tolerance", minimum=0.0, strict=True)
    S = _checks.vector(sensitivity_state, "sensitivity_state", allow_nan=True)
    s = _checks.vector(measured_sensitivity, "measured_sensitivity", allow_nan=True)
    _checks.same_length({"sensitivity_state": S, "measured_sensitivity": s})
    defined = np.isfinite(S) & np.isfinite(s)
    if defined.sum() < 2 or np.ptp(S[defined]) == 0.0:
        raise ValueError(f"sensitivity_state must vary over at least 2 steps where s_t is defined, "
                         f"got {int(defined.sum())} steps")
    alpha, beta = np.polyfit(S[defined], s[defined], 1)
    if alpha <= 0.0:
        raise ValueError(f"measured_sensitivity must rise with sensitivity_state for the bound to apply, "
                         f"got slope {alpha:.4g}")
    return float(tolerance / alpha), float(max(beta, 0.0) / alpha)


def _errors(errors_by_width, length: int, name: str) -> dict[int, np.ndarray]:
    if not isinstance(errors_by_width, dict) or set(errors_by_width) != set(QUANTIZED_BITS):
        keys = sorted(errors_by_width) if isinstance(errors_by_width, dict) else type(errors_by_width).__name__
        raise ValueError(f"{name} must map each width {QUANTIZED_BITS} to per-step errors, got {keys}")
    errors = {b: _checks.vector(errors_by_width[b], f"{name}[{b}]", nonnegative=True) for b in QUANTIZED_BITS}
    for b, e in errors.items():
        if e.size != length:
            raise ValueError(f"{name}[{b}] must have one error per step ({length}), got {e.size}")
    return errors


@dataclasses.dataclass(frozen=True)
class ThresholdCalibration:
    """Result of :func:`calibrate_thresholds`.

    Attributes:
        theta_2_4, theta_4_8: Theta; theta_4_8 is raised to theta_2_4 if the 4-bit limit is lower. None
            when no step may run at that width (2 bits, or 2 and 4 bits, over the bound in every bin):
            the dispatcher then has no such rung (``DispatchConfig(theta_2_4=None)``), since Eq. 6's
            [0, theta] would still send S_t = 0 to it.
        limits: per width b, the S up to which b meets the bound (the crossing).
        status: per width, "crossing", "within bound in the top bin" (no crossing: the limit is
            the largest calibration S) or "over bound in every bin" (the limit is 0).
        bin_upper: upper edge of each S bin (bins are (lower, upper], the first closed).
        bound: eps_a at each bin's upper edge, the tightest bound any step in the bin faces.
        mean_error: per width, the mean e_t^(b) in each bin.
        count: steps per bin.
    """

    theta_2_4: float | None
    theta_4_8: float | None
    limits: dict[int, float]
    status: dict[int, str]
    bin_upper: np.ndarray
    bound: np.ndarray
    mean_error: dict[int, np.ndarray]
    count: np.ndarray


def calibrate_thresholds(sensitivity_state, errors_by_width, d_acc: float, eta: float,
                         bins: int = 10) -> ThresholdCalibration:
    """Theta = {theta_2|4, theta_4|8} from teacher-forced errors (Sec. IV-B2, Eq. 5).

    ``errors_by_width[b][i]`` is e^(b) = ||a^(b) - a^fp||_2 at calibration step i, whose S_t is
    ``sensitivity_state[i]`` (warm steps only: S must be defined). S is cut into quantile bins whose edges are observed values, and
    each width's mean error per bin is compared with eps_a at the bin's upper edge. Width b's limit
    is the lower edge of the lowest bin from which the mean error exceeds the bound in every bin
    up: below it b is precise enough (Eq. 6 maps S ascending to bits ascending), above it the next
    width is needed. theta_2|4 is the 2-bit limit, theta_4|8 the 4-bit one; the 8-bit limit is
    reported as a ceiling for theta_fp.
    """
    S = _checks.vector(sensitivity_state, "sensitivity_state", nonnegative=True)
    errors = _errors(errors_by_width, S.size, "errors_by_width")
    bins = _checks.integer(bins, "bins", 1)
    edges = np.unique(np.quantile(S, np.linspace(0.0, 1.0, bins + 1), method="inverted_cdf"))
    upper = edges[1:] if edges.size > 1 else edges
    which = np.clip(np.searchsorted(edges, S, side="left") - 1, 0, None)
    count = np.bincount(which, minlength=upper.size)
    bound = error_bound(upper, d_acc, eta)
    mean_error = {b: np.bincount(which, weights=e, minlength=upper.size) / count for b, e in errors.items()}
    limits, status = {}, {}
    for b, mean in mean_error.items():
        passing = np.flatnonzero(mean <= bound)
        if passing.size == 0:
            limits[b], status[b] = 0.0, "over bound in every bin"
        elif passing[-1] == upper.size - 1:
            limits[b], status[b] = float(upper[-1]), "within bound in the top bin"
        else:
            limits[b], status[b] = float(upper[passing[-1]]), "crossing"
    too_coarse = {b for b, s in status.items() if s == "over bound in every bin"}
    return ThresholdCalibration(
        theta_2_4=None if 2 in too_coarse else limits[2],
        theta_4_8=None if {2, 4} <= too_coarse else max(limits[4], limits[2]), limits=limits, status=status,
        bin_upper=upper, bound=bound, mean_error=mean_error, count=count,
    )


def dispatch_trace(actions, config) -> tuple[np.ndarray, np.ndarray]:
    """(S_t, b*_t) of a fresh ``dyq.KinematicDispatcher`` over one episode's executed actions (T, D).

    Entry t is what decides step t: step 0 runs at 16 with S_0 undefined (NaN), step t >= 1 at
    what the dispatcher returned for action a_{t-1}. NaN S_t marks the warm-up.
    """
    actions = np.asarray(actions, dtype=np.float64)
    if actions.ndim != 2 or actions.shape[0] == 0:
        raise ValueError(f"actions must have shape (T, D) with T >= 1, got {actions.shape}")
    dispatcher = dyq.KinematicDispatcher(_config(config))
    S = np.full(actions.shape[0], np.nan)
    bits = np.full(actions.shape[0], FULL_PRECISION, dtype=np.int64)
    for t in range(1, actions.shape[0]):
        bits[t] = dispatcher.step(actions[t - 1])
        S[t] = dispatcher.sensitivity
    return S, bits


def _episodes(value, name: str) -> list:
    if isinstance(value, (str, bytes, dict)) or not isinstance(value, Sequence):
        raise TypeError(f"{name} must be a list with one entry per episode, got {type(value).__name__}")
    if len(value) == 0:
        raise ValueError(f"{name} must hold at least one episode, got none")
    return list(value)


def _config(config) -> "dyq.DispatchConfig":
    config = dyq.DispatchConfig() if config is None else config
    if not isinstance(config, dyq.DispatchConfig):
        raise TypeError(f"config must be a dyq.DispatchConfig, got {type(config).__name__}")
    return config


def choose_fusion_weight(actions_by_episode, sensitivity_by_episode, config=None,
                         grid: Sequence[float] = tuple(np.linspace(0.0, 1.0, 11))) -> dict:
    """lambda: the grid value whose S_t (replayed with :func:`dispatch_trace`) has the largest
    Spearman rho with the measured s_t, pooled over the calibration steps where both are defined.
    Ties go to the smaller lambda.

    ``sensitivity_by_episode[i][t]`` is s_t of episode i (NaN where undefined). Returns
    ``fusion_weight`` and ``table``: (lambda, rho, steps) rows.
    """
    actions_by_episode = _episodes(actions_by_episode, "actions_by_episode")
    sensitivity_by_episode = _episodes(sensitivity_by_episode, "sensitivity_by_episode")
    _checks.same_length({"actions_by_episode": actions_by_episode, "sensitivity_by_episode": sensitivity_by_episode})
    config = _config(config)
    measured = []
    for i, (actions, s) in enumerate(zip(actions_by_episode, sensitivity_by_episode)):
        s = _checks.vector(s, f"sensitivity_by_episode[{i}]", allow_nan=True)
        if s.size != len(actions):
            raise ValueError(f"sensitivity_by_episode[{i}] must have one s_t per step ({len(actions)}), got {s.size}")
        measured.append(s)
    s = np.concatenate(measured)
    table = []
    for fusion_weight in grid:
        replay = config.replace(fusion_weight=fusion_weight)
        S = np.concatenate([dispatch_trace(a, replay)[0] for a in actions_by_episode])
        defined = np.isfinite(S) & np.isfinite(s)
        rho = spearman(S[defined], s[defined]) if defined.sum() >= 2 else math.nan
        table.append((replay.fusion_weight, rho, int(defined.sum())))
    scored = [row for row in table if not math.isnan(row[1])]
    if not scored:
        raise ValueError("sensitivity_by_episode: no lambda in the grid gives a defined rank correlation")
    best = max(scored, key=lambda row: row[1])  # max keeps the first (smallest lambda) of ties
    return {"fusion_weight": best[0], "table": table}


def choose_delay(actions_by_episode, errors_by_episode, config, d_acc: float, eta: float,
                 max_rate: float = 0.05, delays: Sequence[int] = range(1, 9)) -> dict:
    """K: the smallest delay whose downgrade-error rate is at most ``max_rate``.

    A step needs the smallest width b in {2, 4, 8} with e_t^(b) <= eps_a(S_t), else 16; a
    downgrade error is a warm step dispatched below what it needs. The rate is over the warm steps
    of all calibration episodes, replayed with ``config`` (lambda and Theta already chosen) and
    each K. If no K meets ``max_rate``, the K with the lowest rate is returned with ``met`` False.
    Returns ``delay_window``, ``met`` and ``table``: (K, rate, mean_bits) rows.
    """
    actions_by_episode = _episodes(actions_by_episode, "actions_by_episode")
    errors_by_episode = _episodes(errors_by_episode, "errors_by_episode")
    _checks.same_length({"actions_by_episode": actions_by_episode, "errors_by_episode": errors_by_episode})
    config = _config(config)
    max_rate = _checks.real(max_rate, "max_rate", minimum=0.0)
    d_acc = _checks.real(d_acc, "d_acc", minimum=0.0, strict=True)
    eta = _checks.real(eta, "eta", minimum=0.0)
    delays = [_checks.integer(k, "delays[]", 1) for k in delays]
    if not delays:
        raise ValueError("delays must hold at least one K >= 1, got none")
    warm, needed = [], []
    for i, (actions, errors) in enumerate(zip(actions_by_episode, errors_by_episode)):
        S, _ = dispatch_trace(actions, config)
        errors = _errors(errors, S.size, f"errors_by_episode[{i}]")
        defined = np.isfinite(S)
        bound = np.full(S.size, np.inf)
        if defined.any():  # an episode shorter than the warm-up has no warm step, which is no error
            bound[defined] = error_bound(S[defined], d_acc, eta)
        need = np.full(S.size, FULL_PRECISION)
        for b in reversed(QUANTIZED_BITS):  # the smallest width that meets the bound wins
            need[errors[b] <= bound] = b
        warm.append(defined)
        needed.append(need)
    warm, needed = np.concatenate(warm), np.concatenate(needed)
    table = []
    for k in delays:
        replay = config.replace(delay_window=k)
        bits = np.concatenate([dispatch_trace(a, replay)[1] for a in actions_by_episode])
        rate = float(np.mean(bits[warm] < needed[warm])) if warm.any() else 0.0
        table.append((k, rate, float(bits.mean())))
    meeting = [row for row in table if row[1] <= max_rate]
    chosen = min(meeting, key=lambda row: row[0]) if meeting else min(table, key=lambda row: (row[1], row[0]))
    return {"delay_window": chosen[0], "met": bool(meeting), "table": table}


def choose_theta_fp(sweep: Sequence[tuple[float, float, float]], episodes: int, z: float = 1.96) -> dict:
    """theta_fp at the knee of a closed-loop sweep (Figure 7, Sec. VI-D).

    ``sweep`` rows are (theta_fp, success_rate, mean_bits), each measured on the same ``episodes``
    calibration seeds. Rule: take the best success rate and the lower end of its Wilson interval;
    among the rows whose success rate reaches that floor, pick the one with the fewest mean bits
    (ties: higher success, then smaller theta_fp). Returns theta_fp, its success_rate and
    mean_bits, best_success_rate and success_floor.
    """
    episodes = _checks.integer(episodes, "episodes", 1)
    if isinstance(sweep, (str, bytes)) or not isinstance(sweep, Sequence) or len(sweep) == 0:
        raise ValueError(f"sweep must be a non-empty list of (theta_fp, success_rate, mean_bits), got {sweep!r}")
    rows = []
    for i, row in enumerate(sweep):
        if not isinstance(row, Sequence) or len(row) != 3:
            raise ValueError(f"sweep[{i}] must be (theta_fp, success_rate, mean_bits), got {row!r}")
        theta_fp = _checks.real(row[0], f"sweep[{i}] theta_fp", minimum=0.0)
        rate = _checks.real(row[1], f"sweep[{i}] success_rate", minimum=0.0)
        mean_bits = _checks.real(row[2], f"sweep[{i}] mean_bits", minimum=2.0)
        if rate > 1.0 or abs(rate * episodes - round(rate * episodes)) > 1e-6:
            raise ValueError(f"sweep[{i}] success_rate must be successes / episodes ({episodes}), got {rate}")
        if mean_bits > FULL_PRECISION:
            raise ValueError(f"sweep[{i}] mean_bits must be in [2, 16], got {mean_bits}")
        rows.append((theta_fp, rate, mean_bits))
    if len({row[0] for row in rows}) != len(rows):
        raise ValueError(f"sweep must hold each theta_fp once, got {[row[0] for row in rows]}")
    best = max(row[1] for row in rows)
    floor, _ = wilson_interval(round(best * episodes), episodes, z)
    knee = min((row for row in rows if row[1] >= floor), key=lambda row: (row[2], -row[1], row[0]))
    return {"theta_fp": knee[0], "success_rate": knee[1], "mean_bits": knee[2],
            "best_success_rate": best, "success_floor": floor}


def write_config(path: str | os.PathLike, *, fusion_weight: float, delay_window: int, theta_2_4: float | None,
                 theta_4_8: float | None, theta_fp: float, base=None) -> "dyq.DispatchConfig":
    """Write the calibrated dispatcher config as JSON with the paper's symbols as keys ("lambda",
    "K", "theta_2|4", "theta_4|8", "theta_fp"; other fields from ``base``, default DispatchConfig()).

    Theta is clipped to theta_fp: steps above theta_fp run at 16 anyway, so Eq. 6 is unchanged. A theta
    of None (written as null) means the ladder has no rung of that width.
    The values are validated by ``dyq.DispatchConfig`` before the file is written; returns it.
    """
    data = _config(base).to_dict()
    for name in ("fusion_weight", "delay_window", "theta_2_4", "theta_4_8", "theta_fp"):
        del data[name]
    theta_fp = _checks.real(theta_fp, "theta_fp", minimum=0.0)
    data.update({
        "lambda": fusion_weight,
        "K": delay_window,
        "theta_2|4": None if theta_2_4 is None else min(_checks.real(theta_2_4, "theta_2_4", minimum=0.0), theta_fp),
        "theta_4|8": None if theta_4_8 is None else min(_checks.real(theta_4_8, "theta_4_8", minimum=0.0), theta_fp),
        "theta_fp": theta_fp,
    })
    config = dyq.DispatchConfig.from_dict(data)
    # The validated values (numpy scalars become Python numbers), written whole or not at all: a failed dump
    # into the open file had left the previous config truncated.
    data.update({"lambda": config.fusion_weight, "K": config.delay_window})
    text = json.dumps(data, indent=2) + "\n"
    tmp = Path(path).with_name(Path(path).name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
    return config
