"""DyQLinear on the CPU at every activation width against every CPU peer, in one process on the same inputs.

Peers: torch's fp32 and bf16 ``nn.Linear`` (oneDNN), its INT4 weight-only kernel
(``_weight_int4pack_mm_for_cpu``, bf16 input, group 128) and its dynamic INT8 linear
(``torch.ao.quantization.quantize_dynamic``, fp32 input); with ``--bitsandbytes``, bitsandbytes' NF4 and
LLM.int8() layers too (bf16 and fp16 input; bench/bitsandbytes_peers.py), whose CPU path is many times slower than
the others. dyq takes bf16 input, as the layers of a bf16 model do and as the bf16 peer does (its outputs
then bf16 too; ``--dtype float32`` gives it fp32 input and outputs, twice the bytes of both), group 128.

Each (shape, M) is timed hot (one copy of the weights, resident in the caches as far as they fit) and cold (as
many copies as fill four times the last-level cache, called in turn, so that every call reads its weights from
memory). The layers of one (shape, M, mode) are timed in turns, each round calling every one once in its own
shuffled order, so that each ratio compares calls made under the same conditions of a shared machine and no
layer always follows the same other one; hot, each timed call follows two untimed ones of the same layer, which
bring back what the others evicted. Decode (M = 1, cold) is the exception: a bandwidth measurement, it times
one layer's calls after another's, as a decode streams the weights of one layer after another's (in turns with
the other layers' cold reads between its calls, W4A8 on 4096 x 4096 took 9 % longer on the AMD EPYC); only
dyq's widths, which read the same copies, take turns there (every copy bound to one PrecisionFlag, whose one
write sets the width), each timed call after two untimed ones of its own width, as a control step runs all its
layers at one width. M = 1 is timed over four times the repeats of the others, which the larger M divide by
three from 64 rows on; short calls get more, until each layer's timed calls add up to 0.1 s (at most 1000
rounds). The same run measures the machine's streaming-read bandwidth (the faster of a sum and a max over 1 GiB
at the same thread count, on huge pages as dyq's packed weights are), once per thread count and again right
before and after each shape's decode timings, and the decode table states dyq's effective bandwidth at M = 1,
cold (the bytes of its packed weights and scales over the median time) as a share of both: on a shared machine
the bandwidth moves within a run.

Prints the tables and writes bench/results/linear_cpu.json (device, CPU flags, versions, threads, shapes,
medians, the kernel each dyq call ran and the load average before and after each thread count's run).

    python bench/bench_linear.py                        # Llama-7B and policy shapes, 1 and 2 threads
    python bench/bench_linear.py --quick                # one shape, M = 1 and 16, for a smoke run
    python bench/bench_linear.py --shape 4096x4096 --threads 2 --out linear_4096.json
    python bench/bench_linear.py --readme bench/results/linear_cpu.json   # the README's table from a JSON
"""
from __future__ import annotations

import argparse
import copy
import json
import math
import os
import warnings
from pathlib import Path

import torch
import torch.nn.functional as F

import dyq
from dyq.core.host_memory import huge_page_empty
from dyq.results import environment, interleaved_median_ms, median_ms, print_table, write_json

from bitsandbytes_peers import INPUT_DTYPES as BITSANDBYTES_INPUT_DTYPES, PEERS as BITSANDBYTES_PEERS, \
    bitsandbytes_layers, bitsandbytes_version, statistics_bytes

GROUP_SIZE = 128
LLAMA_7B_SHAPES = [(4096, 4096), (11008, 4096), (4096, 11008)]  # (N, K): attention, MLP up/gate, MLP down
BATCHES = [1, 16, 64, 256]
BITS = [16, 8, 4, 2]
PEERS = ["fp32", "bf16", "int8_dynamic", "int4_torch"]
STREAM_BYTES = 1 << 30
STREAM_REPEATS_AROUND = 5  # the streaming reads timed around each decode measurement


