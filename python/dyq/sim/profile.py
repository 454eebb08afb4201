"""``dyq profile`` and ``dyq calibrate``: the simulator drivers of the step-wise sensitivity profile
(paper Sec. III-A, III-B) and of the dispatcher's offline calibration (Sec. IV-B, VI-D). The numbers
are computed by :mod:`dyq.analysis`; definitions, rules, budgets and results: docs/profiling.md.

**Reference episodes.** A full-precision episode runs the float policy from ``reset_env(env, seed)``,
stepping with :func:`dyq.sim.envs.step_env` (the observation read from the state reached), until
success or the horizon, and records per step the observation vector, the action bins and the
executed (clipped) action. MuJoCo and the controller are deterministic, so resetting with the seed
and replaying the first t executed actions restores the state of step t exactly; :func:`restore`
checks that the observation vector comes back bit for bit.

**A perturbation** (:func:`perturb`) restores step t, runs that one step at a low activation width
(prefill and decode of the INT4 model, ``runner.flag.bits = b``), then the float policy up to the
reference's length T (no early stop, so D_T compares positions at the same time). e_t is the distance
between the two executed actions at step t, D_T = ||eef_T - eef*_T|| + ||object_T - object*_T|| (final
end-effector and object positions against the reference's), success is success at any step up to the
task's horizon, as the closed-loop table counts it: the reference succeeded first at T, so an episode
delayed by one step would otherwise count as a failure; one not done by T runs on until it succeeds
or the horizon ends (those steps decide success only). Width 16
is the float policy itself, a null perturbation (e_t = D_T = 0) that checks the machinery. A step
whose low-width action equals the reference's (e_t = 0) changes nothing downstream, so its result
(D_T = 0, the reference's success) is recorded without simulating it.

**Seeds.** Profiling and calibration use :data:`CALIBRATION_SEEDS` (5000..5999), disjoint from the
evaluation seeds (0..999) and the demonstrations' (100000+): the first seeds whose reference succeeds.
On a LIBERO suite these are perturbed initial states (every seed from 500 on is), ten per task in turn.

**Cache.** ``.cache/profile/<task>/<checkpoint digest>/`` holds one gzipped JSON per seed under
``reference/``, ``teacher/`` (teacher-forced errors), ``perturb/w<bits>/`` (rewritten after every
perturbed step) and ``sweep/<config key>/`` (closed-loop episodes of the theta_fp sweep), so an
interrupted command resumes where it stopped and a retrained checkpoint never mixes with an old one.
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import sys
import time
from pathlib import Path
from typing import NamedTuple, Sequence

import numpy as np

import dyq

from .. import results as results_io
from ..apps import usage
from ..analysis import (
    ProfiledStep,
    bound_parameters,
    calibrate_thresholds,
    choose_delay,
    choose_fusion_weight,
    choose_theta_fp,
    plot_perturbation_profile,
    plot_proxy_trajectories,
    proxy_correlations,
    wilson_interval,
    write_config,
)
from ..analysis.sensitivity import sensitivity
from . import envs
from .evaluate import (_jsonable, _read_episode, _write_episode, check_checkpoint_files, checkpoint_digest,
                       default_checkpoint)
from .rollout import PolicyRunner, RunConfig, run_episode

CALIBRATION_SEEDS = range(5000, 6000)
FULL_PRECISION = 16
QUANTIZED_WIDTHS = (2, 4, 8)
DEFAULT_CACHE = Path(".cache/profile")
RESULTS = Path("bench/results")
RESULT_STEMS = {"profile": "profile", "calibrate": "calibration"}  # command -> its result file's stem
FIGURES = Path("docs/figures")

# The success tolerance of each task in the units of D_T (metres): the positional margin of the task's
# own success test, fixed from the task's geometry before any profile or evaluation was run.
SUCCESS_TOLERANCE = {
    "lift": 0.04,  # the cube's centre must rise 4 cm above the table top
    "pick_place_can": 0.05,  # the expert's drop point lies 5 cm inside the bin quadrant's near edges
    "square": 0.03,  # the nut's centre must lie within 3 cm of the peg's axis in x and in y
    # LIBERO's predicates: "in" holds while the object's origin lies in the basket's contain-region box (half
    # size 6.1 cm in x and y); "on" needs contact within 3 cm of the plate's centre in x and y.
    "libero_object": 0.06,
    "libero_spatial": 0.03,
}


@dataclasses.dataclass(frozen=True)
class ProfileBudget:
    """What ``dyq profile`` samples: ``episodes`` successful references, each perturbed at every
    ``strides[i]``-th step (t = 0, stride, 2 stride, ...) at width ``widths[i]``.

    Only steps whose low-width action differs from the reference's cost a simulation (T - t policy
    steps); the rest are free, which is why the common W4A4 can afford stride 1 where W4A2, whose
    action differs at most steps, cannot."""

    episodes: int
    widths: tuple[int, ...]
    strides: tuple[int, ...]

    def __post_init__(self):
        if not isinstance(self.episodes, int) or self.episodes < 1:
            raise ValueError(f"episodes must be an integer >= 1, got {self.episodes!r}")
        if not self.widths or any(w not in QUANTIZED_WIDTHS for w in self.widths) or len(set(self.widths)) != len(self.widths):
            raise ValueError(f"widths must be distinct widths from {QUANTIZED_WIDTHS}, got {self.widths!r}")
        if len(self.strides) != len(self.widths) or any(not isinstance(k, int) or k < 1 for k in self.strides):
            raise ValueError(f"strides must hold one integer >= 1 per width {self.widths}, got {self.strides!r}")

    def steps(self, width: int, length: int) -> range:
        return range(0, length, self.strides[self.widths.index(width)])


# Sized for about 15 minutes a task on one niced, shared core (docs/profiling.md, "Budgets").
PROFILE_BUDGETS = {
    "lift": ProfileBudget(episodes=8, widths=(4, 2), strides=(1, 4)),
    "pick_place_can": ProfileBudget(episodes=3, widths=(4,), strides=(2,)),
    "square": ProfileBudget(episodes=3, widths=(4,), strides=(2,)),
    # LIBERO (in its own environment): ~120-step episodes on a slower scene, so every third step.
    "libero_object": ProfileBudget(episodes=3, widths=(4,), strides=(3,)),
    "libero_spatial": ProfileBudget(episodes=3, widths=(4,), strides=(3,)),
}
CALIBRATION_EPISODES = 20
# theta_fp sweep (Figure 7): these quantiles of the calibration steps' S_t.
THETA_FP_QUANTILES = (0.25, 0.5, 0.75, 0.9, 0.97, 1.0)


# -- episodes --------------------------------------------------------------------------------------

@dataclasses.dataclass
class Reference:
    """One full-precision episode, ``steps`` long, as the perturbations replay it."""

    task: str
    seed: int
    success: bool
    observations: np.ndarray  # (T, D) float32: what the policy saw at each step
    bins: np.ndarray  # (T, 7) int64: the action tokens it decoded
    actions: np.ndarray  # (T, 7) float64: the executed (clipped) actions
    final_eef: np.ndarray  # end-effector position after the last step
    final_object: np.ndarray  # the task object's position after the last step

    @property
    def steps(self) -> int:
        return len(self.actions)

    def to_dict(self) -> dict:
        return {"task": self.task, "seed": self.seed, "success": self.success,
                "observations": self.observations.tolist(), "bins": self.bins.tolist(),
                "actions": self.actions.tolist(), "final_eef": self.final_eef.tolist(),
                "final_object": self.final_object.tolist()}

    @classmethod
    def from_dict(cls, data: dict) -> "Reference":
        return cls(task=data["task"], seed=int(data["seed"]), success=bool(data["success"]),
                   observations=np.asarray(data["observations"], dtype=np.float32),
                   bins=np.asarray(data["bins"], dtype=np.int64),
                   actions=np.asarray(data["actions"], dtype=np.float64),
                   final_eef=np.asarray(data["final_eef"], dtype=np.float64),
                   final_object=np.asarray(data["final_object"], dtype=np.float64))


def act_at_width(runner: PolicyRunner, observation: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(bins, executed action) of one control step with prefill and decode at activation width
    ``width``: 2, 4 or 8 on the INT4 model, 16 the full-precision policy itself."""
    if width == FULL_PRECISION:
        policy = runner.float_policy
    elif width in QUANTIZED_WIDTHS:
        policy = runner.quantized_policy("rtn")
        runner.flag.bits = width
    else:
        raise ValueError(f"width must be one of {QUANTIZED_WIDTHS + (FULL_PRECISION,)}, got {width!r}")
    try:
        bins = policy.decode(policy.prefill(observation))
    finally:
        runner.flag.bits = FULL_PRECISION
    return bins, np.clip(policy.action(bins), -1.0, 1.0)  # clipped as the closed loop executes it


