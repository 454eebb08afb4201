"""LIBERO-Object and LIBERO-Spatial as closed-loop tasks: the scenes, BDDL goals and official initial
states of the LIBERO benchmark (installed offline by the ``libero`` extra, robosuite 1.4), with a Panda arm
under OSC_POSE at 20 Hz, state observations only.

A *suite* is one dyq task: ``libero_object`` or ``libero_spatial``, ten LIBERO tasks each, and one policy
serves all ten, told which one by a task-id token (the prompt's second token; see
:func:`observation_vector`). Seeds choose the LIBERO task and the initial state:

- seeds 0..499: the official initial states, task ``seed % 10``, state ``seed // 10`` (all 50 per task);
- seeds 500..999 and the demonstration seeds (from :data:`dyq.sim.envs.DEMO_SEED0`): the official state
  ``(seed // 10) % 50`` of task ``seed % 10`` with its movable objects shifted by up to
  :data:`PERTURB_XY` and turned by up to :data:`PERTURB_YAW`, drawn from ``numpy.random.default_rng(seed)``
  (the official states barely vary: in LIBERO-Object the target starts at the same spot in all 50).

Every reset waits :data:`SETTLE_STEPS` no-op steps first, as LIBERO's own evaluation does, because the
stored states are taken before the objects settle. The episode ends at the suite's horizon, LIBERO's own
evaluation length (220 steps for Spatial, 280 for Object), or at success (the BDDL goal holds).

The environment here is :class:`SuiteEnv`, which holds one LIBERO environment per task (building one takes
about 6 s) and adds the privileged quantities that the expert and the policy's observation need to the
observation dict under ``dyq_*`` keys: the target object's grasp point, the finger yaw to grasp it with
(chosen at reset so that the hand clears the neighbouring objects), and the place point over the goal.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from .pose import finger_yaw, quat_to_mat, wrap

SETTLE_STEPS = 10
PERTURB_XY = 0.025  # m, each movable object, uniform in [-PERTURB_XY, PERTURB_XY] per axis
PERTURB_YAW = np.radians(30.0)
OFFICIAL_SEEDS = range(500)
TASKS_PER_SUITE = 10
STATES_PER_TASK = 50

# The Panda hand seen from above, around the point between the fingertips: about 21 cm along the line the
# fingers close on, 6.4 cm across it. A grasp whose hand box overlaps a neighbour knocks it over.
HAND_HALF_ALONG = 0.105
HAND_HALF_ACROSS = 0.032
GRIPPER_SPAN = 0.075  # widest object the open fingers take with margin
# Objects wider than the gripper (bowls) are taken by their rim: the fingertips close on the wall.
RIM_INSET = 0.012


@dataclass(frozen=True)
class SuiteSpec:
    name: str
    horizon: int


SUITES: dict[str, SuiteSpec] = {
    "libero_object": SuiteSpec("libero_object", 280),
    "libero_spatial": SuiteSpec("libero_spatial", 220),
}


def is_suite(task: str) -> bool:
    return task in SUITES


def task_of_seed(seed: int) -> tuple[int, int, bool]:
    """(LIBERO task index, official initial state index, perturbed) of ``seed``."""
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    task = seed % TASKS_PER_SUITE
    if seed in OFFICIAL_SEEDS:
        return task, seed // TASKS_PER_SUITE, False
    return task, (seed // TASKS_PER_SUITE) % STATES_PER_TASK, True


def benchmark_suite(suite: str):
    if suite not in SUITES:
        raise ValueError(f"unknown LIBERO suite {suite!r}; choose from {sorted(SUITES)}")
    try:
        from libero.libero import benchmark
    except ImportError as e:
        raise ImportError("LIBERO is not installed: set up its environment with `bash scripts/setup_libero.sh` "
                          "(see the README)") from e
    return benchmark.get_benchmark_dict()[suite]()


def task_names(suite: str) -> list[str]:
    bench = benchmark_suite(suite)
    return [bench.get_task(i).name for i in range(bench.n_tasks)]


# ------------------------------------------------------------------------------------------ geometry

@dataclass
class Footprint:
    """An object's collision geometry as a box in the world: centre, half sizes along two horizontal axes
    (``axis`` is the unit vector of the first), and its height range."""

    centre: np.ndarray  # xy
    axis: np.ndarray  # xy unit vector of half_sizes[0]
    half_sizes: np.ndarray  # (along axis, across it)
    bottom: float
    top: float
    round: bool  # a cylinder or a bowl: any yaw grasps it alike

    def corners(self) -> np.ndarray:
        a = self.axis * self.half_sizes[0]
        b = np.array([-self.axis[1], self.axis[0]]) * self.half_sizes[1]
        return self.centre + np.array([a + b, a - b, -a - b, -a + b])


def _body_subtree(model, body: int) -> list[int]:
    return [b for b in range(model.nbody) if b == body or _is_descendant(model, b, body)]


def _is_descendant(model, b: int, ancestor: int) -> bool:
    while b > 0:
        b = int(model.body_parentid[b])
        if b == ancestor:
            return True
    return False


def footprint(sim, body: int) -> Footprint:
    """The box around the collision geoms of ``body`` and its children, in the frame of the body's most
    horizontal axes (objects stand upright in LIBERO, though their frames differ: some have local y up)."""
    model, data = sim.model, sim.data
    rot = data.body_xmat[body].reshape(3, 3)
    up = int(np.argmax(np.abs(rot[2])))  # the local axis closest to world z
    horizontal = [i for i in range(3) if i != up]
    points = []
    types = set()
    for g in range(model.ngeom):
        if int(model.geom_bodyid[g]) not in _body_subtree(model, body):
            continue
        if model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0:
            continue  # visual only
        types.add(int(model.geom_type[g]))
        gpos, grot, size = data.geom_xpos[g], data.geom_xmat[g].reshape(3, 3), model.geom_size[g]
        kind = int(model.geom_type[g])
        if kind == 6:  # box
            half = size
        elif kind in (3, 5):  # capsule, cylinder: radius, half-length along local z
            half = np.array([size[0], size[0], size[1] + (size[0] if kind == 3 else 0.0)])
        elif kind == 2:  # sphere
            half = np.full(3, size[0])
        elif kind == 7:  # mesh: its bounding box, which MuJoCo centres on the geom
            half = model.geom_aabb[g][3:] if hasattr(model, "geom_aabb") else np.full(3, model.geom_rbound[g])
        else:
            continue
        for corner in np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).T.reshape(-1, 3):
            points.append(gpos + grot @ (corner * half))
    points = np.asarray(points)
    local = (points - data.body_xpos[body]) @ rot  # in the body's frame
    lo, hi = local.min(axis=0), local.max(axis=0)
    centre_local = (lo + hi) / 2
    centre = data.body_xpos[body] + rot @ centre_local
    a0 = rot[:2, horizontal[0]]
    a0 = a0 / np.linalg.norm(a0)
    half = (hi - lo)[horizontal] / 2
    round_ = abs(half[0] - half[1]) < 0.004 and types <= {3, 5, 7}
    return Footprint(centre[:2].copy(), a0, half, float(points[:, 2].min()), float(points[:, 2].max()), round_)


def _boxes_overlap(a: np.ndarray, b: np.ndarray) -> float:
    """Penetration depth (> 0 overlap) of two convex quadrilaterals by separating axes; negative: clearance
    along the best separating axis."""
    best = -np.inf
    for poly in (a, b):
        for i in range(4):
            edge = poly[(i + 1) % 4] - poly[i]
            normal = np.array([-edge[1], edge[0]]) / (np.linalg.norm(edge) + 1e-12)
            pa, pb = a @ normal, b @ normal
            gap = max(pb.min() - pa.max(), pa.min() - pb.max())
            best = max(best, gap)
    return -best


def hand_box(point: np.ndarray, finger_yaw: float) -> np.ndarray:
    along = np.array([np.cos(finger_yaw), np.sin(finger_yaw)])
    across = np.array([-along[1], along[0]])
    a, b = along * HAND_HALF_ALONG, across * HAND_HALF_ACROSS
    return point[:2] + np.array([a + b, a - b, -a - b, -a + b])


# ------------------------------------------------------------------------------------------ the grasp

@dataclass
class GraspPlan:
    """Where and how the expert takes the target, relative to the target's body so that it follows the
    object when it moves: the grasp point's offset in the body frame, the finger yaw relative to the body's
    yaw, and the height of the fingertips above the object's bottom."""

    offset_local: np.ndarray
    yaw_offset: float
    height: float  # grasp point above the object's bottom
    clearance: float  # m between the hand box and the nearest neighbour (negative: overlap)
    rim: bool


