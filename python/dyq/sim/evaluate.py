"""``dyq eval``: the closed-loop table, a task x configuration x seed grid run in worker processes.

Every episode is cached as one gzipped JSON file keyed by (task, configuration, seed, checkpoint
digest), so an interrupted run resumes, a new configuration adds rows without re-running the others,
and a retrained checkpoint never mixes with an old one. A configuration that runs the dispatcher (and a
random schedule drawn from DyQ's episodes) is keyed by its effective dispatcher config as well
(:func:`config_cache_name`), so a recalibrated or re-budgeted dispatcher never reuses old episodes.
After the grid, the summary of every cached episode in the grid is merged into ``bench/results/closed_loop.json`` (other tasks and configurations
already there are kept) and the markdown table is rewritten.

Seeds are fixed lists, written into the results: evaluation seeds are ``0 .. episodes-1`` (disjoint from
the demonstration seeds, which start at :data:`dyq.sim.envs.DEMO_SEED0`), the same for every
configuration, so configurations are compared pairwise on the same initial states.
"""
from __future__ import annotations

import argparse
import gzip
import hashlib
import json
import math
import multiprocessing
import os
from pathlib import Path
from typing import Any

import numpy as np

from .. import results as results_io
from ..errors import FileFormatError
from ..analysis.stats import paired_comparison, wilson_interval
from . import envs

DEFAULT_OUT = Path("bench/results/closed_loop.json")
DEFAULT_TABLE = Path("docs/closed_loop.md")
DEFAULT_CACHE = Path(".cache/closed_loop")
WIDTHS = (2, 4, 8, 16)
# The weight methods the closed loop runs besides round-to-nearest (rollout.WEIGHT_METHODS, named here so
# that summarizing needs no torch).
WEIGHT_METHODS = ("mse", "awq", "gptq")
# Paired comparisons reported for every task: (configuration, against).
COMPARISONS = (("dyq", "fp32"), ("dyq", "w4a16"), ("dyq", "w4a2"), ("dyq", "random_schedule"),
               ("dyq", "random_runs"), ("dyq_inverted", "dyq"), ("dyq_calibrated", "fp32"), ("dyq_calibrated", "dyq"),
               # Another weight method against round-to-nearest at the same width.
               *((f"{method}_{config}", config) for method in WEIGHT_METHODS for config in ("w4a4", "w4a2", "dyq")))
# The target of the closed loop (paper Table I's claim): DyQ keeps this share of fp32's success ...
TARGET_RETENTION = 0.995
# ... with at least this share of its control steps below 8 bits.
TARGET_SHARE_BELOW_8 = 0.60
# The LIBERO suites: LIBERO's own initial states, ten episodes per task by default, and the configs that
# Table I of the paper needs.
SUITE_CONFIGS = "fp32,w4a16,w4a8,w4a4,w4a2,dyq,random_schedule"
SUITE_EPISODES = 100
# DyQ-VLA's Table I (OpenVLA-7B fine-tuned on LIBERO's human demonstrations, 200 trials per suite), success %.
PAPER_TABLE_I = {
    "libero_object": {"BF16": 88.4, "SmoothQuant W4A4": 73.2, "QVLA W4A4": 87.6, "DyQ-VLA W4AX": 87.8},
    "libero_spatial": {"BF16": 84.7, "SmoothQuant W4A4": 69.2, "QVLA W4A4": 84.4, "DyQ-VLA W4AX": 84.7},
}


def checkpoint_label(checkpoint: str | os.PathLike) -> str:
    """How results name a checkpoint: a shipped policy as ``dyq/sim/policies/<task>`` wherever dyq is
    installed, another folder relative to the working directory when inside it, else absolute."""
    path = Path(checkpoint).resolve()
    shipped = Path(__file__).resolve().parent / "policies"
    if path.is_relative_to(shipped):
        return str(Path("dyq/sim/policies") / path.relative_to(shipped))
    return str(path.relative_to(Path.cwd())) if path.is_relative_to(Path.cwd()) else str(path)


CHECKPOINT_FILES = ("policy.json", "model.safetensors")