def _final_positions(task: str, obs: dict) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(obs["robot0_eef_pos"], dtype=np.float64), envs.object_pos(task, obs)


def _terminal_deviation(obs: dict, reference: "Reference") -> float:
    """D_T: distance of the end-effector plus distance of the object from the reference's final ones."""
    eef, obj = _final_positions(reference.task, obs)
    return float(np.linalg.norm(eef - reference.final_eef) + np.linalg.norm(obj - reference.final_object))


def reference_episode(runner: PolicyRunner, task: str, seed: int, env=None) -> Reference:
    """The full-precision episode of ``seed``, up to success or the task's horizon."""
    env = envs.make_env(task) if env is None else env
    obs = envs.reset_env(env, seed)
    observations, bins, actions = [], [], []
    success = False
    for _ in range(envs.spec(task).horizon):
        observation = envs.observation_vector(task, obs)
        step_bins, action = act_at_width(runner, observation, FULL_PRECISION)
        obs, _, _, _ = envs.step_env(env, action)
        observations.append(observation)
        bins.append(step_bins)
        actions.append(action)
        if envs.check_success(env):
            success = True
            break
    eef, obj = _final_positions(task, obs)
    return Reference(task, int(seed), success, np.asarray(observations, dtype=np.float32),
                     np.asarray(bins, dtype=np.int64), np.asarray(actions, dtype=np.float64), eef, obj)


def restore(env, reference: Reference, t: int) -> dict:
    """Reset to the reference's seed and replay its first ``t`` executed actions: the state of step t.
    Raises RuntimeError if the observation vector at t differs from the one recorded."""
    if not 0 <= t < reference.steps:
        raise ValueError(f"t must be in [0, {reference.steps}) for this {reference.steps}-step episode, got {t}")
    obs = envs.reset_env(env, reference.seed)
    for action in reference.actions[:t]:
        obs, _, _, _ = envs.step_env(env, action)
    observation = envs.observation_vector(reference.task, obs)
    if not np.array_equal(observation, reference.observations[t]):
        raise RuntimeError(f"replaying seed {reference.seed} to step {t} did not reproduce the recorded observation "
                           f"(max difference {np.abs(observation - reference.observations[t]).max():.3g}): "
                           "the reference was recorded with another environment or policy")
    return obs


class Perturbation(NamedTuple):
    action_error: float  # e_t
    terminal_deviation: float  # D_T: final end-effector distance + final object distance
    success: bool  # success at any step up to the horizon
    simulated: bool  # False: e_t = 0, the episode is the reference itself


