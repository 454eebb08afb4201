"""Where the quantization error lands: each width's action error on the full-precision trajectories.

For every step of a successful full-precision reference episode (calibration seeds, disjoint from the
evaluation seeds: :func:`dyq.sim.profile.references`), the INT4 policy at 2, 4 and 8 bits acts on the
reference's own observation (teacher-forced, no simulation) and its executed action is compared with the
full-precision one. The error is split by channel, because the three channel groups fail differently:

* ``translation`` and ``rotation``: the L2 distance of the xyz (resp. axis-angle) deltas, in the
  normalized action units (1.0 = 5 cm resp. 0.5 rad per step);
* ``gripper``: a **flip**, the sign of the gripper command changed (open <-> close): one flip at the
  wrong moment drops the object, whatever the other channels do;
* ``exact``: the share of steps whose action is identical (all 7 tokens decoded the same).

Steps are classed two ways, both from what the dispatcher saw when it chose the step's width
(:func:`dyq.sim.profile.proxy_trace` with the checkpoint's primed dispatcher):

* **coarse / fine** by Motion Fineness M~_t against its median over the task's calibration steps
  (coarse: large, saturated translations; fine: small corrections near a target);
* by the **width DyQ's ladder targets** there, b^_t = Φ(S_t) with the checkpoint's dispatcher config:
  the question is whether the steps DyQ sends to 2 bits are those where 2 bits cost little.

Warm-up steps (S_t undefined) are left out of both classings and counted.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

import dyq

from .profile import Reference, act_at_width, proxy_trace
from .rollout import PolicyRunner

WIDTHS = (2, 4, 8)
CHANNELS = {"translation": slice(0, 3), "rotation": slice(3, 6)}
GRIPPER = 6


def width_actions(runner: PolicyRunner, reference: Reference, widths: Sequence[int] = WIDTHS) -> dict[int, np.ndarray]:
    """Each width's executed action (T, 7) on the reference's observations."""
    return {b: np.stack([act_at_width(runner, o, b)[1] for o in reference.observations]) for b in widths}


def step_errors(reference_actions: np.ndarray, actions: np.ndarray) -> dict[str, np.ndarray]:
    """Per-step errors of ``actions`` against the full-precision ``reference_actions`` (both (T, 7))."""
    reference_actions = np.asarray(reference_actions, dtype=np.float64)
    actions = np.asarray(actions, dtype=np.float64)
    if reference_actions.shape != actions.shape or reference_actions.ndim != 2 or reference_actions.shape[1] != 7:
        raise ValueError(f"actions must both be (T, 7), got {reference_actions.shape} and {actions.shape}")
    difference = actions - reference_actions
    errors = {"total": np.linalg.norm(difference, axis=1)}
    for name, channels in CHANNELS.items():
        errors[name] = np.linalg.norm(difference[:, channels], axis=1)
    errors["gripper_flip"] = (np.sign(actions[:, GRIPPER]) != np.sign(reference_actions[:, GRIPPER])).astype(float)
    errors["exact"] = (np.abs(difference).max(axis=1) == 0).astype(float)
    return errors


def _summary(errors: dict[str, np.ndarray], mask: np.ndarray) -> dict[str, float]:
    n = int(mask.sum())
    if n == 0:
        return {"steps": 0}
    row = {"steps": n}
    for name in ("total", "translation", "rotation"):
        row[f"mean_{name}"] = float(errors[name][mask].mean())
    row["median_total"] = float(np.median(errors["total"][mask]))
    row["gripper_flip_rate"] = float(errors["gripper_flip"][mask].mean())
    row["exact_share"] = float(errors["exact"][mask].mean())
    return row


def classify(references: Sequence[Reference], config: "dyq.DispatchConfig",
             prime: np.ndarray | None) -> tuple[list[dict[str, np.ndarray]], float]:
    """Per reference: M~_t, S_t and DyQ's target width b^_t (0 in warm-up); and the median M~_t over all
    warm steps, the coarse/fine split."""
    dispatcher = dyq.KinematicDispatcher(config)
    traces = []
    for reference in references:
        trace = proxy_trace(reference.actions, config, prime)
        sensitivity = trace["fused_sensitivity"]
        warm = np.isfinite(sensitivity) & np.isfinite(trace["smoothed_fineness"])
        target = np.array([dispatcher.allocate(s) if w else 0 for s, w in zip(sensitivity, warm)])
        traces.append({"fineness": trace["smoothed_fineness"], "sensitivity": sensitivity, "warm": warm,
                       "target_bits": target})
    warm_fineness = np.concatenate([t["fineness"][t["warm"]] for t in traces]) if traces else np.zeros(0)
    if not len(warm_fineness):
        raise ValueError("no reference step left the dispatcher's warm-up: nothing to classify")
    return traces, float(np.median(warm_fineness))


def breakdown(references: Sequence[Reference], actions_by_width: Sequence[dict[int, np.ndarray]],
              config: "dyq.DispatchConfig", prime: np.ndarray | None = None) -> dict:
    """The error table: per width, all warm steps, coarse and fine steps, and the steps of each target width."""
    if not references or len(references) != len(actions_by_width):
        raise ValueError(f"need one actions_by_width entry per reference, got {len(actions_by_width)} for "
                         f"{len(references)} references")
    traces, median_fineness = classify(references, config, prime)
    warm = np.concatenate([t["warm"] for t in traces])
    fineness = np.concatenate([t["fineness"] for t in traces])
    target = np.concatenate([t["target_bits"] for t in traces])
    widths = sorted(actions_by_width[0])
    result = {"references": len(references), "steps": int(len(warm)), "warm_steps": int(warm.sum()),
              "median_smoothed_fineness": median_fineness,
              "target_bits_share": {str(b): float(np.mean(target[warm] == b)) for b in (2, 4, 8, 16)},
              "widths": {}}
    for b in widths:
        errors = {}
        for reference, actions in zip(references, actions_by_width):
            for name, values in step_errors(reference.actions, actions[b]).items():
                errors.setdefault(name, []).append(values)
        errors = {name: np.concatenate(values) for name, values in errors.items()}
        result["widths"][str(b)] = {
            "all": _summary(errors, warm),
            # NaN fineness never reaches these: warm steps have a defined M~_t.
            "coarse": _summary(errors, warm & (fineness <= median_fineness)),
            "fine": _summary(errors, warm & (fineness > median_fineness)),
            "by_target_bits": {str(t): _summary(errors, warm & (target == t)) for t in (2, 4, 8, 16)},
        }
    return result


def markdown(task: str, result: dict) -> str:
    """One task's table: rows per width and class."""
    def fmt(value, digits=3):
        return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"

    lines = [f"### {task}", "",
             f"{result['references']} full-precision references, {result['warm_steps']} warm steps "
             f"(of {result['steps']}); coarse/fine split at median M~_t = {result['median_smoothed_fineness']:.3f}; "
             "DyQ's ladder targets " + ", ".join(f"{b} bits on {100 * s:.0f} %" for b, s in result["target_bits_share"].items())
             + " of them.", "",
             "| width | steps | mean e_t | median e_t | translation | rotation | gripper flips | exact |",
             "|---|---|---|---|---|---|---|---|"]
    for b, row in result["widths"].items():
        classes = [("all", row["all"]), ("coarse", row["coarse"]), ("fine", row["fine"])]
        classes += [(f"DyQ targets {t}", row["by_target_bits"][t]) for t in ("2", "4", "8", "16")]
        for name, cell in classes:
            if not cell.get("steps"):
                continue
            lines.append(f"| W4A{b} {name} | {cell['steps']} | {fmt(cell['mean_total'])} | {fmt(cell['median_total'])} | "
                         f"{fmt(cell['mean_translation'])} | {fmt(cell['mean_rotation'])} | "
                         f"{100 * cell['gripper_flip_rate']:.1f} % | {100 * cell['exact_share']:.0f} % |")
    return "\n".join(lines) + "\n"
