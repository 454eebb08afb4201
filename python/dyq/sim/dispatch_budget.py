"""The closed loop's dispatcher settings, fixed from the training demonstrations before any evaluation.

:class:`dyq.DispatchConfig`'s default ladder Θ = {0.15, 0.3}, θ_fp = 0.5 is a neutral placeholder, and
on these tasks it is far from neutral: replayed through the dispatcher, the Lift demonstrations' own
actions give S_t a median of about 0.5, so the defaults would send most steps to the 16-bit fallback. The
paper calibrates Θ per task (Sec. IV-B, ``dyq calibrate``); until a task is calibrated, the closed loop
uses a **width budget** stated before any closed-loop result was seen:

* the ladder's thresholds are set so that the dispatcher, replayed over the training demonstrations'
  clean actions **with its hysteresis**, runs 40 % of their steps at 2 bits, 20 % at 4, 20 % at 8 and
  20 % at the fallback (``BUDGET_SHARES``); λ, K, the windows and the percentile stay the package
  defaults. Whether the kinematics put the low widths on the right steps is then what the closed-loop
  table measures, against random schedules with the same shares. (The first checkpoints, ``rule`` in
  their ``dispatch.json``, put the thresholds at the 40/60/80th percentiles of S_t itself, the shares of
  the targets b^_t; the hysteresis then holds a step at the higher width for K steps after S_t falls,
  which moved about a sixth of the low-width steps up to 8 or 16.) The shares are met by a few rounds of
  a fixed-point correction on the thresholds' percentile levels (:func:`budget_dispatch`);
* the dispatcher's scale histories (μ_max, ν_max) are **primed** with the last demonstrations'
  actions at the start of every episode, as a deployed dispatcher carries them over from earlier
  episodes (``reset(keep_history=True)``), without making one evaluation episode depend on another.

``dyq train`` writes both into ``dispatch.json`` beside the checkpoint.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

import dyq

BUDGET_SHARES = {2: 0.4, 4: 0.2, 8: 0.2, 16: 0.2}  # of the demonstrations' warm steps, after hysteresis
# The cumulative shares, at most 2, 4 and 8 bits: (0.4, 0.6, 0.8).
BUDGET_QUANTILES = tuple(float(v) for v in np.cumsum(list(BUDGET_SHARES.values()))[:3])
BUDGET_ROUNDS = 12
PRIME_STEPS = 320  # more than DispatchConfig.history (256): the histories start full
DISPATCH_FILE = "dispatch.json"


def demonstration_replay(actions_by_demo: list[np.ndarray],
                         config: "dyq.DispatchConfig") -> tuple[np.ndarray, np.ndarray]:
    """S_t and the widths b*_t over the demonstrations, replayed in order through one dispatcher that keeps
    its scale histories from one demonstration to the next (the warm-up of the first one is left out)."""
    dispatcher = dyq.KinematicDispatcher(config)
    values, widths = [], []
    for actions in actions_by_demo:
        dispatcher.reset(keep_history=True)
        for action in np.asarray(actions, dtype=np.float64):
            bits = dispatcher.step(action)
            if np.isfinite(dispatcher.sensitivity):
                values.append(dispatcher.sensitivity)
                widths.append(bits)
    if not values:
        raise ValueError("the demonstrations are too short for the dispatcher to leave its warm-up")
    return np.asarray(values), np.asarray(widths)


def demonstration_sensitivity(actions_by_demo: list[np.ndarray], config: "dyq.DispatchConfig") -> np.ndarray:
    """S_t over the demonstrations (see :func:`demonstration_replay`)."""
    return demonstration_replay(actions_by_demo, config)[0]


def cumulative_shares(widths: np.ndarray, rungs=(2, 4, 8)) -> np.ndarray:
    """The share of steps at or below each rung's width."""
    return np.array([np.mean(widths <= b) for b in rungs])


def budget_dispatch(actions_by_demo: list[np.ndarray], quantiles=BUDGET_QUANTILES,
                    base: "dyq.DispatchConfig | None" = None, *, after_hysteresis: bool = True,
                    rounds: int = BUDGET_ROUNDS) -> tuple["dyq.DispatchConfig", np.ndarray]:
    """The budget ladder and the priming actions (see the module docstring).

    ``quantiles``: the cumulative shares of steps at most 2, 4 and 8 bits. With ``after_hysteresis``
    the shares are those of b*_t, the widths the dispatcher runs (found by ``rounds`` of
    ``level += target - realized`` on the thresholds' percentile levels, the closest round kept);
    without, the thresholds are the plain percentiles of S_t (the shares of the targets b^_t).
    """
    if not actions_by_demo:
        raise ValueError("actions_by_demo must hold at least one demonstration")
    target = np.asarray(quantiles, dtype=np.float64)
    if target.shape != (3,) or not np.all(np.diff(target) >= 0) or target[0] < 0 or target[-1] > 1:
        raise ValueError(f"quantiles must be 3 non-decreasing shares in [0, 1], got {quantiles}")
    base = base or dyq.DispatchConfig()
    sensitivity = demonstration_sensitivity(actions_by_demo, base)

    def ladder_at(levels: np.ndarray) -> "dyq.DispatchConfig":
        theta_2_4, theta_4_8, theta_fp = (float(v) for v in np.quantile(sensitivity, levels))
        return base.replace(theta_2_4=theta_2_4, theta_4_8=theta_4_8, theta_fp=theta_fp)

    levels = target.copy()
    config = ladder_at(levels)
    if after_hysteresis:
        best = (np.inf, config)
        for _ in range(rounds):
            realized = cumulative_shares(demonstration_replay(actions_by_demo, config)[1])
            error = float(np.max(np.abs(realized - target)))
            if error < best[0]:
                best = (error, config)
            if error < 0.005:
                break
            levels = np.maximum.accumulate(np.clip(levels + (target - realized), 0.0, 1.0))
            config = ladder_at(levels)
        config = best[1]
    prime: list[np.ndarray] = []
    for actions in reversed(actions_by_demo):
        prime.insert(0, np.asarray(actions, dtype=np.float64))
        if sum(len(a) for a in prime) >= PRIME_STEPS:
            break
    return config, np.concatenate(prime)


def save(directory: str | os.PathLike, config: "dyq.DispatchConfig", prime: np.ndarray, source: str,
         rule: str | None = None) -> Path:
    path = Path(directory) / DISPATCH_FILE
    rule = rule or (f"ladder set so that the dispatcher, hysteresis included, runs the training demonstrations' "
                    f"steps at 2/4/8/16 bits in the shares {list(BUDGET_SHARES.values())}; scale histories "
                    "primed with prime_actions")
    path.write_text(json.dumps({
        "rule": rule,
        "source": source,
        "config": config.to_dict(),
        "prime_actions": np.round(prime, 6).tolist(),
    }, indent=1) + "\n")
    return path


def load(directory: str | os.PathLike) -> tuple["dyq.DispatchConfig", np.ndarray]:
    path = Path(directory) / DISPATCH_FILE
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {directory} has no {DISPATCH_FILE} (written by dyq train)")
    data = json.loads(path.read_text())
    return dyq.DispatchConfig.from_dict(data["config"]), np.asarray(data["prime_actions"], dtype=np.float64)


def prime(dispatcher: "dyq.KinematicDispatcher", actions: np.ndarray) -> "dyq.KinematicDispatcher":
    """Fills the dispatcher's scale histories with ``actions`` and starts a fresh episode on them."""
    dispatcher.reset()
    for action in actions:
        dispatcher.step(action)
    dispatcher.reset(keep_history=True)
    return dispatcher
