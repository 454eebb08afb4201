"""Task registry for the closed-loop evaluation: robosuite Lift, PickPlaceCan and NutAssemblySquare with a
Panda arm under the BASIC composite controller (arm OSC_POSE, delta input) at 20 Hz, state observations only.

Episodes are reproducible by seed: robosuite 1.5 draws every random choice of a reset (object poses, the
cube's size, the robot's initial joint noise) from the environment's ``rng`` generator, which the placement
samplers hold a reference to. :func:`reset_env` swaps in a fresh ``numpy.random.default_rng(seed)`` for both
before each reset, so one environment can be reused across seeds and the same seed always gives the same
initial state, and (MuJoCo being deterministic) the same trajectory under the same actions. Step through
:func:`step_env`, not ``env.step``: robosuite samples each observable on a timer that survives resets, so the
observation ``env.step`` returns can lag the simulator state by physics substeps depending on the history;
:func:`step_env` re-reads it from the state reached.

Seed ranges: evaluation uses seeds 0..999, demonstrations start at :data:`DEMO_SEED0` (disjoint).

The LIBERO suites (``libero_object``, ``libero_spatial``; :mod:`dyq.sim.libero`, in the environment of the
``libero`` extra) are tasks too: every function here takes them, and routes them there.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import libero
from .pose import finger_yaw, quat_to_mat, quat_yaw, wrap  # noqa: F401  (part of this module's interface)

DEMO_SEED0 = 100_000
EVAL_SEEDS = range(1000)


@dataclass(frozen=True)
class TaskSpec:
    env_name: str
    horizon: int  # control steps per episode: about 1.5-2x the clean expert's 95th percentile
    object_key: str  # prefix of the object's ``_pos`` / ``_quat`` observations
    # Angular period (rad) of the object's yaw as the gripper sees it: a cube looks the same every 90 degrees,
    # the nut's handle every 180 (the two fingers are interchangeable); 0 for the can (no yaw to align with).
    yaw_period: float


# Horizons are about 2x the clean expert's 95th percentile of steps on seeds 0..49: lift 42, can 167, square
# 162 (with the demos' execution noise: 61, 249 and 180).
TASKS: dict[str, TaskSpec] = {
    "lift": TaskSpec("Lift", 90, "cube", np.pi / 2),
    "pick_place_can": TaskSpec("PickPlaceCan", 340, "Can", 0.0),
    "square": TaskSpec("NutAssemblySquare", 320, "SquareNut", np.pi),
}

# Where the expert grasps the square nut: this far along the nut's local x axis from its centre, the middle of
# the handle's part outside the ring (the handle box spans 0.029..0.079, the ring's wall ends at 0.044).
# At the handle box's centre, 0.054, the finger pads landed on the ring's wall whenever the hand stopped a
# few mm short (3/50 seeds, all with the handle pointing at the robot).
SQUARE_HANDLE_OFFSET = 0.062
# Fixed in the robosuite scenes (not randomized), so they are constants rather than observations.
SQUARE_PEG_POS = np.array([0.23, 0.1, 0.85])  # axis-aligned square peg, 3.2 cm wide, top at z = 0.95
SQUARE_NUT_LIFTED_Z = 0.87  # the nut's centre rests at about z = 0.83 on the table
# The can's quadrant of the goal bin spans x 0.10..0.295, y 0.28..0.525; its centre (0.1975, 0.4025) is at
# the edge of the Panda's reach with the gripper pointing down, so the expert aims at a point 4-5 cm inside
# the quadrant's corner nearest the robot.
CAN_BIN_POS = np.array([0.15, 0.33, 0.8])

ENV_KWARGS = dict(
    robots="Panda",
    has_renderer=False,
    has_offscreen_renderer=False,
    use_camera_obs=False,
    control_freq=20,
    reward_shaping=False,
)


# The LIBERO suites' horizons are LIBERO's own evaluation lengths; their objects and goals vary per task.
LIBERO_TASKS: dict[str, TaskSpec] = {name: TaskSpec(name, s.horizon, "", 0.0) for name, s in libero.SUITES.items()}
ALL_TASKS = sorted(TASKS) + sorted(LIBERO_TASKS)


def spec(task: str) -> TaskSpec:
    if task in LIBERO_TASKS:
        return LIBERO_TASKS[task]
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; choose from {ALL_TASKS}")
    return TASKS[task]


def controller_config() -> dict:
    from robosuite import load_composite_controller_config

    return load_composite_controller_config(controller="BASIC")


def make_env(task: str, seed: int | None = None, horizon: int | None = None, render: bool = False):
    """A fresh environment for ``task``, reset with ``seed`` when one is given (see :func:`reset_env`);
    ``render`` adds MuJoCo's offscreen renderer for videos (``env.sim.render``)."""
    if libero.is_suite(task):
        if render:
            raise NotImplementedError("videos of the LIBERO suites are not supported (state-only environments)")
        env = libero.SuiteEnv(task)
        if seed is not None:
            env.reset(seed)
        return env
    import robosuite

    kwargs = dict(ENV_KWARGS, has_offscreen_renderer=render)
    env = robosuite.make(spec(task).env_name, controller_configs=controller_config(),
                         horizon=horizon or spec(task).horizon, seed=seed, **kwargs)
    if seed is not None:
        reset_env(env, seed)
    return env


