"""``dyq train``: behavior cloning of a :class:`~dyq.sim.policy.TokenPolicy` on demonstrations.

The loss is the cross-entropy of the 7 action tokens given the observation prompt (teacher forcing over
one whole step), restricted to the 256 action bins as decoding is. Training is seeded and resumable: the
batch of step ``i`` is drawn from ``numpy.random.default_rng([seed, i])``, and ``train_state.pt`` in the
output folder (model, optimizer, step) is rewritten every ``--save-every`` steps, so an interrupted run
continues where it stopped and gives the same result. The finished policy is saved as bf16 safetensors
plus ``policy.json``, with the command line that produced it.
"""
from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch

from ..errors import FileFormatError
from . import dispatch_budget
from .policy import TASK_INDEX, PolicyConfig, TokenPolicy
from .tokens import ACTION_DIMS, BinTokenizer

STATE_FILE = "train_state.pt"
CALIBRATION_FILE = "calibration.safetensors"
CALIBRATION_SAMPLES = 512


def load_demonstrations(path) -> tuple[list[np.ndarray], list[np.ndarray], list[str]]:
    """Per-demo observation vectors and clean action labels from a robomimic-layout HDF5 file, or from
    several in order (collections run side by side on disjoint seeds); their observation names must agree."""
    if not isinstance(path, (str, Path)):
        paths = list(path)
        if not paths:
            raise ValueError("data: give at least one demonstration file")
        observations, actions, names = load_demonstrations(paths[0])
        for other in paths[1:]:
            more_obs, more_act, more_names = load_demonstrations(other)
            if more_names != names:
                raise ValueError(f"data: {other} has observations {more_names}, {paths[0]} has {names}")
            if more_obs[0].shape[1] != observations[0].shape[1]:
                raise ValueError(f"data: {other} has {more_obs[0].shape[1]} observation values a step, {paths[0]} "
                                 f"has {observations[0].shape[1]}")
            observations += more_obs
            actions += more_act
        return observations, actions, names
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"demonstration file {path} does not exist")
    observations, actions = [], []
    with _open_demonstrations(path) as f:
        # h5py reports a damaged object or link table as OSError, KeyError or RuntimeError when it is read.
        try:
            data = f["data"]
            names = _demo_names(path, data)
            observation_names = [str(n) for n in data.attrs.get("policy_vector_names", [])]
            for name in names:
                observation, action = _demo_arrays(path, data, name)
                if observations and observation.shape[1] != observations[0].shape[1]:
                    raise FileFormatError(f"demonstration file {path}: {name} has {observation.shape[1]} "
                                          f"observation values a step, {names[0]} has {observations[0].shape[1]}")
                observations.append(observation)
                actions.append(action)
        except (OSError, KeyError, RuntimeError) as error:
            raise FileFormatError(f"demonstration file {path} is damaged: {error}") from None
    if not observations:
        raise FileFormatError(f"demonstration file {path} holds no demonstrations")
    if observation_names and len(observation_names) != observations[0].shape[1]:
        raise FileFormatError(f"demonstration file {path}: policy_vector_names names {len(observation_names)} "
                              f"observation values, its demos have {observations[0].shape[1]}")
    return observations, actions, observation_names


def _open_demonstrations(path: Path):
    """``path`` opened read-only, with a ``data`` group: a FileFormatError otherwise (not HDF5, truncated)."""
    import h5py

    try:
        f = h5py.File(path, "r")
    except OSError as error:
        raise FileFormatError(f"demonstration file {path} is not an HDF5 file that h5py can read ({error})") from None
    try:
        laid_out = isinstance(f.get("data"), h5py.Group)
    except (OSError, KeyError, RuntimeError) as error:
        f.close()
        raise FileFormatError(f"demonstration file {path} is damaged: {error}") from None
    if not laid_out:
        f.close()
        raise FileFormatError(f"demonstration file {path} is not in robomimic's layout (no 'data' group)")
    return f