def perturb(runner: PolicyRunner, reference: Reference, t: int, width: int, env=None) -> Perturbation:
    """The reference with step ``t`` at activation width ``width`` and the float policy elsewhere:
    D_T at the reference's length T, success up to the horizon (see the module docstring). Always
    simulates."""
    task = reference.task
    env = envs.make_env(task) if env is None else env
    obs = restore(env, reference, t)
    _, action = act_at_width(runner, reference.observations[t], width)
    error = float(np.linalg.norm(action - reference.actions[t]))
    # D_T at the reference's length T; success as the closed-loop table counts it, at any step up to
    # the horizon, so an episode not done by T runs on (those steps decide success only).
    success, deviation = False, None
    for step in range(t, envs.spec(task).horizon):
        if step >= reference.steps:
            if deviation is None:
                deviation = _terminal_deviation(obs, reference)
            if success:
                break
        if step > t:
            _, action = act_at_width(runner, envs.observation_vector(task, obs), FULL_PRECISION)
        obs, _, _, _ = envs.step_env(env, action)
        success = success or envs.check_success(env)
    if deviation is None:  # T is the whole horizon
        deviation = _terminal_deviation(obs, reference)
    return Perturbation(error, deviation, bool(success), True)


def teacher_forced_errors(runner: PolicyRunner, reference: Reference,
                          widths: Sequence[int] = QUANTIZED_WIDTHS) -> dict[int, np.ndarray]:
    """e_t^(b) = ||a_t^(b) - a_t^fp||_2 at every step of the reference: each width's executed action on
    the reference's own observation (no simulation)."""
    return {b: np.array([np.linalg.norm(act_at_width(runner, o, b)[1] - a)
                         for o, a in zip(reference.observations, reference.actions)]) for b in widths}


PROXY_FIELDS = ("motion_fineness", "angular_jerk", "smoothed_fineness", "smoothed_jerk", "fused_sensitivity")


def proxy_trace(actions, config: "dyq.DispatchConfig | None" = None, prime=None) -> dict[str, np.ndarray]:
    """M_t, J_t, M~_t, J~_t and S_t that the closed loop's dispatcher reports over an episode's
    executed actions, aligned as :func:`dyq.analysis.dispatch_trace`: entry t is what it saw when
    choosing step t's precision (after ``step(a_{t-1})``); NaN at t = 0 and while it warms up.

    ``prime``: the actions that fill its scale histories before the episode, as the closed loop does
    with a checkpoint's ``dispatch.json`` (``runner.dispatch_prime``); None starts it fresh."""
    actions = np.asarray(actions, dtype=np.float64)
    dispatcher = dyq.KinematicDispatcher(config or dyq.DispatchConfig())
    if prime is not None:
        from .dispatch_budget import prime as prime_dispatcher

        prime_dispatcher(dispatcher, np.asarray(prime, dtype=np.float64))
    trace = {name: np.full(len(actions), math.nan) for name in PROXY_FIELDS}
    attribute = {"fused_sensitivity": "sensitivity"}
    for t in range(1, len(actions)):
        dispatcher.step(actions[t - 1])
        for name in PROXY_FIELDS:
            trace[name][t] = getattr(dispatcher, attribute.get(name, name))
    return trace


# -- cached drivers ---------------------------------------------------------------------------------

class Store:
    """The resumable cache of one task and checkpoint: one gzipped JSON per (kind, seed)."""

    def __init__(self, root: str | Path, task: str, digest: str):
        self.root = Path(root) / task / digest

    def path(self, kind: str, seed: int) -> Path:
        return self.root / kind / f"seed_{seed:05d}.json.gz"

    def read(self, kind: str, seed: int) -> dict | None:
        path = self.path(kind, seed)
        return _read_episode(path) if path.is_file() else None

    def write(self, kind: str, seed: int, data: dict) -> None:
        _write_episode(self.path(kind, seed), data)


def _bar(total: int, description: str, progress: bool):
    from tqdm import tqdm

    return tqdm(total=total, desc=description, disable=not progress, file=sys.stderr)


def references(runner: PolicyRunner, task: str, store: Store, count: int, env, progress: bool = True,
               max_tries: int | None = None) -> tuple[list[Reference], list[int]]:
    """The first ``count`` successful references on :data:`CALIBRATION_SEEDS` (cached), and every seed
    tried (successful or not). Gives up after ``max_tries`` seeds (default 4 count + 10)."""
    max_tries = 4 * count + 10 if max_tries is None else max_tries
    found, tried = [], []
    bar = _bar(count, f"{task} references", progress)
    for seed in CALIBRATION_SEEDS[:max_tries]:
        cached = store.read("reference", seed)
        reference = Reference.from_dict(cached) if cached else reference_episode(runner, task, seed, env)
        if cached is None:
            store.write("reference", seed, reference.to_dict())
        tried.append(seed)
        if reference.success:
            found.append(reference)
            bar.update(1)
        bar.set_postfix(tried=len(tried))
        if len(found) == count:
            break
    bar.close()
    if not found:
        raise ValueError(f"no full-precision episode of {task} succeeded on seeds {tried[0]}..{tried[-1]}: "
                         "nothing to profile or calibrate")
    return found, tried


def cached_teacher_errors(runner: PolicyRunner, reference: Reference, store: Store) -> dict[int, np.ndarray]:
    cached = store.read("teacher", reference.seed)
    if cached is None:
        errors = teacher_forced_errors(runner, reference)
        store.write("teacher", reference.seed, {str(b): e.tolist() for b, e in errors.items()})
        return errors
    return {int(b): np.asarray(e, dtype=np.float64) for b, e in cached.items()}


