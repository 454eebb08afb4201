"""dyq.analysis.calibration: the error bound (Eq. 5), Theta, lambda, K, theta_fp and the config file."""
import json
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import dyq
from dyq.analysis import (
    bound_parameters,
    calibrate_thresholds,
    choose_delay,
    choose_fusion_weight,
    choose_theta_fp,
    dispatch_trace,
    error_bound,
    write_config,
)

LEVELS = np.arange(1, 11) / 10.0  # S_t in ten levels 0.1 .. 1.0, twenty steps each
S_LEVELS = np.repeat(LEVELS, 20)


def constant_errors(d_acc, eta, crossing_2, crossing_4, n=S_LEVELS.size):
    """Per-width errors that meet the bound D_acc / (S + eta) exactly up to S = crossing_b."""
    return {2: np.full(n, d_acc / (crossing_2 + eta)), 4: np.full(n, d_acc / (crossing_4 + eta)), 8: np.zeros(n)}


def random_actions(steps, seed):
    """Executed 7-D actions with coarse and fine phases, enough to warm the dispatcher up."""
    draw = np.random.default_rng(seed)
    speed = np.where(np.arange(steps) % 40 < 20, 0.8, 0.05)
    actions = draw.normal(0.0, 0.1, (steps, 7))
    actions[:, :3] += speed[:, None]
    return actions


def test_error_bound_is_d_acc_over_s_plus_eta():
    np.testing.assert_allclose(error_bound(np.array([0.0, 0.5, 1.5]), 2.0, 0.5), [4.0, 2.0, 1.0])
    assert error_bound(1.0, 3.0, 0.5) == 2.0


def test_error_bound_is_infinite_at_zero_sensitivity_without_eta():
    assert error_bound(0.0, 1.0, 0.0) == math.inf


@pytest.mark.parametrize("S, d_acc, eta, match", [
    (0.5, 0.0, 0.1, "d_acc must be > 0"),
    (0.5, -1.0, 0.1, "d_acc must be > 0"),
    (0.5, 1.0, -0.1, "eta must be >= 0"),
    (math.nan, 1.0, 0.1, "sensitivity_state must be finite"),
    (-0.2, 1.0, 0.1, "sensitivity_state must be >= 0"),
    ([], 1.0, 0.1, "sensitivity_state must have at least 1 entries"),
])
def test_error_bound_rejects_bad_arguments(S, d_acc, eta, match):
    with pytest.raises(ValueError, match=match):
        error_bound(S, d_acc, eta)


def test_a_known_crossing_gives_known_thresholds():
    result = calibrate_thresholds(S_LEVELS, constant_errors(1.0, 0.2, 0.35, 0.75), 1.0, 0.2, bins=40)
    assert (result.theta_2_4, result.theta_4_8) == (LEVELS[2], LEVELS[6])
    assert result.status == {2: "crossing", 4: "crossing", 8: "within bound in the top bin"}
    assert result.limits[8] == LEVELS[-1]


def test_bins_are_right_closed_like_eq6():
    result = calibrate_thresholds(S_LEVELS, constant_errors(1.0, 0.2, 0.35, 0.75), 1.0, 0.2, bins=40)
    # the lowest two levels share the closed first bin [0.1, 0.2]; every other level is its own bin
    np.testing.assert_array_equal(result.bin_upper, LEVELS[1:])
    np.testing.assert_array_equal(result.count, [40] + [20] * 8)
    np.testing.assert_allclose(result.bound, 1.0 / (LEVELS[1:] + 0.2))


def test_an_excursion_below_the_top_run_does_not_set_the_threshold():
    errors = constant_errors(1.0, 0.0, 0.65, 2.0)
    errors[2][S_LEVELS == 0.3] = 100.0  # a violation at S = 0.3, but 2 bits meet the bound again at 0.4 .. 0.6
    assert calibrate_thresholds(S_LEVELS, errors, 1.0, 0.0, bins=40).theta_2_4 == LEVELS[5]


def test_a_width_over_the_bound_everywhere_gets_no_rung():
    result = calibrate_thresholds(S_LEVELS, constant_errors(1.0, 0.0, 0.01, 0.55), 1.0, 0.0, bins=40)
    assert result.theta_2_4 is None and result.limits[2] == 0.0 and result.status[2] == "over bound in every bin"
    assert result.theta_4_8 == LEVELS[4]


def test_two_and_four_bits_over_the_bound_everywhere_leave_only_the_8_bit_rung():
    result = calibrate_thresholds(S_LEVELS, constant_errors(1.0, 0.0, 0.01, 0.01), 1.0, 0.0, bins=40)
    assert result.theta_2_4 is None and result.theta_4_8 is None


