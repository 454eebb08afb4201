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

from . import dispatch_budget
from .policy import TASK_INDEX, PolicyConfig, TokenPolicy
from .tokens import BinTokenizer

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
            observations += more_obs
            actions += more_act
        return observations, actions, names
    import h5py

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"demonstration file {path} does not exist")
    observations, actions = [], []
    with h5py.File(path, "r") as f:
        if "data" not in f:
            raise ValueError(f"{path} is not in robomimic's layout (no 'data' group)")
        names = sorted(f["data"].keys(), key=lambda k: int(k.rsplit("_", 1)[-1]))
        for name in names:
            demo = f["data"][name]
            observations.append(np.asarray(demo["obs"]["policy_vector"], dtype=np.float32))
            actions.append(np.asarray(demo["actions"], dtype=np.float32))
        observation_names = [str(n) for n in f["data"].attrs.get("policy_vector_names", [])]
    if not observations:
        raise ValueError(f"{path} holds no demonstrations")
    return observations, actions, observation_names


def task_names_of(path) -> list[str]:
    """The tasks of a multi-task demonstration file: its ``data`` attr ``task_names`` (a JSON list), or
    the LIBERO suite's task names where the file names a suite as its task. Several files must agree."""
    import h5py

    from . import libero

    if not isinstance(path, (str, Path)):
        paths = list(path)
        names = [task_names_of(p) for p in paths]
        for other, other_names in zip(paths[1:], names[1:]):
            if other_names != names[0]:
                raise ValueError(f"data: {other} holds tasks {other_names}, {paths[0]} holds {names[0]}")
        return names[0]

    with h5py.File(path, "r") as f:
        names = f["data"].attrs.get("task_names")
        task = f["data"].attrs.get("task")
    if names is not None:
        return [str(n) for n in json.loads(names)]
    if task is not None and libero.is_suite(str(task)):
        return libero.task_names(str(task))
    raise ValueError(f"{path} has task_index observations but no task_names attribute")


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
