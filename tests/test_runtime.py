"""DyQRuntime with fake prefill/decode callables standing in for a VLA model."""

import copy
import pickle
import statistics
import threading
import time

import numpy as np
import pytest

from dyq.control.dispatch import DispatchConfig, KinematicDispatcher, replay_trajectory, synthetic_trajectory
from dyq import PrecisionFlag
from dyq.control.runtime import DyQRuntime, StepStats, force_precision

ACTIONS = synthetic_trajectory(120, seed=3)
CONFIG = DispatchConfig(warmup=5)


@pytest.fixture
def runtime():
    with DyQRuntime(KinematicDispatcher(CONFIG), PrecisionFlag(), barrier=None) as runtime:
        yield runtime


class FakeModel:
    """Records the flag value at prefill and at decode; the prefill sleeps like a GPU prefill."""

    def __init__(self, flag, prefill_seconds=0.0):
        self.flag, self.prefill_seconds = flag, prefill_seconds
        self.prefill_bits, self.decode_bits = [], []

    def prefill(self):
        self.prefill_bits.append(self.flag.bits)
        if self.prefill_seconds:
            time.sleep(self.prefill_seconds)
        return "kv-cache"

    def decode(self, prefill_output):
        assert prefill_output == "kv-cache"
        self.decode_bits.append(self.flag.bits)
        return len(self.decode_bits)


def control_loop(runtime, model, actions):
    previous = None  # nothing executed before the first step
    for action in actions:
        runtime.step(previous, model.prefill, model.decode)
        previous = action


def test_decode_runs_at_the_dispatchers_bits(runtime):
    model = FakeModel(runtime.flag)
    control_loop(runtime, model, ACTIONS)
    expected = replay_trajectory(ACTIONS[:-1], CONFIG)["bits"].tolist()
    assert model.decode_bits == [16] + expected  # step 0 has no past: full precision
    assert [s.bits for s in runtime.stats] == model.decode_bits
    assert [s.dispatched_bits for s in runtime.stats] == model.decode_bits
    assert len(set(expected)) > 1


def test_prefill_runs_at_the_previous_steps_precision_by_default(runtime):
    model = FakeModel(runtime.flag)
    control_loop(runtime, model, ACTIONS)
    assert model.prefill_bits == [16] + model.decode_bits[:-1]


def test_a_fixed_prefill_precision_is_written_before_each_prefill():
    flag = PrecisionFlag()
    with DyQRuntime(KinematicDispatcher(CONFIG), flag, prefill_bits=16, barrier=None) as runtime:
        model = FakeModel(flag)
        control_loop(runtime, model, ACTIONS)
    assert set(model.prefill_bits) == {16}
    assert model.decode_bits == [16] + replay_trajectory(ACTIONS[:-1], CONFIG)["bits"].tolist()


def test_the_dispatcher_overlaps_the_prefill():
    """The prefill blocks until the dispatcher has run: only possible if they run concurrently."""
    dispatched = threading.Event()

    class SignallingDispatcher(KinematicDispatcher):
        def step(self, action):
            bits = super().step(action)
            dispatched.set()
            return bits

    def prefill():
        assert dispatched.wait(timeout=5.0), "the dispatcher did not run during the prefill"
        dispatched.clear()

    with DyQRuntime(SignallingDispatcher(CONFIG), PrecisionFlag(), barrier=None) as runtime:
        for action in ACTIONS[:10]:
            runtime.step(action, prefill, lambda _: None)


def test_the_dispatcher_runs_on_one_persistent_worker_thread(runtime):
    threads = []
    dispatcher_step = runtime.dispatcher.step

    def recording_step(action):
        threads.append(threading.get_ident())
        return dispatcher_step(action)

    runtime.dispatcher.step = recording_step
    control_loop(runtime, FakeModel(runtime.flag), ACTIONS[:20])
    assert len(set(threads)) == 1
    assert threads[0] != threading.get_ident()


