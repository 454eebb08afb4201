"""Pictures of closed-loop episodes (matplotlib, imported only when a picture is asked for)."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as err:
        raise RuntimeError("plots need matplotlib: pip install matplotlib") from err
    return plt


def plot_episode(episode, path: str | Path, title: str = "", dispatch=None) -> Path:
    """The dispatcher over one episode: M̃_t and J̃_t, their fusion S_t with the ladder's thresholds
    (of ``dispatch``, the episode's :class:`dyq.DispatchConfig`), and the bit-width each control step's
    decode ran at."""
    plt = _pyplot()

    steps = np.arange(episode.steps)
    fig, (top, middle, bottom) = plt.subplots(3, 1, figsize=(9, 6.5), sharex=True,
                                              gridspec_kw={"height_ratios": [2, 2, 1.3]})
    top.plot(steps, episode.smoothed_fineness, label="M̃_t (Motion Fineness, W_macro mean)")
    top.plot(steps, episode.smoothed_jerk, label="J̃_t (Angular Jerk, W_micro mean)")
    top.set_ylabel("normalized")
    top.legend(loc="upper right", fontsize=8)
    middle.plot(steps, episode.sensitivity, color="black", label="S_t")
    if dispatch is not None:
        for threshold, bits in dispatch.ladder:
            middle.axhline(threshold, linestyle=":", linewidth=1, color="gray")
            middle.annotate(f"{bits} bits below", (0, threshold), fontsize=7, color="gray", va="bottom")
    middle.set_ylabel("S_t")
    middle.legend(loc="upper right", fontsize=8)
    bottom.step(steps, episode.bits, where="post", color="tab:red")
    bottom.set_yticks([2, 4, 8, 16])
    bottom.set_ylabel("bits")
    bottom.set_xlabel("control step")
    outcome = "success" if episode.success else "failure"
    fig.suptitle(title or f"{episode.task}, {episode.config}, seed {episode.seed}: {outcome} in {episode.steps} steps")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_success_vs_bits(entry: dict, task: str, path: str | Path) -> Path:
    """The closed-loop table as a picture: success (with its Wilson 95 % interval) against mean bits,
    one point per configuration."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 5.5))
    placed: list[tuple[float, float]] = []
    for name, row in entry["configs"].items():
        lo, hi = row["wilson95"]
        rate = row["success_rate"]
        ax.errorbar(row["mean_bits"], rate, yerr=[[rate - lo], [hi - rate]], fmt="o", capsize=3)
        # Rows at about the same point (DyQ and the random schedule at DyQ's shares) get their labels one
        # under another rather than on top of each other.
        near = sum(abs(bits - row["mean_bits"]) < 0.6 and abs(r - rate) < 0.01 for bits, r in placed)
        placed.append((row["mean_bits"], rate))
        ax.annotate(name, (row["mean_bits"], rate), textcoords="offset points", xytext=(5, 4 - 10 * near), fontsize=8)
    ax.set_xlabel("mean activation bits per control step (decode)")
    ax.set_ylabel("success rate (Wilson 95 % interval)")
    counts = sorted({row["episodes"] for row in entry["configs"].values()})
    episodes = f"{counts[0]}" if len(counts) == 1 else f"{counts[0]} to {counts[-1]}"
    ax.set_title(f"{task}: closed-loop success against mean bits\n({episodes} seeded episodes per configuration)")
    ax.set_xticks([2, 4, 8, 16])
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
