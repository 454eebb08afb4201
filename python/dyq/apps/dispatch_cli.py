"""``dyq dispatch``: replay a trajectory through the dispatcher, write a demo one, write a config.

    dyq dispatch demo traj.npz                      # synthetic trajectory
    dyq dispatch config cfg.json                    # default DispatchConfig as JSON
    dyq dispatch replay traj.npz --config cfg.json --out plot.png [--json trace.json]

``replay`` reads an ``.npz`` (array ``--key``, default ``actions``, or the file's only array) or a
``.csv`` (one row per step, numeric columns, optional header line), runs every row through a fresh
dispatcher, prints a summary and, with ``--out``, plots M~, J~, S_t and the bits over time.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import warnings
import zipfile

import numpy as np

from ..control.dispatch import TRACE_FIELDS, DispatchConfig, KinematicDispatcher, replay_trajectory, synthetic_trajectory
from ..core.precision import VALID_BITS
from .usage import UsageError, input_file, output_file, positive_int, require


def load_trajectory(path: str | os.PathLike, key: str | None = None) -> np.ndarray:
    """A (T, D) float64 array from an ``.npz`` (array ``key``, else ``actions``, else the only array)
    or a ``.csv`` (comma-separated, an optional non-numeric header line)."""
    path = os.fspath(path)
    suffix = os.path.splitext(path)[1].lower()
    if suffix == ".npz":
        with np.load(path) as archive:
            names = list(archive.files)
            if key is None:
                key = "actions" if "actions" in names else (names[0] if len(names) == 1 else None)
            if key is None or key not in names:
                raise ValueError(f"{path}: choose the trajectory with --key, one of {names}")
            data = archive[key]
    elif suffix == ".csv":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "no data": reported below as a bad shape
            try:
                data = np.loadtxt(path, delimiter=",", ndmin=2)
            except ValueError:
                data = np.loadtxt(path, delimiter=",", ndmin=2, skiprows=1)
    else:
        raise ValueError(f"{path}: expected a .npz or .csv trajectory")
    data = np.asarray(data, dtype=np.float64)
    if data.ndim != 2 or data.shape[0] == 0:
        raise ValueError(f"{path}: expected a (T, D) trajectory, got shape {data.shape}")
    return data


def summarize(trace: dict[str, np.ndarray]) -> dict:
    """Counts and means of a replay trace (see ``dispatch.replay_trajectory``)."""
    bits = trace["bits"]
    sensitivity = trace["sensitivity"]
    warm = np.isfinite(sensitivity)
    return {
        "steps": int(bits.size),
        "warmup_steps": int((~warm).sum()),
        "steps_per_bits": {int(b): int((bits == b).sum()) for b in VALID_BITS},
        "switches": int((bits[1:] != bits[:-1]).sum()),
        "mean_bits": float(bits.mean()),
        "mean_sensitivity": float(sensitivity[warm].mean()) if warm.any() else math.nan,
    }


def format_summary(summary: dict, config: DispatchConfig) -> str:
    lines = [
        f"steps          {summary['steps']}  (warm-up at 16 bits: {summary['warmup_steps']})",
        f"hysteresis     {config.hysteresis}, K = {config.delay_window}",
        f"switches       {summary['switches']}",
        f"mean bits      {summary['mean_bits']:.2f}  (BF16 = 16)",
        f"mean S_t       {summary['mean_sensitivity']:.3f}  (warm steps)",
        "",
        "bits  steps  share",
    ]
    for bits, count in summary["steps_per_bits"].items():
        share = count / summary["steps"] if summary["steps"] else 0.0
        lines.append(f"{bits:>4}  {count:>5}  {share:6.1%}")
    return "\n".join(lines)


def plot_trace(trace: dict[str, np.ndarray], config: DispatchConfig, path: str | os.PathLike, title: str = "") -> None:
    """Write a PNG with M~ and M, J~ and J, S_t with the thresholds, and b^ and b* over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = np.arange(trace["bits"].size)
    fig, axes = plt.subplots(4, 1, figsize=(10, 9), sharex=True, constrained_layout=True)
    windows = {p.name: p.window for p in config.proxies}
    axes[0].plot(steps, trace["motion_fineness"], color="0.7", lw=0.8, label="M_t")
    axes[0].plot(steps, trace["smoothed_fineness"], color="C0", label=f"M~_t (W_macro={windows.get('motion_fineness')})")
    axes[0].set_ylabel("motion fineness")
    axes[1].plot(steps, trace["angular_jerk"], color="0.7", lw=0.8, label="J_t")
    axes[1].plot(steps, trace["smoothed_jerk"], color="C1", label=f"J~_t (W_micro={windows.get('angular_jerk')})")
    axes[1].set_ylabel("angular jerk")
    weights = ", ".join(f"{p.name} {p.weight:g}" for p in config.proxies)
    axes[2].plot(steps, trace["sensitivity"], color="C2", label=f"S_t ({weights})")
    for i, (threshold, bits) in enumerate(config.ladder):
        top = i == len(config.ladder) - 1
        axes[2].axhline(threshold, color="k", ls="--" if top else ":", lw=0.8,
                        label="theta_fp" if top else f"theta {bits}|{config.ladder[i + 1][1]}")
    axes[2].set_ylabel("sensitivity")
    axes[3].step(steps, trace["target_bits"], where="post", color="0.6", ls="--", label="b^_t (target)")
    axes[3].step(steps, trace["bits"], where="post", color="C3", label=f"b*_t ({config.hysteresis}, K={config.delay_window})")
    axes[3].set_yticks(VALID_BITS)
    axes[3].set_ylabel("bits")
    axes[3].set_xlabel("control step")
    for axis in axes:
        axis.legend(loc="upper right", fontsize=8)
        axis.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _read_inputs(args: argparse.Namespace) -> tuple[DispatchConfig, np.ndarray]:
    """The config and trajectory that ``replay`` names; a file that does not parse is a UsageError."""
    try:
        config = DispatchConfig.load(args.config) if args.config else DispatchConfig()
    except (ValueError, TypeError, KeyError) as error:
        raise UsageError(f"{args.config}: not a DispatchConfig JSON ({error})") from None
    try:
        actions = load_trajectory(args.trajectory, args.key)
    except (zipfile.BadZipFile, EOFError, OSError, ValueError) as error:
        raise UsageError(f"{args.trajectory}: not a readable trajectory ({error})") from None
    if args.input is not None:
        config = config.replace(input=args.input)
    return config, actions