def test_a_dropped_rung_is_never_dispatched_even_at_zero_sensitivity(tmp_path):
    # S_t = 0 (the arm holds still) lies in Eq. 6's [0, theta_2|4] even when theta_2|4 = 0.
    config = write_config(tmp_path / "c.json", fusion_weight=0.0, delay_window=1, theta_2_4=None, theta_4_8=None,
                          theta_fp=0.5)
    assert [bits for _, bits in config.ladder] == [8]
    still = np.zeros((60, 7))
    still[:30] = random_actions(30, seed=3)  # warm the scale histories, then hold still
    _, bits = dispatch_trace(still, config)
    _, bits_with_zero_threshold = dispatch_trace(still, config.replace(ladder=((0.0, 2), (0.0, 4), (0.5, 8))))
    assert 2 in bits_with_zero_threshold and 2 not in bits and 4 not in bits


def test_theta_4_8_is_raised_to_theta_2_4():
    result = calibrate_thresholds(S_LEVELS, constant_errors(1.0, 0.0, 0.55, 0.25), 1.0, 0.0, bins=40)
    assert result.limits[4] == LEVELS[1] and result.theta_4_8 == result.theta_2_4 == LEVELS[4]


@given(st.lists(st.tuples(st.floats(0.0, 2.0), st.floats(0.0, 5.0), st.floats(0.0, 5.0)), min_size=1, max_size=60),
       st.integers(1, 12))
def test_every_bin_above_a_limit_exceeds_the_bound_and_the_one_at_it_does_not(steps, bins):
    S, error_2, error_4 = (np.array(column) for column in zip(*steps))
    result = calibrate_thresholds(S, {2: error_2, 4: error_4, 8: error_4 / 2}, 1.0, 0.1, bins=bins)
    for b, mean in result.mean_error.items():
        above = result.bin_upper > result.limits[b]
        assert np.all(mean[above] > result.bound[above])
        assert np.all(mean[result.bin_upper == result.limits[b]] <= result.bound[result.bin_upper == result.limits[b]])
    theta_2_4 = 0.0 if result.theta_2_4 is None else result.theta_2_4
    theta_4_8 = theta_2_4 if result.theta_4_8 is None else result.theta_4_8
    assert 0.0 <= theta_2_4 <= theta_4_8 <= S.max()
    assert (result.theta_2_4 is None) == (result.status[2] == "over bound in every bin")


@pytest.mark.parametrize("errors, match", [
    ({2: [0.1, 0.2], 4: [0.1, 0.2]}, r"errors_by_width must map each width \(2, 4, 8\)"),
    ({2: [0.1], 4: [0.1, 0.2], 8: [0.1, 0.2]}, r"errors_by_width\[2\] must have one error per step \(2\)"),
    ({2: [0.1, math.nan], 4: [0.1, 0.2], 8: [0.1, 0.2]}, r"errors_by_width\[2\] must be finite"),
])
def test_calibrate_thresholds_rejects_bad_errors(errors, match):
    with pytest.raises(ValueError, match=match):
        calibrate_thresholds([0.1, 0.2], errors, 1.0, 0.1)


def test_calibrate_thresholds_rejects_an_empty_calibration_set():
    with pytest.raises(ValueError, match="sensitivity_state must have at least 1 entries"):
        calibrate_thresholds([], {2: [], 4: [], 8: []}, 1.0, 0.1)


def test_bound_parameters_follow_the_line_fit():
    S = np.linspace(0.0, 1.0, 11)
    d_acc, eta = bound_parameters(S, 2.0 * S + 1.0, tolerance=0.05)
    assert d_acc == pytest.approx(0.025) and eta == pytest.approx(0.5)
    np.testing.assert_allclose(error_bound(S, d_acc, eta), 0.05 / (2.0 * S + 1.0))


def test_bound_parameters_clip_a_negative_intercept():
    S = np.linspace(0.0, 1.0, 11)
    assert bound_parameters(S, 4.0 * S - 1.0, tolerance=1.0) == pytest.approx((0.25, 0.0))


@pytest.mark.parametrize("s, tolerance, match", [
    (-np.linspace(0.0, 1.0, 5), 1.0, "measured_sensitivity must rise with sensitivity_state"),
    (np.linspace(0.0, 1.0, 5), 0.0, "tolerance must be > 0"),
    (np.full(5, np.nan), 1.0, "sensitivity_state must vary over at least 2 steps"),
])
def test_bound_parameters_reject_a_meaningless_fit(s, tolerance, match):
    with pytest.raises(ValueError, match=match):
        bound_parameters(np.linspace(0.0, 1.0, 5), s, tolerance)