def test_the_model_barely_waits_for_the_dispatcher(runtime):
    model = FakeModel(runtime.flag, prefill_seconds=0.005)
    control_loop(runtime, model, ACTIONS[:60])
    stats = runtime.stats
    # The dispatcher finished during the 5 ms prefill: what is left is the hand-over of the result.
    assert statistics.median(s.wait_us for s in stats) < 500
    assert all(s.prefill_ms >= 5.0 for s in stats)
    assert all(s.dispatcher_us > 0 for s in stats[1:])


def test_force_precision_overrides_prefill_and_decode_but_keeps_dispatching(runtime):
    model = FakeModel(runtime.flag)
    with force_precision(runtime, 4) as forced:
        assert forced is runtime and runtime.flag.bits == 4
        control_loop(runtime, model, ACTIONS)
    assert set(model.prefill_bits) == set(model.decode_bits) == {4}
    assert all(s.forced and s.bits == 4 for s in runtime.stats)
    expected = [16] + replay_trajectory(ACTIONS[:-1], CONFIG)["bits"].tolist()
    assert [s.dispatched_bits for s in runtime.stats] == expected
    assert runtime.flag.bits == 16  # the value held on entry
    runtime.step(ACTIONS[-1], model.prefill, model.decode)
    assert model.decode_bits[-1] == runtime.dispatcher.bits == replay_trajectory(ACTIONS, CONFIG)["bits"][-1]


def test_force_precision_nests_and_restores_on_error():
    flag = PrecisionFlag(8)
    with pytest.raises(RuntimeError, match="boom"):
        with force_precision(flag, 16):
            with force_precision(flag, 2):
                assert flag.bits == 2
            assert flag.bits == 16
            raise RuntimeError("boom")
    assert flag.bits == 8


@pytest.mark.parametrize("bits, error", [(3, ValueError), (8.0, TypeError)])
def test_force_precision_rejects_bad_bits_at_the_call(bits, error):
    with pytest.raises(error, match="bits"):
        force_precision(PrecisionFlag(), bits)


def test_force_precision_rejects_other_targets():
    with pytest.raises(TypeError, match="PrecisionFlag or DyQRuntime"):
        force_precision(object(), 4)


def test_the_barrier_runs_only_before_writes_that_change_the_flag():
    flag = PrecisionFlag()
    seen_at_barrier = []
    with DyQRuntime(KinematicDispatcher(CONFIG), flag, barrier=lambda: seen_at_barrier.append(flag.bits)) as runtime:
        model = FakeModel(flag)
        control_loop(runtime, model, ACTIONS)
    changes = [(a, b) for a, b in zip([16] + model.decode_bits, model.decode_bits) if a != b]
    assert len(seen_at_barrier) == len(changes) > 0
    assert seen_at_barrier == [old for old, _ in changes]  # called before the write
    assert sum(s.switched for s in runtime.stats) == len(changes)


def test_summary_counts_steps_bits_and_switches(runtime):
    model = FakeModel(runtime.flag)
    control_loop(runtime, model, ACTIONS)
    summary = runtime.summary()
    bits = model.decode_bits
    assert summary["steps"] == len(ACTIONS)
    assert summary["steps_per_bits"] == {b: bits.count(b) for b in (2, 4, 8, 16)}
    assert summary["switches"] == sum(a != b for a, b in zip(bits, bits[1:]))
    assert summary["mean_bits"] == pytest.approx(np.mean(bits))
    assert summary["forced_steps"] == 0


def test_empty_summary():
    with DyQRuntime(KinematicDispatcher(), PrecisionFlag()) as runtime:
        assert runtime.summary() == {"steps": 0}


def test_statistics_are_bounded():
    with DyQRuntime(KinematicDispatcher(CONFIG), PrecisionFlag(), max_stats=10) as runtime:
        control_loop(runtime, FakeModel(runtime.flag), ACTIONS[:30])
        assert len(runtime.stats) == 10
        assert runtime.stats[-1].step == 29
        assert isinstance(runtime.stats[0], StepStats)


