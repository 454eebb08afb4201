"""Closed-loop episodes: a policy drives the robot, with DyQ choosing each step's activation width.

A **configuration** says how the policy runs (:data:`CONFIGS`):

* ``fp32``: the trained policy in full precision, no dyq layer at all (the reference);
* ``w4a16``, ``w4a8``, ``w4a4``, ``w4a2``: every projection on static INT4 weights
  (``dyq.quantize_model``, group 128) at one fixed activation width for the whole episode;
* ``dyq``: the same INT4 model, with the width of every control step chosen by
  :class:`dyq.KinematicDispatcher` under :class:`dyq.DyQRuntime` (paper Sec. IV-V);
* controls that decide whether the kinematics matter: ``smoothquant_w4a4`` (static W4A4 on weights
  smoothed SmoothQuant-style, :mod:`dyq.smoothing`, calibrated on the checkpoint's training sample);
  dispatcher ablations ``dyq_no_hysteresis`` (b* = b^), ``dyq_motion_only`` (λ = 1),
  ``dyq_jerk_only`` (λ = 0); ``dyq_inverted`` (the ladder reversed: 2 <-> 16 and 4 <-> 8, so fine
  motion gets low widths); ``random_schedule`` (per step, a width drawn independently with the shares
  DyQ had on the same seed) and ``random_runs`` (DyQ's own runs of equal width on that seed in shuffled
  order: the run lengths kept, the timing lost). A schedule's prefill runs at the previous step's
  width, as DyQ's does;
* the same static widths and DyQ on INT4 weights chosen by another method of ``dyq.quantize_model``
  (docs/quantization.md): ``mse_w4a16`` .. ``mse_w4a2`` and ``mse_dyq`` (per-group clipping search),
  ``awq_w4a16`` .. ``awq_w4a2`` and ``awq_dyq`` (activation-aware scales calibrated on the checkpoint's
  training sample, for all widths together), ``gptq_w4a16`` .. ``gptq_w4a2`` and ``gptq_dyq``
  (error-compensating rounding from the same sample's float inputs). Each method makes one weight set,
  which serves all its rows.

DyQ in the loop, per control step t (paper Algorithm 1 and Sec. V-B):

1. the runtime hands the dispatcher a_{t-1}, the action the arm executed at the previous step (none at
   t = 0), on its worker thread, while the **prefill** of the observation prompt runs;
2. the prefill runs at the flag's current value, b*_{t-1} (the runtime's ``prefill_bits="previous"``;
   16 at t = 0): the prefill cannot wait for b*_t without losing the overlap. This choice is the same
   for every DyQ variant;
3. the runtime publishes b*_t into the precision flag, and the **decode** of the 7 action tokens runs at
   b*_t; every GEMM reads the flag itself.

The dispatcher's configuration for ``dyq`` is the checkpoint's width budget (:mod:`dyq.sim.dispatch_budget`:
the ladder at fixed percentiles of S_t on the training demonstrations, the package's λ, K and windows),
fixed before any closed-loop result was seen; calibration per task writes another configuration. Each
episode starts a new dispatcher whose scale histories are primed with training actions, so an episode is
a function of its seed alone and can be cached and run in any order.

The per-step log keeps the bits chosen, the bits each GEMM actually ran at (counted by the kernels,
:func:`dyq.ops.width_counts`), S_t, M̃_t, J̃_t, the action and the policy's latency.
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

from pathlib import Path

import numpy as np
import torch

import dyq

from ..core.precision import check_bits
from . import envs
from .policy import TokenPolicy

GROUP_SIZE = 128
SMOOTHQUANT_ALPHA = 0.5  # SmoothQuant's default migration strength
# How a configuration's INT4 weights are chosen: a dyq.quantize_model method, or round-to-nearest after
# SmoothQuant smoothing. "awq", "gptq" and "smoothquant" calibrate on the checkpoint's training sample.
WEIGHT_METHODS = tuple(m for m in dyq.core.weight_methods.METHODS if m != "rtn")
WEIGHTS = ("rtn", "smoothquant") + WEIGHT_METHODS


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """How the policy runs in one closed-loop configuration."""

    name: str
    kind: str  # "float", "static", "dyq" or "schedule"
    bits: int | None = None  # the fixed width of a "static" configuration
    dispatch: dict = dataclasses.field(default_factory=dict)  # DispatchConfig.replace overrides for "dyq"
    weights: str = "rtn"  # one of WEIGHTS: how the INT4 weights are chosen
    inverted: bool = False  # "dyq" with the ladder reversed
    schedule: str | None = None  # "shares" or "runs": a "schedule" drawn from DyQ's episode on the seed
    source: str = ""  # the file the dispatch overrides came from (``dyq_calibrated``)

    def dispatch_config(self, base: "dyq.DispatchConfig | None" = None) -> "dyq.DispatchConfig":
        """The dispatcher's config: ``base`` (the checkpoint's, :mod:`dyq.sim.dispatch_budget`) with this
        configuration's overrides."""
        return (base or dyq.DispatchConfig()).replace(**self.dispatch)


