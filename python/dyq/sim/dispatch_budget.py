"""The closed loop's dispatcher settings, fixed from the training demonstrations before any evaluation.

:class:`dyq.DispatchConfig`'s default ladder Θ = {0.15, 0.3}, θ_fp = 0.5 is a neutral placeholder, and
on these tasks it is far from neutral: replayed through the dispatcher, the Lift demonstrations' own
actions give S_t a median of about 0.5, so the defaults would send most steps to the 16-bit fallback. The
paper calibrates Θ per task (Sec. IV-B, ``dyq calibrate``); until a task is calibrated, the closed loop
uses a **width budget** stated before any closed-loop result was seen:

* the ladder's thresholds are the 40th, 60th and 80th percentiles of S_t over the training
  demonstrations' clean actions, so that on the demonstrations' own kinematics 40 % of steps fall on the
  2-bit rung, 20 % on 4, 20 % on 8 and 20 % on the fallback; λ, K, the windows and the percentile stay
  the package defaults. Whether the kinematics put the low widths on the right steps is then what the
  closed-loop table measures, against random schedules with the same shares;
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

BUDGET_QUANTILES = (0.4, 0.6, 0.8)
PRIME_STEPS = 320  # more than DispatchConfig.history (256): the histories start full
DISPATCH_FILE = "dispatch.json"


def demonstration_sensitivity(actions_by_demo: list[np.ndarray], config: "dyq.DispatchConfig") -> np.ndarray:
    """S_t over the demonstrations, replayed in order through one dispatcher that keeps its scale
    histories from one demonstration to the next (the warm-up of the first one is left out)."""
    dispatcher = dyq.KinematicDispatcher(config)
    values = []
    for actions in actions_by_demo:
        dispatcher.reset(keep_history=True)
        for action in np.asarray(actions, dtype=np.float64):
            dispatcher.step(action)
            if np.isfinite(dispatcher.sensitivity):
                values.append(dispatcher.sensitivity)
    if not values:
        raise ValueError("the demonstrations are too short for the dispatcher to leave its warm-up")
    return np.asarray(values)


def budget_dispatch(actions_by_demo: list[np.ndarray], quantiles=BUDGET_QUANTILES,
                    base: "dyq.DispatchConfig | None" = None) -> tuple["dyq.DispatchConfig", np.ndarray]:
    """The budget ladder and the priming actions (see the module docstring)."""
    if not actions_by_demo:
        raise ValueError("actions_by_demo must hold at least one demonstration")
    base = base or dyq.DispatchConfig()
    sensitivity = demonstration_sensitivity(actions_by_demo, base)
    theta_2_4, theta_4_8, theta_fp = (float(v) for v in np.quantile(sensitivity, quantiles))
    config = base.replace(theta_2_4=theta_2_4, theta_4_8=theta_4_8, theta_fp=theta_fp)
    prime: list[np.ndarray] = []
    for actions in reversed(actions_by_demo):
        prime.insert(0, np.asarray(actions, dtype=np.float64))
        if sum(len(a) for a in prime) >= PRIME_STEPS:
            break
    return config, np.concatenate(prime)


def save(directory: str | os.PathLike, config: "dyq.DispatchConfig", prime: np.ndarray, source: str) -> Path:
    path = Path(directory) / DISPATCH_FILE
    path.write_text(json.dumps({
        "rule": f"ladder at the {[int(100 * q) for q in BUDGET_QUANTILES]} percentiles of S_t on the training "
                "demonstrations; scale histories primed with prime_actions",
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
