"""Timing and result files shared by the benchmarks and dyq's own commands: medians, a readable
table, and JSON that records the machine and the versions it was measured with."""
from __future__ import annotations

import json
import os
import platform
import random
import statistics
import subprocess
import time
from pathlib import Path

import torch

# bench/results/ of a source checkout; commands take an explicit path when installed elsewhere.
RESULTS = Path.cwd() / "bench" / "results"

# Environment variables that change CPU timings, recorded where set: how the OpenMP threads wait between
# parallel regions moved a 0.06 ms call by 30 % on a 2-core VM, and dyq's own switches pick its path.
TIMING_VARIABLES = ("OMP_NUM_THREADS", "OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "KMP_BLOCKTIME", "DYQ_CPU_ISA",
                    "DYQ_HUGE_PAGES")


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def environment() -> dict:
    import numpy

    import dyq

    cpu = dyq.cpu_info()
    env = {
        "cpu": cpu_name(),
        "cpu_isa": cpu["isa"],
        "cpu_threads": cpu["threads"],  # whose threads run dyq's CPU kernels
        "cpu_huge_pages": cpu["huge_pages"],  # whether dyq's packed CPU weights are on huge pages
        "cores": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": numpy.__version__,
        "dyq": dyq.__version__,
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "timing_variables": {name: os.environ[name] for name in TIMING_VARIABLES if name in os.environ},
    }
    if torch.cuda.is_available():
        props = torch.cuda.get_device_properties(0)
        env.update(gpu=props.name, capability=f"{props.major}.{props.minor}", sms=props.multi_processor_count,
                   l2_bytes=props.L2_cache_size, driver=_driver_version(), cuda=torch.version.cuda)
    return env


def _driver_version() -> str:
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
                             capture_output=True, text=True, check=False).stdout
        return out.strip().splitlines()[0]
    except (OSError, IndexError):
        return ""