def plan_grasp(sim, target: int, neighbours: list[int], current_finger_yaw: float,
               robot_base: np.ndarray) -> GraspPlan:
    """The grasp with the most clearance between the hand and the neighbours: across the object's narrow
    side (either way round) for boxes, at any of 16 yaws for round objects, or on the rim at any of 16
    points for objects wider than the gripper; a box may also be taken off its centre along its long side.
    Among grasps clear by 3 cm, the nearest to the robot's base wins (far rim points are out of the arm's
    reach at the hover height), then the one nearest the centre and with the smallest turn."""
    fp = footprint(sim, target)
    rot = sim.data.body_xmat[target].reshape(3, 3)
    body_pos = sim.data.body_xpos[target]
    body_yaw = float(np.arctan2(rot[1, 0], rot[0, 0]))
    height = fp.top - fp.bottom
    others = [footprint(sim, b) for b in neighbours]
    candidates = []  # (point xy, finger yaw, rim)
    narrow = int(np.argmin(fp.half_sizes))
    axis_yaw = float(np.arctan2(fp.axis[1], fp.axis[0]))
    if 2 * fp.half_sizes.min() > GRIPPER_SPAN:
        radius = fp.half_sizes.min() - RIM_INSET
        for k in range(16):
            phi = 2 * np.pi * k / 16
            direction = np.array([np.cos(phi), np.sin(phi)])
            candidates.append((fp.centre + radius * direction, phi, True))
    elif fp.round:
        for k in range(16):
            candidates.append((fp.centre, np.pi * k / 16, False))
    else:
        # Across the narrow side, at the centre or shifted along the long side (away from a neighbour that
        # the hand would land on), keeping the fingers well inside the object's length.
        yaw = axis_yaw + (0.0 if narrow == 0 else np.pi / 2)
        long_axis = fp.axis if narrow == 1 else np.array([-fp.axis[1], fp.axis[0]])
        for shift in (0.0, -0.3, 0.3, -0.6, 0.6):
            point = fp.centre + shift * fp.half_sizes.max() * long_axis
            candidates += [(point, yaw, False), (point, yaw + np.pi, False)]

    def score(c):
        point, yaw, _ = c
        box = hand_box(point, yaw)
        clear = min((-_boxes_overlap(box, o.corners()) for o in others if o.top > fp.bottom + 0.01),
                    default=1.0)
        turn = abs((yaw - current_finger_yaw + np.pi / 2) % np.pi - np.pi / 2)
        reach = float(np.linalg.norm(point[:2] - robot_base[:2]))
        off_centre = 0.0 if c[2] else float(np.linalg.norm(point[:2] - fp.centre))
        return min(clear, 0.03) - 0.3 * reach - 0.01 * turn - 0.5 * off_centre, clear

    best = max(candidates, key=lambda c: score(c)[0])
    point, yaw, rim = best
    # The palm sits about 6 cm above the fingertips: on tall objects the fingers take the top 3 cm.
    grasp_height = height - 0.02 if rim else float(np.clip(height - 0.03, 0.015, height))
    grasp_world = np.array([point[0], point[1], fp.bottom + grasp_height])
    return GraspPlan(offset_local=rot.T @ (grasp_world - body_pos), yaw_offset=float(yaw - body_yaw),
                     height=grasp_height, clearance=float(score(best)[1]), rim=rim)