CONFIGS: dict[str, RunConfig] = {c.name: c for c in (
    RunConfig("fp32", "float"),
    RunConfig("w4a16", "static", 16),
    RunConfig("w4a8", "static", 8),
    RunConfig("w4a4", "static", 4),
    RunConfig("w4a2", "static", 2),
    RunConfig("dyq", "dyq"),
    RunConfig("smoothquant_w4a4", "static", 4, weights="smoothquant"),
    RunConfig("dyq_no_hysteresis", "dyq", dispatch={"hysteresis": "none"}),
    RunConfig("dyq_motion_only", "dyq", dispatch={"fusion_weight": 1.0}),
    RunConfig("dyq_jerk_only", "dyq", dispatch={"fusion_weight": 0.0}),
    RunConfig("dyq_inverted", "dyq", inverted=True),
    RunConfig("random_schedule", "schedule", schedule="shares"),
    RunConfig("random_runs", "schedule", schedule="runs"),
)}
# The static widths and DyQ again on each other weight method's one weight set.
CONFIGS.update({c.name: c for method in WEIGHT_METHODS for c in (
    *(RunConfig(f"{method}_w4a{bits}", "static", bits, weights=method) for bits in (16, 8, 4, 2)),
    RunConfig(f"{method}_dyq", "dyq", weights=method),
)})


class InvertedLadderDispatcher(dyq.KinematicDispatcher):
    """The dispatcher with Φ reversed (2 <-> 16, 4 <-> 8): a sanity control, fine motion gets low widths.
    Warm-up still runs at 16 bits and the hysteresis acts on the reversed targets."""

    REVERSED = {2: 16, 4: 8, 8: 4, 16: 2}

    def allocate(self, sensitivity: float) -> int:
        return self.REVERSED[super().allocate(sensitivity)]


def make_schedule(kind: str, dyq_bits: list[int], seed: int, length: int) -> list[int]:
    """A random width schedule with DyQ's statistics on one seed (``dyq_bits``: its per-step widths).

    ``"shares"``: each step's width drawn independently with DyQ's shares. ``"runs"``: DyQ's runs of
    equal width in a random order, reshuffled and appended again while the episode needs more steps.
    Seeded by the episode seed, so a schedule is reproducible and differs between seeds.
    """
    if not dyq_bits:
        raise ValueError("dyq_bits must hold DyQ's widths of at least one step")
    if kind == "shares":
        widths, counts = np.unique(np.asarray(dyq_bits), return_counts=True)
        rng = np.random.default_rng([seed, 1])
        return [int(b) for b in rng.choice(widths, size=length, p=counts / counts.sum())]
    if kind == "runs":
        runs: list[list[int]] = []
        for b in dyq_bits:
            if runs and runs[-1][0] == b:
                runs[-1].append(b)
            else:
                runs.append([b])
        rng = np.random.default_rng([seed, 2])
        schedule: list[int] = []
        while len(schedule) < length:
            for i in rng.permutation(len(runs)):
                schedule += runs[i]
        return schedule[:length]
    raise ValueError(f"schedule kind must be 'shares' or 'runs', got {kind!r}")


CALIBRATED = "dyq_calibrated"  # DyQ with the task's config from ``dyq calibrate`` (resolved per task)


def run_config(name: str, task: str | None = None) -> RunConfig:
    """The configuration called ``name``; ``dyq_calibrated`` needs the ``task`` whose calibration it reads
    (``bench/results/dispatch_<task>.json``, :func:`dyq.sim.profile.calibrated_run_config`)."""
    if name == CALIBRATED:
        if task is None:
            raise ValueError(f"configuration {CALIBRATED!r} is per task: pass the task")
        from .profile import calibrated_run_config

        return calibrated_run_config(task)
    if name not in CONFIGS:
        raise ValueError(f"unknown configuration {name!r}; choose from {sorted(CONFIGS) + [CALIBRATED]}")
    return CONFIGS[name]


def width_counts() -> dict[int, int]:
    return dict(dyq.ops.width_counts())