# M = 1 calls take a tenth of a millisecond to a few: they get this many times the repeats. Medians of 15
# calls moved by up to a fifth between runs on the AMD EPYC (W4A4 at 4096 x 4096, cold, one thread: 0.356
# and 0.437 ms, the same kernel as W4A8's 0.376 and 0.378); of 61, the three integer widths agreed to 2 %.
DECODE_REPEAT_FACTOR = 4
# And every candidate's timed calls add up to at least this many seconds, within MAX_ROUNDS rounds: the
# policy's layers take 0.01 to 0.6 ms a call, where 5 rounds of the larger M left the medians of the three
# integer widths, which run one kernel, up to a quarter apart (256 x 256, M = 16, one thread, cold).
MIN_SECONDS_PER_CANDIDATE = 0.1
MAX_ROUNDS = 1000
# Decode's timed call of a width follows this many untimed calls of the same width (on the next copies):
# a decode runs a whole control step's layers at one width, and on the Xeon with AMX a call right after
# one of another width paid for the switch (W4A8 on 4096 x 4096, two threads, cold: 0.52 ms right after
# a W4A16 call and still after one call of its own, 0.40 to 0.41 after two or four, 0.38 in a loop of its own).
DECODE_SAME_WIDTH_CALLS = 2
# Hot, each timed call follows this many untimed ones of its own layer. One was not enough on the Xeon with
# AMX, whose last-level cache does not keep everything that passes through it: after torch's fp32 layer of
# 11008 x 4096 had swept its 180 MB, W4A4 at 16 rows took 1.79, 1.62, then 1.27 ms over its next three calls
# (1.21 in a loop of its own), so that a width's median moved with how often its turn followed that layer,
# and W4A2 came out up to 1.5x slower than W4A4, the same kernel, in the rows of both 11008-wide shapes.
HOT_REWARM_CALLS = 2


def policy_shapes() -> list[tuple[int, int]]:
    """The (N, K) of the closed-loop policies' layers (python/dyq/sim/policies/*/policy.json)."""
    shapes = set()
    for path in sorted((Path(dyq.__file__).parent / "sim" / "policies").glob("*/policy.json")):
        config = json.loads(path.read_text())
        hidden, intermediate = config["hidden_size"], config["intermediate_size"]
        shapes |= {(hidden, hidden), (intermediate, hidden), (hidden, intermediate)}
    return sorted(shapes)


def last_level_cache_bytes() -> int:
    sizes = []
    for index in Path("/sys/devices/system/cpu/cpu0/cache").glob("index*"):
        try:
            text = (index / "size").read_text().strip()
        except OSError:
            continue
        scale = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}.get(text[-1], 1)
        sizes.append(int(text.rstrip("KMG")) * scale)
    return max(sizes, default=32 << 20)


def cpu_flags() -> list[str]:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                flags = line.split(":", 1)[1].split()
                return sorted(f for f in flags if f.startswith(("avx", "amx", "fma", "f16c")))
    except OSError:
        pass
    return []