def test_dispatch_trace_aligns_the_decision_with_its_step():
    actions = random_actions(40, seed=1)
    config = dyq.DispatchConfig(warmup=5)
    S, bits = dispatch_trace(actions, config)
    dispatcher = dyq.KinematicDispatcher(config)
    expected = [16] + [dispatcher.step(action) for action in actions[:-1]]
    np.testing.assert_array_equal(bits, expected)
    # the jerk history lags one call: the first warm decision follows call warmup + 1, i.e. step 6
    assert np.isnan(S[:6]).all() and np.isfinite(S[6:]).all()


def test_fusion_weight_maximizes_the_rank_correlation():
    episodes = [random_actions(80, seed) for seed in range(3)]
    measured = [np.exp(dispatch_trace(a, dyq.DispatchConfig(fusion_weight=1.0))[0]) for a in episodes]
    result = choose_fusion_weight(episodes, measured)
    assert result["fusion_weight"] == 1.0
    assert max(result["table"], key=lambda row: row[1])[0] == 1.0 and len(result["table"]) == 11


def test_fusion_weight_needs_matching_episodes():
    with pytest.raises(ValueError, match="actions_by_episode and sensitivity_by_episode must have the same length"):
        choose_fusion_weight([random_actions(20, 0), random_actions(20, 1)], [np.ones(20)])


def test_fusion_weight_needs_episodes():
    with pytest.raises(ValueError, match="actions_by_episode must hold at least one episode"):
        choose_fusion_weight([], [])


def delay_inputs(error, episodes=2, steps=80):
    actions = [random_actions(steps, seed) for seed in range(episodes)]
    errors = [{b: np.full(steps, error) for b in (2, 4, 8)} for _ in actions]
    return actions, errors


def test_delay_is_one_when_every_width_meets_the_bound():
    actions, errors = delay_inputs(0.0)
    result = choose_delay(actions, errors, dyq.DispatchConfig(), d_acc=1.0, eta=0.1, max_rate=0.0)
    assert result["delay_window"] == 1 and result["met"] and result["table"][0][1] == 0.0


def test_delay_is_the_smallest_that_meets_the_rate():
    actions, errors = delay_inputs(1e6)  # no width meets the bound: every downgrade is an error
    result = choose_delay(actions, errors, dyq.DispatchConfig(), d_acc=1.0, eta=0.1, max_rate=0.2,
                          delays=range(1, 41))
    rates = {k: rate for k, rate, _ in result["table"]}
    assert result["met"] and rates[result["delay_window"]] <= 0.2
    assert all(rates[k] > 0.2 for k in rates if k < result["delay_window"])


def test_delay_reports_when_no_k_meets_the_rate():
    actions, errors = delay_inputs(1e6)
    result = choose_delay(actions, errors, dyq.DispatchConfig(), d_acc=1.0, eta=0.1, max_rate=0.0, delays=[1, 2])
    assert not result["met"] and result["delay_window"] == min(result["table"], key=lambda row: (row[1], row[0]))[0]


def test_delay_takes_an_episode_shorter_than_the_warm_up():
    """Such an episode has no warm step, so no downgrade error: the rates are the long episodes' alone."""
    actions, errors = delay_inputs(1e6)
    short_actions, short_errors = delay_inputs(1e6, episodes=1, steps=8)
    alone = choose_delay(actions, errors, dyq.DispatchConfig(), d_acc=1.0, eta=0.1, max_rate=0.2)
    mixed = choose_delay(actions + short_actions, errors + short_errors, dyq.DispatchConfig(), d_acc=1.0, eta=0.1,
                         max_rate=0.2)
    assert mixed["delay_window"] == alone["delay_window"]
    assert [row[:2] for row in mixed["table"]] == [row[:2] for row in alone["table"]]
    with pytest.raises(ValueError, match="d_acc"):
        choose_delay(short_actions, short_errors, dyq.DispatchConfig(), d_acc=0.0, eta=0.1)


def test_delay_rejects_errors_of_the_wrong_length():
    actions, errors = delay_inputs(0.0)
    errors[1][4] = np.zeros(3)
    with pytest.raises(ValueError, match=r"errors_by_episode\[1\]\[4\] must have one error per step \(80\)"):
        choose_delay(actions, errors, dyq.DispatchConfig(), d_acc=1.0, eta=0.1)