def _count_difference(after: dict[int, int], before: dict[int, int]) -> dict[str, int]:
    return {str(bits): after[bits] - before.get(bits, 0) for bits in after if after[bits] != before.get(bits, 0)}


class PolicyRunner:
    """The policy of one checkpoint in every configuration: the float model and its INT4 copies, one per
    weight method (built once per process on first use), all bound to one precision flag.

    ``calibration``: training observations and actions for methods that calibrate (SmoothQuant, AWQ);
    :meth:`load` takes the sample that ``dyq train`` saved beside the checkpoint.
    """

    def __init__(self, policy: TokenPolicy, calibration: tuple[np.ndarray, np.ndarray] | None = None,
                 dispatch: tuple["dyq.DispatchConfig", np.ndarray | None] | None = None):
        self.float_policy = policy
        self.calibration = calibration
        # The dispatcher's base config and the actions that prime its scale histories each episode.
        self.dispatch_base, self.dispatch_prime = dispatch or (dyq.DispatchConfig(), None)
        self.flag = dyq.PrecisionFlag(16)
        self._quantized: dict[str, TokenPolicy] = {}
        self.reports: dict[str, "dyq.QuantizationReport"] = {}
        self.quantized = self.quantized_policy("rtn")
        self.report = self.reports["rtn"]

    @classmethod
    def load(cls, checkpoint) -> "PolicyRunner":
        from . import dispatch_budget
        from .train import CALIBRATION_FILE, load_calibration_set

        calibration = load_calibration_set(checkpoint) if (Path(checkpoint) / CALIBRATION_FILE).is_file() else None
        dispatch = dispatch_budget.load(checkpoint) if (Path(checkpoint) / dispatch_budget.DISPATCH_FILE).is_file() else None
        return cls(TokenPolicy.load(checkpoint), calibration, dispatch)

    def quantized_policy(self, weights: str) -> TokenPolicy:
        if weights in self._quantized:
            return self._quantized[weights]
        if weights not in WEIGHTS:
            raise ValueError(f"weights must be one of {WEIGHTS}, got {weights!r}")
        policy = self.float_policy.copy()
        method = weights if weights in WEIGHT_METHODS else "rtn"
        if weights == "smoothquant":
            self._smooth(policy)
        calibration = (self._calibration_ids(policy, weights)
                       if method in dyq.core.weight_methods.CALIBRATED_METHODS else None)
        report = dyq.quantize_model(policy.model, group_size=GROUP_SIZE, flag=self.flag, method=method,
                                    calibration=calibration)
        if any(name != "lm_head" for name in report.skipped):
            raise ValueError(f"the policy has layers dyq cannot convert: {report.skipped}")
        self.reports[weights] = report
        self._quantized[weights] = policy
        return policy

    def _calibration_ids(self, policy: TokenPolicy, weights: str) -> torch.Tensor:
        """Token ids of the calibration sample's whole steps (prompt and the expert's action tokens)."""
        if self.calibration is None:
            raise ValueError(f"weights={weights!r} needs calibration data: a checkpoint saved by dyq train, or "
                             "PolicyRunner(policy, calibration=(observations, actions))")
        return policy.sequences(*self.calibration)[0]

    def _smooth(self, policy: TokenPolicy) -> None:
        from ..smoothing import activation_maxima, smooth_llama

        ids = self._calibration_ids(policy, "smoothquant")
        with torch.no_grad():
            maxima = activation_maxima(policy.model, lambda: policy.model(input_ids=ids))
            smooth_llama(policy.model, maxima, alpha=SMOOTHQUANT_ALPHA)

    def policy_for(self, config: RunConfig) -> TokenPolicy:
        return self.float_policy if config.kind == "float" else self.quantized_policy(config.weights)


@dataclasses.dataclass
class Episode:
    """One closed-loop episode and its per-step log (lists of equal length ``steps``)."""

    task: str
    config: str
    seed: int
    success: bool
    steps: int
    bits: list[int]  # the width the decode was published at (16 for fp32)
    prefill_kernel_bits: list[dict[str, int]]  # GEMM calls per width the kernels ran, prefill phase
    decode_kernel_bits: list[dict[str, int]]  # the same, decode phase
    sensitivity: list[float]  # S_t (NaN in warm-up or without a dispatcher)
    smoothed_fineness: list[float]  # M̃_t
    smoothed_jerk: list[float]  # J̃_t
    actions: list[list[float]]
    latency_ms: list[float]  # prefill + decode of the policy, including the dispatcher's hand-off
    final_eef: list[float] = dataclasses.field(default_factory=list)
    final_object: list[float] = dataclasses.field(default_factory=list)
    cpu_isa: str = ""  # the CPU kernel path the policy ran on (dyq.cpu_info()); "" in episodes cached before

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "Episode":
        return cls(**data)


