"""dyq.results.interleaved_median_ms: the order of the calls and the medians, on a clock the test drives."""
import pytest

import dyq.results as results


class FakeClock:
    def __init__(self):
        self.now = 0.0

    def perf_counter(self):
        return self.now


@pytest.fixture
def clock(monkeypatch):
    fake = FakeClock()
    monkeypatch.setattr(results.time, "perf_counter", fake.perf_counter)
    return fake


def test_every_round_calls_each_candidate_once_and_each_median_is_its_own(clock):
    log = []
    durations = {"a": [0.002, 0.004, 0.003], "b": [0.010, 0.030, 0.020], "c": [0.001, 0.001, 0.005]}
    counters = {name: iter(values) for name, values in durations.items()}

    def call(name):
        log.append(name)
        clock.now += next(counters[name])

    candidates = {name: (lambda name=name: call(name)) for name in durations}
    medians = results.interleaved_median_ms(candidates, warmup=0, repeats=3)
    assert [sorted(log[3 * r:3 * r + 3]) for r in range(3)] == [["a", "b", "c"]] * 3
    assert medians == pytest.approx({"a": 3.0, "b": 20.0, "c": 1.0})


def test_each_candidate_follows_every_other_and_the_order_is_reproducible(clock):
    names = [f"c{i}" for i in range(5)]

    def run(seed):
        log = []
        candidates = {name: (lambda name=name: log.append(name)) for name in names}
        results.interleaved_median_ms(candidates, warmup=0, repeats=200, seed=seed)
        return log

    log = run(0)
    follows, within_rounds = {}, {}
    for i, (before, after) in enumerate(zip(log, log[1:])):
        follows[(before, after)] = follows.get((before, after), 0) + 1
        if (i + 1) % len(names):  # both in the same round
            within_rounds[(before, after)] = within_rounds.get((before, after), 0) + 1
    # A fixed or rotated order would put each candidate after one other nearly every time. Here the 200
    # rounds are 20 cycles of a Williams design of 10 rounds: within the rounds, each of the 20 ordered pairs
    # follows exactly twice a cycle; the 199 successions across rounds, which each cycle's relabelling
    # spreads, add about 10 each (45 to 54 in all with this seed).
    pairs = [(x, y) for x in names for y in names if x != y]
    assert within_rounds == {pair: 40 for pair in pairs}
    assert all(42 <= follows[pair] <= 58 for pair in pairs), follows
    assert run(0) == log and run(1) != log


def test_no_candidates_give_no_medians(clock):
    assert results.interleaved_median_ms({}, warmup=0, repeats=3) == {}


@pytest.mark.parametrize("count", range(1, 10))
def test_balanced_orders_put_each_candidate_after_every_other_equally_often(count):
    import random

    orders = results.balanced_orders(count, random.Random(count))
    assert len(orders) == (2 * count if count % 2 else count)
    assert all(sorted(order) == list(range(count)) for order in orders)
    follows = {}
    for order in orders:
        for before, after in zip(order, order[1:]):
            follows[(before, after)] = follows.get((before, after), 0) + 1
    each = 2 if count % 2 else 1
    assert follows == {(x, y): each for x in range(count) for y in range(count) if x != y}


def test_prepare_runs_untimed_before_each_call_and_rewarm_adds_an_untimed_call(clock):
    log = []

    def prepare():
        log.append("prepare")
        clock.now += 1.0  # never counted

    def fn():
        log.append("fn")
        clock.now += 0.004

    medians = results.interleaved_median_ms({"x": (prepare, fn)}, warmup=1, repeats=2, rewarm=True)
    assert log == ["prepare", "fn"] + ["prepare", "fn", "fn"] * 2
    assert medians == pytest.approx({"x": 4.0})
    log.clear()
    results.interleaved_median_ms({"x": (prepare, fn)}, warmup=0, repeats=2, rewarm=2)
    assert log == ["prepare", "fn", "fn", "fn"] * 2


@pytest.mark.parametrize("warmup, repeats, rewarm", [(-1, 3, 0), (0, 0, 0), (1, 3, -1)])
def test_bad_counts_are_refused(warmup, repeats, rewarm):
    with pytest.raises(ValueError, match="warmup and rewarm must be >= 0 and repeats >= 1"):
        results.interleaved_median_ms({"x": lambda: None}, warmup=warmup, repeats=repeats, rewarm=rewarm)


def test_rounds_go_on_until_the_timed_calls_reach_min_seconds(clock):
    calls = []

    def fn():
        calls.append(len(calls))
        clock.now += 0.010 if len(calls) % 2 else 0.030  # 10 ms and 30 ms in turn: median of 20 ms rounds

    # 3 rounds time 50 ms; 0.1 s of timed calls takes 6 (five time 90 ms).
    medians = results.interleaved_median_ms({"x": fn}, warmup=0, repeats=3, min_seconds=0.1)
    assert len(calls) == 6
    assert medians == pytest.approx({"x": 20.0})