def test_begin_step_and_publish_drive_a_model_of_ones_own(runtime):
    runtime.begin_step(None)
    assert runtime.publish() == 16
    with pytest.raises(RuntimeError, match="publish called without begin_step"):
        runtime.publish()
    runtime.begin_step(ACTIONS[0])
    with pytest.raises(RuntimeError, match="begin_step called twice"):
        runtime.begin_step(ACTIONS[1])
    runtime.publish()
    assert runtime.dispatcher.steps == 1


def test_no_kinematics_does_not_advance_the_dispatcher(runtime):
    runtime.step(None, lambda: None, lambda _: None)
    assert runtime.dispatcher.steps == 0
    assert runtime.stats[-1].bits == 16


def test_a_bad_action_surfaces_at_publish_and_the_runtime_recovers(runtime):
    runtime.begin_step(np.full(7, np.nan))
    with pytest.raises(ValueError, match="action must be finite"):
        runtime.publish()
    model = FakeModel(runtime.flag)
    control_loop(runtime, model, ACTIONS[:10])
    assert len(model.decode_bits) == 10


def test_a_failing_prefill_leaves_the_runtime_usable(runtime):
    def prefill():
        raise RuntimeError("out of memory")

    with pytest.raises(RuntimeError, match="out of memory"):
        runtime.step(ACTIONS[0], prefill, lambda _: None)
    runtime.step(ACTIONS[1], lambda: None, lambda _: None)
    assert runtime.dispatcher.steps == 2


@pytest.mark.parametrize("prefill, decode, message", [(None, lambda _: None, "prefill must be a callable"),
                                                       (lambda: None, "decode", "decode must be a callable")])
def test_a_step_without_callables_is_refused_before_the_dispatcher_moves(runtime, prefill, decode, message):
    with pytest.raises(TypeError, match=message):
        runtime.step(ACTIONS[0], prefill, decode)
    assert runtime.dispatcher.steps == 0 and not runtime.stats
    runtime.step(ACTIONS[0], lambda: None, lambda _: None)
    assert runtime.dispatcher.steps == 1


def test_reset_restores_full_precision_for_the_next_episode(runtime):
    model = FakeModel(runtime.flag)
    control_loop(runtime, model, ACTIONS)
    assert runtime.flag.bits < 16
    runtime.reset()
    assert runtime.flag.bits == 16 and runtime.dispatcher.steps == 0
    second = FakeModel(runtime.flag)
    control_loop(runtime, second, ACTIONS)
    assert second.decode_bits == model.decode_bits


@pytest.mark.parametrize(
    "kwargs, error, message",
    [
        ({"dispatcher": "d"}, TypeError, "dispatcher must be a KinematicDispatcher"),
        ({"flag": 16}, TypeError, "flag must be a PrecisionFlag"),
        ({"prefill_bits": 12}, ValueError, "prefill_bits must be one of"),
        ({"prefill_bits": "first"}, TypeError, "prefill_bits must be an int"),
        ({"barrier": "sync"}, TypeError, "barrier must be a callable"),
        ({"max_stats": 0}, ValueError, "max_stats must be an int >= 1"),
    ],
)
def test_bad_runtime_arguments_are_rejected(kwargs, error, message):
    arguments = {"dispatcher": KinematicDispatcher(), "flag": PrecisionFlag(), **kwargs}
    with pytest.raises(error, match=message):
        DyQRuntime(**arguments)


class FailingOnce:
    """A barrier (or decode) that raises on its n-th call only."""

    def __init__(self, fail_at):
        self.calls, self.fail_at = 0, fail_at

    def __call__(self, *args):
        self.calls += 1
        if self.calls == self.fail_at:
            raise RuntimeError("device lost")


def bits_of_a_clean_run():
    with DyQRuntime(KinematicDispatcher(CONFIG), PrecisionFlag(), barrier=None) as clean:
        model = FakeModel(clean.flag)
        control_loop(clean, model, ACTIONS)
    return model.decode_bits