def profile(runner: PolicyRunner, task: str, store: Store, budget: ProfileBudget, env=None,
            progress: bool = True) -> dict:
    """The step-wise perturbation profile of ``task`` (Sec. III-A) under ``budget``, resumable.

    Returns ``references`` (the profiled Reference list), ``tried_seeds``, ``records``
    (ProfiledStep, proxies from the default DispatchConfig on the reference's actions), and the
    counts ``simulated`` and ``zero_error`` (recorded without simulating).
    """
    env = envs.make_env(task) if env is None else env
    found, tried = references(runner, task, store, budget.episodes, env, progress)
    todo = [(r, b, t) for r in found for b in budget.widths for t in budget.steps(b, r.steps)]
    records, simulated, zero_error = [], 0, 0
    bar = _bar(len(todo), f"{task} perturbations", progress)
    done: dict[tuple[int, int], dict] = {}
    teacher: dict[int, dict[int, np.ndarray]] = {}
    for reference, width, t in todo:
        kind = f"perturb/w{width}"
        key = (reference.seed, width)
        if key not in done:
            done[key] = store.read(kind, reference.seed) or {}
        result = done[key].get(str(t))
        if result is None:
            if reference.seed not in teacher:
                teacher[reference.seed] = cached_teacher_errors(runner, reference, store)
            error = teacher[reference.seed][width][t]
            if error == 0.0:
                result = Perturbation(0.0, 0.0, reference.success, False)._asdict()
            else:
                result = perturb(runner, reference, t, width, env)._asdict()
            done[key][str(t)] = result
            store.write(kind, reference.seed, done[key])
        simulated += result["simulated"]
        zero_error += not result["simulated"]
        records.append((reference, width, t, result))
        bar.update(1)
        bar.set_postfix(simulated=simulated, zero_error=zero_error)
    bar.close()
    proxies = {r.seed: proxy_trace(r.actions, prime=_prime(runner)) for r in found}
    steps = [ProfiledStep(episode=r.seed, t=t, act_bits=width, action_error=result["action_error"],
                          terminal_deviation=result["terminal_deviation"], success=bool(result["success"]),
                          **{name: float(proxies[r.seed][name][t]) for name in PROXY_FIELDS})
             for r, width, t, result in records]
    return {"references": found, "tried_seeds": tried, "records": steps, "simulated": simulated,
            "zero_error": zero_error}


def _prime(runner: PolicyRunner):
    """The actions that prime the closed loop's dispatcher for this runner's checkpoint (None: fresh)."""
    return getattr(runner, "dispatch_prime", None)


def load_records(data: dict) -> list[ProfiledStep]:
    """The ProfiledStep records of a profile JSON written by ``dyq profile`` (null -> NaN)."""
    return [ProfiledStep(**{k: (math.nan if v is None else v) for k, v in r.items()}) for r in data["records"]]


def measured_sensitivity(records: Sequence[ProfiledStep], reference: Reference, width: int) -> np.ndarray:
    """s_t of one reference at one width, per step (NaN where not sampled or e_t = 0)."""
    s = np.full(reference.steps, math.nan)
    mine = [r for r in records if r.episode == reference.seed and r.act_bits == width]
    if mine:
        values = sensitivity([r.action_error for r in mine], [r.terminal_deviation for r in mine]).values
        s[[r.t for r in mine]] = values
    return s


# -- calibration --------------------------------------------------------------------------------------

def config_key(config: "dyq.DispatchConfig", prime=None) -> str:
    """A closed-loop episode's dispatcher: its config and the actions that primed it."""
    h = hashlib.sha256(json.dumps(config.to_dict(), sort_keys=True).encode())
    if prime is not None:
        h.update(np.ascontiguousarray(prime, dtype=np.float64).tobytes())
    return h.hexdigest()[:12]


def with_theta_fp(config: "dyq.DispatchConfig", theta_fp: float) -> "dyq.DispatchConfig":
    """``config`` with theta_fp as its top threshold and every lower rung's threshold clipped to it
    (steps above theta_fp run at 16 bits anyway); rungs the ladder lacks stay absent."""
    lower = [(min(threshold, theta_fp), bits) for threshold, bits in config.ladder[:-1]]
    return config.replace(ladder=lower + [(theta_fp, config.ladder[-1][1])])


def _rung_threshold(theta: float) -> float | None:
    """A DispatchConfig's theta (NaN for a rung it lacks) as write_config takes it (None)."""
    return None if math.isnan(theta) else theta


def sweep_theta_fp(runner: PolicyRunner, task: str, store: Store, base: "dyq.DispatchConfig",
                   grid: Sequence[float], seeds: Sequence[int], env=None, progress: bool = True) -> list[dict]:
    """Closed-loop DyQ episodes (``run_episode``, as ``dyq eval`` runs them) on ``seeds`` for each
    theta_fp in ``grid``, Theta clipped to it (cached). One row per theta_fp: successes, episodes,
    success_rate, its Wilson interval, mean_bits and the share of steps per width."""
    env = envs.make_env(task) if env is None else env
    rows = []
    bar = _bar(len(grid) * len(seeds), f"{task} theta_fp sweep", progress)
    for theta_fp in grid:
        config = with_theta_fp(base, theta_fp)
        kind = f"sweep/{config_key(config, _prime(runner))}"
        episodes = []
        for seed in seeds:
            episode = store.read(kind, seed)
            if episode is None:
                run = RunConfig("dyq_theta_fp_sweep", "dyq", dispatch=config.to_dict())
                episode = run_episode(runner, task, run, seed, env=env).to_dict()
                store.write(kind, seed, episode)
            episodes.append(episode)
            bar.update(1)
        successes = sum(e["success"] for e in episodes)
        bits = np.concatenate([e["bits"] for e in episodes])
        rows.append({"theta_fp": float(theta_fp), "successes": int(successes), "episodes": len(episodes),
                     "success_rate": successes / len(episodes), "wilson95": list(wilson_interval(successes, len(episodes))),
                     "mean_bits": float(bits.mean()),
                     "bits_share": {str(w): float((bits == w).mean()) for w in QUANTIZED_WIDTHS + (FULL_PRECISION,)}})
    bar.close()
    return rows