def test_max_repeats_caps_the_rounds_that_min_seconds_adds(clock):
    calls = []

    def fn():
        calls.append(1)
        clock.now += 0.001

    results.interleaved_median_ms({"x": fn, "y": fn}, warmup=0, repeats=2, min_seconds=10.0, max_repeats=7)
    assert len(calls) == 14  # 7 rounds of both candidates


@pytest.mark.parametrize("min_seconds, max_repeats", [(-0.5, None), (0.1, 2)])
def test_bad_time_bounds_are_refused(min_seconds, max_repeats):
    with pytest.raises(ValueError, match="min_seconds must be >= 0 and max_repeats >= repeats"):
        results.interleaved_median_ms({"x": lambda: None}, repeats=3, min_seconds=min_seconds, max_repeats=max_repeats)


def test_environment_records_the_variables_that_change_cpu_timings(monkeypatch):
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    monkeypatch.delenv("GOMP_SPINCOUNT", raising=False)
    recorded = results.environment()["timing_variables"]
    assert recorded["OMP_WAIT_POLICY"] == "ACTIVE"
    assert "GOMP_SPINCOUNT" not in recorded


# dyq.results.cuda_device_median_ms on a simulated stream: the host advances its own clock by each call's
# launch cost, the GPU runs the queued work in order (a spin of c cycles takes c ns), and an event is
# reached at the GPU time when the work queued before it is done.
class FakeStream:
    def __init__(self, launch_us: float, kernel_us: float):
        self.launch, self.kernel = launch_us * 1e-3, kernel_us * 1e-3  # ms
        self.host = 0.0  # ms
        self.gpu_free = 0.0  # when the GPU finishes what is queued

    def enqueue(self, duration_ms: float) -> float:
        self.gpu_free = max(self.gpu_free, self.host) + duration_ms
        return self.gpu_free

    def sleep(self, cycles: int):
        self.enqueue(cycles * 1e-6)

    def call(self):
        self.host += self.launch
        self.enqueue(self.kernel)

    def synchronizing_call(self):
        self.call()
        self.host = self.gpu_free

    def event(self):
        stream = self

        class Event:
            def record(self):
                self.at = stream.enqueue(0.0)

            def query(self):
                return self.at <= stream.host

            def synchronize(self):
                stream.host = max(stream.host, self.at)

            def elapsed_time(self, other):
                return other.at - self.at

        return Event()


@pytest.mark.parametrize("launch_us, kernel_us", [(40.0, 5.0), (2.0, 30.0)])
def test_device_time_excludes_the_launches_that_a_lone_call_measures(launch_us, kernel_us):
    stream = FakeStream(launch_us, kernel_us)
    device = results.cuda_device_median_ms(stream.call, warmup=2, repeats=7, calls=10, spin_cycles=1000,
                                           sleep=stream.sleep, event=stream.event)
    assert device == pytest.approx(kernel_us * 1e-3)
    # Bracketing one call adds its launch to the kernel: the reason for the device time.
    start, end = stream.event(), stream.event()
    start.record()
    stream.call()
    end.record()
    end.synchronize()
    assert start.elapsed_time(end) == pytest.approx((launch_us + kernel_us) * 1e-3)


def test_a_spin_shorter_than_the_launches_doubles_until_the_calls_are_queued_in_time():
    stream = FakeStream(launch_us=40.0, kernel_us=5.0)
    spins = []

    def sleep(cycles):
        spins.append(cycles)
        stream.sleep(cycles)

    device = results.cuda_device_median_ms(stream.call, warmup=0, repeats=3, calls=10, spin_cycles=1000,
                                           sleep=sleep, event=stream.event)
    assert device == pytest.approx(5e-3)
    # 10 launches take 400 us = 400000 cycles of the spin: 1000 doubled 9 times (512000) is the first long enough.
    assert spins[:10] == [1000 * 2 ** i for i in range(10)] and spins[10:] == [512000] * 2


def test_a_call_that_waits_for_the_gpu_is_refused():
    stream = FakeStream(launch_us=1.0, kernel_us=5.0)
    with pytest.raises(results.HostSynchronizes, match="waits for the GPU"):
        results.cuda_device_median_ms(stream.synchronizing_call, warmup=0, repeats=3, calls=4, spin_cycles=1000,
                                      max_spin_cycles=1 << 16, sleep=stream.sleep, event=stream.event)


@pytest.mark.parametrize("warmup, repeats, calls", [(-1, 3, 10), (0, 0, 10), (0, 3, 0)])
def test_device_time_refuses_bad_counts(warmup, repeats, calls):
    with pytest.raises(ValueError, match="calls"):
        results.cuda_device_median_ms(lambda: None, warmup=warmup, repeats=repeats, calls=calls)