def _demo_names(path: Path, data) -> list[str]:
    """The demos of ``data`` in their order, demo_0, demo_1, ... (the number after the last underscore)."""
    def order(name: str) -> int:
        number = name.rsplit("_", 1)[-1]
        if not number.isdigit():
            raise FileFormatError(f"demonstration file {path}: data/{name} is not a demo_<number> group")
        return int(number)

    return sorted(data.keys(), key=order)


def _demo_arrays(path: Path, data, name: str) -> tuple[np.ndarray, np.ndarray]:
    """One demo's observation vectors [T, D] and action labels [T, 7], checked: present, of those shapes,
    finite, and as many of each."""
    import h5py

    demo = data[name]
    arrays = {}
    for key in ("obs/policy_vector", "actions"):
        dataset = demo.get(key) if isinstance(demo, h5py.Group) else None
        if not isinstance(dataset, h5py.Dataset):
            raise FileFormatError(f"demonstration file {path}: data/{name} has no {key} dataset")
        try:
            values = np.asarray(dataset[()], dtype=np.float32)
        except (TypeError, ValueError) as error:
            raise FileFormatError(f"demonstration file {path}: data/{name}/{key} cannot be read as numbers "
                                  f"({error})") from None
        if values.ndim != 2 or values.shape[0] == 0:
            raise FileFormatError(f"demonstration file {path}: data/{name}/{key} must be [steps, values] with at "
                                  f"least one step, got shape {values.shape}")
        if not np.isfinite(values).all():
            raise FileFormatError(f"demonstration file {path}: data/{name}/{key} holds NaN or Inf")
        arrays[key] = values
    observation, action = arrays["obs/policy_vector"], arrays["actions"]
    if action.shape[1] != ACTION_DIMS:
        raise FileFormatError(f"demonstration file {path}: data/{name}/actions has {action.shape[1]} values a "
                              f"step, a policy decodes {ACTION_DIMS}")
    if len(observation) != len(action):
        raise FileFormatError(f"demonstration file {path}: data/{name} has {len(observation)} observations and "
                              f"{len(action)} actions")
    return observation, action


def task_names_of(path) -> list[str]:
    """The tasks of a multi-task demonstration file: its ``data`` attr ``task_names`` (a JSON list), or
    the LIBERO suite's task names where the file names a suite as its task. Several files must agree."""
    from . import libero

    if not isinstance(path, (str, Path)):
        paths = list(path)
        names = [task_names_of(p) for p in paths]
        for other, other_names in zip(paths[1:], names[1:]):
            if other_names != names[0]:
                raise ValueError(f"data: {other} holds tasks {other_names}, {paths[0]} holds {names[0]}")
        return names[0]

    with _open_demonstrations(Path(path)) as f:
        names = f["data"].attrs.get("task_names")
        task = f["data"].attrs.get("task")
    if names is not None:
        try:
            tasks = json.loads(names)
        except (TypeError, ValueError):
            tasks = None
        if not isinstance(tasks, list) or not all(isinstance(n, str) for n in tasks):
            raise FileFormatError(f"demonstration file {path}: the task_names attribute must be a JSON list of "
                                  f"task names, got {names!r}")
        return tasks
    if task is not None and libero.is_suite(str(task)):
        return libero.task_names(str(task))
    raise FileFormatError(f"demonstration file {path} has task_index observations but no task_names attribute")


def _lr(step: int, steps: int, peak: float, warmup: int) -> float:
    if step < warmup:
        return peak * (step + 1) / warmup
    progress = (step - warmup) / max(1, steps - warmup)
    return peak * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * progress)))