def calibrate(runner: PolicyRunner, task: str, store: Store, records: Sequence[ProfiledStep], *,
              episodes: int = CALIBRATION_EPISODES, sweep_episodes: int | None = None,
              theta_fp_grid: Sequence[float] | None = None, profile_width: int = 4,
              tolerance: float | None = None, base: "dyq.DispatchConfig | None" = None, env=None,
              progress: bool = True) -> dict:
    """The calibrated dispatcher of ``task`` (Sec. IV-B2, VI-D; rules in docs/profiling.md section 3).

    ``records``: the task's profile (``dyq profile``), whose W4A<profile_width> s_t choose lambda and
    fit D_acc, eta. Theta and K come from teacher-forced errors on ``episodes`` successful
    calibration references; theta_fp from a closed-loop sweep on the first ``sweep_episodes`` of them.
    S_t for the bound and Theta is what the closed loop's dispatcher computes (:func:`proxy_trace`,
    primed as the runner's checkpoint says); lambda and K are chosen by ``choose_fusion_weight`` and
    ``choose_delay``, which replay through fresh dispatchers. Returns everything measured; ``config``
    is the DispatchConfig to write.
    """
    base = base or dyq.DispatchConfig()
    tolerance = SUCCESS_TOLERANCE[task] if tolerance is None else tolerance
    env = envs.make_env(task) if env is None else env
    found, tried = references(runner, task, store, episodes, env, progress)
    by_seed = {r.seed: r for r in found}
    profiled = sorted({r.episode for r in records if r.act_bits == profile_width})
    missing = [seed for seed in profiled if seed not in by_seed]
    for seed in missing:  # a profiled reference beyond the calibration count
        cached = store.read("reference", seed)
        if cached is None:
            raise ValueError(f"profiled seed {seed} has no cached reference: the profile was made with another "
                             "checkpoint or cache; run dyq profile again")
        by_seed[seed] = Reference.from_dict(cached)
    if not profiled:
        raise ValueError(f"the profile holds no W4A{profile_width} step: run dyq profile with that width")
    profile_refs = [by_seed[seed] for seed in profiled]
    measured = [measured_sensitivity(records, r, profile_width) for r in profile_refs]

    # 1. lambda: the fusion weight whose S_t ranks the measured s_t best.
    fusion = choose_fusion_weight([r.actions for r in profile_refs], measured, base)
    fused = base.replace(fusion_weight=fusion["fusion_weight"])

    # 2. D_acc, eta from the tolerance and the line s_t ~ alpha S_t + beta. A slope <= 0 (S_t does not
    # rise with s_t) leaves the flat bound, the eta -> infinity limit of Eq. 5 with D_acc / eta =
    # tolerance / mean s_t: every S gets the same error budget.
    prime = _prime(runner)
    S_profile = np.concatenate([proxy_trace(r.actions, fused, prime)["fused_sensitivity"] for r in profile_refs])
    s_profile = np.concatenate(measured)
    defined = np.isfinite(S_profile) & np.isfinite(s_profile)
    if defined.sum() < 2 or np.ptp(S_profile[defined]) == 0.0:
        raise ValueError(f"the profile has {int(defined.sum())} steps with both s_t and S_t defined; the bound "
                         "needs at least 2 with varying S_t: profile more episodes or a smaller stride")
    alpha, beta = np.polyfit(S_profile[defined], s_profile[defined], 1)
    try:
        d_acc, eta = bound_parameters(S_profile, s_profile, tolerance)
        bound = {"form": "D_acc / (S_t + eta)", "d_acc": d_acc, "eta": eta}
    except ValueError as err:  # the slope is not positive
        eta = 1e9
        d_acc = tolerance / float(np.mean(s_profile[defined])) * eta
        bound = {"form": "flat: tolerance / mean s_t (eta -> infinity)", "d_acc": d_acc, "eta": eta,
                 "reason": str(err)}
    bound.update(tolerance=tolerance, alpha=float(alpha), beta=float(beta), steps=int(defined.sum()),
                 profile_width=profile_width, episodes=len(profile_refs))

    # 3. Theta from the teacher-forced errors of every calibration step where S_t is defined.
    errors = [cached_teacher_errors(runner, r, store) for r in found]
    S_all = [proxy_trace(r.actions, fused, prime)["fused_sensitivity"] for r in found]
    warm = [np.isfinite(S) for S in S_all]
    S_warm = np.concatenate([S[w] for S, w in zip(S_all, warm)])
    thresholds = calibrate_thresholds(S_warm, {b: np.concatenate([e[b][w] for e, w in zip(errors, warm)])
                                               for b in QUANTIZED_WIDTHS}, d_acc, eta)
    # theta_fp until the sweep: the 8-bit limit, where 8 bits stop meeting the bound.
    ceiling = max(thresholds.limits[8], thresholds.theta_4_8 or 0.0)
    laddered = fused.replace(theta_2_4=thresholds.theta_2_4, theta_4_8=thresholds.theta_4_8, theta_fp=ceiling)

    # 4. K: the smallest delay that keeps downgrade errors rare.
    delay = choose_delay([r.actions for r in found], errors, laddered, d_acc, eta)
    delayed = laddered.replace(delay_window=delay["delay_window"])

    # 5. theta_fp: the knee of the closed-loop sweep on the calibration seeds.
    if theta_fp_grid is None:
        theta_fp_grid = sorted({round(float(q), 4) for q in np.quantile(S_warm, THETA_FP_QUANTILES)})
    sweep_seeds = [r.seed for r in found[: sweep_episodes or len(found)]]
    sweep = sweep_theta_fp(runner, task, store, delayed, theta_fp_grid, sweep_seeds, env, progress)
    knee = choose_theta_fp([(row["theta_fp"], row["success_rate"], row["mean_bits"]) for row in sweep],
                           len(sweep_seeds))
    theta_fp = knee["theta_fp"]
    config = with_theta_fp(delayed, theta_fp)
    return {
        "references": found, "tried_seeds": tried, "profiled_seeds": profiled,
        "fusion_weight": fusion, "bound": bound, "thresholds": thresholds, "theta_fp_ceiling": ceiling,
        "delay": delay, "sweep": sweep, "sweep_seeds": sweep_seeds, "knee": knee, "config": config,
        "calibration_steps": int(S_warm.size), "dispatcher_primed": prime is not None,
    }


