"""Scripted experts for the dyq evaluation tasks, acting on privileged object state.

Each expert is a short phase machine over targets for the end-effector. Its commands are proportional
errors with saturation, so they are large in free space and small near a target: the same structure that
dyq's kinematic dispatcher keys on (Motion Fineness from the translation magnitude, Angular Jerk from
changes of the rotation command). The rotation channels are used on every step: they level the gripper
(it starts tilted by about 10 degrees) and turn its finger line to the object's yaw, which the square nut
needs and the cube and can get as a per-episode variation.

Phase changes depend only on what :func:`dyq.sim.envs.observation_vector` shows (distances to targets, the
gripper's opening, the object's height), apart from a short grasp dwell that the gripper's opening reveals,
so a policy cloned from these labels can infer the phase. When a grasp is lost (the object falls away from
the fingers), the experts go back to approaching it, which also makes them recover from execution noise.

Action layout (robosuite OSC_POSE, delta input, BASIC controller): xyz delta (1.0 = 0.05 m), axis-angle
rotation delta in the base frame (1.0 = 0.5 rad), gripper (-1 open, +1 close).
"""
from __future__ import annotations

import numpy as np

from . import envs

OPEN, CLOSE = -1.0, 1.0
# Saturation gains: 1/gain is the error at which a command saturates. About 1 cm/step is reached at full
# translation command; 12 per metre keeps the approach overdamped (20 overshoots by 3 mm).
POS_GAIN = 12.0
ROT_GAIN = 3.0  # per radian: saturates beyond about 19 degrees of error


def rotation_command(obs: dict, finger_yaw: float) -> np.ndarray:
    """Axis-angle command (scaled, clipped) that turns the gripper to point straight down with its finger
    line at ``finger_yaw``."""
    current = envs.quat_to_mat(obs["robot0_eef_quat"])
    a = finger_yaw - np.pi / 2  # the finger line is the end-effector's x axis turned by 90 degrees
    x = np.array([np.cos(a), np.sin(a), 0.0])
    z = np.array([0.0, 0.0, -1.0])
    target = np.stack([x, np.cross(z, x), z], axis=1)
    err = target @ current.T
    angle = np.arccos(np.clip((np.trace(err) - 1) / 2, -1.0, 1.0))
    if angle < 1e-9:
        return np.zeros(3)
    axis = np.array([err[2, 1] - err[1, 2], err[0, 2] - err[2, 0], err[1, 0] - err[0, 1]]) / (2 * np.sin(angle))
    return np.clip(ROT_GAIN * angle * axis, -1.0, 1.0)


def move_command(obs: dict, target: np.ndarray, gripper: float, finger_yaw: float) -> np.ndarray:
    """One expert action: the saturating step towards ``target`` for the end-effector, the rotation to
    point down with the finger line at ``finger_yaw``, and the gripper command."""
    action = np.zeros(7)
    action[:3] = np.clip(POS_GAIN * (np.asarray(target) - obs["robot0_eef_pos"]), -1.0, 1.0)
    action[3:6] = rotation_command(obs, finger_yaw)
    action[6] = gripper
    return action


def noisy_action(clean: np.ndarray, rng: np.random.Generator, scale: float) -> np.ndarray:
    """DART-style execution noise: Gaussian noise of std ``scale`` on every channel of the executed action,
    clipped to [-1, 1]. The recorded label stays ``clean``, so a cloned policy learns the expert's
    corrections from the states the noise leads to. (On the saturated gripper channel the clipped noise
    only weakens the command, it never flips it.)"""
    noisy = np.asarray(clean, dtype=np.float64) + rng.normal(0.0, scale, len(clean)) if scale > 0 else clean
    return np.clip(noisy, -1.0, 1.0)


class Expert:
    """Shared phase machine: approach above the grasp point, descend, close, then task-specific moves.

    Subclasses set the heights and tolerances and define :meth:`carry` (the moves after the grasp).
    """

    task: str
    hover = 0.08  # approach height above the grasp point (m)
    xy_tol = 0.01  # before descending, and to close
    z_tol = 0.01  # to close
    yaw_tol = np.radians(8.0)
    close_steps = 8  # dwell while the fingers close

    def reset(self, env) -> None:
        self.phase = "approach"
        self.closed_for = 0

    def _move(self, obs: dict, target: np.ndarray, gripper: float, yaw: float | None = None) -> np.ndarray:
        return move_command(obs, target, gripper, envs.target_finger_yaw(self.task, obs) if yaw is None else yaw)

    def _yaw_error(self, obs: dict) -> float:
        return abs(envs.target_finger_yaw(self.task, obs) - envs.finger_yaw(obs))

    def grasped(self, obs: dict) -> bool:
        """The object is between the fingers: close to the grasp site and the fingers not shut on air."""
        near = np.linalg.norm(envs.grasp_point(self.task, obs) - obs["robot0_eef_pos"]) < 0.03
        return near and envs.gripper_opening(obs) > 0.01

    def act(self, env, obs: dict) -> np.ndarray:
        eef = obs["robot0_eef_pos"]
        grasp = envs.grasp_point(self.task, obs)
        if self.phase in ("carry", "lower") and not self.grasped(obs):
            self.phase = "approach"  # dropped it: start over
        if self.phase == "approach":
            target = grasp + [0.0, 0.0, self.hover]
            # Gripper well above the object: go straight for the hover point; otherwise rise first so the
            # fingers do not sweep the object away.
            if eef[2] < grasp[2] + 0.5 * self.hover and np.linalg.norm(grasp[:2] - eef[:2]) > 2 * self.xy_tol:
                target = np.array([eef[0], eef[1], target[2]])
            if np.linalg.norm(grasp[:2] - eef[:2]) < self.xy_tol and self._yaw_error(obs) < self.yaw_tol \
                    and abs(target[2] - eef[2]) < 0.02:
                self.phase = "descend"
            return self._move(obs, target, OPEN)
        if self.phase == "descend":
            # A funnel: the lower the hand, the better aligned it must be. All the way down within twice the
            # xy tolerance, back at ``hover`` above the grasp point at 5x; so a push from noise or contact
            # raises the hand a little while it re-centres instead of restarting the approach.
            xy_err = float(np.linalg.norm(grasp[:2] - eef[:2]))
            lift = self.hover * np.clip((xy_err - 2 * self.xy_tol) / (3 * self.xy_tol), 0.0, 1.0)
            target = grasp + [0.0, 0.0, lift]
            if xy_err < self.xy_tol and abs(target[2] - eef[2]) < self.z_tol:
                self.phase, self.closed_for = "close", 0
            elif xy_err > 0.05:
                self.phase = "approach"  # the object was knocked away: aim again from above
            return self._move(obs, target, OPEN)
        if self.phase == "close":
            self.closed_for += 1
            if self.closed_for >= self.close_steps:
                self.phase = "carry"
            return self._move(obs, grasp, CLOSE)
        return self.carry(obs)

    def carry(self, obs: dict) -> np.ndarray:
        raise NotImplementedError


