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
    follows = {}
    for before, after in zip(log, log[1:]):
        follows[(before, after)] = follows.get((before, after), 0) + 1
    # A fixed or rotated order would put each candidate after one other nearly every time: 20 ordered pairs
    # share the 999 successions, each at least 20 times.
    pairs = [(x, y) for x in names for y in names if x != y]
    assert all(follows.get(pair, 0) >= 20 for pair in pairs), follows
    assert run(0) == log and run(1) != log


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


@pytest.mark.parametrize("warmup, repeats", [(-1, 3), (0, 0)])
def test_bad_counts_are_refused(warmup, repeats):
    with pytest.raises(ValueError, match="warmup must be >= 0 and repeats >= 1"):
        results.interleaved_median_ms({"x": lambda: None}, warmup=warmup, repeats=repeats)


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
