"""Overhead of the kinematic dispatcher, the hysteresis, the flag write and the runtime's hand-over.

    python bench/bench_dispatcher.py [--steps 20000] [--out bench/results/dispatcher.json]

Every timing is the median (and 99th percentile) over single calls timed with perf_counter_ns, the
trajectory being the synthetic demo tiled to ``--steps``. The paper's budget (Table IV) is < 0.5 ms
and < 64 KB for the kinematic evaluation and its history buffers.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numpy as np

import dyq
from dyq import DispatchConfig, DyQRuntime, Hysteresis, KinematicDispatcher, PrecisionFlag
from dyq.control.dispatch import HYSTERESIS_MODES, synthetic_trajectory
from dyq.results import call_times_ns, environment, percentiles_us, write_json

DEFAULT_OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "dispatcher.json")


def bench_dispatcher(config: DispatchConfig, actions: np.ndarray) -> dict:
    dispatcher = KinematicDispatcher(config)
    call_times_ns(dispatcher.step, actions[: config.history])  # fill the history first
    dispatcher.reset()
    samples = call_times_ns(dispatcher.step, actions)
    return {**percentiles_us(samples), "state_bytes": dispatcher.state_bytes}


def bench_runtime(actions: np.ndarray, prefill_seconds: float) -> dict:
    """Host time per step spent outside prefill and decode, and the wait for the dispatcher."""
    flag = PrecisionFlag()
    with DyQRuntime(KinematicDispatcher(), flag) as runtime:
        prefill = (lambda: time.sleep(prefill_seconds)) if prefill_seconds else (lambda: None)
        overhead = []
        for action in actions:
            start = time.perf_counter_ns()
            runtime.step(action, prefill, lambda _: None)
            step = runtime.stats[-1]
            overhead.append(time.perf_counter_ns() - start - (step.prefill_ms + step.decode_ms) * 1e6)
        stats = runtime.stats
    return {
        "prefill_ms": prefill_seconds * 1e3,
        "steps": len(stats),
        "host_overhead_median_us": float(np.median(overhead)) / 1e3,
        "wait_median_us": statistics.median(s.wait_us for s in stats),
        "wait_p99_us": float(np.percentile([s.wait_us for s in stats], 99)),
        "dispatcher_in_worker_median_us": statistics.median(s.dispatcher_us for s in stats),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20000)
    parser.add_argument("--runtime-steps", type=int, default=400)
    parser.add_argument("--out", default=DEFAULT_OUT)
    args = parser.parse_args(argv)

    actions = np.tile(synthetic_trajectory(240, seed=0), (args.steps // 240 + 1, 1))[: args.steps]
    base = DispatchConfig()
    variants = {
        "counter, history 256 (default)": base,
        "window, history 256": base.replace(hysteresis="window"),
        "counter, history 512": base.replace(history=512),
        "counter, history 1024": base.replace(history=1024),
        "pose input, history 256": base.replace(input="pose"),
    }
    rows = {name: bench_dispatcher(config, actions) for name, config in variants.items()}

    targets = [int(b) for b in np.random.default_rng(0).choice(dyq.VALID_BITS, size=args.steps)]
    hysteresis = {mode: percentiles_us(call_times_ns(Hysteresis(3, mode).update, targets)) for mode in HYSTERESIS_MODES}
    flag = PrecisionFlag()

    def write_flag(bits):
        flag.bits = bits

    flag_write = percentiles_us(call_times_ns(write_flag, targets))
    runtime = {
        "no prefill": bench_runtime(actions[: args.runtime_steps], 0.0),
        "5 ms prefill": bench_runtime(actions[: args.runtime_steps], 0.005),
    }

    env = environment()
    print(f"dispatcher step ({args.steps} steps, {env['cpu']}, {env['cores']} CPUs, Python {env['python']})")
    print(f"{'variant':<34}{'median us':>10}{'p99 us':>10}{'state bytes':>13}")
    for name, row in rows.items():
        print(f"{name:<34}{row['median_us']:>10.2f}{row['p99_us']:>10.2f}{row['state_bytes']:>13}")
    print()
    print(f"{'component':<34}{'median us':>10}{'p99 us':>10}")
    for mode, row in hysteresis.items():
        print(f"{'hysteresis ' + mode:<34}{row['median_us']:>10.2f}{row['p99_us']:>10.2f}")
    print(f"{'flag write':<34}{flag_write['median_us']:>10.2f}{flag_write['p99_us']:>10.2f}")
    print()
    print(f"{'runtime (' + str(args.runtime_steps) + ' steps)':<20}{'host overhead us':>18}{'wait us':>10}"
          f"{'wait p99 us':>13}{'dispatch in worker us':>23}")
    for name, row in runtime.items():
        print(f"{name:<20}{row['host_overhead_median_us']:>18.1f}{row['wait_median_us']:>10.1f}"
              f"{row['wait_p99_us']:>13.1f}{row['dispatcher_in_worker_median_us']:>23.1f}")

    record = {
        "benchmark": "dispatcher",
        "environment": env,
        "steps": args.steps,
        "config": base.to_dict(),
        "dispatcher_step": rows,
        "hysteresis_update": hysteresis,
        "flag_write": flag_write,
        "runtime": runtime,
        "budget": {"paper_step_us": 500, "paper_state_bytes": 65536, "target_step_us": 20},
    }
    print(f"\nwrote {write_json(args.out, record)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