class LiftExpert(Expert):
    """Lift: grasp the cube across two faces, raise it to 15 cm above the table (success needs 4 cm)."""

    task = "lift"
    lift_z = 0.95

    def carry(self, obs: dict) -> np.ndarray:
        eef = obs["robot0_eef_pos"]
        return self._move(obs, np.array([eef[0], eef[1], self.lift_z]), CLOSE)


class PickPlaceCanExpert(Expert):
    """PickPlaceCan: grasp the can at mid-height, lift it over the bins' walls, carry it above its goal
    (the bin's fixed quadrant), lower it and let go."""

    task = "pick_place_can"
    hover = 0.10
    transport_z = 1.05  # the can's bottom clears the walls between the bins
    release_z = 0.92  # end-effector height to let go at: the can's centre a few cm above the goal's floor
    goal_tol = 0.02  # xy distance of the can from the goal before lowering

    def act(self, env, obs: dict) -> np.ndarray:
        if self.phase == "release":
            # Fingers open and rising: done once the can stands in the bin (the episode ends on success).
            eef = obs["robot0_eef_pos"]
            return self._move(obs, np.array([eef[0], eef[1], self.transport_z]), OPEN, envs.finger_yaw(obs))
        return super().act(env, obs)

    def carry(self, obs: dict) -> np.ndarray:
        eef = obs["robot0_eef_pos"]
        can = envs.object_pos(self.task, obs)
        to_goal = envs.CAN_BIN_POS[:2] - can[:2]
        if np.linalg.norm(to_goal) > self.goal_tol:
            if eef[2] < self.transport_z - 0.03 and np.linalg.norm(to_goal) > 0.1:
                return self._move(obs, np.array([eef[0], eef[1], self.transport_z]), CLOSE)  # rise first
            target = np.array([eef[0] + to_goal[0], eef[1] + to_goal[1], self.transport_z])
            return self._move(obs, target, CLOSE)
        target = np.array([eef[0] + to_goal[0], eef[1] + to_goal[1], self.release_z])
        if eef[2] < self.release_z + 0.01:
            self.phase = "release"
        return self._move(obs, target, CLOSE)


class SquareExpert(Expert):
    """NutAssemblySquare: grasp the nut's handle across it, lift it over the peg's top (z = 0.95), turn its
    hole to the peg's yaw, centre it over the peg and lower it down the peg."""

    task = "square"
    hover = 0.10
    xy_tol = 0.006
    z_tol = 0.006
    close_steps = 10
    lift_z = 1.0  # end-effector height for the transfer: the nut hangs just below it, over the peg's top
    lower_z = 0.83
    peg_tol = 0.004  # nut centre over the peg, xy
    peg_yaw_tol = np.radians(4.0)

    def carry(self, obs: dict) -> np.ndarray:
        eef = obs["robot0_eef_pos"]
        nut = envs.object_pos(self.task, obs)
        to_peg = envs.SQUARE_PEG_POS[:2] - nut[:2]
        over = np.linalg.norm(to_peg) < self.peg_tol and self._yaw_error(obs) < self.peg_yaw_tol
        if self.phase == "carry" and over and eef[2] > self.lift_z - 0.02:
            self.phase = "lower"
        if self.phase == "lower":
            if np.linalg.norm(to_peg) > 0.02:
                self.phase = "carry"  # slid off: lift again
            return self._move(obs, np.array([eef[0] + to_peg[0], eef[1] + to_peg[1], self.lower_z]), CLOSE)
        if eef[2] < self.lift_z - 0.03 and np.linalg.norm(to_peg) > 0.03:
            return self._move(obs, np.array([eef[0], eef[1], self.lift_z]), CLOSE)  # rise first
        return self._move(obs, np.array([eef[0] + to_peg[0], eef[1] + to_peg[1], self.lift_z]), CLOSE)


EXPERTS = {"lift": LiftExpert, "pick_place_can": PickPlaceCanExpert, "square": SquareExpert}


def make_expert(task: str):
    envs.spec(task)
    if envs.libero.is_suite(task):
        return envs.libero.PickPlaceExpert()
    return EXPERTS[task]()
