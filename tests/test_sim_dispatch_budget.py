"""The closed loop's width budget: ladder at fixed percentiles of S_t on the demonstrations, primed histories."""
import json

import numpy as np
import pytest

import dyq
from dyq.sim import dispatch_budget


def demonstrations(seed=0, count=12, length=60):
    """Coarse-then-fine trajectories with some rotation, like a reaching expert's."""
    rng = np.random.default_rng(seed)
    demos = []
    for _ in range(count):
        t = np.linspace(0, 1, length)[:, None]
        translation = np.clip((1 - t) * 2 + rng.normal(scale=0.1, size=(length, 3)), -1, 1)
        rotation = 0.3 * np.sin(6 * t + rng.uniform(0, 6)) + rng.normal(scale=0.05, size=(length, 3))
        demos.append(np.concatenate([translation, rotation, np.ones((length, 1))], axis=1))
    return demos


def test_percentile_ladder_splits_the_targets_by_the_budget():
    demos = demonstrations()
    config, prime = dispatch_budget.budget_dispatch(demos, after_hysteresis=False)
    thresholds = [t for t, _ in config.ladder]
    assert thresholds == sorted(thresholds) and [b for _, b in config.ladder] == [2, 4, 8]
    # Replaying the same demonstrations with the same history rule, the targets follow the budget.
    s = dispatch_budget.demonstration_sensitivity(demos, config)
    shares = [np.mean(s <= thresholds[0]), np.mean((s > thresholds[0]) & (s <= thresholds[1])),
              np.mean((s > thresholds[1]) & (s <= thresholds[2])), np.mean(s > thresholds[2])]
    np.testing.assert_allclose(shares, [0.4, 0.2, 0.2, 0.2], atol=0.01)
    assert len(prime) >= dispatch_budget.PRIME_STEPS and np.array_equal(prime[-60:], demos[-1])
    assert config.replace(theta_2_4=0.0, theta_4_8=0.0, theta_fp=0.0).delay_window == dyq.DispatchConfig().delay_window


def test_default_ladder_meets_the_budget_after_hysteresis():
    demos = demonstrations(seed=3, count=20)
    config, _ = dispatch_budget.budget_dispatch(demos)
    # An independent count of b*_t: a fresh dispatcher per call, the same replay order, warm steps only.
    dispatcher = dyq.KinematicDispatcher(config)
    widths = []
    for demo in demos:
        dispatcher.reset(keep_history=True)
        for action in demo:
            bits = dispatcher.step(action)
            if np.isfinite(dispatcher.sensitivity):
                widths.append(bits)
    widths = np.asarray(widths)
    shares = [np.mean(widths == b) for b in (2, 4, 8, 16)]
    np.testing.assert_allclose(shares, list(dispatch_budget.BUDGET_SHARES.values()), atol=0.02)
    # The hysteresis holds steps at higher widths: the plain percentile ladder runs fewer 2-bit steps.
    plain, _ = dispatch_budget.budget_dispatch(demos, after_hysteresis=False)
    plain_widths = dispatch_budget.demonstration_replay(demos, plain)[1]
    assert np.mean(plain_widths == 2) < shares[0] - 0.02
    assert config.ladder[0][0] > plain.ladder[0][0]


def test_budget_shares_must_be_ordered_shares():
    with pytest.raises(ValueError, match="quantiles"):
        dispatch_budget.budget_dispatch(demonstrations(), quantiles=(0.6, 0.4, 0.8))
    with pytest.raises(ValueError, match="quantiles"):
        dispatch_budget.budget_dispatch(demonstrations(), quantiles=(0.4, 0.6))


def test_primed_dispatcher_skips_the_warm_up_and_is_independent_of_earlier_episodes():
    demos = demonstrations()
    config, prime = dispatch_budget.budget_dispatch(demos[:-2])
    fresh = dyq.KinematicDispatcher(config)
    primed = dispatch_budget.prime(dyq.KinematicDispatcher(config), prime)
    first_fresh = [fresh.step(a) for a in demos[-1][:12]]
    first_primed = [primed.step(a) for a in demos[-1][:12]]
    assert all(b == 16 for b in first_fresh[:9])  # warm-up
    assert any(b < 16 for b in first_primed[:9])
    # A dispatcher that ran another episode first, primed again, decides the same.
    other = dispatch_budget.prime(dyq.KinematicDispatcher(config), prime)
    for a in demos[-2]:
        other.step(a)
    dispatch_budget.prime(other, prime)
    assert [other.step(a) for a in demos[-1][:12]] == first_primed


def test_dispatch_file_round_trip(tmp_path):
    config, prime = dispatch_budget.budget_dispatch(demonstrations())
    path = dispatch_budget.save(tmp_path, config, prime, source="synthetic")
    assert json.loads(path.read_text())["source"] == "synthetic"
    loaded, loaded_prime = dispatch_budget.load(tmp_path)
    assert loaded.ladder == config.ladder
    np.testing.assert_allclose(loaded_prime, prime, atol=1e-6)
    with pytest.raises(FileNotFoundError, match="dispatch.json"):
        dispatch_budget.load(tmp_path / "missing")


def test_empty_or_too_short_demonstrations_are_rejected():
    with pytest.raises(ValueError, match="at least one"):
        dispatch_budget.budget_dispatch([])
    with pytest.raises(ValueError, match="too short"):
        dispatch_budget.budget_dispatch([np.zeros((3, 7))])
