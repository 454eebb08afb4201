"""Closed-loop episodes: a policy drives the robot, with DyQ choosing each step's activation width.

A **configuration** says how the policy runs (:data:`CONFIGS`):

* ``fp32``: the trained policy in full precision, no dyq layer at all (the reference);
* ``w4a16``, ``w4a8``, ``w4a4``, ``w4a2``: every projection on static INT4 weights
  (``dyq.quantize_model``, group 128) at one fixed activation width for the whole episode;
* ``dyq``: the same INT4 model, with the width of every control step chosen by
  :class:`dyq.KinematicDispatcher` under :class:`dyq.DyQRuntime` (paper Sec. IV-V).

DyQ in the loop, per control step t (paper Algorithm 1 and Sec. V-B):

1. the runtime hands the dispatcher a_{t-1}, the action the arm executed at the previous step (none at
   t = 0), on its worker thread, while the **prefill** of the observation prompt runs;
2. the prefill runs at the flag's current value, b*_{t-1} (the runtime's ``prefill_bits="previous"``;
   16 at t = 0): the prefill cannot wait for b*_t without losing the overlap. This choice is the same
   for every DyQ variant;
3. the runtime publishes b*_t into the precision flag, and the **decode** of the 7 action tokens runs at
   b*_t; every GEMM reads the flag itself.

The dispatcher's configuration for ``dyq`` is :class:`dyq.DispatchConfig`'s defaults (the paper's
windows and θ_fp, neutral Θ, λ and K), fixed before any closed-loop result was seen; calibration per
task writes another configuration. Each episode resets the dispatcher with no history, so an episode is
a function of its seed alone and can be cached and run in any order.

The per-step log keeps the bits chosen, the bits each GEMM actually ran at (counted by the kernels,
:func:`dyq.ops.width_counts`), S_t, M̃_t, J̃_t, the action and the policy's latency.
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import numpy as np

import dyq

from . import envs
from .policy import TokenPolicy

GROUP_SIZE = 128


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """How the policy runs in one closed-loop configuration."""

    name: str
    kind: str  # "float", "static" or "dyq"
    bits: int | None = None  # the fixed width of a "static" configuration
    dispatch: dict = dataclasses.field(default_factory=dict)  # DispatchConfig overrides for "dyq"

    def dispatch_config(self) -> "dyq.DispatchConfig":
        return dyq.DispatchConfig(**self.dispatch)


CONFIGS: dict[str, RunConfig] = {
    "fp32": RunConfig("fp32", "float"),
    "w4a16": RunConfig("w4a16", "static", 16),
    "w4a8": RunConfig("w4a8", "static", 8),
    "w4a4": RunConfig("w4a4", "static", 4),
    "w4a2": RunConfig("w4a2", "static", 2),
    "dyq": RunConfig("dyq", "dyq"),
}


def run_config(name: str) -> RunConfig:
    if name not in CONFIGS:
        raise ValueError(f"unknown configuration {name!r}; choose from {sorted(CONFIGS)}")
    return CONFIGS[name]


def width_counts() -> dict[int, int]:
    return dict(dyq.ops.width_counts())


def _count_difference(after: dict[int, int], before: dict[int, int]) -> dict[str, int]:
    return {str(bits): after[bits] - before.get(bits, 0) for bits in after if after[bits] != before.get(bits, 0)}


class PolicyRunner:
    """The policy of one checkpoint in every configuration: the float model and one INT4 copy bound to
    a precision flag (built once per process, shared by all quantized configurations)."""

    def __init__(self, policy: TokenPolicy):
        self.float_policy = policy
        self.quantized = policy.copy()
        self.flag = dyq.PrecisionFlag(16)
        self.report = dyq.quantize_model(self.quantized.model, group_size=GROUP_SIZE, flag=self.flag)
        if self.report.skipped and any(name != "lm_head" for name in self.report.skipped):
            raise ValueError(f"the policy has layers dyq cannot convert: {self.report.skipped}")

    @classmethod
    def load(cls, checkpoint) -> "PolicyRunner":
        return cls(TokenPolicy.load(checkpoint))


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

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "Episode":
        return cls(**data)


def run_episode(runner: PolicyRunner, task: str, config: RunConfig | str, seed: int, *, env=None,
                frames: list | None = None, camera: str = "frontview", frame_size: int = 256) -> Episode:
    """Runs one seeded episode of ``task`` under ``config``; stops at success or at the task's horizon.

    ``frames``, if given, receives one RGB frame per step (needs an environment with an offscreen
    renderer, see :func:`dyq.sim.envs.make_env`).
    """
    if isinstance(config, str):
        config = run_config(config)
    spec = envs.spec(task)
    if env is None:
        env = envs.make_env(task)
    obs = envs.reset_env(env, seed)
    if config.kind == "float":
        policy = runner.float_policy
    else:
        policy = runner.quantized
    runtime = None
    if config.kind == "dyq":
        runtime = dyq.DyQRuntime(dyq.KinematicDispatcher(config.dispatch_config()), runner.flag,
                                 prefill_bits="previous")
        runtime.reset()
    elif config.kind == "static":
        runner.flag.bits = config.bits

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
            else:
                bins = policy.decode(prefill())
                bits = config.bits if config.kind == "static" else 16
                sensitivity = fineness = jerk = math.nan
            latency = (time.perf_counter() - start) * 1e3
            counts.append(width_counts())
            action = np.clip(policy.action(bins), -1.0, 1.0)
            obs, _, _, _ = env.step(action)
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
                   final_object=[float(v) for v in envs.object_pos(task, obs)], **log)