# ------------------------------------------------------------------------------------------ environment

def holding(eef: np.ndarray, grasp: np.ndarray, gripper_qpos) -> bool:
    """The fingers are closed on the target: its grasp point between them and the fingers short of fully
    open (0.08 m) and of shut on air."""
    opening = float(gripper_qpos[0] - gripper_qpos[1])
    return bool(np.linalg.norm(grasp - eef) < 0.03 and 0.004 < opening < 0.07)


class SuiteEnv:
    """The ten LIBERO environments of one suite behind one reset/step interface (see the module docstring).

    ``reset(seed)`` picks the task and initial state from the seed, perturbs it if the seed says so, lets
    it settle and plans the grasp; observations carry ``dyq_*`` entries for the expert and the policy.
    """

    def __init__(self, suite: str):
        self.suite = suite
        self.spec = SUITES[suite]
        self.benchmark = benchmark_suite(suite)
        self._envs: dict[int, object] = {}
        self._init_states: dict[int, np.ndarray] = {}
        self.task_index = -1
        self.env = None
        self._opening = None  # the gripper's opening at the last observation (for dyq_opening_change)

    # -- the LIBERO environment of a task --------------------------------------------------------------
    def _task_env(self, index: int):
        if index not in self._envs:
            from libero.libero import get_libero_path
            from libero.libero.envs.env_wrapper import ControlEnv

            task = self.benchmark.get_task(index)
            bddl = os.path.join(get_libero_path("bddl_files"), task.problem_folder, task.bddl_file)
            self._envs[index] = ControlEnv(bddl_file_name=bddl, use_camera_obs=False, has_renderer=False,
                                           has_offscreen_renderer=False, horizon=10_000, control_freq=20)
            self._init_states[index] = np.asarray(self.benchmark.get_task_init_states(index))
        return self._envs[index]

    @property
    def sim(self):
        return self.env.env.sim  # re-read: a reset rebuilds the simulator

    @property
    def language(self) -> str:
        return self.benchmark.get_task(self.task_index).language

    def close(self) -> None:
        for env in self._envs.values():
            env.close()
        self._envs.clear()

    # -- objects -----------------------------------------------------------------------------------------
    def body(self, name: str) -> int:
        return int(self.env.env.obj_body_id[name])

    def _goal(self) -> tuple[str, str, str]:
        goal = self.env.env.parsed_problem["goal_state"]
        if len(goal) != 1 or goal[0][0] not in ("in", "on"):
            raise NotImplementedError(f"only single 'in'/'on' goals are supported, got {goal}")
        relation, target, place = goal[0]
        return relation, target, place

    def _movable(self) -> list[str]:
        return [n for n in self.env.env.objects_dict]

    def _supports(self, names: list[str]) -> dict[str, str]:
        """Which movable object each movable object rests on, if any (the bowl on the ramekin or on the
        cookie box): the two footprints overlapping, its bottom above the other's top by up to 15 cm
        (LIBERO's stored states hold such an object in the air over its support; it drops during the
        settling steps, the bowl onto the ramekin's rim). A bowl beside the plate, whose square footprint
        touches the plate's, stands lower than the plate's top and is not on it."""
        prints = {n: footprint(self.sim, self.body(n)) for n in names}
        supports = {}
        for name, fp in prints.items():
            below = [(other, p) for other, p in prints.items() if other != name
                     and 0.0 < fp.bottom - p.top < 0.15 and _boxes_overlap(fp.corners(), p.corners()) > 0.005]
            if below:
                supports[name] = max(below, key=lambda item: item[1].top)[0]
        return supports

    def _perturb(self, rng: np.random.Generator) -> None:
        """Shift and turn every movable object (free joint) a little; retried until no two footprints
        overlap more than they did in the official state. An object resting on another one moves with it,
        rigidly about the support's centre, so that a bowl on a ramekin stays on it: moved on its own, it
        would slide off and the perturbed scenes would no longer show the task's layout."""
        sim = self.sim
        names = [n for n in self._movable() if self.env.env.get_object(n).joints]
        supports = self._supports(names)

        def root(name: str) -> str:
            while name in supports:
                name = supports[name]
            return name

        base = sim.get_state()
        for _ in range(20):
            sim.set_state(base)
            moves = {n: (rng.uniform(-PERTURB_XY, PERTURB_XY, 2), rng.uniform(-PERTURB_YAW, PERTURB_YAW))
                     for n in names}
            centres = {n: sim.data.qpos[self._qpos_addr(n): self._qpos_addr(n) + 2].copy() for n in names}
            for name in names:
                anchor = root(name)
                shift, turn = moves[anchor]
                addr = self._qpos_addr(name)
                qpos = sim.data.qpos[addr: addr + 7].copy()
                c, s = np.cos(turn), np.sin(turn)
                arm = qpos[:2] - centres[anchor]
                qpos[:2] = centres[anchor] + np.array([c * arm[0] - s * arm[1], s * arm[0] + c * arm[1]]) + shift
                w, x, y, z = qpos[3:7]  # MuJoCo's wxyz
                c, s = np.cos(turn / 2), np.sin(turn / 2)  # q_turn (about world z) * q
                qpos[3:7] = [c * w - s * z, c * x - s * y, c * y + s * x, c * z + s * w]
                sim.data.qpos[addr: addr + 7] = qpos
            sim.forward()
            prints = {n: footprint(sim, self.body(n)) for n in names}
            overlap = max((_boxes_overlap(prints[a].corners(), prints[b].corners())
                           for i, a in enumerate(names) for b in names[i + 1:]
                           if root(a) != root(b)
                           and min(prints[a].top, prints[b].top) > max(prints[a].bottom, prints[b].bottom)),
                          default=-1.0)
            if overlap < 0.0:
                return
        sim.set_state(base)  # no clean draw: keep the official state
        sim.forward()

    def _qpos_addr(self, name: str) -> int:
        joint = self.env.env.get_object(name).joints[-1]
        return int(self.sim.model.get_joint_qpos_addr(joint)[0])

    def reset(self, seed: int) -> dict:
        index, state, perturbed = task_of_seed(int(seed))
        self.task_index = index
        self.env = self._task_env(index)
        self._rebuild_scene(int(seed))
        self.env.set_init_state(self._init_states[index][state])
        if perturbed:
            self._perturb(np.random.default_rng(seed))
        for _ in range(SETTLE_STEPS):
            self.env.step(np.zeros(7))
        obs = self._raw_observation()
        self.relation, self.target, self.place = self._goal()
        self.plan = plan_grasp(self.sim, self.body(self.target), self._neighbours(), finger_yaw(obs),
                               self._robot_base())
        self._plan_transport()
        self.steps = 0
        self._opening = None
        return self._augment(self._with_opening_change(obs))

    def _rebuild_scene(self, seed: int) -> None:
        """``env.reset()`` with numpy's global RNG seeded by ``seed``, then restored. A reset rebuilds the
        scene and places the fixtures (LIBERO-Spatial's cabinet and stove: bodies without joints, so not
        in a stored initial state) anew from that RNG, up to 1.6 cm apart from one reset to the next;
        unseeded, a seed's scene would depend on what ran before it in the process, and a replay of an
        episode, or the same seed under two configurations, would see another cabinet."""
        saved = np.random.get_state()
        np.random.seed(seed % 2**32)
        try:
            self.env.reset()
        finally:
            np.random.set_state(saved)

    def _robot_base(self) -> np.ndarray:
        return self.sim.data.body_xpos[self.sim.model.body_name2id(self.env.env.robots[0].robot_model.root_body)]

    def _neighbours(self) -> list[int]:
        skip = {self.target}
        return [self.body(n) for n in list(self.env.env.objects_dict) + list(self.env.env.fixtures_dict)
                if n not in skip]

    def replan(self, obs: dict) -> None:
        """A new grasp for the target where it lies now (after a drop)."""
        self.plan = plan_grasp(self.sim, self.body(self.target), self._neighbours(), finger_yaw(obs),
                               self._robot_base())
        self._plan_transport()

    def _place_point(self) -> np.ndarray:
        """Where the target's centre goes, xy, and the top of what it goes into or onto."""
        if self.relation == "in":
            site = self.sim.data.get_site_xpos(self.place)
            container = self.env.env.object_sites_dict[self.place].parent_name
            top = footprint(self.sim, self.body(container)).top
            return np.array([site[0], site[1], top])
        fp = footprint(self.sim, self.body(self.place))
        return np.array([fp.centre[0], fp.centre[1], fp.top])

    def _plan_transport(self) -> None:
        """Carry height (everything near the path cleared by 3 cm) and release height of the grasp point."""
        sim = self.sim
        target = footprint(sim, self.body(self.target))
        place = self._place_point()
        start, end = target.centre, place[:2]
        tops = [place[2]]
        for b in self._neighbours():
            fp = footprint(sim, b)
            d = end - start
            t = float(np.clip(np.dot(fp.centre - start, d) / (np.dot(d, d) + 1e-12), 0.0, 1.0))
            if np.linalg.norm(fp.centre - (start + t * d)) < 0.12 + fp.half_sizes.max():
                tops.append(fp.top)
        carry_bottom = max(tops) + 0.03
        self.carry_z = carry_bottom + self.plan.height
        if self.relation == "in":
            # Dropped in from just above the container's rim, with the hand clear of it.
            self.release_z = max(place[2] + 0.01 + self.plan.height, place[2] - 0.05)
        else:
            self.release_z = place[2] + 0.005 + self.plan.height
        self.place_xy = place[:2]

    # -- observations ------------------------------------------------------------------------------------
    def _raw_observation(self) -> dict:
        return dict(self.env.env._get_observations(force_update=True))

    def _with_opening_change(self, obs: dict) -> dict:
        """``dyq_opening_change``: the gripper's opening minus the previous step's (0 after a reset). The
        expert ends its waits when the fingers stop moving, so the policy must see whether they still move:
        from the opening alone, the last step of a wait and the first step after it look the same."""
        q = obs["robot0_gripper_qpos"]
        opening = float(q[0] - q[1])
        obs["dyq_opening_change"] = 0.0 if self._opening is None else opening - self._opening
        self._opening = opening
        return obs

    def _augment(self, obs: dict) -> dict:
        sim = self.sim
        b = self.body(self.target)
        rot = sim.data.body_xmat[b].reshape(3, 3)
        pos = sim.data.body_xpos[b].copy()
        body_yaw = float(np.arctan2(rot[1, 0], rot[0, 0]))
        current = finger_yaw(obs)
        grasp_yaw = current + wrap(body_yaw + self.plan.yaw_offset - current, np.pi)
        if holding(obs["robot0_eef_pos"], pos + rot @ self.plan.offset_local, obs["robot0_gripper_qpos"]):
            grasp_yaw = current  # in the hand, it turns with it: the hand holds its yaw
        obs["dyq_task_index"] = self.task_index
        obs["dyq_object"] = pos
        obs["dyq_grasp"] = pos + rot @ self.plan.offset_local
        obs["dyq_grasp_yaw"] = grasp_yaw
        # The grasp point's target over the goal: the object's centre over the place point.
        obs["dyq_place"] = np.array([self.place_xy[0], self.place_xy[1], self.release_z]) + \
            np.append(obs["dyq_grasp"][:2] - footprint(sim, b).centre, 0.0)
        obs["dyq_carry_z"] = self.carry_z
        return obs

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, dict]:
        _, reward, done, info = self.env.step(np.asarray(action, dtype=np.float64))
        self.steps += 1
        return self._augment(self._with_opening_change(self._raw_observation())), reward, done, info

    def check_success(self) -> bool:
        return bool(self.env.check_success())