def check_checkpoint_files(checkpoint: Path, task: str) -> None:
    """A command-line mistake (one line) if ``checkpoint`` lacks a file of a trained policy."""
    from ..apps.usage import UsageError

    for name in CHECKPOINT_FILES:
        if not (checkpoint / name).is_file():
            raise UsageError(f"checkpoint {checkpoint} has no {name}: train one with `dyq train {task}` "
                             "or pass --checkpoint")


def checkpoint_digest(checkpoint: str | os.PathLike) -> str:
    """First 12 hex digits of the SHA-256 of the checkpoint's weights and config."""
    h = hashlib.sha256()
    for name in CHECKPOINT_FILES:
        h.update((Path(checkpoint) / name).read_bytes())
    return h.hexdigest()[:12]


def cache_path(cache: Path, task: str, config: str, seed: int, digest: str) -> Path:
    """``config`` is the configuration's cache name (:func:`config_cache_name`)."""
    return cache / task / digest / config / f"seed_{seed:05d}.json.gz"


def dispatch_digest(run: "RunConfig", checkpoint: str | os.PathLike) -> str:
    """First 8 hex digits of the SHA-256 of everything DyQ's dispatcher runs on in ``run``: the effective
    config (the checkpoint's ``dispatch.json`` with the run's overrides), the priming actions and the
    ladder's direction."""
    from . import dispatch_budget
    import dyq

    base, prime = (dispatch_budget.load(checkpoint) if (Path(checkpoint) / dispatch_budget.DISPATCH_FILE).is_file()
                   else (dyq.DispatchConfig(), None))
    h = hashlib.sha256(json.dumps(run.dispatch_config(base).to_dict(), sort_keys=True).encode())
    h.update(b"inverted" if run.inverted else b"")
    if prime is not None:
        h.update(np.ascontiguousarray(prime, dtype=np.float64).tobytes())
    return h.hexdigest()[:8]


def config_cache_name(run: "RunConfig", checkpoint: str | os.PathLike) -> str:
    """The cache folder of a configuration: its name, and for one that depends on the dispatcher
    (``dyq*``, and the schedules drawn from ``dyq``), ``name@<dispatch digest>``."""
    from .rollout import run_config

    if run.kind == "dyq":
        return f"{run.name}@{dispatch_digest(run, checkpoint)}"
    if run.kind == "schedule":
        return f"{run.name}@{dispatch_digest(run_config('dyq'), checkpoint)}"
    return run.name


def _read_episode(path: Path) -> dict[str, Any]:
    try:
        with gzip.open(path, "rt") as f:
            return json.load(f)
    except (OSError, EOFError, ValueError) as error:  # gzip's BadGzipFile is an OSError; JSON errors ValueErrors
        raise FileFormatError(f"episode record {path} is not one written by dyq eval ({error}): delete it to run "
                              f"the episode again") from None