def run_episode(runner: PolicyRunner, task: str, config: RunConfig | str, seed: int, *, env=None,
                schedule: list[int] | None = None, frames: list | None = None, camera: str = "frontview",
                frame_size: int = 256) -> Episode:
    """Runs one seeded episode of ``task`` under ``config``; stops at success or at the task's horizon.

    ``schedule``: the per-step widths of a ``"schedule"`` configuration (:func:`make_schedule`), at
    least the task's horizon long. ``frames``, if given, receives one RGB frame per step (needs an
    environment with an offscreen renderer, see :func:`dyq.sim.envs.make_env`).
    """
    if isinstance(config, str):
        config = run_config(config, task)
    spec = envs.spec(task)
    if config.kind == "schedule":
        if schedule is None or len(schedule) < spec.horizon:
            raise ValueError(f"configuration {config.name} needs a schedule of at least {spec.horizon} widths")
        schedule = [check_bits(b, "schedule") for b in schedule]
    elif schedule is not None:
        raise ValueError(f"configuration {config.name} takes no schedule")
    if env is None:
        env = envs.make_env(task)
    obs = envs.reset_env(env, seed)
    policy = runner.policy_for(config)
    runtime = None
    if config.kind == "dyq":
        from . import dispatch_budget

        dispatcher_class = InvertedLadderDispatcher if config.inverted else dyq.KinematicDispatcher
        dispatcher = dispatcher_class(config.dispatch_config(runner.dispatch_base))
        if runner.dispatch_prime is not None:
            dispatch_budget.prime(dispatcher, runner.dispatch_prime)
        runtime = dyq.DyQRuntime(dispatcher, runner.flag, prefill_bits="previous")
        runtime.reset(keep_history=True)
    elif config.kind == "static":
        runner.flag.bits = config.bits
    else:
        runner.flag.bits = 16  # the first prefill of a schedule, as DyQ's

    log: dict[str, list] = {k: [] for k in ("bits", "prefill_kernel_bits", "decode_kernel_bits", "sensitivity",
                                            "smoothed_fineness", "smoothed_jerk", "actions", "latency_ms")}
    previous_action = None
    success = False
    try:
        for _ in range(spec.horizon):
            observation = envs.observation_vector(task, obs)
            counts = [width_counts()]

            def prefill():
                out = policy.prefill(observation)
                counts.append(width_counts())
                return out

            start = time.perf_counter()
            if runtime is not None:
                bins = runtime.step(previous_action, prefill, policy.decode)
                stats = runtime.stats[-1]
                bits = stats.bits
                sensitivity = stats.sensitivity
                fineness = runtime.dispatcher.smoothed_fineness
                jerk = runtime.dispatcher.smoothed_jerk
            elif schedule is not None:
                prefilled = prefill()  # at the previous step's width, still in the flag
                bits = runner.flag.bits = schedule[len(log["bits"])]
                bins = policy.decode(prefilled)
                sensitivity = fineness = jerk = math.nan
            else:
                bins = policy.decode(prefill())
                bits = config.bits if config.kind == "static" else 16
                sensitivity = fineness = jerk = math.nan
            latency = (time.perf_counter() - start) * 1e3
            counts.append(width_counts())
            action = np.clip(policy.action(bins), -1.0, 1.0)
            obs, _, _, _ = envs.step_env(env, action)
            if frames is not None:
                frames.append(env.sim.render(camera_name=camera, width=frame_size, height=frame_size)[::-1])
            log["bits"].append(int(bits))
            log["prefill_kernel_bits"].append(_count_difference(counts[1], counts[0]))
            log["decode_kernel_bits"].append(_count_difference(counts[2], counts[1]))
            log["sensitivity"].append(float(sensitivity))
            log["smoothed_fineness"].append(float(fineness))
            log["smoothed_jerk"].append(float(jerk))
            log["actions"].append([round(float(a), 6) for a in action])
            log["latency_ms"].append(round(latency, 3))
            previous_action = action
            if envs.check_success(env):
                success = True
                break
    finally:
        if runtime is not None:
            runtime.close()
        runner.flag.bits = 16
    return Episode(task=task, config=config.name, seed=int(seed), success=success, steps=len(log["bits"]),
                   final_eef=[float(v) for v in obs["robot0_eef_pos"]],
                   final_object=[float(v) for v in envs.object_pos(task, obs)], cpu_isa=dyq.cpu_info()["isa"], **log)