def env_args(task: str) -> dict:
    """What recreates the environment (stored with demonstrations, in robomimic's ``env_args`` shape)."""
    if libero.is_suite(task):
        return {"env_name": task, "type": "libero", "task": task,
                "env_kwargs": {"horizon": spec(task).horizon, "control_freq": 20,
                               "settle_steps": libero.SETTLE_STEPS}}
    kwargs = {k: v for k, v in ENV_KWARGS.items()}
    kwargs.update(controller_configs=controller_config(), horizon=spec(task).horizon)
    return {"env_name": spec(task).env_name, "type": 1, "task": task, "env_kwargs": kwargs}


def _set_sampler_rng(sampler, rng) -> None:
    if sampler is None:
        return
    sampler.rng = rng
    for child in getattr(sampler, "samplers", {}).values():
        _set_sampler_rng(child, rng)


def reset_env(env, seed: int) -> dict:
    """Reset ``env`` to the initial state that ``seed`` determines and return the first observation."""
    if isinstance(env, libero.SuiteEnv):
        return env.reset(seed)
    rng = np.random.default_rng(seed)
    env.rng = rng
    _set_sampler_rng(getattr(env, "placement_initializer", None), rng)
    return env.reset()


def step_env(env, action: np.ndarray) -> tuple[dict, float, bool, dict]:
    """``env.step`` with the observation read from the state reached (see the module docstring)."""
    if isinstance(env, libero.SuiteEnv):
        return env.step(action)
    _, reward, done, info = env.step(action)
    return env._get_observations(force_update=True), reward, done, info


def check_success(env) -> bool:
    """The task's own success test, independent of the reward settings."""
    if isinstance(env, libero.SuiteEnv):
        return env.check_success()
    return bool(env._check_success())


# ---------------------------------------------------------------------------------------- observations

def object_pos(task: str, obs: dict) -> np.ndarray:
    if libero.is_suite(task):
        return np.asarray(obs["dyq_object"], dtype=np.float64)
    return np.asarray(obs[spec(task).object_key + "_pos"], dtype=np.float64)


def grasp_point(task: str, obs: dict) -> np.ndarray:
    """Where the expert puts the fingertips: the object's centre, or the square nut's handle."""
    pos = object_pos(task, obs)
    if task == "square":
        pos = pos + SQUARE_HANDLE_OFFSET * quat_to_mat(obs["SquareNut_quat"])[:, 0]
    return pos


def goal_pos(task: str) -> np.ndarray | None:
    return {"square": SQUARE_PEG_POS, "pick_place_can": CAN_BIN_POS}.get(task)


