"""``dyq demo``: a trained robot policy in closed loop, with DyQ choosing each step's width, against fp32.

It loads the policy that ships with dyq (an OpenVLA-shaped Llama trained by ``dyq train`` on dyq's own
scripted Lift demonstrations), converts it to INT4 weights with ``dyq.quantize_model``, and runs a few
seeded robosuite episodes twice: in full precision and under DyQ. It prints the success of both, the
histogram of the widths DyQ chose (and the widths the kernels ran at), the policy's latency per step,
and writes a picture of S_t, M̃_t, J̃_t and the bits over the first DyQ episode.
"""
from __future__ import annotations

import argparse
import collections
from pathlib import Path

import numpy as np

DEFAULT_TASK = "lift"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from .usage import input_dir, nonnegative_int, output_file, positive_int

    parser.add_argument("--task", default=DEFAULT_TASK, help="task whose shipped policy to run (default: lift)")
    parser.add_argument("--checkpoint", type=input_dir, default=None, help="a policy folder from `dyq train`")
    parser.add_argument("--episodes", type=positive_int, default=3, help="seeded episodes per configuration")
    parser.add_argument("--seed0", type=nonnegative_int, default=0, help="first evaluation seed")
    parser.add_argument("--plot", type=output_file(".png"), default=Path("dyq_demo_episode.png"),
                        help="PNG of the first DyQ episode")
    parser.add_argument("--threads", type=nonnegative_int, default=0, help="torch threads (0: torch's default)")


def main(args: argparse.Namespace) -> int:
    import torch

    from ..sim import envs
    from ..sim.evaluate import default_checkpoint
    from ..sim.plots import plot_episode
    from ..sim.rollout import PolicyRunner, run_episode
    from .usage import UsageError

    if args.episodes < 1:
        raise ValueError(f"--episodes must be >= 1, got {args.episodes}")
    if args.threads:
        torch.set_num_threads(args.threads)
    checkpoint = args.checkpoint or default_checkpoint(args.task)
    try:
        runner = PolicyRunner.load(checkpoint)
    except FileNotFoundError as error:
        if args.checkpoint is not None:
            raise UsageError(f"--checkpoint {checkpoint}: {error}") from None
        shipped = sorted(p.name for p in checkpoint.parent.iterdir() if (p / "policy.json").is_file())
        raise UsageError(f"--task {args.task}: no policy ships for it (shipped: {', '.join(shipped)}; or pass "
                         "--checkpoint)") from None
    print(f"policy {checkpoint}: {runner.float_policy.config.layers} layers, hidden "
          f"{runner.float_policy.config.hidden_size}, trained with: {runner.float_policy.config.training.get('command')}")
    print(runner.report)
    env = envs.make_env(args.task)
    seeds = list(range(args.seed0, args.seed0 + args.episodes))
    results = {}
    for config in ("fp32", "dyq"):
        episodes = []
        for seed in seeds:
            episode = run_episode(runner, args.task, config, seed, env=env)
            episodes.append(episode)
            print(f"  {config:5s} seed {seed}: {'success' if episode.success else 'failure'} in {episode.steps} steps, "
                  f"mean bits {np.mean(episode.bits):.2f}, {np.median(episode.latency_ms):.1f} ms/step")
        results[config] = episodes

    print()
    print(f"{'config':8s}{'success':>10s}{'mean bits':>11s}{'ms/step (median)':>18s}")
    for config, episodes in results.items():
        latency = np.concatenate([e.latency_ms for e in episodes])
        bits = np.concatenate([e.bits for e in episodes])
        print(f"{config:8s}{sum(e.success for e in episodes):>6d}/{len(episodes):<3d}{bits.mean():>11.2f}"
              f"{np.median(latency):>18.1f}")
    dyq_episodes = results["dyq"]
    chosen = collections.Counter(int(b) for e in dyq_episodes for b in e.bits)
    kernel = collections.Counter()
    for e in dyq_episodes:
        for counts in e.prefill_kernel_bits + e.decode_kernel_bits:
            kernel.update({int(w): c for w, c in counts.items()})
    total_steps, total_calls = sum(chosen.values()), sum(kernel.values())
    print("\nDyQ's widths: steps chosen per width, and GEMM calls the kernels ran per width")
    for width in (2, 4, 8, 16):
        print(f"  {width:2d} bits: {chosen[width]:5d} steps ({100 * chosen[width] / total_steps:5.1f} %)   "
              f"{kernel[width]:7d} GEMMs ({100 * kernel[width] / max(1, total_calls):5.1f} %)")
    path = plot_episode(dyq_episodes[0], args.plot, dispatch=runner.dispatch_base)
    print(f"\nwrote {path}")
    return 0
