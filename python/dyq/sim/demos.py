"""Demonstration collection for the dyq evaluation tasks, in robomimic's HDF5 layout.

File layout::

    data                     attrs: total (samples in all demos), env_args (JSON), task, noise, seed0,
                                    attempts, kept
    data/demo_<i>            attrs: num_samples, seed, success
        actions              float32 [T, 7]  the expert's clean labels (what a policy should learn)
        executed_actions     float32 [T, 7]  what was sent to the simulator (labels + DART noise)
        obs/<key>            the raw robosuite observations in OBS_KEYS, before each action
        obs/policy_vector    float32 [T, D]  dyq.sim.envs.observation_vector, before each action
        rewards, dones       float32 / uint8 [T]  (dones is 1 on the step that reached success)
        states               float64 [T, S]  env.sim.get_state().flatten() before each action

Each demo is reproducible from its seed: the initial state comes from ``reset_env(env, seed)`` and the
execution noise from ``numpy.random.default_rng([seed, 1])``. Demo seeds start at
:data:`dyq.sim.envs.DEMO_SEED0` (100000), disjoint from the evaluation seeds 0..999.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ..errors import FileFormatError
from . import envs, experts

# Execution noise (std, in action units) per task, chosen so the noisy expert still meets its success target
# within the horizon (seeds 0..49): lift and can 50/50 at 0.2; the square nut 50/50 at 0.1 but 28/30 at 0.2
# with long detours, since its 6 mm grasp tolerance is slow to meet under more noise.
DEFAULT_NOISE = {"lift": 0.2, "pick_place_can": 0.2, "square": 0.1, "libero_object": 0.1, "libero_spatial": 0.1}

ROBOT_OBS_KEYS = ["robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos", "robot0_joint_pos",
                  "robot0_joint_vel"]


def obs_keys(task: str) -> list[str]:
    """The raw observations stored per demo: the robot's state and the task object's pose (for the LIBERO
    suites, the target's position and the expert's grasp and place points)."""
    if envs.libero.is_suite(task):
        return ROBOT_OBS_KEYS + ["dyq_object", "dyq_grasp", "dyq_place"]
    key = envs.spec(task).object_key
    return ROBOT_OBS_KEYS + [f"{key}_pos", f"{key}_quat"]


def run_episode(env, expert, task: str, seed: int, noise: float) -> dict:
    """One expert episode from ``seed``, stopping at success or the horizon; returns its arrays."""
    rng = np.random.default_rng([seed, 1])
    obs = envs.reset_env(env, seed)
    expert.reset(env)
    keys = obs_keys(task)
    rec: dict[str, list] = {k: [] for k in ("actions", "executed_actions", "policy_vector", "rewards", "dones",
                                            "states")}
    raw: dict[str, list] = {k: [] for k in keys}
    success = False
    for _ in range(envs.spec(task).horizon):
        clean = np.clip(expert.act(env, obs), -1.0, 1.0)
        executed = experts.noisy_action(clean, rng, noise)
        rec["states"].append(env.sim.get_state().flatten())
        rec["policy_vector"].append(envs.observation_vector(task, obs))
        for k in keys:
            raw[k].append(np.asarray(obs[k]))
        obs, reward, done, _ = envs.step_env(env, executed)
        success = envs.check_success(env)
        rec["actions"].append(clean)
        rec["executed_actions"].append(executed)
        rec["rewards"].append(reward)
        rec["dones"].append(success)
        if success or done:
            break
    out = {
        "seed": seed,
        "success": success,
        "task_index": envs.libero.task_of_seed(seed)[0] if envs.libero.is_suite(task) else 0,
        "actions": np.asarray(rec["actions"], dtype=np.float32),
        "executed_actions": np.asarray(rec["executed_actions"], dtype=np.float32),
        "policy_vector": np.asarray(rec["policy_vector"], dtype=np.float32),
        "rewards": np.asarray(rec["rewards"], dtype=np.float32),
        "dones": np.asarray(rec["dones"], dtype=np.uint8),
        "states": np.asarray(rec["states"], dtype=np.float64),
        "obs": {k: np.asarray(v) for k, v in raw.items()},
    }
    out["num_samples"] = len(out["actions"])
    return out


def _write_demo(group, demo: dict) -> None:
    group.attrs["num_samples"] = demo["num_samples"]
    group.attrs["seed"] = demo["seed"]
    group.attrs["success"] = demo["success"]
    group.attrs["task_index"] = demo["task_index"]
    for k in ("actions", "executed_actions", "rewards", "dones", "states"):
        group.create_dataset(k, data=demo[k], compression="gzip")
    obs = group.create_group("obs")
    for k, v in demo["obs"].items():
        obs.create_dataset(k, data=v, compression="gzip")
    obs.create_dataset("policy_vector", data=demo["policy_vector"], compression="gzip")


def collect(task: str, n_demos: int, out_path, seed0: int = envs.DEMO_SEED0, noise: float | None = None,
            keep_failures: bool = False, max_attempts: int | None = None, progress: bool = True,
            resume: bool = False, task_indices: list[int] | None = None) -> dict:
    """Run the expert on seeds ``seed0, seed0 + 1, ...`` until ``n_demos`` episodes are kept (successful
    ones only, unless ``keep_failures``), writing them to ``out_path``. Gives up after ``max_attempts``
    (default 3 * n_demos + 10). Returns a summary: attempts, kept, successes, steps of the kept demos, and
    per task index the successes and attempts (the LIBERO suites' ten tasks).

    The file is flushed after every demo with its running totals, so an interrupted collection keeps what
    it wrote; ``resume`` continues such a file (same task, noise and first seed) where it stopped.

    ``task_indices`` (the LIBERO suites) keeps only the seeds of those tasks, to collect more of the tasks
    the expert or the policy finds hard."""
    import h5py
    from tqdm import tqdm

    noise = DEFAULT_NOISE[task] if noise is None else float(noise)
    max_attempts = 3 * n_demos + 10 if max_attempts is None else max_attempts
    seeds = _seeds(task, seed0, task_indices)
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    if resume and not out_path.is_file():
        resume = False  # nothing to resume: start the file
    try:
        f = h5py.File(out_path, "a" if resume else "w")
    except OSError as error:
        if not resume:
            raise
        raise FileFormatError(f"{out_path} is not an HDF5 file that h5py can read ({error}): collect into "
                              f"another file") from None
    with f:
        if resume:
            try:
                data = f["data"]
                stored = {k: data.attrs.get(k) for k in ("task", "noise", "seed0")}
                stored["task_indices"] = json.loads(data.attrs.get("task_indices", "null"))
                same = (str(stored["task"]), float(stored["noise"]), int(stored["seed0"]), stored["task_indices"]) == (
                    task, noise, seed0, _indices_attr(task_indices))
                per_task = {int(k): v for k, v in json.loads(data.attrs["per_task_success"]).items()}
                attempts = int(data.attrs["attempts"])
                successes = int(data.attrs.get("successes", sum(s for s, _ in per_task.values())))
                steps = [int(data[f"demo_{i}"].attrs["num_samples"]) for i in range(int(data.attrs["kept"]))]
                later = [k for k in data if int(k.split("_")[1]) >= len(steps)]
            except (OSError, KeyError, RuntimeError, TypeError, ValueError, IndexError, AttributeError) as error:
                raise FileFormatError(f"{out_path} is not a collection that dyq collect wrote, or is damaged "
                                      f"({type(error).__name__}: {error}): collect into another file") from None
            if not same:
                raise ValueError(f"{out_path} was collected with {stored}, not task={task!r}, noise={noise}, "
                                 f"seed0={seed0}, task_indices={task_indices}: collect into another file")
            for name in later:
                del data[name]  # written after the last flushed totals
        else:
            data = f.create_group("data")
            data.attrs["env_args"] = json.dumps(envs.env_args(task))
            data.attrs.update(task=task, noise=noise, seed0=seed0, task_indices=json.dumps(_indices_attr(task_indices)))
            if envs.libero.is_suite(task):
                data.attrs["task_names"] = json.dumps(envs.libero.task_names(task))
            attempts = successes = 0
            steps = []
            per_task = {}  # task index: [successes, attempts]
        env = envs.make_env(task)
        expert = experts.make_expert(task)
        bar = tqdm(total=n_demos, initial=len(steps), desc=f"collect {task}", disable=not progress)
        while len(steps) < n_demos and attempts < max_attempts:
            demo = run_episode(env, expert, task, seeds(attempts), noise)
            attempts += 1
            successes += demo["success"]
            tally = per_task.setdefault(int(demo["task_index"]), [0, 0])
            tally[0] += int(demo["success"])
            tally[1] += 1
            if demo["success"] or keep_failures:
                _write_demo(data.create_group(f"demo_{len(steps)}"), demo)
                steps.append(demo["num_samples"])
                bar.update(1)
            data.attrs.update(total=sum(steps), attempts=attempts, successes=successes, kept=len(steps),
                              per_task_success=json.dumps({str(k): v for k, v in sorted(per_task.items())}))
            f.flush()
            bar.set_postfix(attempts=attempts, success=f"{successes / attempts:.0%}")
        bar.close()
    env.close()
    return {"task": task, "path": str(out_path), "noise": noise, "attempts": attempts, "successes": successes,
            "kept": len(steps), "steps": steps, "per_task": dict(sorted(per_task.items()))}


def _indices_attr(task_indices):
    return None if task_indices is None else sorted(int(i) for i in task_indices)


def _seeds(task: str, seed0: int, task_indices):
    """The seed of attempt ``i``: ``seed0 + i``, or the ``i``-th seed from ``seed0`` on whose task index
    is one of ``task_indices``."""
    if task_indices is None:
        return lambda i: seed0 + i
    if not envs.libero.is_suite(task):
        raise ValueError(f"task_indices selects tasks of a LIBERO suite; {task!r} is one task")
    count = envs.libero.TASKS_PER_SUITE
    bad = [i for i in task_indices if not 0 <= int(i) < count]
    if bad or not task_indices:
        raise ValueError(f"task_indices must be task indices 0..{count - 1} of {task}, got {list(task_indices)}")
    wanted = set(int(i) for i in task_indices)
    period = envs.libero.TASKS_PER_SUITE  # the task index is the seed modulo this
    chosen = [s for s in range(seed0, seed0 + period) if envs.libero.task_of_seed(s)[0] in wanted]
    return lambda i: chosen[i % len(chosen)] + period * (i // len(chosen))


def load(path) -> list[dict]:
    """Every demo in ``path`` as a dict of arrays (the datasets above; ``obs`` a dict of its keys, plus
    ``policy_vector`` at top level) with the attrs ``seed``, ``success`` and ``num_samples``."""
    import h5py

    demos = []
    with h5py.File(path, "r") as f:
        data = f["data"]
        for name in sorted(data, key=lambda n: int(n.split("_")[1])):
            g = data[name]
            obs = {k: g["obs"][k][()] for k in g["obs"] if k != "policy_vector"}
            demo = {k: g[k][()] for k in ("actions", "executed_actions", "rewards", "dones", "states")}
            demo.update(obs=obs, policy_vector=g["obs"]["policy_vector"][()], name=name,
                        seed=int(g.attrs["seed"]), success=bool(g.attrs["success"]),
                        num_samples=int(g.attrs["num_samples"]))
            demos.append(demo)
    return demos


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``dyq collect``."""
    from ..apps.usage import nonnegative_float, nonnegative_int, output_file, positive_int

    parser.add_argument("task", choices=envs.ALL_TASKS)
    parser.add_argument("--demos", type=positive_int, default=200, help="successful demos to keep")
    parser.add_argument("--out", type=output_file(".hdf5"), default=None,
                        help="HDF5 path (default: demos/<task>.hdf5)")
    parser.add_argument("--noise", type=nonnegative_float, default=None,
                        help=f"execution noise std (default per task: {DEFAULT_NOISE})")
    parser.add_argument("--seed0", type=nonnegative_int, default=envs.DEMO_SEED0,
                        help="first seed; keep demo seeds out of the evaluation range 0..999")
    parser.add_argument("--keep-failures", action="store_true", help="store failed episodes too")
    parser.add_argument("--task-indices", type=int, nargs="+", default=None,
                        help="LIBERO suites: collect only these task indices (e.g. the ones the policy fails)")
    parser.add_argument("--resume", action="store_true",
                        help="continue an interrupted collection in --out (same task, noise and seed0)")


def main(args: argparse.Namespace) -> int:
    """``dyq collect``: collect, then print the success rate of the attempts. Returns 1 if fewer demos than
    asked for were kept."""
    out = args.out or Path("demos") / f"{args.task}.hdf5"
    summary = collect(args.task, args.demos, out, seed0=args.seed0, noise=args.noise,
                      keep_failures=args.keep_failures, resume=args.resume, task_indices=args.task_indices)
    steps = np.asarray(summary["steps"])
    print(f"{summary['task']}: {summary['successes']}/{summary['attempts']} attempts succeeded "
          f"({summary['successes'] / max(summary['attempts'], 1):.1%}) at noise {summary['noise']}; "
          f"kept {summary['kept']} demos in {summary['path']}"
          + (f", steps median {np.median(steps):.0f}, p95 {np.percentile(steps, 95):.0f}" if len(steps) else ""))
    if len(summary["per_task"]) > 1:
        print("per task (successes/attempts): " + ", ".join(f"{k}: {s}/{a}" for k, (s, a) in summary["per_task"].items()))
    return 0 if summary["kept"] >= args.demos else 1


if __name__ == "__main__":
    import sys

    p = argparse.ArgumentParser(prog="python -m dyq.sim.demos")
    add_arguments(p)
    sys.exit(main(p.parse_args()))