OBSERVATION_NAMES = ["task_index", "eef_x", "eef_y", "eef_z", "finger_yaw_sin", "finger_yaw_cos", "eef_down_x",
                     "eef_down_y", "gripper_opening", "gripper_opening_change", "grasp_x", "grasp_y", "grasp_z", "grasp_dx", "grasp_dy",
                     "grasp_dz", "yaw_error", "place_dx", "place_dy", "place_dz", "carry_dz"]


def observation_vector(obs: dict) -> np.ndarray:
    """The policy's state, in :data:`OBSERVATION_NAMES` order. Its first entry is the LIBERO task's index,
    which the policy reads as its task-id token rather than as a binned value."""
    eef = np.asarray(obs["robot0_eef_pos"], dtype=np.float64)
    yaw = finger_yaw(obs)
    down = quat_to_mat(obs["robot0_eef_quat"])[:, 2]
    q = obs["robot0_gripper_qpos"]
    grasp = np.asarray(obs["dyq_grasp"])
    place = np.asarray(obs["dyq_place"])
    parts = [[obs["dyq_task_index"]], eef, [np.sin(yaw), np.cos(yaw)], down[:2], [q[0] - q[1]],
             [obs["dyq_opening_change"]], grasp, grasp - eef,
             [obs["dyq_grasp_yaw"] - yaw], place - grasp, [obs["dyq_carry_z"] - grasp[2]]]
    return np.concatenate([np.asarray(p, dtype=np.float64).ravel() for p in parts]).astype(np.float32)