def stream_read_gbps(repeats: int) -> float:
    """Bytes per second of the faster of two plain streaming reads of 1 GiB, a sum and a max (the machine's read
    bandwidth), in memory on huge pages as dyq's packed weights are (dyq.core.host_memory), so that both reads
    meet the same TLB: on 4 KiB pages the sum ran about 8 % slower on the AMD EPYC. On the Intel Xeon with AMX
    torch's max read 17.1 GB/s on one thread and 33.8 on two where its sum read 15.2 and 30.0 (a prefetching
    C++ loop, bench_cpu_kernels.cpp's, 18 to 20 and 34 to 35)."""
    data = huge_page_empty((STREAM_BYTES // 4,), torch.float32).fill_(1.0)
    ms = min(median_ms(lambda: data.sum(), warmup=1, repeats=repeats),
             median_ms(lambda: data.amax(), warmup=1, repeats=repeats))
    return STREAM_BYTES / ms / 1e6


class Rotation:
    """Calls one of several copies of a layer in turn: one copy is hot, enough copies are cold."""

    def __init__(self, make, weight_bytes: int, cold: bool, cache_bytes: int):
        copies = max(1, math.ceil(4 * cache_bytes / weight_bytes)) if cold else 1
        self.layers = [make() for _ in range(copies)]
        self.next = 0

    def __call__(self, x):
        layer = self.layers[self.next]
        self.next = (self.next + 1) % len(self.layers)
        return layer(x)


def int4_torch_layer(weight: torch.Tensor):
    """torch's INT4 weight-only CPU kernel: asymmetric 4-bit codes (0..15) per group, bf16 scales/zeros."""
    n, k = weight.shape
    groups = weight.reshape(n, k // GROUP_SIZE, GROUP_SIZE)
    lo, hi = groups.amin(-1, keepdim=True), groups.amax(-1, keepdim=True)
    scale = ((hi - lo) / 15).clamp(min=1e-8)
    codes = ((groups - lo) / scale).round().clamp(0, 15).to(torch.int32).reshape(n, k)
    # The kernel dequantizes as (code - 8) * scale + zero.
    zero = lo + 8 * scale
    scale_and_zeros = torch.stack([scale.squeeze(-1), zero.squeeze(-1)], -1).transpose(0, 1).contiguous()
    packed = torch._convert_weight_to_int4pack_for_cpu(codes, 1)
    scale_and_zeros = scale_and_zeros.bfloat16()
    return (lambda x: torch._weight_int4pack_mm_for_cpu(x, packed, GROUP_SIZE, scale_and_zeros),
            packed.nbytes + scale_and_zeros.nbytes)


def bitsandbytes_peer(bf16: torch.Tensor, peer: str) -> tuple:
    """(factory of a fresh copy, bytes of its weights and statistics) of one bitsandbytes peer."""
    def make():
        return bitsandbytes_layers(bf16, (peer,))[peer]

    layer = make()
    return make, layer.weight.nbytes + statistics_bytes(layer)


def peer_layers(linear: torch.nn.Linear, bitsandbytes: bool = False) -> dict:
    """name -> (factory of a fresh copy, bytes of its weights, input dtype)."""
    weight = linear.weight.detach()
    bf16 = weight.bfloat16()
    with warnings.catch_warnings():  # torch.ao's deprecation notices: this is the peer being measured
        warnings.simplefilter("ignore")
        int8 = torch.ao.quantization.quantize_dynamic(torch.nn.Sequential(linear), {torch.nn.Linear},
                                                      dtype=torch.qint8)
    int4_call, int4_bytes = int4_torch_layer(weight)
    peers = {
        "fp32": (lambda: (lambda w: lambda x: F.linear(x, w))(weight.clone()), weight.nbytes, torch.float32),
        "bf16": (lambda: (lambda w: lambda x: F.linear(x, w))(bf16.clone()), bf16.nbytes, torch.bfloat16),
        "int8_dynamic": (lambda: copy.deepcopy(int8), weight.numel() + 4 * weight.shape[0], torch.float32),
        "int4_torch": (lambda: int4_torch_layer(weight)[0], int4_bytes, torch.bfloat16),
    }
    for peer in BITSANDBYTES_PEERS if bitsandbytes else ():
        peers[peer] = (*bitsandbytes_peer(bf16, peer), BITSANDBYTES_INPUT_DTYPES[peer])
    return peers


def time_shape(n: int, k: int, batches, modes, repeats: int, cache_bytes: int, bitsandbytes: bool = False,
               dyq_dtype: torch.dtype = torch.bfloat16) -> list[dict]:
    torch.manual_seed(0)
    linear = torch.nn.Linear(k, n, bias=False)
    peers = peer_layers(linear, bitsandbytes)
    layer = dyq.DyQLinear.from_linear(linear, group_size=GROUP_SIZE)
    dyq_bytes = layer.qweight.nbytes + layer.scales.nbytes
    results = []
    for mode in modes:
        cold = mode == "cold"
        rotations = {name: (Rotation(make, size, cold, cache_bytes), dtype) for name, (make, size, dtype) in peers.items()}
        dyq_rotation = Rotation(lambda: copy.deepcopy(layer), dyq_bytes, cold, cache_bytes)
        # Every copy reads one flag, so that a width is set with one write, as a model switches. Set copy by
        # copy, each timed call followed a walk over thousands of small layers' modules that had evicted
        # everything the call touches: 256 x 256 at M = 1, cold, took 0.11 ms against 0.011 (AMD EPYC).
        flag = dyq.PrecisionFlag(16)
        for copied in dyq_rotation.layers:
            copied.bind_flag(flag)
        for m in batches:
            x = torch.randn(m, k)
            dyq_input = x.to(dyq_dtype)
            reps = repeats * DECODE_REPEAT_FACTOR if m == 1 else max(5, repeats // 3) if m >= 64 else repeats
            peer_calls = {name: (lambda rotation=rotation, inputs=x.to(dtype): rotation(inputs))
                          for name, (rotation, dtype) in rotations.items()}
            decode = cold and m == 1
            same_width_calls = DECODE_SAME_WIDTH_CALLS if decode else 0

            def set_width(bits: int) -> None:
                flag.bits = bits
                for _ in range(same_width_calls):
                    dyq_rotation(dyq_input)

            width_calls = {f"w4a{bits}": (lambda bits=bits: set_width(bits), lambda: dyq_rotation(dyq_input))
                           for bits in BITS}
            kernels = {f"w4a{bits}": dyq.cpu_gemm_kernel(m, k, GROUP_SIZE, bits) for bits in BITS}
            # Decode's bandwidth share is taken against a streaming read timed right before and after it: on
            # a shared machine the bandwidth moves within a run (the run-level read stays too).
            stream_around = [stream_read_gbps(STREAM_REPEATS_AROUND)] if decode else []
            with torch.inference_mode():
                if decode:
                    # One layer after another, as a decode streams one layer's weights after another's: the
                    # bandwidth measurement, between the two streaming reads. dyq's widths share one rotation
                    # of copies, so they still take turns.
                    timings = {name: median_ms(fn, repeats=reps, min_seconds=MIN_SECONDS_PER_CANDIDATE)
                               for name, fn in peer_calls.items()}
                    timings.update(interleaved_median_ms(width_calls, warmup=3, repeats=reps,
                                                         min_seconds=MIN_SECONDS_PER_CANDIDATE * len(width_calls),
                                                         max_repeats=max(reps, MAX_ROUNDS)))
                else:
                    # In turns, so that every ratio compares calls made under the same conditions; hot calls
                    # each after HOT_REWARM_CALLS untimed ones of their own, as the other layers evicted their weights.
                    candidates = {**peer_calls, **width_calls}
                    timings = interleaved_median_ms(candidates, warmup=3, repeats=reps,
                                                    rewarm=0 if cold else HOT_REWARM_CALLS,
                                                    min_seconds=MIN_SECONDS_PER_CANDIDATE * len(candidates),
                                                    max_repeats=max(reps, MAX_ROUNDS))
            if decode:
                stream_around.append(stream_read_gbps(STREAM_REPEATS_AROUND))
            result = {"m": m, "n": n, "k": k, "mode": mode, "group_size": GROUP_SIZE, "median_ms": timings,
                      "dyq_kernel": kernels, "copies": len(dyq_rotation.layers),
                      "weight_bytes": {"dyq": dyq_bytes, **{p: peers[p][1] for p in peers}}}
            if stream_around:
                result["stream_read_gbps_around"] = stream_around
            results.append(result)
    return results


def print_results(threads: int, stream_gbps: float, results: list[dict]) -> None:
    extra = [p for p in BITSANDBYTES_PEERS if results and p in results[0]["median_ms"]]
    columns = PEERS + extra + [f"w4a{b}" for b in BITS]
    rows = []
    for r in results:
        t = r["median_ms"]
        ratio = lambda b: f"{t['bf16'] / t[f'w4a{b}']:.2f}x"  # noqa: E731
        rows.append([r["m"], f"{r['n']}x{r['k']}", r["mode"]] + [f"{t[c]:.3f}" for c in columns]
                    + [ratio(b) for b in BITS])
    headers = ["M", "NxK", "weights"] + ["fp32", "bf16", "int8 dyn", "int4 torch"] + [p.replace("_", " ") for p in extra] \
        + [f"W4A{b}" for b in BITS] + [f"bf16/A{b}" for b in BITS]
    print_table(headers, rows, title=f"\n{threads} thread(s): median ms, and torch bf16 time over dyq's")
    rows = []
    for r in results:
        if r["m"] != 1 or r["mode"] != "cold":
            continue
        t = r["median_ms"]
        around = sum(r["stream_read_gbps_around"]) / len(r["stream_read_gbps_around"])
        row = [f"{r['n']}x{r['k']}", f"{stream_gbps:.1f}", f"{around:.1f}"]
        for b in BITS:
            gbps = r["weight_bytes"]["dyq"] / t[f"w4a{b}"] / 1e6
            row.append(f"{gbps:.1f} ({100 * gbps / stream_gbps:.0f} / {100 * gbps / around:.0f} %)")
        rows.append(row)
    if rows:
        print_table(["NxK", "stream GB/s (run)", "stream GB/s (around)"] + [f"W4A{b} GB/s" for b in BITS], rows,
                    title=f"\n{threads} thread(s): decode (M = 1, cold) bytes of packed weights + scales per second, "
                          "and its share of the run's streaming read / of the mean of those right before and after")


def readme_table(payload: dict, shapes=LLAMA_7B_SHAPES) -> str:
    """The README's CPU table: Llama-7B shapes, cold weights, the most threads measured."""
    threads = max(run["threads"] for run in payload["runs"])
    run = next(r for r in payload["runs"] if r["threads"] == threads)
    lines = ["| M | N x K | fp32 | bf16 | int8 dyn. | int4 torch | W4A16 | W4A8 | W4A4 | W4A2 |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in run["results"]:
        if r["mode"] != "cold" or (r["n"], r["k"]) not in shapes:
            continue
        t = r["median_ms"]
        cells = [f"{t[p]:.2f}" for p in PEERS]
        cells += [f"{t[f'w4a{b}']:.2f} ({t['bf16'] / t[f'w4a{b}']:.1f}x)" for b in BITS]
        lines.append(f"| {r['m']} | {r['n']} x {r['k']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="one shape, M = 1 and 16")
    parser.add_argument("--shape", action="append", metavar="NxK", help="only these (N, K) shapes (repeatable)")
    parser.add_argument("--batches", type=int, nargs="+", default=BATCHES)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--modes", nargs="+", choices=["hot", "cold"], default=["hot", "cold"])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--out", default="linear_cpu.json")
    parser.add_argument("--dtype", choices=["bfloat16", "float32"], default="bfloat16",
                        help="dyq's input (and output) dtype; the peers keep theirs")
    parser.add_argument("--readme", metavar="JSON", help="print the README's table from a results file, then exit")
    parser.add_argument("--bitsandbytes", action="store_true",
                        help="also time bitsandbytes' NF4 and LLM.int8() layers (slow on the CPU)")
    args = parser.parse_args()
    if args.readme:
        print(readme_table(json.loads(Path(args.readme).read_text())))
        return
    shapes, batches = LLAMA_7B_SHAPES + policy_shapes(), args.batches
    if args.quick:
        shapes, batches = [(4096, 4096)], [1, 16]
    if args.shape:
        shapes = [tuple(int(v) for v in shape.lower().split("x")) for shape in args.shape]
    cache_bytes = last_level_cache_bytes()
    if args.bitsandbytes:
        probe = bitsandbytes_layers(torch.randn(8, 64).bfloat16())
        if isinstance(probe, str):
            parser.error(f"--bitsandbytes: {probe}")

    runs = []
    for threads in args.threads:
        torch.set_num_threads(threads)
        load_before = os.getloadavg()
        stream_gbps = stream_read_gbps(args.repeats)
        results = [r for n, k in shapes
                   for r in time_shape(n, k, batches, args.modes, args.repeats, cache_bytes, args.bitsandbytes,
                                       getattr(torch, args.dtype))]
        print_results(threads, stream_gbps, results)
        load_after = os.getloadavg()
        print(f"load average (1, 5, 15 min): {load_before} before, {load_after} after")
        # The machine may be shared: the load average around the run says how busy it was.
        runs.append({"threads": threads, "stream_read_gbps": stream_gbps, "stream_bytes": STREAM_BYTES,
                     "load_average_before": load_before, "load_average_after": load_after, "results": results})
    payload = {"benchmark": "linear_cpu", "environment": {**environment(), "cpu_flags": cpu_flags(),
                                                          "last_level_cache_bytes": cache_bytes,
                                                          "dyq_cpu_paths": dyq.cpu_info()["runnable"]},
               "group_size": GROUP_SIZE, "dyq_input_dtype": args.dtype,
               "peers": PEERS + (list(BITSANDBYTES_PEERS) if args.bitsandbytes else []),
               "bitsandbytes": bitsandbytes_version() if args.bitsandbytes else None,
               "timing": "interleaved: each round calls every layer once, in a shuffled order; hot calls each "
                         f"after {HOT_REWARM_CALLS} untimed ones; M = 1 cold one peer after another, dyq's widths "
                         f"in turns, each timed call after {DECODE_SAME_WIDTH_CALLS} untimed ones of its width",
               "stream_read": "the faster of torch's sum and max over 1 GiB of fp32 on huge pages",
               "runs": runs}
    path = write_json(args.out, payload)
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
