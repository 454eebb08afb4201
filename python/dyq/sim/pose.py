"""Poses from robosuite's observations, shared by the robosuite tasks (:mod:`dyq.sim.envs`) and the LIBERO
suites (:mod:`dyq.sim.libero`): quaternions are xyzw, as robosuite reports them."""
from __future__ import annotations

import numpy as np


def quat_yaw(quat_xyzw: np.ndarray) -> float:
    """Yaw (rad) of the body's local x axis projected on the world xy plane."""
    x, y, z, w = quat_xyzw
    return float(np.arctan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z)))


def quat_to_mat(quat_xyzw: np.ndarray) -> np.ndarray:
    x, y, z, w = quat_xyzw
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def finger_yaw(obs: dict) -> float:
    """Yaw of the line the Panda's fingers close along: the end-effector's local x axis turned by 90 degrees
    (measured from the finger pads' positions)."""
    return quat_yaw(obs["robot0_eef_quat"]) + np.pi / 2


def wrap(angle: float, period: float = 2 * np.pi) -> float:
    """``angle`` folded into [-period/2, period/2)."""
    return float((angle + period / 2) % period - period / 2)