def median_ms(fn, *, warmup: int = 3, repeats: int = 15, min_seconds: float = 0.0) -> float:
    """Median wall time of fn() in milliseconds (CPU work; synchronous)."""
    for _ in range(warmup):
        fn()
    times = []
    start = time.perf_counter()
    while len(times) < repeats or time.perf_counter() - start < min_seconds:
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def balanced_orders(count: int, rng: random.Random) -> list[list[int]]:
    """One cycle of round orders of ``count`` candidates (indices) in which every candidate comes right after
    every other equally often within the rounds: a Williams design (``count`` rounds, each the first one
    0, 1, count - 1, 2, count - 2, ... shifted by its index modulo ``count``; for an odd count those and
    their reverses, twice as many rounds), the candidates relabelled at random by ``rng``."""
    # 0, 1, count - 1, 2, count - 2, ...: position i holds (i + 1) // 2 for odd i, count - i // 2 for even i > 0.
    first = [0] + [(i + 1) // 2 if i % 2 else count - i // 2 for i in range(1, count)]
    rounds = [[(index + shift) % count for index in first] for shift in range(count)]
    if count % 2:
        rounds += [order[::-1] for order in rounds]
    relabel = list(range(count))
    rng.shuffle(relabel)
    return [[relabel[index] for index in order] for order in rounds]


def interleaved_median_ms(candidates: dict, *, warmup: int = 1, repeats: int = 15, rewarm: int = 0,
                          min_seconds: float = 0.0, max_repeats: int | None = None, seed: int = 0) -> dict:
    """Median wall milliseconds of each candidate, timed in turns: every round calls each candidate once, so
    that all of them meet the same drifts of a shared machine (on a 2-core VM the same bf16 control step
    took 32 ms in one minute and 42 in the next, which moved ratios of candidates timed one after another
    by a fifth). Each round takes its own order, shuffled with ``seed``, so that every candidate follows
    each of the others about equally often: a call pays for what the one before it left behind (with
    two threads, the call after some of torch's kernels found the other thread asleep, which made it up to
    30 % slower on a 0.06 ms layer of the AMD EPYC), and a fixed order, even one rotated every round,
    charged that to the same candidate nearly every time. The orders come in cycles of a Williams design
    (:func:`balanced_orders`), each cycle under its own seeded relabelling, rather than from independent
    shuffles: over the 60 rounds of a decode row of ``bench/bench_linear.py`` those had put one width after
    torch's fp32 and bf16 layers, whose weights evict the most, 21 times where 15 was its share, and that
    width's hot call of 11008 x 4096 at one row came out 1.2x to 1.3x slower than its twin's in two runs
    (the same kernel; alternating in one loop they tied, 0.93 ms each).

    ``candidates`` maps a name to fn, or to (prepare, fn) where prepare() runs untimed before each call
    of fn (to set a precision, say). With ``rewarm`` (a count; True is 1) every timed call follows that many
    untimed ones of the same candidate, which bring back into the caches what the other candidates' calls
    evicted.

    Rounds go on past ``repeats`` until the timed calls add up to ``min_seconds``, up to ``max_repeats``
    rounds in all: calls of a tenth of a millisecond then get hundreds of rounds where a fixed count fit
    for a long call leaves their medians to a few rounds' drift."""
    calls = {name: entry if isinstance(entry, tuple) else (None, entry) for name, entry in candidates.items()}
    if warmup < 0 or repeats < 1 or rewarm < 0:
        raise ValueError(f"warmup and rewarm must be >= 0 and repeats >= 1, got {warmup}, {rewarm} and {repeats}")
    if min_seconds < 0 or (max_repeats is not None and max_repeats < repeats):
        raise ValueError(f"min_seconds must be >= 0 and max_repeats >= repeats ({repeats}), "
                         f"got {min_seconds} and {max_repeats}")
    for prepare, fn in calls.values():
        for _ in range(warmup):
            if prepare is not None:
                prepare()
            fn()
    names = list(calls)
    if not names:
        return {}
    rng = random.Random(seed)
    orders = []  # the rounds still to come in the current cycle
    times = {name: [] for name in names}
    timed_ms = 0.0
    rounds = 0
    while rounds < repeats or (timed_ms < 1e3 * min_seconds and (max_repeats is None or rounds < max_repeats)):
        if not orders:
            orders = balanced_orders(len(names), rng)
        for name in (names[i] for i in orders.pop(0)):
            prepare, fn = calls[name]
            if prepare is not None:
                prepare()
            for _ in range(rewarm):  # True counts as 1
                fn()
            t0 = time.perf_counter()
            fn()
            elapsed = (time.perf_counter() - t0) * 1e3
            times[name].append(elapsed)
            timed_ms += elapsed
        rounds += 1
    return {name: statistics.median(values) for name, values in times.items()}


def cuda_median_ms(fn, *, warmup: int, repeats: int) -> float:
    """Median milliseconds of a lone fn() call, bracketed by CUDA events on an idle stream: what one
    eager call costs a Python caller, the host's launch included. A call that the GPU finishes faster
    than the host launches it (a GEMV of a few microseconds behind tens of microseconds of Python, op
    dispatch and launches) measures the host: :func:`cuda_device_median_ms` measures the GPU."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        fn()
        end.record()
        end.synchronize()
        times.append(start.elapsed_time(end))
    return statistics.median(times)


class HostSynchronizes(RuntimeError):
    """fn waits for the GPU, so its calls can never be queued ahead of it."""


def cuda_device_median_ms(fn, *, warmup: int, repeats: int, calls: int = 10, spin_cycles: int = 1 << 20,
                          max_spin_cycles: int = 1 << 28, sleep=None, event=None) -> float:
    """Median device milliseconds of one fn() call, without the host's launch time.

    Each sample queues ``calls`` calls behind a spin kernel (``torch.cuda._sleep``), so that the GPU finds
    them all queued and runs them back to back (as a CUDA graph or a busy stream does), and divides the
    events' interval by ``calls``. A sample counts only if the GPU was still spinning when the host had
    queued the last call (the start event not yet reached); otherwise the spin doubles and the sample is
    taken again. A fn that synchronizes with the host can never pass: past ``max_spin_cycles`` it raises
    :class:`HostSynchronizes`. ``sleep`` and ``event`` replace ``torch.cuda._sleep`` and
    ``torch.cuda.Event`` (tests)."""
    if warmup < 0 or repeats < 1 or calls < 1:
        raise ValueError(f"warmup must be >= 0, repeats and calls >= 1, got {warmup}, {repeats} and {calls}")
    sleep = sleep or torch.cuda._sleep
    event = event or (lambda: torch.cuda.Event(enable_timing=True))
    for _ in range(warmup):
        fn()
    times = []
    while len(times) < repeats:
        start, end = event(), event()
        sleep(spin_cycles)
        start.record()
        for _ in range(calls):
            fn()
        end.record()
        queued_in_time = not start.query()
        end.synchronize()
        if queued_in_time:
            times.append(start.elapsed_time(end) / calls)
        elif spin_cycles >= max_spin_cycles:
            raise HostSynchronizes(f"the GPU reached the calls before the host had queued {calls} of them even "
                                   f"behind a spin of {spin_cycles} cycles: fn waits for the GPU")
        else:
            spin_cycles *= 2
    return statistics.median(times)


def call_times_ns(fn, arguments) -> list[int]:
    """Wall time of each single call fn(argument), in nanoseconds (calls too short for median_ms)."""
    clock = time.perf_counter_ns
    samples = []
    for argument in arguments:
        start = clock()
        fn(argument)
        samples.append(clock() - start)
    return samples


def percentiles_us(samples_ns) -> dict[str, float]:
    """Median and 99th percentile of nanosecond samples, in microseconds."""
    ordered = sorted(samples_ns)
    return {"median_us": statistics.median(ordered) / 1e3,
            "p99_us": statistics.quantiles(ordered, n=100, method="inclusive")[98] / 1e3}


def print_table(headers: list[str], rows: list[list], title: str = "") -> None:
    cells = [[str(c) for c in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) if cells else len(h) for i, h in enumerate(headers)]
    if title:
        print(title)
    print("  ".join(h.rjust(w) for h, w in zip(headers, widths)))
    print("  ".join("-" * w for w in widths))
    for r in cells:
        print("  ".join(c.rjust(w) for c, w in zip(r, widths)))


def results_path(path: str | os.PathLike) -> Path:
    """Where a results file is read and written: a bare file name in ``RESULTS`` (bench/results/), any other
    path as it is."""
    path = Path(path)
    return RESULTS / path if path.parent == Path(".") else path


def write_json(path: str | os.PathLike, payload: dict) -> Path:
    """Writes payload as indented JSON at :func:`results_path`; returns that path."""
    path = results_path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(payload, indent=2) + "\n")
    tmp.replace(path)  # atomic: a reader never sees half a file
    return path