def calibrated_run_config(task: str, path: str | Path | None = None,
                          checkpoint_digest: str | None = None) -> RunConfig:
    """The ``dyq_calibrated`` closed-loop configuration of ``task``: DyQ with the dispatcher config
    that ``dyq calibrate`` wrote (default ``bench/results/dispatch_<task>.json``).

    With ``checkpoint_digest``, the calibration record beside it (``calibration_<task>.json``) must have
    been measured on that checkpoint: a config calibrated on another policy is an error, not a row.
    """
    path = Path(path) if path is not None else RESULTS / f"dispatch_{task}.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist: run `dyq calibrate {task}` first")
    if checkpoint_digest is not None:
        record = path.with_name(f"calibration_{task}.json")
        calibrated_on = json.loads(record.read_text()).get("checkpoint_digest") if record.is_file() else None
        if calibrated_on != checkpoint_digest:
            raise ValueError(f"{path} was calibrated on checkpoint {calibrated_on or '(no record at ' + str(record) + ')'}, "
                             f"not on the evaluated checkpoint {checkpoint_digest}: run `dyq calibrate {task}` again")
    # Every field, by its readable name: the whole calibrated config, whatever base it is applied to.
    return RunConfig("dyq_calibrated", "dyq", dispatch=dyq.DispatchConfig.load(path).to_dict(), source=str(path))


# -- figures ----------------------------------------------------------------------------------------

def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_thresholds(result: dict, title: str = ""):
    """Binned teacher-forced error per width against eps_a(S_t), with Theta (Sec. IV-B2)."""
    import matplotlib.pyplot as plt

    calibration = result["thresholds"]
    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    for bits in QUANTIZED_WIDTHS:
        ax.plot(calibration.bin_upper, calibration.mean_error[bits], marker="o", label=f"mean e_t^({bits}) per bin")
    ax.plot(calibration.bin_upper, calibration.bound, color="k", lw=2, label="eps_a(S) at the bin's upper edge")
    for name, value, style in (("theta_2|4", calibration.theta_2_4, ":"), ("theta_4|8", calibration.theta_4_8, "--")):
        if value is not None:  # None: no rung of that width
            ax.axvline(value, color="gray", linestyle=style, label=f"{name} = {value:.3g}")
    ax.set(xlabel="S_t (bin upper edge)", ylabel="action error", yscale="log", title=title)
    ax.legend(fontsize=8)
    return fig


def plot_theta_fp_sweep(result: dict, title: str = ""):
    """Figure 7: success rate (Wilson 95 %) and mean bits per theta_fp, the chosen knee marked."""
    import matplotlib.pyplot as plt

    sweep = result["sweep"]
    theta = [row["theta_fp"] for row in sweep]
    rate = np.array([row["success_rate"] for row in sweep])
    low = rate - np.array([row["wilson95"][0] for row in sweep])
    high = np.array([row["wilson95"][1] for row in sweep]) - rate
    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    ax.errorbar(theta, rate, yerr=[low, high], marker="o", capsize=3, color="tab:blue", label="success rate")
    ax.set(xlabel="theta_fp", ylabel="success rate", ylim=(-0.05, 1.05), title=title)
    bits_axis = ax.twinx()
    bits_axis.plot(theta, [row["mean_bits"] for row in sweep], marker="s", color="tab:red", label="mean bits")
    bits_axis.set_ylabel("mean activation bits (CPU: latency flat across widths)")
    ax.axvline(result["knee"]["theta_fp"], color="gray", linestyle="--", label=f"knee {result['knee']['theta_fp']:.3g}")
    ax.axhline(result["knee"]["success_floor"], color="tab:blue", linestyle=":", lw=1, label="success floor")
    lines = ax.get_legend_handles_labels()
    more = bits_axis.get_legend_handles_labels()
    ax.legend(lines[0] + more[0], lines[1] + more[1], fontsize=8, loc="lower right")
    return fig


# -- command line -----------------------------------------------------------------------------------

def _command(parser: argparse.ArgumentParser) -> str:
    return parser.prog.rsplit(" ", 1)[-1]


def _list_type(parse_one, accept, expected: str, invalid: list[str]):
    """A comma-separated list argument: each item parsed by ``parse_one`` and accepted by ``accept``."""

    def parse(text: str) -> tuple:
        try:
            values = tuple(parse_one(v) for v in text.split(","))
        except ValueError:
            values = ()
        if not values or not all(accept(v) for v in values):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return values

    parse.invalid_examples = lambda folder: invalid
    return parse


_widths = _list_type(int, lambda w: w in QUANTIZED_WIDTHS, f"comma-separated widths from {QUANTIZED_WIDTHS}",
                     ["3", "4,x", ""])
