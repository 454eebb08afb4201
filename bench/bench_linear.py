"""DyQLinear on the CPU at every activation bit-width against torch's nn.Linear in fp32 and bf16.

Prints a table of median milliseconds and writes bench/results/linear_cpu.json.

    python bench/bench_linear.py              # the full grid
    python bench/bench_linear.py --quick      # one shape, for a smoke run
    DYQ_CPU_ISA=avx2 python bench/bench_linear.py --out linear_cpu_avx2.json   # another CPU path
"""
from __future__ import annotations

import argparse

import torch

import dyq
from dyq.results import environment, median_ms, print_table, write_json

SHAPES = [(4096, 4096), (11008, 4096), (4096, 11008)]  # (N, K): Llama-2-7B's attention, MLP up, MLP down
BATCHES = [1, 16, 256]
BITS = [2, 4, 8, 16]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="one small shape only")
    parser.add_argument("--shape", action="append", metavar="NxK", help="only these (N, K) shapes (repeatable)")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--out", default="linear_cpu.json")
    args = parser.parse_args()
    shapes, batches = ([(4096, 4096)], [1, 16]) if args.quick else (SHAPES, BATCHES)
    if args.shape:
        shapes = [tuple(int(v) for v in shape.lower().split("x")) for shape in args.shape]

    torch.manual_seed(0)
    rows, results = [], []
    for n, k in shapes:
        linear = torch.nn.Linear(k, n, bias=False)
        linear_bf16 = torch.nn.Linear(k, n, bias=False).to(torch.bfloat16)
        layer = dyq.DyQLinear.from_linear(linear, group_size=128)
        for m in batches:
            x = torch.randn(m, k)
            x_bf16 = x.bfloat16()
            with torch.inference_mode():
                timings = {
                    "fp32": median_ms(lambda: linear(x), repeats=args.repeats),
                    "bf16": median_ms(lambda: linear_bf16(x_bf16), repeats=args.repeats),
                }
                for bits in BITS:
                    layer.act_bits = bits
                    timings[f"w4a{bits}"] = median_ms(lambda: layer(x), repeats=args.repeats)
            speedups = {key: timings["fp32"] / timings[key] for key in timings}
            results.append({"m": m, "n": n, "k": k, "group_size": 128, "median_ms": timings,
                            "speedup_vs_fp32": speedups})
            rows.append([m, n, k] + [f"{timings[key]:.2f}" for key in timings]
                        + [f"{min(speedups[f'w4a{b}'] for b in BITS):.2f}x"])

    headers = ["M", "N", "K", "fp32", "bf16"] + [f"W4A{b}" for b in BITS] + ["min speedup vs fp32"]
    isa = dyq.cpu_info()["isa"]
    print_table(headers, rows, title=f"DyQLinear on the CPU ({isa} path), median ms (input fp32, group 128)")
    path = write_json(args.out, {"benchmark": "linear_cpu", "environment": environment(), "results": results})
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
