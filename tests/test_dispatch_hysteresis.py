"""Hysteresis (paper Eq. 4 and Algorithm 1): the rules as properties, and the worked examples."""

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dyq.control.dispatch import Hysteresis
from dyq import VALID_BITS

MODES = ("window", "counter")
targets_strategy = st.lists(st.sampled_from(VALID_BITS), min_size=1, max_size=60)
k_strategy = st.integers(1, 8)


def run(mode, k, targets):
    hysteresis = Hysteresis(k, mode=mode)
    return [hysteresis.update(target) for target in targets]


def reference_eq4(k, targets):
    """Eq. 4 with the window read off a padded list: b^_{t-K+1..t}, K - 1 leading 16s."""
    padded = [16] * (k - 1) + list(targets)
    out, previous = [], 16
    for t, target in enumerate(targets):
        window = padded[t : t + k]
        if target >= previous:
            previous = target
        elif max(window) <= target:
            previous = target
        out.append(previous)
    return out


def reference_algorithm1(k, targets):
    """Algorithm 1 transcribed with indicator arithmetic, I(x) = int(x)."""
    c, b_star, b_bar = 0, 16, 16
    out = []
    for b_hat in targets:
        if b_hat >= b_star:
            b_star, c, b_bar = b_hat, 0, b_hat
        else:
            b_bar_new = max(b_hat, b_bar * int(c > 0))
            c = c * int(b_bar_new == b_bar) + 1
            b_bar = b_bar_new
            b_star, c = b_bar * int(c == k) + b_star * int(c < k), c % k
        out.append(b_star)
    return out


@given(k_strategy, targets_strategy)
def test_window_mode_is_eq4(k, targets):
    assert run("window", k, targets) == reference_eq4(k, targets)


@given(k_strategy, targets_strategy)
def test_counter_mode_is_algorithm1(k, targets):
    assert run("counter", k, targets) == reference_algorithm1(k, targets)


@pytest.mark.parametrize("mode", MODES)
@given(k=k_strategy, targets=targets_strategy)
def test_outputs_are_valid_bits_never_below_the_target(mode, k, targets):
    for target, bits in zip(targets, run(mode, k, targets)):
        assert bits in VALID_BITS
        assert bits >= target


@pytest.mark.parametrize("mode", MODES)
@given(k=k_strategy, targets=targets_strategy)
def test_upgrades_take_effect_at_once(mode, k, targets):
    outputs = run(mode, k, targets)
    previous = [16] + outputs[:-1]
    for target, before, bits in zip(targets, previous, outputs):
        if target >= before:
            assert bits == target


@pytest.mark.parametrize("mode", MODES)
@given(k=k_strategy, targets=targets_strategy)
def test_downgrades_wait_for_k_steps_of_lower_targets(mode, k, targets):
    outputs = run(mode, k, targets)
    previous = [16] + outputs[:-1]
    for t, (before, bits) in enumerate(zip(previous, outputs)):
        if bits < before:
            assert t + 1 >= k, "a downgrade before K targets were seen"
            recent = targets[t - k + 1 : t + 1]
            assert all(target <= bits < before for target in recent)


@pytest.mark.parametrize("mode", MODES)
@given(k=k_strategy, targets=targets_strategy)
def test_the_output_holds_upgrades_or_drops_to_the_recent_maximum(mode, k, targets):
    outputs = run(mode, k, targets)
    previous = [16] + outputs[:-1]
    for t, (target, before, bits) in enumerate(zip(targets, previous, outputs)):
        if bits < before:  # a downgrade lands on the largest of the last K targets
            assert bits == max(targets[t - k + 1 : t + 1])
        else:
            assert bits in (before, target)
        if mode == "window":  # Eq. 4 only ever returns b^_t or b*_{t-1}
            assert bits in (before, target)


@given(k=k_strategy, targets=targets_strategy, settle=st.sampled_from(VALID_BITS))
def test_window_settles_on_a_steady_target_within_k_steps(k, targets, settle):
    assert run("window", k, targets + [settle] * k)[-1] == settle