_strides = _list_type(int, lambda k: k >= 1, "a stride >= 1 or comma-separated strides", ["0", "1,x"])
_thetas = _list_type(float, lambda v: math.isfinite(v) and v >= 0, "comma-separated thresholds >= 0",
                     ["-1", "0.5,nan", "x"])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    command = _command(parser)
    parser.add_argument("task", choices=envs.ALL_TASKS)
    parser.add_argument("--checkpoint", type=usage.input_dir,
                        help="policy checkpoint (default: the one that ships with dyq)")
    parser.add_argument("--cache", type=usage.output_dir, default=DEFAULT_CACHE)
    parser.add_argument("--out", type=usage.output_file(".json"),
                        help=f"result JSON (default: {RESULTS}/{RESULT_STEMS[command]}_<task>.json)")
    parser.add_argument("--figures", type=usage.output_dir, default=FIGURES, help="folder for the PNG figures")
    parser.add_argument("--threads", type=usage.positive_int, default=1, help="torch threads")
    parser.add_argument("--no-progress", action="store_true")
    if command == "profile":
        parser.add_argument("--episodes", type=usage.positive_int,
                            help="successful references to profile (default: per task)")
        parser.add_argument("--widths", type=_widths, help="comma-separated widths to inject (default: per task)")
        parser.add_argument("--stride", type=_strides,
                            help="perturb every stride-th step: one stride, or one per width (default: per task)")
    else:
        parser.add_argument("--episodes", type=usage.positive_int, default=CALIBRATION_EPISODES,
                            help="successful calibration references (teacher-forced errors, Theta, K)")
        parser.add_argument("--sweep-episodes", type=usage.positive_int,
                            help="calibration seeds of the closed-loop theta_fp sweep (default: all)")
        parser.add_argument("--theta-fp", type=_thetas,
                            help=f"comma-separated theta_fp to sweep (default: S_t quantiles {THETA_FP_QUANTILES})")
        parser.add_argument("--profile", type=usage.input_file(".json"),
                            help=f"profile JSON (default: {RESULTS}/profile_<task>.json)")
        parser.add_argument("--config-out", type=usage.output_file(".json"),
                            help=f"dispatcher config (default: {RESULTS}/dispatch_<task>.json)")


def _header(task: str, checkpoint: Path, digest: str) -> dict:
    from .evaluate import checkpoint_label

    data = {"task": task, "checkpoint": checkpoint_label(checkpoint), "checkpoint_digest": digest, "device": "cpu",
            "environment": results_io.environment()}
    try:
        import mujoco
        import robosuite

        data["versions"] = {"robosuite": robosuite.__version__, "mujoco": mujoco.__version__}
    except ImportError:
        pass
    return data


def _write(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(_jsonable(data), indent=1) + "\n")


def _budget(args) -> ProfileBudget:
    """The profile's budget: the task's default, with the command line's changes."""
    default = PROFILE_BUDGETS[args.task]
    widths = args.widths or default.widths
    strides = args.stride or (default.strides if widths == default.widths else (max(default.strides),))
    if len(strides) == 1:
        strides = strides * len(widths)
    if len(strides) != len(widths):
        raise ValueError(f"--stride must give one stride or one per width {list(widths)}, got {list(strides)}")
    return ProfileBudget(args.episodes or default.episodes, widths, strides)


def _run_profile(args, runner: PolicyRunner, store: Store, header: dict) -> int:
    budget = _budget(args)
    start = time.perf_counter()
    result = profile(runner, args.task, store, budget, progress=not args.no_progress)
    records = result["records"]
    by_width = {}
    for width in budget.widths:
        mine = [r for r in records if r.act_bits == width]
        try:
            by_width[str(width)] = proxy_correlations(mine)
        except ValueError as err:  # fewer than 2 usable steps: reported, not fatal
            by_width[str(width)] = {**{f"{statistic}_{proxy}{ci}": None for statistic in ("pearson", "spearman")
                                       for proxy in ("motion_fineness", "angular_jerk", "fused") for ci in ("", "_ci")},
                                    "episodes": 0, "steps": 0, "error": str(err)}
        by_width[str(width)]["success_rate"] = float(np.mean([r.success for r in mine]))
        by_width[str(width)]["sampled_steps"] = len(mine)
    main_width = 4 if 4 in budget.widths else budget.widths[0]
    data = {**header, **by_width[str(main_width)], "width": main_width, "by_width": by_width,
            "budget": dataclasses.asdict(budget), "seeds": [r.seed for r in result["references"]],
            "episode_steps": {str(r.seed): r.steps for r in result["references"]},
            "tried_seeds": result["tried_seeds"], "simulated": result["simulated"],
            "zero_error": result["zero_error"], "terminal_deviation": "final eef distance + final object distance (m)",
            "wall_s": round(time.perf_counter() - start, 1),
            "records": [dataclasses.asdict(r) for r in records]}
    out = args.out or RESULTS / f"{RESULT_STEMS['profile']}_{args.task}.json"
    _write(out, data)
    figures = [_save(plot_perturbation_profile(records), args.figures / f"profile_{args.task}_fig2.png")]
    usable = [r for r in records if r.act_bits == main_width and r.action_error > 0 and math.isfinite(r.fused_sensitivity)]
    if usable:
        episode = max({r.episode for r in usable}, key=lambda e: sum(r.episode == e for r in usable))
        figures.append(_save(plot_proxy_trajectories(records, episode, main_width),
                             args.figures / f"profile_{args.task}_fig3.png"))
    print(f"{args.task}: {len(records)} perturbed steps over {len(result['references'])} episodes "
          f"({result['simulated']} simulated, {result['zero_error']} with e_t = 0)")
    for width, row in by_width.items():
        if "error" in row:
            print(f"  W4A{width}: {row['error']}")
            continue
        print(f"  W4A{width}: {row['steps']} steps with s_t, success {row['success_rate']:.2f}")
        for proxy in ("motion_fineness", "angular_jerk", "fused"):
            p, s = row[f"pearson_{proxy}"], row[f"spearman_{proxy}"]
            print(f"    {proxy:16s} pearson {_fmt(p)} {_fmt_ci(row[f'pearson_{proxy}_ci'])}  "
                  f"spearman {_fmt(s)} {_fmt_ci(row[f'spearman_{proxy}_ci'])}")
    print(f"wrote {out} and {', '.join(map(str, figures))}")
    return 0


def _fmt(value) -> str:
    return "  n/a" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:+.2f}"