def target_finger_yaw(task: str, obs: dict) -> float:
    """The finger-line yaw the expert turns to, nearest to the current one among the symmetric choices.

    Cube: across two faces. Square nut: across the handle (a bar along the nut's local x axis, so the fingers
    close along its local y); once lifted, the nut's yaw turns to the peg's instead (mod 90 degrees). Can: symmetric itself, so the fingers close across the line to the bin, which
    keeps the can between the fingers against the transport's acceleration and makes the yaw vary with the
    can's placement; the turn fades out near the goal, where that line is undefined.
    """
    current = finger_yaw(obs)
    if task == "pick_place_can":
        d = CAN_BIN_POS[:2] - object_pos(task, obs)[:2]
        # The bearing is undefined over the goal: fade the turn out over the last 5 cm.
        fade = min(1.0, float(np.linalg.norm(d)) / 0.05)
        return current + fade * wrap(np.arctan2(d[1], d[0]) + np.pi / 2 - current, np.pi)
    obj_yaw = quat_yaw(obs[spec(task).object_key + "_quat"])
    if task == "square" and square_nut_lifted(obs):
        # Held: turn the nut so its square hole lines up with the axis-aligned square peg, its handle pointing
        # to the robot or sideways (the gripper cannot reach beyond the peg with the handle pointing away).
        return current + min((wrap(y - obj_yaw) for y in (np.pi / 2, np.pi, -np.pi / 2)), key=abs)
    target = obj_yaw + (np.pi / 2 if task == "square" else 0.0)
    return current + wrap(target - current, spec(task).yaw_period)


def square_nut_lifted(obs: dict) -> bool:
    return float(obs["SquareNut_pos"][2]) > SQUARE_NUT_LIFTED_Z


def gripper_opening(obs: dict) -> float:
    q = obs["robot0_gripper_qpos"]
    return float(q[0] - q[1])


def observation_names(task: str) -> list[str]:
    """Names of :func:`observation_vector`'s dims, in order."""
    if libero.is_suite(task):
        return list(libero.OBSERVATION_NAMES)
    names = ["eef_x", "eef_y", "eef_z", "finger_yaw_sin", "finger_yaw_cos", "eef_down_x", "eef_down_y",
             "gripper_opening", "grasp_x", "grasp_y", "grasp_z", "grasp_dx", "grasp_dy", "grasp_dz", "yaw_error"]
    if spec(task).yaw_period:
        names += ["object_yaw_sin", "object_yaw_cos"]
    if goal_pos(task) is not None:
        names += ["object_to_goal_dx", "object_to_goal_dy", "object_to_goal_dz"]
    return names


def observation_vector(task: str, obs: dict) -> np.ndarray:
    """A compact, fixed-order float32 state for a learned policy (names in :func:`observation_names`).

    It holds everything the expert's decisions depend on, so its phase is inferable: the end-effector's
    position, finger yaw (sin/cos) and tilt (the x/y of its pointing axis, which the roll/pitch commands
    level), the gripper's opening (grasped or not), the grasp point (absolute, so its height says lifted or
    not, and relative to the end-effector), the yaw the expert still has to turn, the object's yaw in its
    symmetry period (sin/cos of period-scaled angle), and the object's offset from the goal (the bin or peg).
    """
    if libero.is_suite(task):
        return libero.observation_vector(obs)
    s = spec(task)
    eef = np.asarray(obs["robot0_eef_pos"], dtype=np.float64)
    yaw = finger_yaw(obs)
    down = quat_to_mat(obs["robot0_eef_quat"])[:, 2]
    grasp = grasp_point(task, obs)
    parts = [eef, [np.sin(yaw), np.cos(yaw)], down[:2], [gripper_opening(obs)], grasp, grasp - eef,
             [target_finger_yaw(task, obs) - yaw]]
    if s.yaw_period:
        k = 2 * np.pi / s.yaw_period
        obj_yaw = quat_yaw(obs[s.object_key + "_quat"])
        parts.append([np.sin(k * obj_yaw), np.cos(k * obj_yaw)])
    goal = goal_pos(task)
    if goal is not None:
        parts.append(object_pos(task, obs) - goal)
    return np.concatenate([np.asarray(p, dtype=np.float64).ravel() for p in parts]).astype(np.float32)