@given(k=k_strategy, targets=targets_strategy, settle=st.sampled_from(VALID_BITS))
def test_counter_settles_on_a_steady_target_within_2k_minus_1_steps(k, targets, settle):
    assert run("counter", k, targets + [settle] * (2 * k - 1))[-1] == settle


@given(k=k_strategy, targets=targets_strategy)
def test_state_stays_bounded(k, targets):
    window, counter = Hysteresis(k, "window"), Hysteresis(k, "counter")
    for target in targets:
        window.update(target)
        counter.update(target)
        assert len(window.window) == k
        assert 0 <= counter.counter < k
        assert counter.candidate in VALID_BITS


@pytest.mark.parametrize("mode", MODES)
@given(targets=targets_strategy)
def test_k_of_one_follows_the_target(mode, targets):
    assert run(mode, 1, targets) == targets


@pytest.mark.parametrize("mode", MODES)
def test_initial_state_is_full_precision(mode):
    hysteresis = Hysteresis(4, mode)
    assert hysteresis.bits == 16
    assert hysteresis.counter == 0
    if mode == "window":
        assert hysteresis.window == (16, 16, 16)  # K - 1 targets of 16 before the first step


@pytest.mark.parametrize("mode", MODES)
def test_a_downgrade_needs_k_steps_from_the_start(mode):
    assert run(mode, 3, [2, 2, 2, 2]) == [16, 16, 2, 2]


@pytest.mark.parametrize("mode", MODES)
def test_a_single_spike_upgrades_then_decays_after_k_steps(mode):
    assert run(mode, 3, [2, 2, 2, 16, 2, 2, 2]) == [16, 16, 2, 16, 16, 16, 2]


def test_eq4_and_algorithm1_differ_when_the_run_falls():
    # After a 16, the lower targets 8, 4, 4: Algorithm 1's candidate is the run's max (8) and its
    # counter reaches K = 3, so it drops to 8; Eq. 4 holds 16 while 8 is in its window and drops
    # straight to 4 once the window is [4, 4, 4].
    targets = [16, 8, 4, 4, 4]
    assert run("counter", 3, targets) == [16, 16, 16, 8, 8]
    assert run("window", 3, targets) == [16, 16, 16, 16, 4]


def test_eq4_and_algorithm1_differ_when_the_run_rises():
    # After a 16, the lower targets 4, 4, 8: the rising candidate restarts Algorithm 1's counter,
    # so it holds 16 until 8 was seen K times; Eq. 4 downgrades as soon as the current target is
    # the window's maximum.
    targets = [16, 4, 4, 8, 8, 8]
    assert run("window", 3, targets) == [16, 16, 16, 8, 8, 8]
    assert run("counter", 3, targets) == [16, 16, 16, 16, 16, 8]


@pytest.mark.parametrize("mode", MODES)
def test_reset_restores_the_initial_state(mode):
    hysteresis = Hysteresis(3, mode)
    for target in (2, 2, 2, 4):
        hysteresis.update(target)
    hysteresis.reset()
    fresh = Hysteresis(3, mode)
    assert (hysteresis.bits, hysteresis.counter, hysteresis.window) == (fresh.bits, fresh.counter, fresh.window)
    assert run(mode, 3, [2, 2, 2]) == [hysteresis.update(2) for _ in range(3)]


@pytest.mark.parametrize("k, error", [(0, ValueError), (-3, ValueError), (2.0, TypeError), (None, TypeError)])
def test_bad_delay_window_is_rejected(k, error):
    with pytest.raises(error, match=r"delay_window \(K\) must be an int in \[1, 4096\]"):
        Hysteresis(k)


def test_bad_mode_is_rejected():
    with pytest.raises(ValueError, match="mode must be one of"):
        Hysteresis(3, mode="sliding")


@pytest.mark.parametrize("target, error", [(3, ValueError), (32, ValueError), (8.0, TypeError), ("8", TypeError)])
def test_bad_target_is_rejected_naming_target_bits(target, error):
    hysteresis = Hysteresis(3)
    with pytest.raises(error, match="target_bits"):
        hysteresis.update(target)
    assert hysteresis.bits == 16 and hysteresis.window == (16, 16)
