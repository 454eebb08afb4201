"""Action error per width and step class: against a direct numpy computation on synthetic episodes."""
import numpy as np
import pytest

import dyq
from dyq.sim import action_error
from dyq.sim.profile import Reference, proxy_trace


def reference(seed, length=40):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, length)[:, None]
    actions = np.concatenate([np.clip(2 * (1 - t) + rng.normal(scale=0.1, size=(length, 3)), -1, 1),
                              0.3 * np.sin(5 * t + rng.uniform(0, 6)) + rng.normal(scale=0.05, size=(length, 3)),
                              np.where(t > 0.5, 1.0, -1.0)], axis=1)
    return Reference("lift", seed, True, np.zeros((length, 4), np.float32), np.zeros((length, 7), np.int64),
                     actions, np.zeros(3), np.zeros(3))


def test_step_errors_split_by_channel():
    ref = np.zeros((3, 7))
    ref[:, 6] = [-1, 1, 1]
    low = ref.copy()
    low[0, :3] = [0.3, 0.4, 0.0]  # translation 0.5
    low[1, 3:6] = [0.0, 0.0, 0.2]  # rotation 0.2
    low[2, 6] = -1  # a gripper flip
    errors = action_error.step_errors(ref, low)
    np.testing.assert_allclose(errors["translation"], [0.5, 0, 0])
    np.testing.assert_allclose(errors["rotation"], [0, 0.2, 0])
    np.testing.assert_allclose(errors["total"], [0.5, 0.2, 2.0])
    np.testing.assert_array_equal(errors["gripper_flip"], [0, 0, 1])
    np.testing.assert_array_equal(errors["exact"], [0, 0, 0])
    assert action_error.step_errors(ref, ref)["exact"].tolist() == [1, 1, 1]
    with pytest.raises(ValueError, match="actions must both be"):
        action_error.step_errors(ref, low[:, :6])


def test_breakdown_matches_a_direct_computation():
    config = dyq.DispatchConfig(theta_2_4=0.3, theta_4_8=0.45, theta_fp=0.6, warmup=5)
    refs = [reference(s) for s in range(4)]
    rng = np.random.default_rng(9)
    # Width b's action: the reference plus noise of scale 1/b, so lower widths err more.
    widths = [{b: np.clip(r.actions + rng.normal(scale=1.0 / b, size=r.actions.shape), -1, 1) for b in (2, 4, 8)}
              for r in refs]
    result = action_error.breakdown(refs, widths, config)

    fineness, sensitivity, errors = [], [], {b: [] for b in (2, 4, 8)}
    for r, w in zip(refs, widths):
        trace = proxy_trace(r.actions, config)
        fineness.append(trace["smoothed_fineness"])
        sensitivity.append(trace["fused_sensitivity"])
        for b in errors:
            errors[b].append(np.linalg.norm(w[b] - r.actions, axis=1))
    fineness, sensitivity = np.concatenate(fineness), np.concatenate(sensitivity)
    warm = np.isfinite(sensitivity) & np.isfinite(fineness)
    median = np.median(fineness[warm])
    assert result["warm_steps"] == warm.sum() and result["median_smoothed_fineness"] == pytest.approx(median)
    target = np.array([dyq.KinematicDispatcher(config).allocate(s) if ok else 0 for s, ok in zip(sensitivity, warm)])
    for b in (2, 4, 8):
        e = np.concatenate(errors[b])
        row = result["widths"][str(b)]
        assert row["all"]["mean_total"] == pytest.approx(e[warm].mean())
        coarse = warm & (fineness <= median)
        assert row["coarse"]["steps"] == coarse.sum()
        assert row["coarse"]["mean_total"] == pytest.approx(e[coarse].mean())
        assert row["fine"]["mean_total"] == pytest.approx(e[warm & ~coarse].mean())
        for t in (2, 4, 8, 16):
            cell = row["by_target_bits"][str(t)]
            assert cell["steps"] == np.sum(warm & (target == t))
            if cell["steps"]:
                assert cell["median_total"] == pytest.approx(np.median(e[warm & (target == t)]))
    assert result["widths"]["2"]["all"]["mean_total"] > result["widths"]["8"]["all"]["mean_total"]
    assert sum(result["target_bits_share"].values()) == pytest.approx(1.0)
    assert "W4A2 coarse" in action_error.markdown("lift", result)


def test_breakdown_rejects_mismatched_inputs():
    refs = [reference(0)]
    with pytest.raises(ValueError, match="one actions_by_width entry per reference"):
        action_error.breakdown(refs, [], dyq.DispatchConfig())
    short = Reference("lift", 0, True, np.zeros((2, 4), np.float32), np.zeros((2, 7), np.int64),
                      np.zeros((2, 7)), np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="warm-up"):
        action_error.breakdown([short], [{2: np.zeros((2, 7))}], dyq.DispatchConfig())