def _replay(args: argparse.Namespace) -> int:
    if args.out:
        require("matplotlib", "--out (the plot)")
    config, actions = _read_inputs(args)
    try:
        trace = replay_trajectory(actions, KinematicDispatcher(config))
    except ValueError as error:  # rows the dispatcher refuses: too narrow, ragged, NaN or Inf
        raise UsageError(f"{args.trajectory}: {error}") from None
    summary = summarize(trace)
    print(f"trajectory     {args.trajectory}  shape {actions.shape}")
    print(format_summary(summary, config))
    if args.out:
        plot_trace(trace, config, args.out, title=os.path.basename(os.fspath(args.trajectory)))
        print(f"\nplot written to {args.out}")
    if args.json:
        record = {
            "config": config.to_dict(),
            "summary": summary,
            "trace": {name: [None if not math.isfinite(v) else v for v in trace[name].tolist()] for name in TRACE_FIELDS},
        }
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(record, f, indent=1)
        print(f"trace written to {args.json}")
    return 0


def _demo(args: argparse.Namespace) -> int:
    try:
        actions = synthetic_trajectory(args.steps, args.seed)
    except ValueError as error:  # too few --steps for its phases, or a negative --seed
        raise UsageError(f"--steps {args.steps} --seed {args.seed}: {error}") from None
    np.savez(args.output, actions=actions)
    print(f"wrote {args.output}: actions {actions.shape} (coarse transit, fine rotation-heavy manipulation, carry)")
    return 0


def _config(args: argparse.Namespace) -> int:
    DispatchConfig().save(args.output)
    print(f"wrote {args.output}")
    return 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    tools = parser.add_subparsers(dest="tool", required=True)

    replay = tools.add_parser("replay", help="run a recorded trajectory through the dispatcher")
    replay.add_argument("trajectory", type=input_file(".npz", ".csv"), help=".npz or .csv, one row per control step")
    replay.add_argument("--config", type=input_file(".json"), help="DispatchConfig JSON (default: built-in defaults)")
    replay.add_argument("--key", help="array name inside an .npz (default: 'actions' or the only array)")
    replay.add_argument("--input", choices=("action", "pose"), help="override the config's input kind")
    replay.add_argument("--out", type=output_file(".png"), help="write a PNG of M~, J~, S_t and the bits")
    replay.add_argument("--json", type=output_file(".json"), help="write the config, summary and per-step trace as JSON")
    replay.set_defaults(run=_replay)

    demo = tools.add_parser("demo", help="write a synthetic 7-D action trajectory (.npz)")
    demo.add_argument("output", type=output_file(".npz"))
    demo.add_argument("--steps", type=positive_int, default=240)
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(run=_demo)

    config = tools.add_parser("config", help="write the default DispatchConfig as JSON")
    config.add_argument("output", type=output_file(".json"))
    config.set_defaults(run=_config)


def main(args: argparse.Namespace) -> int:
    return args.run(args)
