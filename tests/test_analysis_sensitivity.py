"""dyq.analysis.sensitivity: s_t = D_T / e_t (Sec. III-A) and the proxy correlations (Sec. III-B)."""
import json
import math
import sys

import numpy as np
import pytest

import dyq
from dyq.analysis import ProfiledStep, plot_perturbation_profile, plot_proxy_trajectories, proxy_correlations
from dyq.analysis.sensitivity import sensitivity

PROXY_KEYS = {f"{stat}_{proxy}{ci}" for stat in ("pearson", "spearman")
              for proxy in ("motion_fineness", "angular_jerk", "fused") for ci in ("", "_ci")}


def profile(s_of_fineness, episodes=3, steps=30, seed=0, zero_error_every=0):
    """Records whose measured sensitivity is s_of_fineness(M_t); J_t and S_t are noise."""
    draw = np.random.default_rng(seed)
    records = []
    for episode in range(episodes):
        for t in range(steps):
            fineness = draw.uniform(-0.5, 1.0)
            error = 0.0 if zero_error_every and t % zero_error_every == 0 else draw.uniform(0.01, 0.2)
            records.append(ProfiledStep(
                episode=episode, t=t, act_bits=4, action_error=error,
                terminal_deviation=s_of_fineness(fineness) * max(error, 0.01), success=bool(t % 3),
                motion_fineness=fineness, angular_jerk=draw.uniform(0, 2), smoothed_fineness=fineness,
                smoothed_jerk=draw.uniform(0, 2), fused_sensitivity=draw.uniform(0, 1),
            ))
    return records


def test_sensitivity_is_deviation_over_error():
    result = sensitivity([0.5, 0.25], [1.0, 1.0])
    np.testing.assert_array_equal(result.values, [2.0, 4.0])
    assert result.zero_error_steps == 0


def test_zero_error_steps_are_counted_and_left_out():
    result = sensitivity([0.0, 0.5, 0.0], [0.3, 1.0, 0.0])
    assert result.zero_error_steps == 2
    assert np.isnan(result.values[[0, 2]]).all() and result.values[1] == 2.0


@pytest.mark.parametrize("error, deviation, match", [
    ([], [], "action_error must have at least 1 entries"),
    ([0.1, 0.2], [1.0], "action_error and terminal_deviation must have the same length"),
    ([-0.1], [1.0], "action_error must be >= 0"),
    ([0.1], [math.nan], "terminal_deviation must be finite"),
])
def test_sensitivity_rejects_bad_input(error, deviation, match):
    with pytest.raises(ValueError, match=match):
        sensitivity(error, deviation)


@pytest.mark.parametrize("field, value, error, match", [
    ("act_bits", 16, ValueError, "act_bits must be one of"),
    ("act_bits", 4.0, TypeError, "act_bits must be an int"),
    ("act_bits", True, TypeError, "act_bits must be an int"),
    ("action_error", -1.0, ValueError, "action_error must be >= 0"),
    ("terminal_deviation", math.inf, ValueError, "terminal_deviation must be finite"),
    ("success", 1, TypeError, "success must be a bool"),
    ("t", -1, ValueError, "t must be an int >= 0"),
    ("motion_fineness", "0.5", TypeError, "motion_fineness must be a real number"),
])
def test_profiled_step_rejects_bad_fields(field, value, error, match):
    fields = dict(episode=0, t=3, act_bits=4, action_error=0.1, terminal_deviation=0.2, success=True)
    fields[field] = value
    with pytest.raises(error, match=match):
        ProfiledStep(**fields)