def _fmt_ci(interval) -> str:
    return f"[{_fmt(interval[0])}, {_fmt(interval[1])}]"


def _read_profile(args, digest: str) -> tuple[Path, dict]:
    """The profile ``dyq calibrate`` starts from: it must exist and describe this checkpoint."""
    profile_path = args.profile or RESULTS / f"{RESULT_STEMS['profile']}_{args.task}.json"
    if not profile_path.is_file():
        raise usage.UsageError(f"{profile_path} does not exist: run `dyq profile {args.task}` first")
    try:
        profiled = json.loads(profile_path.read_text())
    except json.JSONDecodeError as err:
        raise usage.UsageError(f"{profile_path} is not a profile written by dyq profile: {err}") from None
    if not isinstance(profiled, dict) or "records" not in profiled:
        raise usage.UsageError(f"{profile_path} is not a profile written by dyq profile (no records)")
    if profiled.get("checkpoint_digest") != digest:
        raise usage.UsageError(f"{profile_path} profiles checkpoint {profiled.get('checkpoint_digest')}, not "
                               f"{digest}: run `dyq profile {args.task}` again")
    return profile_path, profiled


def _run_calibrate(args, runner: PolicyRunner, store: Store, header: dict) -> int:
    profile_path, profiled = _read_profile(args, header["checkpoint_digest"])
    start = time.perf_counter()
    result = calibrate(runner, args.task, store, load_records(profiled), episodes=args.episodes,
                       sweep_episodes=args.sweep_episodes, theta_fp_grid=args.theta_fp,
                       progress=not args.no_progress)
    config = result["config"]
    config_out = args.config_out or RESULTS / f"dispatch_{args.task}.json"
    config_out.parent.mkdir(parents=True, exist_ok=True)
    write_config(config_out, fusion_weight=config.fusion_weight, delay_window=config.delay_window,
                 theta_2_4=_rung_threshold(config.theta_2_4), theta_4_8=_rung_threshold(config.theta_4_8),
                 theta_fp=config.theta_fp)
    thresholds = result["thresholds"]
    data = {
        **header, "profile": str(profile_path), "config_file": str(config_out),
        "config": json.loads(config_out.read_text()),
        "seeds": [r.seed for r in result["references"]], "tried_seeds": result["tried_seeds"],
        "profiled_seeds": result["profiled_seeds"], "calibration_steps": result["calibration_steps"],
        "dispatcher_primed": result["dispatcher_primed"],
        "lambda": {"value": result["fusion_weight"]["fusion_weight"],
                   "rule": "largest Spearman rho of S_t with the W4A4 s_t (ties: smaller lambda)",
                   "table": [{"lambda": round(weight, 4), "spearman": rho, "steps": steps}
                             for weight, rho, steps in result["fusion_weight"]["table"]]},
        "bound": result["bound"],
        "theta": {"theta_2|4": thresholds.theta_2_4, "theta_4|8": thresholds.theta_4_8,
                  "limits": {str(b): v for b, v in thresholds.limits.items()},
                  "status": {str(b): v for b, v in thresholds.status.items()},
                  "bins": {"upper": thresholds.bin_upper.tolist(), "bound": thresholds.bound.tolist(),
                           "count": thresholds.count.tolist(),
                           "mean_error": {str(b): v.tolist() for b, v in thresholds.mean_error.items()}}},
        "theta_fp_ceiling": result["theta_fp_ceiling"],
        "K": {"value": result["delay"]["delay_window"], "met": result["delay"]["met"],
              "rule": "smallest K in 1..8 with downgrade-error rate <= 5 %",
              "table": [dict(zip(("K", "downgrade_error_rate", "mean_bits"), row)) for row in result["delay"]["table"]]},
        "theta_fp": {**result["knee"], "sweep_seeds": result["sweep_seeds"], "sweep": result["sweep"],
                     "rule": "fewest mean bits among theta_fp whose success reaches the lower Wilson 95 % bound "
                             "of the best success rate"},
        "wall_s": round(time.perf_counter() - start, 1),
    }
    out = args.out or RESULTS / f"{RESULT_STEMS['calibrate']}_{args.task}.json"
    _write(out, data)
    figures = [_save(plot_thresholds(result, f"{args.task}: Theta"), args.figures / f"calibration_{args.task}_theta.png"),
               _save(plot_theta_fp_sweep(result, f"{args.task}: theta_fp sweep"),
                     args.figures / f"calibration_{args.task}_theta_fp.png")]
    print(f"{args.task}: lambda {config.fusion_weight:g}, K {config.delay_window}, theta_2|4 {config.theta_2_4:.4g}, "
          f"theta_4|8 {config.theta_4_8:.4g}, theta_fp {config.theta_fp:.4g} ({result['bound']['form']}, "
          f"D_acc {result['bound']['d_acc']:.4g}, eta {result['bound']['eta']:.4g})")
    for row in result["sweep"]:
        print(f"  theta_fp {row['theta_fp']:.4g}: success {row['successes']}/{row['episodes']}, "
              f"mean bits {row['mean_bits']:.2f}")
    print(f"wrote {config_out}, {out} and {', '.join(map(str, figures))}")
    return 0


def main(args: argparse.Namespace) -> int:
    import torch

    torch.set_num_threads(args.threads)
    if args.command == "profile":
        _budget(args)  # refuse a bad budget before loading anything
    checkpoint = args.checkpoint or default_checkpoint(args.task)
    check_checkpoint_files(checkpoint, args.task)
    digest = checkpoint_digest(checkpoint)
    if args.command == "calibrate":
        _read_profile(args, digest)  # refuse a missing or foreign profile before loading anything
    runner = PolicyRunner.load(checkpoint)
    store = Store(args.cache, args.task, digest)
    header = _header(args.task, checkpoint, digest)
    return (_run_profile if args.command == "profile" else _run_calibrate)(args, runner, store, header)
