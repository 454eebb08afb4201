"""The LIBERO suites' pieces that need no LIBERO install: seeds, geometry, the multi-task policy's prompt;
and, where the ``libero`` extra is installed, one short episode of each suite."""
import importlib.util
import types

import numpy as np
import pytest
import torch

from dyq.sim import envs, libero
from dyq.sim.policy import PolicyConfig, TokenPolicy
from dyq.sim.tokens import BOS, BinTokenizer, Vocabulary

HAS_LIBERO = importlib.util.find_spec("libero") is not None


def test_seeds_cover_the_official_states_then_perturbed_ones():
    official = [libero.task_of_seed(s) for s in libero.OFFICIAL_SEEDS]
    assert sorted((t, i) for t, i, p in official) == [(t, i) for t in range(10) for i in range(50)]
    assert not any(p for _, _, p in official)
    assert libero.task_of_seed(500) == (0, 0, True)
    assert libero.task_of_seed(envs.DEMO_SEED0 + 13) == (3, (envs.DEMO_SEED0 + 13) // 10 % 50, True)
    with pytest.raises(ValueError, match="seed"):
        libero.task_of_seed(-1)


def test_collecting_chosen_tasks_takes_only_their_seeds_in_order():
    from dyq.sim.demos import _seeds

    seed0 = envs.DEMO_SEED0 + 3
    chosen = _seeds("libero_spatial", seed0, [4, 5, 7])
    seeds = [chosen(i) for i in range(9)]
    expected = [s for s in range(seed0, seed0 + 40) if s % 10 in (4, 5, 7)][:9]
    assert seeds == expected and len(set(seeds)) == 9
    assert [libero.task_of_seed(s)[0] for s in seeds[:3]] == [4, 5, 7]
    assert _seeds("libero_spatial", seed0, None)(5) == seed0 + 5
    with pytest.raises(ValueError, match="task_indices"):
        _seeds("libero_spatial", seed0, [10])
    with pytest.raises(ValueError, match="task_indices"):
        _seeds("lift", seed0, [1])


def test_suites_are_tasks():
    for suite in libero.SUITES:
        assert envs.spec(suite).horizon == libero.SUITES[suite].horizon
        assert envs.observation_names(suite) == libero.OBSERVATION_NAMES
    with pytest.raises(ValueError, match="unknown task"):
        envs.spec("libero_goal")


def _brute_force_overlap(a, b, n=200):
    """Whether two convex quadrilaterals intersect, by sampling points of ``a`` and testing them in ``b``."""
    def inside(poly, p):
        signs = [np.cross(poly[(i + 1) % 4] - poly[i], p - poly[i]) for i in range(4)]
        return all(s >= 0 for s in signs) or all(s <= 0 for s in signs)
    rng = np.random.default_rng(0)
    for _ in range(n):
        u, v = rng.random(2)
        p = (1 - u) * ((1 - v) * a[0] + v * a[1]) + u * ((1 - v) * a[3] + v * a[2])
        if inside(b, p):
            return True
    return False


@pytest.mark.parametrize("seed", range(20))
def test_box_overlap_sign_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    a = libero.hand_box(rng.uniform(-0.1, 0.1, 2), rng.uniform(-np.pi, np.pi))
    b = libero.hand_box(rng.uniform(-0.1, 0.1, 2), rng.uniform(-np.pi, np.pi))
    depth = libero._boxes_overlap(a, b)
    if abs(depth) > 1e-3:
        assert (depth > 0) == (_brute_force_overlap(a, b) or _brute_force_overlap(b, a))
    # Two boxes moved apart along x by more than their extent: negative, the gap between them.
    far = libero._boxes_overlap(libero.hand_box(np.zeros(2), 0.0), libero.hand_box(np.array([0.3, 0.0]), 0.0))
    assert far == pytest.approx(-(0.3 - 2 * libero.HAND_HALF_ALONG))


def _sim(xml):
    mujoco = pytest.importorskip("mujoco")
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    # robosuite's binding names the body poses body_xpos / body_xmat; raw MuJoCo names them xpos / xmat.
    view = types.SimpleNamespace(body_xpos=data.xpos, body_xmat=data.xmat, geom_xpos=data.geom_xpos,
                                 geom_xmat=data.geom_xmat)
    return types.SimpleNamespace(model=model, data=view)


def test_footprint_of_a_turned_box_and_a_grasp_across_its_narrow_side():
    yaw = 0.4
    quat = f"{np.cos(yaw / 2)} 0 0 {np.sin(yaw / 2)}"
    sim = _sim(f"""<mujoco><worldbody>
        <body name="box" pos="0.1 0.2 0.03" quat="{quat}"><geom type="box" size="0.05 0.02 0.03"/></body>
        <body name="far" pos="1 1 0.03"><geom type="box" size="0.02 0.02 0.03"/></body>
        </worldbody></mujoco>""")
    fp = libero.footprint(sim, 1)
    assert np.allclose(fp.centre, [0.1, 0.2])
    assert sorted(fp.half_sizes) == pytest.approx([0.02, 0.05])
    assert (fp.bottom, fp.top) == pytest.approx((0.0, 0.06))
    plan = libero.plan_grasp(sim, 1, [2], current_finger_yaw=0.0, robot_base=np.array([-0.6, 0.0, 0.0]))
    # Fingers close across the 4 cm side: along the box's local y, i.e. yaw + 90 degrees (mod 180).
    finger = yaw + plan.yaw_offset
    assert abs(np.sin(finger - (yaw + np.pi / 2))) < 1e-6
    assert plan.clearance > 0.5 and not plan.rim


def test_a_bowl_wider_than_the_gripper_is_taken_by_the_rim_nearest_the_robot():
    sim = _sim("""<mujoco><worldbody>
        <body name="bowl" pos="0.0 0.0 0.025"><geom type="cylinder" size="0.055 0.025"/></body>
        </worldbody></mujoco>""")
    plan = libero.plan_grasp(sim, 1, [], current_finger_yaw=0.0, robot_base=np.array([-0.6, 0.0, 0.0]))
    assert plan.rim
    assert np.linalg.norm(plan.offset_local[:2]) == pytest.approx(0.055 - libero.RIM_INSET)
    assert plan.offset_local[0] < -0.04  # the near side


def _multi_task_policy(tasks=("a", "b", "c"), dims=4):
    rng = np.random.default_rng(0)
    values = rng.normal(size=(64, dims))
    config = PolicyConfig(task="suite", tasks=list(tasks), observation_names=["task_index"] + [f"o{i}" for i in range(dims)],
                          observation_tokenizer=BinTokenizer.range_with_margin(values).to_dict(),
                          action_tokenizer=BinTokenizer.percentiles(rng.normal(size=(64, 7))).to_dict(),
                          hidden_size=128, intermediate_size=128, layers=1, heads=2)
    return TokenPolicy(config), values


def test_multi_task_prompt_puts_the_task_index_in_the_task_token():
    policy, values = _multi_task_policy()
    vocab = policy.vocabulary
    tokenizer = policy.observation_tokenizer
    for index in range(3):
        obs = np.concatenate([[index], values[index]])
        ids = policy.prompt(obs)[0].numpy()
        # Independent of the prefix builders: BOS, the index-th task token, then dimension-major bins.
        bins = np.clip(np.floor((np.clip(2 * (values[index] - tokenizer.low) / (tokenizer.high - tokenizer.low) - 1,
                                         -1, 1) + 1) * 0.5 * 256), 0, 255)
        expected = [BOS, vocab.first_task + index] + list(vocab.first_observation + 256 * np.arange(4) + bins)
        assert ids.tolist() == expected
    batch = np.concatenate([np.array([[2], [0]]), values[:2]], axis=1)
    ids, _ = policy.sequences(batch, np.zeros((2, 7)))
    assert ids[:, 1].tolist() == [vocab.first_task + 2, vocab.first_task]
    logits = policy.action_logits(ids)
    assert logits.shape == (2, 7, 256) and torch.isfinite(logits).all()


def test_multi_task_prompt_rejects_bad_task_indices():
    policy, values = _multi_task_policy()
    for bad in (3, -1, 0.5):
        with pytest.raises(ValueError, match="task_index"):
            policy.prompt(np.concatenate([[bad], values[0]]))
    with pytest.raises(ValueError, match="observation values"):
        policy.prompt(values[0])
    with pytest.raises(ValueError, match="task_index"):
        PolicyConfig(task="suite", tasks=["a"], observation_names=["x"], observation_tokenizer={},
                     action_tokenizer={})
    with pytest.raises(ValueError, match="task indices"):
        Vocabulary(tasks=("a",), observation_dims=1).prefix_of_tasks(np.array([1]), np.array([[0]]))


@pytest.mark.skipif(not HAS_LIBERO, reason="the libero extra is not installed (scripts/setup_libero.sh)")
@pytest.mark.parametrize("suite", sorted(libero.SUITES))
def test_one_expert_episode_succeeds(suite):
    from dyq.sim import experts

    env = envs.make_env(suite)
    expert = experts.make_expert(suite)
    obs = envs.reset_env(env, 0)
    expert.reset(env)
    success = False
    for _ in range(envs.spec(suite).horizon):
        vector = envs.observation_vector(suite, obs)
        assert vector.shape == (len(libero.OBSERVATION_NAMES),) and vector[0] == 0
        obs, _, _, _ = envs.step_env(env, expert.act(env, obs))
        if envs.check_success(env):
            success = True
            break
    env.close()
    assert success


@pytest.mark.skipif(not HAS_LIBERO, reason="the libero extra is not installed (scripts/setup_libero.sh)")
def test_a_perturbed_bowl_on_the_ramekin_stays_on_it():
    """LIBERO-Spatial task 5 starts with the bowl on the ramekin; a perturbed state moves the two together
    (moved apart, the bowl would slide off and the scene would not be the task's any more)."""
    env = envs.make_env("libero_spatial")
    layouts = []
    for seed in (5, envs.DEMO_SEED0 + 5, envs.DEMO_SEED0 + 15, envs.DEMO_SEED0 + 25):
        envs.reset_env(env, seed)
        bowl = footprint_of(env, env.target)
        ramekin = footprint_of(env, next(n for n in env._movable() if "ramekin" in n))
        layouts.append((bowl.bottom - ramekin.top, np.linalg.norm(bowl.centre - ramekin.centre), bowl.centre))
    env.close()
    (lean, apart, start), perturbed = layouts[0], layouts[1:]
    assert abs(lean) < 0.02  # the official state: the bowl rests on the ramekin
    for lean_p, apart_p, centre in perturbed:
        assert abs(lean_p - lean) < 0.01 and abs(apart_p - apart) < 0.01, (lean_p, apart_p)
    assert max(np.linalg.norm(c - start) for _, _, c in perturbed) > 0.005  # and the pair did move


@pytest.mark.skipif(not HAS_LIBERO, reason="the libero extra is not installed (scripts/setup_libero.sh)")
def test_a_seed_gives_the_same_scene_fixtures_included_whatever_ran_before():
    """LIBERO places the fixtures (cabinet, stove) at every reset from numpy's global RNG: the scene of a
    seed must not depend on it, or replays and paired seeds would see another cabinet."""
    scenes = []
    for before in (None, 7, 12):
        env = envs.make_env("libero_spatial")
        if before is not None:
            envs.reset_env(env, before)
            np.random.seed(before)  # whatever else a process does with the global RNG
        obs = envs.reset_env(env, 4)
        scenes.append((env.sim.model.body_pos.copy(), envs.observation_vector("libero_spatial", obs)))
        env.close()
    for body_pos, vector in scenes[1:]:
        np.testing.assert_array_equal(body_pos, scenes[0][0])
        np.testing.assert_array_equal(vector, scenes[0][1])
    draw = np.random.get_state()[1][:4].copy()
    env = envs.make_env("libero_spatial")
    envs.reset_env(env, 4)
    env.close()
    np.testing.assert_array_equal(np.random.get_state()[1][:4], draw)  # and the global RNG is left as it was


def footprint_of(env, name):
    return libero.footprint(env.sim, env.body(name))


def test_suite_rows_count_per_task_and_quote_the_paper(tmp_path):
    from dyq.sim import evaluate

    rng = np.random.default_rng(3)
    outcome = rng.random(40) < 0.6
    episodes = [{"task": "libero_object", "seed": s, "success": bool(outcome[s]), "steps": 5, "bits": [16] * 5,
                 "latency_ms": [1.0] * 5, "prefill_kernel_bits": [{}] * 5, "decode_kernel_bits": [{}] * 5}
                for s in range(40)]
    row = evaluate.summarize(episodes)
    for task in range(10):
        seeds = [s for s in range(40) if s % 10 == task]
        assert row["per_task"][str(task)] == [int(outcome[seeds].sum()), len(seeds)]
    data = evaluate.update_results(tmp_path / "r.json", "libero_object", list(range(40)), "ckpt", "abc",
                                   {"fp32": row})
    table = evaluate.markdown_table(data)
    assert "| fp32 | " + " | ".join(f"{s}/{n}" for s, n in row["per_task"].values()) + " |" in table
    assert "BF16 88.4 %" in table and "DyQ-VLA W4AX 87.8 %" in table
    # A robosuite task's rows have no per-task split.
    assert "per_task" not in evaluate.summarize([dict(e, task="lift") for e in episodes])


def test_a_box_is_taken_off_centre_when_a_neighbour_blocks_the_hand():
    sim = _sim("""<mujoco><worldbody>
        <body name="box" pos="0 0 0.01"><geom type="box" size="0.04 0.02 0.01"/></body>
        <body name="jar" pos="-0.03 0.08 0.03"><geom type="box" size="0.015 0.015 0.03"/></body>
        </worldbody></mujoco>""")
    centred = libero.plan_grasp(sim, 1, [], current_finger_yaw=np.pi / 2, robot_base=np.array([0.0, -0.6, 0.0]))
    assert np.allclose(centred.offset_local[:2], 0.0)
    plan = libero.plan_grasp(sim, 1, [2], current_finger_yaw=np.pi / 2, robot_base=np.array([0.0, -0.6, 0.0]))
    # Fingers across y (the narrow side), shifted along +x, away from the jar, until the hand clears it.
    assert abs(np.cos(plan.yaw_offset)) < 1e-6
    assert 0.0 < plan.offset_local[0] <= 0.6 * 0.04 + 1e-9 and plan.clearance > 0


def _closing_obs(opening: float) -> dict:
    """The expert's view while its fingers close on an object at the grasp point."""
    return {"robot0_eef_pos": np.array([0.1, 0.0, 0.9]), "dyq_grasp": np.array([0.1, 0.0, 0.9]),
            "dyq_place": np.array([0.2, 0.2, 0.95]), "dyq_carry_z": 1.05, "dyq_grasp_yaw": 0.0,
            "robot0_eef_quat": np.array([1.0, 0.0, 0.0, 0.0]),
            "robot0_gripper_qpos": np.array([opening / 2, -opening / 2])}


@pytest.mark.parametrize("openings, lifts_at", [
    # Closing on an object: the fingers stop 0.3 mm apart (under the 1 mm rule) at the 7th step.
    ([0.079, 0.074, 0.065, 0.055, 0.049, 0.0475, 0.0472, 0.0471, 0.0471, 0.0471, 0.0471], 7),
    # Fingers that never settle: the step count still ends the wait.
    ([0.079 - 0.005 * i for i in range(12)], libero.PickPlaceExpert.close_steps),
])
def test_the_expert_lifts_when_the_fingers_have_settled(openings, lifts_at):
    # The wait after closing ends on what the policy sees (the opening stops changing), so the cloned
    # policy has no observation that means both "wait" and "lift".
    expert = libero.PickPlaceExpert()
    expert.reset(None)
    expert.phase, expert.count, expert.last_opening = "close", 0, None
    for step, opening in enumerate(openings, start=1):
        action = expert.act(None, _closing_obs(opening))
        assert action[6] == 1.0  # still closing
        if expert.phase == "lift":
            break
    assert (step, expert.phase) == (lifts_at, "lift")


def test_the_policy_sees_whether_the_fingers_still_move():
    # dyq_opening_change: the opening minus the previous observation's, 0 right after a reset; the
    # settled-fingers rule of the expert is a function of it.
    env = object.__new__(libero.SuiteEnv)
    env._opening = None
    openings = [0.079, 0.074, 0.0472, 0.0471]
    changes = [env._with_opening_change(_closing_obs(o))["dyq_opening_change"] for o in openings]
    np.testing.assert_allclose(changes, [0.0, -0.005, 0.0472 - 0.074, -0.0001], atol=1e-12)
    names = libero.OBSERVATION_NAMES
    assert names[names.index("gripper_opening") + 1] == "gripper_opening_change"