# ------------------------------------------------------------------------------------------ the expert

class PickPlaceExpert:
    """One scripted expert for every task of both suites, on the privileged quantities of
    :class:`SuiteEnv`: over the grasp point with the fingers at the planned yaw, down, close, up to the
    carry height, over the place point, down to the release height, open, and back up.

    Its commands have the part-1 experts' structure (saturating proportional errors, rotation on every
    step), and its phase changes depend on what :func:`observation_vector` shows. A lost grasp sends it
    back to the approach with a new plan.
    """

    hover = 0.08
    xy_tol = 0.008
    z_tol = 0.008
    yaw_tol = np.radians(8.0)
    close_steps = 10
    release_steps = 8
    settle_steps = 3
    settled_change = 0.001
    place_tol = 0.01

    def reset(self, env: SuiteEnv) -> None:
        self.phase = "approach"
        self.count = 0
        self.last_opening = None

    def _fingers_settled(self, obs: dict) -> bool:
        """The fingers have stopped moving: closing or opening ends on what the policy sees (an opening
        that no longer changes), not on a step count it cannot see. A count alone leaves the last steps
        of the wait and the first step after it with one observation, and a cloned policy that learned
        the wait holds still there forever."""
        q = obs["robot0_gripper_qpos"]
        opening = float(q[0] - q[1])
        previous, self.last_opening = self.last_opening, opening
        return (self.count >= self.settle_steps and previous is not None
                and abs(opening - previous) < self.settled_change)

    def _move(self, obs: dict, target: np.ndarray, gripper: float, yaw: float | None = None) -> np.ndarray:
        from .experts import move_command  # experts imports envs, which imports this module

        return move_command(obs, target, gripper, obs["dyq_grasp_yaw"] if yaw is None else yaw)

    def _held(self, obs: dict) -> bool:
        return holding(obs["robot0_eef_pos"], obs["dyq_grasp"], obs["robot0_gripper_qpos"])

    def act(self, env: SuiteEnv, obs: dict) -> np.ndarray:
        eef = obs["robot0_eef_pos"]
        grasp = obs["dyq_grasp"]
        place = obs["dyq_place"]
        carry_z = obs["dyq_carry_z"]
        open_, close = -1.0, 1.0
        if self.phase in ("lift", "transfer", "lower") and not self._held(obs):
            env.replan(obs)
            self.phase = "approach"
            obs = env._augment(obs)
            grasp = obs["dyq_grasp"]
        xy_err = float(np.linalg.norm(grasp[:2] - eef[:2]))
        if self.phase == "approach":
            target = grasp + [0.0, 0.0, self.hover]
            if eef[2] < grasp[2] + 0.5 * self.hover and xy_err > 2 * self.xy_tol:
                target = np.array([eef[0], eef[1], target[2]])  # rise first
            yaw_err = abs(obs["dyq_grasp_yaw"] - finger_yaw(obs))
            if xy_err < self.xy_tol and yaw_err < self.yaw_tol and abs(target[2] - eef[2]) < 0.02:
                self.phase = "descend"
            return self._move(obs, target, open_)
        if self.phase == "descend":
            lift = self.hover * np.clip((xy_err - 2 * self.xy_tol) / (3 * self.xy_tol), 0.0, 1.0)
            target = grasp + [0.0, 0.0, lift]
            if xy_err < self.xy_tol and abs(target[2] - eef[2]) < self.z_tol:
                self.phase, self.count, self.last_opening = "close", 0, None
            elif xy_err > 0.05:
                self.phase = "approach"
            return self._move(obs, target, open_)
        if self.phase == "close":
            self.count += 1
            if self._fingers_settled(obs) or self.count >= self.close_steps:
                self.phase = "lift"
            return self._move(obs, grasp, close)
        if self.phase == "lift":
            if eef[2] > carry_z - 0.015:
                self.phase = "transfer"
            return self._move(obs, np.array([eef[0], eef[1], carry_z]), close)
        to_place = place[:2] - grasp[:2]
        if self.phase == "transfer":
            if np.linalg.norm(to_place) < self.place_tol:
                self.phase = "lower"
            return self._move(obs, np.array([eef[0] + to_place[0], eef[1] + to_place[1], carry_z]), close)
        if self.phase == "lower":
            if np.linalg.norm(to_place) > 3 * self.place_tol:
                self.phase = "transfer"
            elif abs(eef[2] - place[2]) < self.z_tol:
                self.phase, self.count, self.last_opening = "release", 0, None
            return self._move(obs, np.array([eef[0] + to_place[0], eef[1] + to_place[1], place[2]]), close)
        if self.phase == "release":
            self.count += 1
            if self._fingers_settled(obs) or self.count >= self.release_steps:
                self.phase = "retreat"
            return self._move(obs, eef, open_, finger_yaw(obs))
        return self._move(obs, np.array([eef[0], eef[1], carry_z + 0.05]), open_, finger_yaw(obs))