def test_a_failing_barrier_reaches_the_caller_and_the_next_steps_run_normally():
    barrier = FailingOnce(fail_at=1)
    with DyQRuntime(KinematicDispatcher(CONFIG), PrecisionFlag(), barrier=barrier) as runtime:
        model = FakeModel(runtime.flag)
        previous, failures = None, 0
        for action in ACTIONS:
            try:
                runtime.step(previous, model.prefill, model.decode)
            except RuntimeError as err:
                assert "device lost" in str(err)
                failures += 1
            previous = action
        assert failures == 1 and barrier.calls > 1
        # Every step but the failed one decoded at the bits the dispatcher chose, as without a failure.
        clean = bits_of_a_clean_run()
        failed_step = next(i for i, (a, b) in enumerate(zip(model.decode_bits, clean)) if a != b) \
            if model.decode_bits != clean[:len(model.decode_bits)] else len(model.decode_bits)
        assert model.decode_bits == clean[:failed_step] + clean[failed_step + 1:]


def test_a_failing_prefill_write_does_not_leave_a_pending_step():
    barrier = FailingOnce(fail_at=1)
    with DyQRuntime(KinematicDispatcher(CONFIG), PrecisionFlag(8), prefill_bits=2, barrier=barrier) as runtime:
        with pytest.raises(RuntimeError, match="device lost"):
            runtime.begin_step(ACTIONS[0])
        runtime.begin_step(ACTIONS[1])  # not "begin_step called twice"
        assert runtime.flag.bits == 2
        assert runtime.publish() == 16


def test_a_failing_flag_write_reaches_the_caller_and_the_runtime_recovers(runtime, monkeypatch):
    writes = []
    write = runtime._write

    def write_fails_once(bits):
        writes.append(bits)
        if len(writes) == 1:
            raise OSError("flag unmapped")
        return write(bits)

    monkeypatch.setattr(runtime, "_write", write_fails_once)
    previous, failures = None, 0
    for action in ACTIONS[:30]:
        try:
            runtime.step(previous, lambda: None, lambda _: None)
        except OSError:
            failures += 1
        previous = action
    assert failures == 1 and len(runtime.stats) == 29
    assert runtime.stats[-1].bits == runtime.flag.bits == runtime.dispatcher.bits


def test_a_failing_decode_reaches_the_caller_and_the_next_step_runs_normally(runtime):
    decode = FailingOnce(fail_at=3)
    previous = None
    for i, action in enumerate(ACTIONS[:10]):
        if i == 2:
            with pytest.raises(RuntimeError, match="device lost"):
                runtime.step(previous, lambda: None, decode)
        else:
            runtime.step(previous, lambda: None, decode)
        previous = action
    assert len(runtime.stats) == 10 and runtime.dispatcher.steps == 9
    assert all(s.decode_ms >= 0 for s in runtime.stats)


def test_force_precision_whose_write_fails_does_not_stay_forced():
    barrier = FailingOnce(fail_at=1)
    with DyQRuntime(KinematicDispatcher(CONFIG), PrecisionFlag(), barrier=barrier) as runtime:
        with pytest.raises(RuntimeError, match="device lost"):
            with force_precision(runtime, 2):
                pass
        assert runtime.flag.bits == 16
        runtime.step(None, lambda: None, lambda _: None)
        assert runtime.stats[-1].forced is False and runtime.stats[-1].bits == 16


def test_a_closed_runtime_says_so():
    runtime = DyQRuntime(KinematicDispatcher(CONFIG), PrecisionFlag(), barrier=None)
    runtime.close()
    with pytest.raises(RuntimeError, match="DyQRuntime is closed"):
        runtime.step(None, lambda: None, lambda _: None)


@pytest.mark.parametrize("copier", [copy.copy, copy.deepcopy, pickle.dumps])
def test_a_runtime_refuses_to_be_copied_naming_itself(copier):
    with DyQRuntime(KinematicDispatcher(DispatchConfig()), PrecisionFlag(16)) as runtime:
        with pytest.raises(TypeError, match="DyQRuntime cannot be copied"):
            copier(runtime)
