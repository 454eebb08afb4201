"""Where the quantization error lands: action error per width on coarse and fine steps (dyq.sim.action_error).

    python bench/action_error.py [--tasks lift,pick_place_can,square] [--references 10]
                                 [--checkpoint TASK=DIR] [--cache .cache/profile]

Teacher-forced on the full-precision references of the calibration seeds (5000+), the ones `dyq profile`
and `dyq calibrate` use and cache (so a task already calibrated costs only the INT4 forward passes).
Writes bench/results/action_error.json and docs/action_error.md.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from dyq.results import environment, write_json
from dyq.sim import action_error, envs
from dyq.sim.evaluate import checkpoint_digest, checkpoint_label, default_checkpoint
from dyq.sim.profile import Store, references
from dyq.sim.rollout import PolicyRunner

ROOT = Path(__file__).resolve().parent.parent


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default="lift,pick_place_can,square")
    parser.add_argument("--references", type=int, default=10, help="successful full-precision references per task")
    parser.add_argument("--checkpoint", action="append", default=[], metavar="TASK=DIR")
    parser.add_argument("--cache", type=Path, default=Path(".cache/profile"))
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "action_error.json")
    parser.add_argument("--table", type=Path, default=ROOT / "docs" / "action_error.md")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    if args.references < 1:
        parser.error(f"--references must be >= 1, got {args.references}")
    torch.set_num_threads(args.threads)
    tasks = [t for t in args.tasks.split(",") if t]
    checkpoints = {t: default_checkpoint(t) for t in tasks}
    for item in args.checkpoint:
        task, _, directory = item.partition("=")
        if task not in tasks or not directory:
            parser.error(f"--checkpoint must be TASK=DIR for one of {tasks}, got {item!r}")
        checkpoints[task] = Path(directory)
    # Tasks already measured stay (a later run of other tasks merges into the same file and table).
    results = json.loads(args.out.read_text()) if args.out.is_file() else {"tasks": {}}
    results["environment"] = environment()
    for task in tasks:
        begin = time.perf_counter()
        runner = PolicyRunner.load(checkpoints[task])
        digest = checkpoint_digest(checkpoints[task])
        env = envs.make_env(task)
        found, tried = references(runner, task, Store(args.cache, task, digest), args.references, env)
        actions = [action_error.width_actions(runner, r) for r in found]
        result = action_error.breakdown(found, actions, runner.dispatch_base, runner.dispatch_prime)
        result.update(checkpoint=checkpoint_label(checkpoints[task]), checkpoint_digest=digest, seeds=[r.seed for r in found],
                      tried_seeds=tried, wall_s=round(time.perf_counter() - begin, 1))
        results["tasks"][task] = result
        print(action_error.markdown(task, result))
    write_json(args.out, results)
    tables = [action_error.markdown(task, result) for task, result in results["tasks"].items()]
    args.table.parent.mkdir(parents=True, exist_ok=True)
    args.table.write_text(
        "# Action error per width\n\nWritten by `python bench/action_error.py` "
        "(`dyq.sim.action_error`; definitions in its docstring and in [closed_loop_reading.md](closed_loop_reading.md)). "
        "e_t is the L2 distance of the 7-D executed action to the full-precision one on the same observation; "
        "translation and rotation are the distances of those channel groups; a gripper flip is a changed sign "
        "of the gripper command; exact is the share of steps whose action is unchanged.\n\n" + "\n".join(tables))
    print(f"wrote {args.out} and {args.table}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