def test_theta_fp_is_the_cheapest_within_the_best_wilson_floor():
    sweep = [(0.3, 0.90, 12.0), (0.5, 0.88, 8.0), (0.7, 0.60, 5.0)]
    result = choose_theta_fp(sweep, episodes=50)
    assert result["theta_fp"] == 0.5 and result["success_floor"] == pytest.approx(0.7864, abs=1e-4)


def test_theta_fp_keeps_the_best_when_nothing_else_is_close():
    assert choose_theta_fp([(0.3, 1.0, 12.0), (0.9, 0.5, 4.0)], episodes=100)["theta_fp"] == 0.3


@pytest.mark.parametrize("sweep, match", [
    ([], "sweep must be a non-empty list"),
    ([(0.5, 0.333, 8.0)], r"sweep\[0\] success_rate must be successes / episodes \(10\)"),
    ([(0.5, 0.5, 8.0), (0.5, 0.6, 6.0)], "sweep must hold each theta_fp once"),
    ([(0.5, 0.5, 20.0)], r"sweep\[0\] mean_bits must be in \[2, 16\]"),
    ([(0.5, 0.5)], r"sweep\[0\] must be \(theta_fp, success_rate, mean_bits\)"),
])
def test_theta_fp_rejects_a_bad_sweep(sweep, match):
    with pytest.raises(ValueError, match=match):
        choose_theta_fp(sweep, episodes=10)


def test_written_config_loads_in_the_dispatcher(tmp_path):
    path = tmp_path / "dispatch.json"
    written = write_config(path, fusion_weight=0.7, delay_window=4, theta_2_4=0.1, theta_4_8=0.35, theta_fp=0.5)
    loaded = dyq.DispatchConfig.load(path)
    assert loaded == written
    assert (loaded.fusion_weight, loaded.delay_window, loaded.theta_2_4, loaded.theta_4_8, loaded.theta_fp) == (
        0.7, 4, 0.1, 0.35, 0.5)
    keys = json.loads(path.read_text())
    assert {"lambda", "K", "theta_2|4", "theta_4|8", "theta_fp"} <= set(keys)
    assert not {"fusion_weight", "delay_window", "theta_2_4", "theta_4_8"} & set(keys)


def test_written_config_without_a_2_bit_rung_writes_null_and_loads(tmp_path):
    path = tmp_path / "dispatch.json"
    written = write_config(path, fusion_weight=0.2, delay_window=8, theta_2_4=None, theta_4_8=0.19, theta_fp=18.3)
    assert json.loads(path.read_text())["theta_2|4"] is None
    loaded = dyq.DispatchConfig.load(path)
    assert loaded == written and loaded.ladder == ((0.19, 4), (18.3, 8)) and math.isnan(loaded.theta_2_4)


def test_written_config_clips_theta_to_theta_fp(tmp_path):
    config = write_config(tmp_path / "c.json", fusion_weight=0.5, delay_window=3, theta_2_4=0.2, theta_4_8=0.9,
                          theta_fp=0.6)
    assert config.theta_4_8 == 0.6


def test_write_config_validates_before_writing(tmp_path):
    path = tmp_path / "bad.json"
    with pytest.raises(ValueError, match="fusion_weight"):
        write_config(path, fusion_weight=2.0, delay_window=3, theta_2_4=0.1, theta_4_8=0.2, theta_fp=0.5)
    assert not path.exists()


def test_fusion_weight_needs_one_sensitivity_per_step():
    with pytest.raises(ValueError, match=r"sensitivity_by_episode\[0\] must have one s_t per step \(20\)"):
        choose_fusion_weight([random_actions(20, 0)], [np.ones(19)])


def test_write_config_takes_numpy_scalars_and_never_leaves_a_truncated_file(tmp_path):
    path = tmp_path / "dispatch.json"
    first = write_config(path, fusion_weight=0.7, delay_window=4, theta_2_4=0.1, theta_4_8=0.35, theta_fp=0.5)
    written = write_config(path, fusion_weight=np.float32(0.5), delay_window=np.int64(3), theta_2_4=np.float64(0.1),
                           theta_4_8=None, theta_fp=np.float32(0.5))
    loaded = dyq.DispatchConfig.load(path)
    assert loaded == written and loaded != first and (loaded.fusion_weight, loaded.delay_window) == (0.5, 3)
    with pytest.raises(ValueError, match="theta_fp"):
        write_config(path, fusion_weight=0.5, delay_window=3, theta_2_4=None, theta_4_8=None, theta_fp=-1.0)
    assert dyq.DispatchConfig.load(path) == written  # the refused write left the file as it was