def test_profiled_step_reads_the_dispatcher_that_chose_the_step():
    dispatcher = dyq.KinematicDispatcher(dyq.DispatchConfig(warmup=2))
    for t in range(6):
        dispatcher.step([0.1 * t, 0.0, 0.05, 0.01 * t * t, 0.0, 0.0, 0.0])
    record = ProfiledStep.from_dispatcher(dispatcher, episode=0, t=6, act_bits=2, action_error=0.1,
                                          terminal_deviation=0.3, success=True)
    assert (record.motion_fineness, record.angular_jerk, record.fused_sensitivity) == (
        dispatcher.motion_fineness, dispatcher.angular_jerk, dispatcher.sensitivity)
    assert (record.smoothed_fineness, record.smoothed_jerk) == (dispatcher.smoothed_fineness, dispatcher.smoothed_jerk)


def test_linear_sensitivity_in_fineness_gives_pearson_one():
    result = proxy_correlations(profile(lambda m: 2.0 * m + 3.0), n_boot=200)
    assert result["pearson_motion_fineness"] == pytest.approx(1.0)
    assert result["spearman_motion_fineness"] == pytest.approx(1.0)
    assert result["pearson_motion_fineness_ci"] == pytest.approx([1.0, 1.0])


def test_monotone_sensitivity_in_fineness_gives_spearman_one():
    result = proxy_correlations(profile(lambda m: math.exp(6.0 * m)), n_boot=200)
    assert result["spearman_motion_fineness"] == pytest.approx(1.0)
    assert result["pearson_motion_fineness"] < 0.95


def test_proxy_correlations_report_the_documented_keys_as_json():
    result = proxy_correlations(profile(lambda m: m + 1.0, zero_error_every=5), n_boot=100)
    assert set(result) == PROXY_KEYS | {"episodes", "steps", "zero_error_steps", "undefined_proxy_steps", "bootstrap"}
    json.dumps(result, allow_nan=False)


def test_zero_error_steps_are_excluded_from_the_correlations():
    result = proxy_correlations(profile(lambda m: m + 1.0, episodes=2, steps=20, zero_error_every=5), n_boot=50)
    assert result["zero_error_steps"] == 8 and result["steps"] == 32 and result["episodes"] == 2


def test_steps_with_undefined_proxies_are_excluded_and_counted():
    records = profile(lambda m: m + 1.0, episodes=1, steps=10)
    warming = ProfiledStep(episode=0, t=10, act_bits=4, action_error=0.1, terminal_deviation=0.1, success=True)
    result = proxy_correlations(records + [warming], n_boot=50)
    assert result["steps"] == 10 and result["undefined_proxy_steps"] == 1


def test_proxy_correlations_need_two_usable_steps():
    record = ProfiledStep(episode=0, t=0, act_bits=4, action_error=0.0, terminal_deviation=0.1, success=True,
                          motion_fineness=0.1, angular_jerk=0.2, fused_sensitivity=0.3)
    with pytest.raises(ValueError, match="records must hold at least 2 steps with e_t > 0"):
        proxy_correlations([record, record])


@pytest.mark.parametrize("records, error", [([], ValueError), ([{"t": 0}], TypeError)])
def test_proxy_correlations_reject_bad_records(records, error):
    with pytest.raises(error, match="records must hold"):
        proxy_correlations(records)


def test_figures_plot_the_profile(tmp_path):
    records = profile(lambda m: math.exp(3.0 * m))
    figure_2 = plot_perturbation_profile(records)
    figure_3 = plot_proxy_trajectories(records, episode=1)
    figure_2.savefig(tmp_path / "figure2.png")
    figure_3.savefig(tmp_path / "figure3.png")
    assert len(figure_2.axes) == 2 and len(figure_3.axes) == 2
    assert (tmp_path / "figure2.png").stat().st_size > 0


def test_trajectory_figure_needs_the_episode():
    with pytest.raises(ValueError, match="records hold no step of episode 7"):
        plot_proxy_trajectories(profile(lambda m: m + 1.0, episodes=1), episode=7)


def test_plotting_without_matplotlib_says_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    with pytest.raises(ImportError, match=r"plotting needs matplotlib: pip install 'dyq\[plot\]'"):
        plot_perturbation_profile(profile(lambda m: m + 1.0, episodes=1))