def train(task: str, data, out: str | Path, *, steps: int = 3000, batch_size: int = 128,
          lr: float = 1e-3, hidden_size: int = 256, intermediate_size: int = 768, layers: int = 4,
          heads: int = 4, seed: int = 0, save_every: int = 250, validation_demos: int = 10,
          observation_names: list[str] | None = None, command: str = "", progress: bool = True) -> TokenPolicy:
    """Trains (or resumes training of) a policy and saves it under ``out``; returns the policy.

    ``data``: one demonstration file or a list of them (their demos in order; the last
    ``validation_demos`` of the last file are held out)."""
    from tqdm import tqdm

    data = str(data) if isinstance(data, (str, Path)) else [str(p) for p in data]
    source = data if isinstance(data, str) else ",".join(data)

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    observations, actions, stored_names = load_demonstrations(data)
    names = observation_names or stored_names or [f"obs_{i}" for i in range(observations[0].shape[1])]
    if len(observations) <= validation_demos:
        raise ValueError(f"need more than validation_demos={validation_demos} demonstrations, "
                         f"{source} has {len(observations)}")
    # The last demos are held out: validation token accuracy says whether training still helps.
    train_obs = np.concatenate(observations[:-validation_demos]) if validation_demos else np.concatenate(observations)
    train_act = np.concatenate(actions[:-validation_demos]) if validation_demos else np.concatenate(actions)
    val_obs = np.concatenate(observations[-validation_demos:]) if validation_demos else train_obs[:0]
    val_act = np.concatenate(actions[-validation_demos:]) if validation_demos else train_act[:0]

    torch.manual_seed(seed)
    tasks = task_names_of(data) if names and names[0] == TASK_INDEX else []
    binned = train_obs[:, 1:] if tasks else train_obs
    config = PolicyConfig(
        task=task,
        tasks=tasks,
        observation_names=list(names),
        observation_tokenizer=BinTokenizer.range_with_margin(binned).to_dict(),
        action_tokenizer=BinTokenizer.percentiles(train_act).to_dict(),
        hidden_size=hidden_size, intermediate_size=intermediate_size, layers=layers, heads=heads,
        training={"data": source, "demos": len(observations) - validation_demos, "samples": len(train_obs),
                  "steps": steps, "batch_size": batch_size, "lr": lr, "seed": seed, "command": command},
    )
    policy = TokenPolicy(config)
    ids, targets = policy.sequences(train_obs, train_act)
    val_ids, val_targets = policy.sequences(val_obs, val_act)
    optimizer = torch.optim.AdamW(policy.model.parameters(), lr=lr, weight_decay=0.01, betas=(0.9, 0.95))

    start, loss_value = 0, float("nan")
    state_path = out / STATE_FILE
    if state_path.is_file():
        state = torch.load(state_path, weights_only=False)
        if state["config"] != config.to_dict():
            raise ValueError(f"{state_path} was written for another configuration; remove it to start over")
        policy.model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        start, loss_value = state["step"], state["loss"]
        print(f"resuming from step {start} of {steps}")

    def validation_accuracy() -> float:
        if not len(val_ids):
            return float("nan")
        policy.model.eval()
        with torch.no_grad():
            predicted = policy.action_logits(val_ids[:2048]).argmax(-1)
        policy.model.train()
        return float((predicted == val_targets[:2048]).float().mean())

    def save_state(step: int) -> None:
        tmp = state_path.with_suffix(".tmp")
        torch.save({"config": config.to_dict(), "model": policy.model.state_dict(),
                    "optimizer": optimizer.state_dict(), "step": step, "loss": loss_value}, tmp)
        tmp.replace(state_path)

    policy.model.train()
    bar = tqdm(range(start, steps), initial=start, total=steps, disable=not progress, desc=f"train {task}")
    begin = time.perf_counter()
    for step in bar:
        rng = np.random.default_rng([seed, step])
        index = torch.from_numpy(rng.integers(0, len(ids), size=batch_size))
        for group in optimizer.param_groups:
            group["lr"] = _lr(step, steps, lr, warmup=min(200, steps // 10 + 1))
        logits = policy.action_logits(ids[index])
        loss = torch.nn.functional.cross_entropy(logits.reshape(-1, logits.shape[-1]), targets[index].reshape(-1))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.model.parameters(), 1.0)
        optimizer.step()
        current = loss.item()
        loss_value = current if math.isnan(loss_value) else 0.9 * loss_value + 0.1 * current
        if (step + 1) % save_every == 0 or step + 1 == steps:
            save_state(step + 1)
            bar.set_postfix(loss=f"{loss_value:.3f}", val_acc=f"{validation_accuracy():.3f}")
    policy.model.eval()
    config.training.update({"final_loss": loss_value, "validation_token_accuracy": validation_accuracy(),
                            "seconds_this_run": round(time.perf_counter() - begin, 1)})
    policy.save(out)
    save_calibration_set(out, train_obs, train_act, seed)
    train_demos = actions[:-validation_demos] if validation_demos else actions
    dispatch_budget.save(out, *dispatch_budget.budget_dispatch(train_demos), source=source)
    return policy


def save_calibration_set(out: Path, observations: np.ndarray, actions: np.ndarray, seed: int) -> None:
    """A random sample of training steps saved beside the checkpoint, so that methods which calibrate
    on data (activation smoothing, threshold calibration) use training data, never evaluation episodes."""
    from safetensors.numpy import save_file

    rng = np.random.default_rng([seed, 1 << 20])
    index = np.sort(rng.choice(len(observations), size=min(CALIBRATION_SAMPLES, len(observations)), replace=False))
    save_file({"observations": np.ascontiguousarray(observations[index], dtype=np.float32),
               "actions": np.ascontiguousarray(actions[index], dtype=np.float32)}, str(out / CALIBRATION_FILE))


def load_calibration_set(checkpoint: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The training observations and actions saved with a checkpoint by :func:`train`."""
    from safetensors.numpy import load_file

    path = Path(checkpoint) / CALIBRATION_FILE
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {checkpoint} has no {CALIBRATION_FILE} (written by dyq train)")
    data = load_file(str(path))
    return data["observations"], data["actions"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..apps.usage import input_file, nonnegative_int, output_dir, positive_float, positive_int

    parser.add_argument("task", help="task name (lift, pick_place_can, square, libero_object, libero_spatial)")
    parser.add_argument("--data", required=True, type=input_file(".hdf5", ".h5"), nargs="+",
                        help="demonstrations (HDF5, robomimic layout) from `dyq collect`: one file or several")
    parser.add_argument("--out", required=True, type=output_dir, help="output folder for the checkpoint")
    parser.add_argument("--steps", type=positive_int, default=3000)
    parser.add_argument("--batch-size", type=positive_int, default=128)
    parser.add_argument("--lr", type=positive_float, default=1e-3)
    parser.add_argument("--hidden-size", type=positive_int, default=256)
    parser.add_argument("--intermediate-size", type=positive_int, default=768)
    parser.add_argument("--layers", type=positive_int, default=4)
    parser.add_argument("--heads", type=positive_int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--save-every", type=positive_int, default=250)
    parser.add_argument("--validation-demos", type=nonnegative_int, default=10)
    parser.add_argument("--threads", type=nonnegative_int, default=0, help="torch threads (0: torch's default)")


def main(args: argparse.Namespace) -> int:
    from . import envs

    if args.threads:
        torch.set_num_threads(args.threads)
    command = "dyq train " + " ".join(shlex.quote(a) for a in sys.argv[2:]) if len(sys.argv) > 2 else ""
    data = args.data[0] if len(args.data) == 1 else args.data
    policy = train(args.task, data, args.out, steps=args.steps, batch_size=args.batch_size, lr=args.lr,
                   hidden_size=args.hidden_size, intermediate_size=args.intermediate_size, layers=args.layers,
                   heads=args.heads, seed=args.seed, save_every=args.save_every,
                   validation_demos=args.validation_demos, command=command,
                   observation_names=envs.observation_names(args.task) if args.task in envs.ALL_TASKS else None)
    info = policy.config.training
    print(f"saved {args.out}: loss {info['final_loss']:.3f}, validation token accuracy "
          f"{info['validation_token_accuracy']:.3f}")
    return 0
