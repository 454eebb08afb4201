"""KinematicDispatcher against a plain numpy re-implementation of paper Sec. III-B and IV."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dyq.control.dispatch import (
    DispatchConfig,
    Hysteresis,
    KinematicDispatcher,
    ProxyWeight,
    RollingPercentile,
    actions_from_poses,
    allocate_bits,
    fuse_sensitivity,
    paper_ladder,
    paper_proxies,
    replay_trajectory,
    synthetic_trajectory,
)


def reference_trace(actions, config):
    """Whole-trajectory numpy version: percentiles by np.percentile over explicit history slices,
    windows by np.mean over slices, Phi by np.searchsorted, then the hysteresis."""
    p, history = config.percentile, config.history
    translation = np.linalg.norm(actions[:, slice(*config.xyz_slice)], axis=1)
    rotation = actions[:, slice(*config.rot_slice)]
    jerk = np.r_[np.nan, np.linalg.norm(np.diff(rotation, axis=0), axis=1)]  # jerk[t] uses t-1, t
    steps = len(actions)
    fineness, angular = np.full(steps, np.nan), np.full(steps, np.nan)
    sensitivity, targets = np.full(steps, np.nan), np.full(steps, 16)
    for t in range(steps):
        mu = np.percentile(translation[max(0, t + 1 - history) : t + 1], p)
        fineness[t] = 1 - translation[t] / mu
        if t >= 1:
            nu = np.percentile(jerk[max(1, t + 1 - history) : t + 1], p)
            angular[t] = jerk[t] / nu
        warm = t + 1 >= config.warmup and t >= config.warmup  # magnitudes seen: t + 1, jerks: t
        if warm:
            (_, lam, macro_window), (_, _, micro_window) = [(p.name, p.weight, p.window) for p in config.proxies]
            m_tilde = np.mean(fineness[max(0, t + 1 - macro_window) : t + 1])
            j_tilde = np.mean(angular[max(1, t + 1 - micro_window) : t + 1])
            sensitivity[t] = max(0.0, lam * m_tilde + (1 - lam) * j_tilde)
            edges = [threshold for threshold, _ in config.ladder]
            widths = [bits for _, bits in config.ladder] + [16]
            targets[t] = widths[np.searchsorted(edges, sensitivity[t], side="left")]
    hysteresis = Hysteresis(config.delay_window, config.hysteresis)
    bits = np.array([hysteresis.update(int(b)) for b in targets])
    return {"motion_fineness": fineness, "angular_jerk": angular, "sensitivity": sensitivity,
            "target_bits": targets, "bits": bits}


def random_actions(seed, steps=80, width=7):
    """Noisy actions with phases of different speeds so every bit-width occurs."""
    rng = np.random.default_rng(seed)
    speed = rng.choice([0.05, 0.3, 1.0], size=(steps // 10 + 1, 1)).repeat(10, axis=0)[:steps]
    actions = rng.normal(0, 1, (steps, width)) * speed
    actions[:, 3:6] *= rng.choice([0.1, 1.0], size=(steps // 8 + 1, 1)).repeat(8, axis=0)[:steps]
    return actions


configs = st.builds(
    DispatchConfig,
    proxies=st.builds(paper_proxies, st.floats(0.05, 0.95), st.integers(1, 12), st.integers(1, 6)),
    ladder=st.builds(paper_ladder, st.just(0.2), st.just(0.4), st.floats(0.45, 1.5)),
    delay_window=st.integers(1, 5),
    percentile=st.floats(50, 100),
    history=st.integers(16, 128),
    warmup=st.integers(1, 16),
    hysteresis=st.sampled_from(["window", "counter"]),
)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), config=configs)
def test_trace_matches_numpy_reference(seed, config):
    actions = random_actions(seed)
    trace = replay_trajectory(actions, config)
    expected = reference_trace(actions, config)
    for name in ("motion_fineness", "angular_jerk", "sensitivity"):
        np.testing.assert_allclose(trace[name], expected[name], rtol=1e-9, atol=1e-12, err_msg=name)
    np.testing.assert_array_equal(trace["target_bits"], expected["target_bits"])
    np.testing.assert_array_equal(trace["bits"], expected["bits"])


def test_history_covering_the_episode_equals_full_history_percentiles():
    actions = random_actions(7, steps=200)
    config = DispatchConfig(history=512)
    trace = replay_trajectory(actions, config)
    translation = np.linalg.norm(actions[:, :3], axis=1)
    mu_full = np.array([np.percentile(translation[: t + 1], 95) for t in range(200)])
    np.testing.assert_allclose(trace["mu_max"], mu_full, rtol=1e-12)


@settings(deadline=None)
@given(
    values=st.lists(st.floats(0, 1e6, allow_nan=False), min_size=1, max_size=300),
    capacity=st.integers(1, 64),
    percentile=st.floats(0.5, 100),
)
def test_rolling_percentile_is_numpy_percentile_of_the_last_samples(values, capacity, percentile):
    rolling = RollingPercentile(capacity, percentile)
    for n, value in enumerate(values, start=1):
        rolling.push(value)
        window = values[max(0, n - capacity) : n]
        assert len(rolling) == len(window)
        assert rolling.value() == pytest.approx(np.percentile(window, percentile), rel=1e-12, abs=1e-12)


def test_rolling_percentile_of_nothing_is_nan():
    assert math.isnan(RollingPercentile(4, 95).value())


def test_warm_up_returns_full_precision():
    config = DispatchConfig(warmup=10, delay_window=1)
    dispatcher = KinematicDispatcher(config)
    for t, action in enumerate(random_actions(3, steps=30)):
        bits = dispatcher.step(action)
        # jerks lag the magnitudes by one step: the first warm step is the (warmup + 1)-th
        assert dispatcher.is_warm == (t >= config.warmup)
        if not dispatcher.is_warm:
            assert bits == 16 and dispatcher.target_bits == 16 and math.isnan(dispatcher.sensitivity)


@pytest.mark.parametrize("field, value", [("motion_fineness", 0), ("angular_jerk", 1)])
def test_metrics_become_available_in_order(field, value):
    dispatcher = KinematicDispatcher()
    assert math.isnan(getattr(dispatcher, field))
    for action in random_actions(5, steps=2):
        dispatcher.step(action)
    assert math.isfinite(getattr(dispatcher, field))


def test_large_translation_gives_negative_fineness_and_clamped_sensitivity():
    config = DispatchConfig(proxies=paper_proxies(fusion_weight=1.0), warmup=5)
    dispatcher = KinematicDispatcher(config)
    small = np.array([0.01, 0, 0, 0.1, 0, 0, 0])
    for _ in range(30):
        dispatcher.step(small)
    dispatcher.step(np.array([10.0, 0, 0, 0.1, 0, 0, 0]))
    assert dispatcher.motion_fineness < -100
    assert dispatcher.sensitivity == 0.0
    assert dispatcher.target_bits == 2


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_sensitivity_is_never_negative_and_bits_always_valid(seed):
    trace = replay_trajectory(random_actions(seed) * 10 ** np.random.default_rng(seed).uniform(-3, 3))
    warm = np.isfinite(trace["sensitivity"])
    assert (trace["sensitivity"][warm] >= 0).all()
    assert set(np.unique(trace["bits"])) <= {2, 4, 8, 16}


def test_rotation_that_never_changes_keeps_full_precision():
    actions = random_actions(11, steps=60)
    actions[:, 3:6] = 0.2  # constant rotation: every jerk is 0, nu_max = 0
    trace = replay_trajectory(actions, DispatchConfig(proxies=paper_proxies(fusion_weight=0.5)))
    assert (trace["bits"] == 16).all()
    assert np.isnan(trace["sensitivity"]).all()


def test_rotation_is_ignored_when_lambda_is_one():
    actions = random_actions(11, steps=60)
    actions[:, 3:6] = 0.2
    trace = replay_trajectory(actions, DispatchConfig(proxies=paper_proxies(fusion_weight=1.0)))
    assert np.isfinite(trace["sensitivity"][20:]).all()
    assert (trace["bits"][20:] < 16).any()


def test_translation_ignored_when_lambda_is_zero():
    actions = random_actions(12, steps=60)
    actions[:, :3] = 0.0  # no translation: mu_max = 0
    trace = replay_trajectory(actions, DispatchConfig(proxies=paper_proxies(fusion_weight=0.0)))
    assert np.isnan(trace["motion_fineness"]).all()
    assert np.isfinite(trace["sensitivity"][20:]).all()


def test_a_still_arm_stays_at_full_precision():
    trace = replay_trajectory(np.zeros((40, 7)))
    assert (trace["bits"] == 16).all()


def test_pose_input_matches_the_actions_between_the_poses():
    rng = np.random.default_rng(0)
    actions = random_actions(21, steps=60)
    actions[:, 3:6] *= 0.5
    start = np.r_[rng.normal(size=3), 3.0, -3.0, 0.5, 0.0]  # near +-pi: the angles wrap
    poses = np.vstack([start, start + np.cumsum(actions, axis=0)])
    poses[:, 3:6] = (poses[:, 3:6] + np.pi) % (2 * np.pi) - np.pi
    by_action = replay_trajectory(actions, DispatchConfig(input="action"))
    by_pose = replay_trajectory(poses, DispatchConfig(input="pose"))
    assert by_pose["bits"][0] == 16 and math.isnan(by_pose["sensitivity"][0])
    for name in ("sensitivity", "motion_fineness", "angular_jerk"):
        np.testing.assert_allclose(by_pose[name][1:], by_action[name], rtol=1e-9, atol=1e-12, err_msg=name)
    np.testing.assert_array_equal(by_pose["bits"][1:], by_action["bits"])
    np.testing.assert_allclose(actions_from_poses(poses)[:, :6], actions[:, :6], atol=1e-12)


def test_slices_select_the_translation_and_rotation():
    actions = random_actions(4, steps=50, width=10)
    moved = np.concatenate([actions[:, 7:10], np.zeros((50, 1)), actions[:, 0:3]], axis=1)
    config = DispatchConfig(xyz_slice=(4, 7), rot_slice=(0, 3))
    np.testing.assert_array_equal(replay_trajectory(moved, config)["bits"], replay_trajectory(actions[:, [0, 1, 2, 7, 8, 9]])["bits"])


def test_reset_starts_a_fresh_episode():
    actions = random_actions(8, steps=50)
    dispatcher = KinematicDispatcher()
    first = [dispatcher.step(a) for a in actions]
    dispatcher.reset()
    assert dispatcher.bits == 16 and dispatcher.steps == 0 and math.isnan(dispatcher.sensitivity)
    assert [dispatcher.step(a) for a in actions] == first


def test_reset_keeping_history_skips_the_warm_up():
    actions = random_actions(9, steps=50)
    dispatcher = KinematicDispatcher(DispatchConfig(warmup=10))
    for action in actions:
        dispatcher.step(action)
    mu = dispatcher.mu_max
    dispatcher.reset(keep_history=True)
    dispatcher.step(actions[0])
    assert not dispatcher.is_warm  # no jerk yet: the previous rotation was cleared
    dispatcher.step(actions[1])
    assert dispatcher.is_warm
    assert dispatcher.mu_max == pytest.approx(mu, rel=0.5)


@pytest.mark.parametrize("action", [torch.arange(7, dtype=torch.float32), list(range(7)), tuple(range(7)), np.arange(7)])
def test_actions_may_be_tensors_arrays_or_sequences(action):
    dispatcher = KinematicDispatcher()
    assert dispatcher.step(action) == 16
    assert dispatcher.motion_fineness == 0.0  # the only sample is its own percentile


BAD_ACTIONS = [
    (np.zeros((2, 7)), ValueError, r"action must be 1-D with at least 6 entries .* got shape \(2, 7\)"),
    (np.zeros(5), ValueError, r"action must be 1-D with at least 6 entries .* got shape \(5,\)"),
    (np.float64(1.0), ValueError, r"got shape \(\)"),
    (np.array([0, 0, np.nan, 0, 0, 0, 0]), ValueError, "action must be finite"),
    (np.array([0, 0, 0, np.inf, 0, 0, 0]), ValueError, "action must be finite"),
    (np.array([0, 0, 0, 0, 0, 0, -np.inf]), ValueError, "action must be finite"),
    ([10**400] * 7, ValueError, "action must be finite real numbers, got values beyond float64's range"),
    ("abcdefg", TypeError, "action must be a 1-D array"),
    (None, ValueError, r"got shape \(\)"),
    ([[1, 2], [3]], TypeError, "action must be a 1-D array"),
]


@pytest.mark.parametrize("action, error, message", BAD_ACTIONS)
def test_bad_actions_are_rejected(action, error, message):
    dispatcher = KinematicDispatcher()
    with pytest.raises(error, match=message):
        dispatcher.step(action)
    assert dispatcher.steps == 0  # a rejected action leaves the state alone


def test_huge_finite_actions_are_accepted():
    dispatcher = KinematicDispatcher()
    dispatcher.step(np.full(7, 1e308))  # their sum overflows, the values do not
    assert dispatcher.steps == 1


def test_config_must_be_a_dispatch_config():
    with pytest.raises(TypeError, match="config must be a DispatchConfig"):
        KinematicDispatcher({"fusion_weight": 0.5})


@pytest.mark.parametrize(
    "sensitivity, bits",
    [(0.0, 2), (0.15, 2), (0.1500001, 4), (0.3, 4), (0.3000001, 8), (0.5, 8), (0.5000001, 16), (7.0, 16)],
)
def test_allocation_is_eq6_with_closed_upper_bounds(sensitivity, bits):
    assert allocate_bits(sensitivity, paper_ladder(0.15, 0.3, 0.5)) == bits


def test_equal_thresholds_skip_bit_widths():
    assert [allocate_bits(s, paper_ladder(0.3, 0.3, 0.3)) for s in (0.1, 0.3, 0.31)] == [2, 2, 16]


def test_a_custom_ladder_maps_each_rung_and_falls_back_above_the_top():
    ladder = ((0.1, 2), (0.6, 8))
    assert [allocate_bits(s, ladder) for s in (0.0, 0.1, 0.2, 0.6, 0.61)] == [2, 2, 8, 8, 16]


@given(st.floats(-5, 5), st.floats(-5, 5), st.floats(0, 1))
def test_fusion_is_the_clamped_convex_combination(m, j, lam):
    assert fuse_sensitivity((m, j), (lam, 1 - lam)) == pytest.approx(max(0.0, lam * m + (1 - lam) * j), abs=1e-12)


def test_fusion_ignores_a_missing_metric_of_zero_weight():
    assert fuse_sensitivity((math.nan, 0.4), (0.0, 1.0)) == 0.4
    assert fuse_sensitivity((0.4, math.nan), (1.0, 0.0)) == 0.4


def test_state_stays_well_under_64_kilobytes_and_stops_growing():
    dispatcher = KinematicDispatcher(DispatchConfig(history=512))
    actions = np.tile(synthetic_trajectory(), (5, 1))
    sizes = []
    for t, action in enumerate(actions):
        dispatcher.step(action)
        if t in (600, 1199):
            sizes.append(dispatcher.state_bytes)
    assert sizes[0] == sizes[1]
    assert sizes[1] < 32 * 1024


def test_synthetic_trajectory_runs_coarse_fine_coarse():
    actions = synthetic_trajectory(240, seed=1)
    assert actions.shape == (240, 7) and np.abs(actions).max() <= 1.0
    np.testing.assert_array_equal(actions, synthetic_trajectory(240, seed=1))
    translation = np.linalg.norm(actions[:, :3], axis=1)
    assert translation[:96].mean() > 5 * translation[96:180].mean()
    bits = replay_trajectory(actions)["bits"]
    assert bits[100:180].mean() > bits[200:].mean()  # manipulation runs at higher precision


def test_a_config_of_one_proxy_equals_the_pair_with_weights_one_and_zero():
    actions = random_actions(13, steps=80)
    pair = replay_trajectory(actions, DispatchConfig(proxies=paper_proxies(fusion_weight=0.0)))
    alone = replay_trajectory(actions, DispatchConfig(proxies=(ProxyWeight("angular_jerk", 1.0, 5),)))
    np.testing.assert_array_equal(alone["bits"], pair["bits"])
    np.testing.assert_array_equal(alone["sensitivity"], pair["sensitivity"])
    assert np.isnan(alone["motion_fineness"]).all()  # a proxy the config does not list reads NaN


@pytest.mark.parametrize("mode", ["window", "counter"])
def test_no_hysteresis_takes_the_target_at_once_as_k_one_does(mode):
    actions = random_actions(14, steps=80)
    none = replay_trajectory(actions, DispatchConfig(hysteresis="none"))
    np.testing.assert_array_equal(none["bits"], none["target_bits"])
    np.testing.assert_array_equal(none["bits"], replay_trajectory(actions, DispatchConfig(hysteresis=mode, delay_window=1))["bits"])


def test_a_new_width_is_one_rung_of_the_ladder():
    actions = random_actions(15, steps=80)
    trace = replay_trajectory(actions, DispatchConfig(ladder=((0.3, 4), (0.5, 8))))
    assert set(np.unique(trace["target_bits"])) <= {4, 8, 16} and (trace["target_bits"] == 4).any()


def warm_dispatcher(**config):
    dispatcher = KinematicDispatcher(DispatchConfig(warmup=3, delay_window=1, **config))
    for action in synthetic_trajectory(40, seed=1)[:30]:
        dispatcher.step(action)
    return dispatcher


def test_an_overflowing_jerk_gives_full_precision_and_stays_out_of_the_history():
    dispatcher = warm_dispatcher()
    scale, window = dispatcher.nu_max, dispatcher.smoothed_jerk
    dispatcher.step(np.array([0.0, 0, 0, 1e308, -1e308, 1e308, 0]))
    dispatcher.step(np.array([0.0, 0, 0, -1e308, 1e308, -1e308, 0]))  # ||delta rotation|| overflows
    assert dispatcher.bits == 16 and dispatcher.target_bits == 16 and dispatcher.sensitivity == math.inf
    assert math.isnan(dispatcher.angular_jerk)
    assert math.isfinite(dispatcher.nu_max) and math.isfinite(dispatcher.smoothed_jerk)
    assert dispatcher._proxies["angular_jerk"]._scale.value() == dispatcher.nu_max
    del scale, window


def test_an_overflowing_translation_gives_full_precision():
    dispatcher = warm_dispatcher()
    dispatcher.step(np.array([1.7e308, 1.7e308, 0, 0, 0, 0, 0]))  # hypot overflows
    assert dispatcher.bits == 16 and math.isfinite(dispatcher.mu_max)


def test_an_overflowing_ratio_gives_full_precision():
    dispatcher = KinematicDispatcher(DispatchConfig(warmup=3, delay_window=1, percentile=1))
    for _ in range(5):
        dispatcher.step(np.array([1e-300, 0, 0, 0, 0, 0, 0]))
    dispatcher.step(np.array([1e300, 0, 0, 0, 0, 0, 0]))  # 1e300 / 1e-300 overflows
    assert dispatcher.bits == 16 and dispatcher.target_bits == 16


def test_fusion_of_a_non_finite_term_is_the_most_sensitive_value():
    assert fuse_sensitivity((math.inf, 0.2), (0.5, 0.5)) == math.inf
    assert fuse_sensitivity((-math.inf, math.inf), (0.5, 0.5)) == math.inf
    assert allocate_bits(fuse_sensitivity((math.nan, 0.2), (0.5, 0.5)), paper_ladder()) == 16


@pytest.mark.parametrize("action", [np.array([1 + 2j, 0, 0, 0, 0, 0, 0]), [0j] * 7,
                                    torch.zeros(7, dtype=torch.complex64)])
def test_complex_actions_are_rejected(action):
    dispatcher = KinematicDispatcher()
    with pytest.raises(TypeError, match="complex"):
        dispatcher.step(action)
    assert dispatcher.steps == 0


def test_pose_slices_outside_the_poses_are_refused():
    poses = np.zeros((5, 4))
    with pytest.raises(ValueError, match=r"rot_slice must be \(start, stop\) with 0 <= start < stop <= D = 4, got \(3, 6\)"):
        actions_from_poses(poses)
    with pytest.raises(ValueError, match=r"xyz_slice must be .* got \(5, 2\)"):
        actions_from_poses(np.zeros((5, 7)), xyz_slice=(5, 2))
    assert actions_from_poses(np.zeros((5, 7))).shape == (4, 6)