def _write_episode(path: Path, episode: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp")
    with gzip.open(tmp, "wt") as f:
        json.dump(episode, f)
    tmp.replace(path)


# -- worker processes -----------------------------------------------------------------------------

_WORKER: dict[str, Any] = {}


def _worker_init(threads: int) -> None:
    import torch

    torch.set_num_threads(threads)


Job = tuple  # (task, RunConfig, seed, checkpoint, cache path, schedule or None)


def _worker_run(job: Job) -> tuple[str, str, int, bool, int]:
    """Runs one episode in a worker (policy and environment built once per process) and caches it."""
    from .rollout import PolicyRunner, run_episode

    task, config, seed, checkpoint, path, schedule = job
    if _WORKER.get("checkpoint") != checkpoint:
        _WORKER.update(checkpoint=checkpoint, runner=PolicyRunner.load(checkpoint))
    env_key = ("env", task)
    if env_key not in _WORKER:
        _WORKER[env_key] = envs.make_env(task)
    episode = run_episode(_WORKER["runner"], task, config, seed, env=_WORKER[env_key], schedule=schedule)
    _write_episode(Path(path), episode.to_dict())
    return task, config.name, seed, episode.success, episode.steps


def run_grid(jobs: list[Job], workers: int, progress: bool = True) -> None:
    """Runs the jobs not yet cached, in ``workers`` processes with one torch thread each."""
    from tqdm import tqdm

    if not jobs:
        return
    # Jobs sorted by checkpoint so that a worker rarely has to load another policy.
    jobs = sorted(jobs, key=lambda j: (j[3], j[0], j[2], j[1].name))
    bar = tqdm(total=len(jobs), disable=not progress, desc="episodes")
    successes = 0
    if workers <= 1:
        _worker_init(1)
        for job in jobs:
            successes += _worker_run(job)[3]
            bar.update(1)
            bar.set_postfix(success=f"{successes}/{bar.n}")
    else:
        context = multiprocessing.get_context("spawn")
        with context.Pool(workers, initializer=_worker_init, initargs=(1,)) as pool:
            for result in pool.imap_unordered(_worker_run, jobs, chunksize=1):
                successes += result[3]
                bar.update(1)
                bar.set_postfix(success=f"{successes}/{bar.n}")
    bar.close()


# -- summaries --------------------------------------------------------------------------------------

def run_lengths(bits: list[int]) -> str:
    """``bits`` as runs, e.g. ``"16x10 8x3 2x40"``: compact, and what a run-preserving shuffle needs."""
    runs: list[list[int]] = []
    for b in bits:
        if runs and runs[-1][0] == b:
            runs[-1][1] += 1
        else:
            runs.append([b, 1])
    return " ".join(f"{b}x{n}" for b, n in runs)


def summarize(episodes: list[dict[str, Any]]) -> dict[str, Any]:
    """One configuration's row: success with its Wilson interval, widths, latency and the per-seed record."""
    episodes = sorted(episodes, key=lambda e: e["seed"])
    n = len(episodes)
    successes = sum(e["success"] for e in episodes)
    bits = np.concatenate([np.asarray(e["bits"]) for e in episodes]) if episodes else np.zeros(0)
    kernel = {str(w): 0 for w in WIDTHS}
    mismatched = 0
    for e in episodes:
        for chosen, decode, prefill in zip(e["bits"], e["decode_kernel_bits"], e["prefill_kernel_bits"]):
            for counts in (decode, prefill):
                for width, calls in counts.items():
                    kernel[width] = kernel.get(width, 0) + calls
            # The decode's GEMMs must all have run at the published width (the float policy runs none).
            if decode and set(decode) != {str(chosen)}:
                mismatched += 1
    kernel_total = sum(kernel.values())
    latency = np.concatenate([np.asarray(e["latency_ms"]) for e in episodes]) if episodes else np.zeros(0)
    lo, hi = wilson_interval(successes, n) if n else (math.nan, math.nan)
    per_task = {}
    if episodes and envs.libero.is_suite(episodes[0].get("task", "")):
        for e in episodes:
            tally = per_task.setdefault(str(envs.libero.task_of_seed(e["seed"])[0]), [0, 0])
            tally[0] += int(e["success"])
            tally[1] += 1
        per_task = dict(sorted(per_task.items(), key=lambda kv: int(kv[0])))
    return {
        "episodes": n,
        "successes": int(successes),
        "success_rate": successes / n if n else math.nan,
        "wilson95": [lo, hi],
        "mean_bits": float(bits.mean()) if len(bits) else math.nan,
        "bits_share": {str(w): float((bits == w).mean()) if len(bits) else 0.0 for w in WIDTHS},
        "share_below_8": float((bits < 8).mean()) if len(bits) else 0.0,
        "kernel_bits_share": {w: c / kernel_total for w, c in kernel.items()} if kernel_total else {},
        "steps_with_mismatched_kernel_bits": mismatched,
        "mean_steps": float(np.mean([e["steps"] for e in episodes])) if episodes else math.nan,
        "latency_ms": {
            "median": float(np.median(latency)) if len(latency) else math.nan,
            "p90": float(np.percentile(latency, 90)) if len(latency) else math.nan,
            "mean": float(latency.mean()) if len(latency) else math.nan,
        },
        **({"per_task": per_task} if per_task else {}),
        # The CPU path(s) the episodes ran on, when every episode records it (update_results fills the rest).
        **({"cpu_isa": "+".join(sorted({e["cpu_isa"] for e in episodes}))}
           if episodes and all(e.get("cpu_isa") for e in episodes) else {}),
        "per_seed": {
            str(e["seed"]): {"success": bool(e["success"]), "steps": e["steps"],
                             "mean_bits": float(np.mean(e["bits"])), "bits_runs": run_lengths(e["bits"])}
            for e in episodes
        },
    }


def compare(rows: dict[str, Any], config: str, against: str) -> dict[str, Any] | None:
    """Paired comparison of two configurations on the seeds both have."""
    if config not in rows or against not in rows:
        return None
    a, b = rows[config]["per_seed"], rows[against]["per_seed"]
    seeds = sorted(set(a) & set(b), key=int)
    if not seeds:
        return None
    result = paired_comparison(np.array([a[s]["success"] for s in seeds]), np.array([b[s]["success"] for s in seeds]))
    result["verdict"] = result["verdict"].replace("A better", f"{config} better").replace("B better", f"{against} better")
    return {"config": config, "against": against, **result}


def _jsonable(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    return value


def update_results(out: Path, task: str, seeds: list[int], checkpoint: str, digest: str,
                   rows: dict[str, Any]) -> dict[str, Any]:
    """Merges one task's rows into the results file (where write_json puts it); returns the whole file's
    content."""
    out = results_io.results_path(out)
    try:
        data = json.loads(out.read_text()) if out.is_file() else {"tasks": {}}
        if not isinstance(data, dict) or not isinstance(data.get("tasks"), dict):
            raise ValueError("no tasks")
    except ValueError as error:
        raise FileFormatError(f"results file {out} is not one written by dyq eval ({error}): move it away to start "
                              f"a new one") from None
    entry = data["tasks"].setdefault(task, {"configs": {}})
    if entry.get("checkpoint_digest") not in (None, digest):
        entry["configs"] = {}  # a retrained policy: the old rows describe another policy
        entry["seeds"] = []
    # The task's seeds are those of all its rows: a run of fewer seeds (one new row on 50 seeds) leaves
    # the rows measured on more as they are, and the header must still cover them.
    seeds = sorted(set(entry.get("seeds", [])) | set(seeds))
    entry.update(horizon=envs.spec(task).horizon, seeds=seeds, checkpoint=checkpoint_label(checkpoint),
                 checkpoint_digest=digest)
    import dyq

    # The CPU kernel path each row ran on: its W4A16 fallback is bf16 on CPUs with AVX512-BF16 and fp32 on
    # the others, so rows merged from machines of different kinds say which numerics they had. Rows written
    # before the field existed take the task's former single value.
    earlier_isa = entry.pop("cpu_isa", None)
    for row in entry["configs"].values():
        if earlier_isa is not None:
            row.setdefault("cpu_isa", earlier_isa)
    # A row whose episodes do not all record their path (cached before they did) keeps the path the row was
    # first written with, so re-summarizing it on another machine does not relabel it; a new one takes this
    # machine's.
    isa = dyq.cpu_info()["isa"]
    entry["configs"].update({
        name: {**row, "cpu_isa": row.get("cpu_isa") or entry["configs"].get(name, {}).get("cpu_isa") or isa}
        for name, row in rows.items()})
    entry["comparisons"] = [c for c in (compare(entry["configs"], a, b) for a, b in COMPARISONS) if c]
    data["device"] = "cpu"
    data["environment"] = results_io.environment()
    try:
        import mujoco
        import robosuite

        # Per task: the LIBERO suites run in an environment of their own, with another robosuite.
        entry["versions"] = {"robosuite": robosuite.__version__, "mujoco": mujoco.__version__}
        if not envs.libero.is_suite(task):
            data["versions"] = entry["versions"]
    except ImportError:
        pass
    data = _jsonable(data)
    results_io.write_json(out, data)
    return data


def _shown_path(path: Path) -> Path:
    """path relative to the working directory where it lies under it (as the repository's tables name their
    JSON), else as it is."""
    try:
        return path.resolve().relative_to(Path.cwd().resolve())
    except ValueError:
        return path


def markdown_table(data: dict[str, Any], source: str | os.PathLike = DEFAULT_OUT) -> str:
    """The results as the Markdown table that ``dyq eval --table`` writes; ``source`` names the JSON it came
    from (``--out``: the perturbed states' rows have a file of their own)."""
    lines = ["# Closed-loop results", "",
             f"Written by `dyq eval` from `{Path(source).as_posix()}`; do not edit by hand. Success with its",
             "Wilson 95 % interval; bits are the decode's activation width per control step (16 = unquantized);",
             "latency is the policy's prefill + decode per control step on the CPU (median).", ""]
    for task, entry in data["tasks"].items():
        seeds = entry["seeds"]
        lines += [f"## {task}", "",
                  f"Horizon {entry['horizon']} steps; seeds {seeds[0]}..{seeds[-1]} ({len(seeds)}); "
                  f"checkpoint `{entry['checkpoint']}` ({entry['checkpoint_digest']}).", "",
                  "| config | success | Wilson 95 % | mean bits | steps < 8 bits | 2 / 4 / 8 / 16 bits | steps | ms/step |",
                  "|---|---|---|---|---|---|---|---|"]
        for name, row in entry["configs"].items():
            lo, hi = row["wilson95"]
            share = row["bits_share"]
            lines.append(
                f"| {name} | {row['successes']}/{row['episodes']} ({100 * row['success_rate']:.0f} %) "
                f"| [{100 * lo:.0f}, {100 * hi:.0f}] % | {row['mean_bits']:.2f} | {100 * row['share_below_8']:.0f} % "
                f"| {' / '.join(f'{100 * share[str(w)]:.0f}' for w in WIDTHS)} % | {row['mean_steps']:.0f} "
                f"| {row['latency_ms']['median']:.1f} |")
        isas = {row.get("cpu_isa") for row in entry["configs"].values()} - {None}
        if len(isas) > 1:  # the W4A16 fallback's numerics follow the CPU path (docs/numerics.md)
            lines += ["", "CPU kernel path per row: " + ", ".join(
                f"{name} {row.get('cpu_isa', '?')}" for name, row in entry["configs"].items()) + "."]
        reference = entry["configs"].get("fp32")
        for name in ("dyq", "dyq_calibrated"):
            row = entry["configs"].get(name)
            if row and reference and reference["successes"]:
                retention = row["success_rate"] / reference["success_rate"]
                met = retention >= TARGET_RETENTION and row["share_below_8"] >= TARGET_SHARE_BELOW_8
                lines += ["", f"{name} keeps {100 * retention:.0f} % of fp32's success rate with "
                              f"{100 * row['share_below_8']:.0f} % of its steps below 8 bits (target: "
                              f"{100 * TARGET_RETENTION:.1f} % with {100 * TARGET_SHARE_BELOW_8:.0f} %): "
                              f"{'met' if met else 'not met'} on these {row['episodes']} seeds."]
        if any("per_task" in row for row in entry["configs"].values()):
            lines += ["", "Per LIBERO task (successes / episodes, task index: see `dyq.sim.libero.task_names`):", "",
                      "| config | " + " | ".join(str(i) for i in range(envs.libero.TASKS_PER_SUITE)) + " |",
                      "|---|" + "---|" * envs.libero.TASKS_PER_SUITE]
            for name, row in entry["configs"].items():
                cells = [f"{row['per_task'][str(i)][0]}/{row['per_task'][str(i)][1]}" if str(i) in row.get("per_task", {})
                         else "" for i in range(envs.libero.TASKS_PER_SUITE)]
                lines.append(f"| {name} | " + " | ".join(cells) + " |")
        if task in PAPER_TABLE_I:
            paper = ", ".join(f"{k} {v:.1f} %" for k, v in PAPER_TABLE_I[task].items())
            lines += ["", f"The paper's Table I for this suite: {paper}. Its policy is OpenVLA-7B fine-tuned on "
                          "LIBERO's human demonstrations and evaluated with camera images; ours is dyq's small "
                          "state-token policy cloned from dyq's scripted expert, so only the shape compares."]
        if entry.get("comparisons"):
            lines += ["", "Paired on the same seeds (exact McNemar test on the discordant seeds):", ""]
            for c in entry["comparisons"]:
                lines.append(f"- {c['config']} vs {c['against']}: {c['successes_a']} vs {c['successes_b']} of {c['n']}, "
                             f"discordant {c['a_only']} / {c['b_only']}, p = {c['p_value']:.3g}: {c['verdict']}")
        lines.append("")
    return "\n".join(lines)


# -- command line -----------------------------------------------------------------------------------

def default_checkpoint(task: str) -> Path:
    """The policy trained for ``task`` that ships with dyq (``dyq/sim/policies/<task>``)."""
    return Path(__file__).resolve().parent / "policies" / task


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..apps.usage import comma_list, name_equals_folder, output_dir, output_file, positive_int

    parser.add_argument("--tasks", type=comma_list(envs.ALL_TASKS), default=None,
                        help="comma-separated task names (default: lift,pick_place_can,square)")
    parser.add_argument("--suite", choices=sorted(envs.LIBERO_TASKS), default=None,
                        help=f"a LIBERO suite (in the `libero` environment): its task, configs {SUITE_CONFIGS} "
                             f"and {SUITE_EPISODES} episodes by default, on LIBERO's official initial states")
    parser.add_argument("--configs", default=None,
                        help="comma-separated configurations (default: fp32,w4a16,w4a8,w4a4,w4a2,dyq)")
    parser.add_argument("--episodes", type=positive_int, default=None,
                        help=f"seeds 0 .. episodes-1 per task and configuration (default: 50; {SUITE_EPISODES} "
                             "for a suite: seed s is task s %% 10 from its official initial state s // 10)")
    parser.add_argument("--seed0", type=int, default=0,
                        help="first seed (default 0); a LIBERO suite's seeds from 500 on are perturbed states: "
                             "write those rows to their own --out and --table")
    parser.add_argument("--checkpoint", type=name_equals_folder(envs.ALL_TASKS), action="append", default=[],
                        metavar="TASK=DIR",
                        help="policy checkpoint for a task (default: the one that ships with dyq)")
    parser.add_argument("--workers", type=positive_int, default=max(1, (os.cpu_count() or 1)))
    parser.add_argument("--cache", type=output_dir, default=DEFAULT_CACHE)
    parser.add_argument("--out", type=output_file(".json"), default=DEFAULT_OUT)
    parser.add_argument("--table", type=output_file(".md"), default=DEFAULT_TABLE)
    parser.add_argument("--video", type=output_dir, default=None, metavar="DIR",
                        help="also record seed 0 of each task (under dyq if evaluated) as DIR/<task>_<config>_seed0.gif")
    parser.add_argument("--summarize-only", action="store_true",
                        help="run nothing: merge the episodes cached so far into the results and the table")
    parser.add_argument("--no-progress", action="store_true")


def main(args: argparse.Namespace) -> int:
    from ..apps.usage import UsageError
    from .profile import calibrated_run_config
    from .rollout import CALIBRATED, run_config

    if args.suite and args.tasks:
        raise ValueError("give --suite or --tasks, not both")
    tasks = [args.suite] if args.suite else args.tasks or ["lift", "pick_place_can", "square"]
    configs = [c for c in (args.configs or (SUITE_CONFIGS if args.suite else "fp32,w4a16,w4a8,w4a4,w4a2,dyq")).split(",") if c]
    if not configs:
        raise UsageError(f"--configs {args.configs!r} names no configuration")
    if args.episodes is None:
        args.episodes = SUITE_EPISODES if args.suite else 50
    for config in configs:
        if config != CALIBRATED:
            try:
                run_config(config)
            except ValueError as error:
                raise UsageError(f"--configs: {error}") from None
    if args.episodes < 1:
        raise ValueError(f"--episodes must be >= 1, got {args.episodes}")
    checkpoints = {task: default_checkpoint(task) for task in tasks}
    for task, directory in args.checkpoint:
        if task not in tasks:
            raise ValueError(f"--checkpoint {task}={directory}: {task!r} is not evaluated (tasks: {tasks})")
        checkpoints[task] = directory
    for task in tasks:
        check_checkpoint_files(checkpoints[task], task)
    digests = {task: checkpoint_digest(checkpoints[task]) for task in tasks}
    # Each task's configurations, dyq_calibrated from that task's calibration of this very checkpoint.
    resolved = {task: {name: (calibrated_run_config(task, checkpoint_digest=digests[task]) if name == CALIBRATED
                              else run_config(name)) for name in configs + ["dyq"]} for task in tasks}
    cache_names = {task: {name: config_cache_name(run, checkpoints[task]) for name, run in resolved[task].items()}
                   for task in tasks}
    if args.seed0 < 0:
        raise ValueError(f"--seed0 must be >= 0, got {args.seed0}")
    seeds = list(range(args.seed0, args.seed0 + args.episodes))
    scheduled = [c for c in configs if resolved[tasks[0]][c].kind == "schedule"] if tasks else []
    # Schedules are drawn from DyQ's episode on the same seed, so those run first.
    first = [c for c in configs if c not in scheduled] + (["dyq"] if scheduled and "dyq" not in configs else [])

    def path_of(task: str, config: str, seed: int) -> Path:
        return cache_path(args.cache, task, cache_names[task][config], seed, digests[task])

    def pending(names: list[str], schedule_of=None) -> list[Job]:
        jobs = []
        for task in tasks:
            for config in names:
                for seed in seeds:
                    path = path_of(task, config, seed)
                    if not path.is_file():
                        schedule = schedule_of(task, config, seed) if schedule_of else None
                        jobs.append((task, resolved[task][config], seed, str(checkpoints[task]), str(path), schedule))
        return jobs

    def schedule_of(task: str, config: str, seed: int) -> list[int]:
        from .rollout import make_schedule

        dyq_bits = _read_episode(path_of(task, "dyq", seed))["bits"]
        return make_schedule(resolved[task][config].schedule, dyq_bits, seed, envs.spec(task).horizon)

    total = len(tasks) * len(set(first) | set(scheduled)) * len(seeds)
    if not args.summarize_only:
        jobs = pending(first)
        print(f"{total} episodes in the grid, {len(jobs)} to run before the schedules")
        run_grid(jobs, args.workers, progress=not args.no_progress)
        jobs = pending(scheduled, schedule_of)
        if jobs:
            print(f"{len(jobs)} scheduled episodes to run")
            run_grid(jobs, args.workers, progress=not args.no_progress)

    data = None
    for task in tasks:
        rows = {}
        for config in configs:
            # With --summarize-only, the episodes cached so far (a row says how many it holds).
            paths = [path_of(task, config, s) for s in seeds]
            episodes = [_read_episode(p) for p in paths if p.is_file()]
            if episodes:
                rows[config] = summarize(episodes)
        data = update_results(args.out, task, seeds, checkpoints[task], digests[task], rows)
    args.table.parent.mkdir(parents=True, exist_ok=True)
    args.table.write_text(markdown_table(data, _shown_path(results_io.results_path(args.out))))
    try:
        from .plots import plot_success_vs_bits

        for task in (t for t in tasks if data["tasks"][t]["configs"]):  # a task with no episodes yet: no figure
            # Named after the table (closed_loop_<task>.png beside docs/closed_loop.md), so that rows written
            # to another table (the perturbed states') do not overwrite the figure of the official ones.
            figure = args.table.parent / "figures" / f"{args.table.stem}_{task}.png"
            print(f"wrote {plot_success_vs_bits(data['tasks'][task], task, figure)}")
    except RuntimeError as err:  # no matplotlib: the table is still complete
        print(f"no figure: {err}")
    print(markdown_table(data, _shown_path(results_io.results_path(args.out))))
    print(f"wrote {results_io.results_path(args.out)} and {args.table}")
    if args.video is not None:
        from .rollout import PolicyRunner
        from .video import record_episode

        config = "dyq" if "dyq" in configs else configs[0]
        for task in tasks:
            path = args.video / f"{task}_{config}_seed{seeds[0]}.gif"
            episode = record_episode(PolicyRunner.load(checkpoints[task]), task, config, seeds[0], path)
            print(f"wrote {path} ({episode.steps} steps, {'success' if episode.success else 'failure'})")
    return 0
