"""The online Hadamard rotation of down_proj's input on the CPU: dyq.ops.hadamard_transform against the torch
path it replaced (two matrix products, ``left^T (x * signs) right`` on x viewed as [m, p]) and against the
dense ``x @ R``, on the same float32 inputs, at one thread.

    python bench/bench_hadamard.py [--sizes 1536 2816 11008] [--rows 1 16 256] [--out hadamard_cpu.json]

Each size uses dyq's construction, n = m x p (OnlineRotation): 1536 = 12 x 128, 2816 = 44 x 64 and
11008 = 344 x 32 (Paley over GF(7^3)). A size whose split differs under the prime-field-only construction 1
is also timed with it (11008 = 5504 x 2, where the Paley factor is nearly the whole matrix and the
butterfly has one stage), as its own rows. Every path computes the same R (each is compared with the float64 product on 4 rows; max_abs_error). Medians of wall time; the table and the
JSON say whether other jobs were running (``--loaded``): timings on a loaded machine are indicative only.
"""
from __future__ import annotations

import argparse
import sys

import torch

import dyq
from dyq.results import environment, median_ms, print_table, write_json
from dyq.rotation import HADAMARD_CONSTRUCTION, OnlineRotation, hadamard_factors


def constructions(n: int) -> list[int]:
    """The current construction, and construction 1 too when it splits n otherwise."""
    shapes = {c: None if (f := hadamard_factors(n, c)) is None else f[0].shape for c in (1, HADAMARD_CONSTRUCTION)}
    return [HADAMARD_CONSTRUCTION] if shapes[1] == shapes[HADAMARD_CONSTRUCTION] else [HADAMARD_CONSTRUCTION, 1]


def paths(rotation: OnlineRotation) -> dict:
    """The three ways to compute x R, on float32 operands prepared once."""
    signs, left, right = (b.float() for b in (rotation.signs, rotation.left, rotation.right))
    dense = rotation.matrix(torch.float32)
    m, p = left.shape[0], right.shape[0]

    def two_matmuls(x):
        y = (x * signs).reshape(*x.shape[:-1], m, p)
        return (left.T @ y @ right).reshape(x.shape)

    return {"dyq op": lambda x: dyq.ops.hadamard_transform(x, signs, left),
            "torch two matmuls": two_matmuls,
            "dense x @ R": lambda x: x @ dense}


def timed(fn, x, budget_seconds: float) -> float:
    """Median ms, with as many repeats as fit the budget (1 to 15: a call longer than the budget is timed
    once, after one warm-up call)."""
    once = median_ms(lambda: fn(x), warmup=1, repeats=1)
    repeats = min(15, int(budget_seconds * 1e3 / max(once, 1e-3)))
    return once if repeats < 2 else median_ms(lambda: fn(x), warmup=0, repeats=repeats)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1536, 2816, 11008])
    parser.add_argument("--rows", type=int, nargs="+", default=[1, 16, 256])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--budget", type=float, default=2.0, help="seconds of repeats per timing")
    parser.add_argument("--loaded", action="store_true",
                        help="other jobs share the machine (recorded: the timings are then indicative only)")
    parser.add_argument("--out", default="hadamard_cpu.json")
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    gen = torch.Generator().manual_seed(0)
    results = []
    for n, construction in ((n, c) for n in args.sizes for c in constructions(n)):
        rotation = OnlineRotation(n, construction=construction)
        ways = paths(rotation)
        m, p = rotation.left.shape[0], rotation.right.shape[0]
        probe = torch.randn(4, n, generator=gen)  # the three paths agree with the float64 R
        reference = probe.double() @ rotation.matrix()
        errors = {name: (fn(probe).double() - reference).abs().max().item() for name, fn in ways.items()}
        for rows in args.rows:
            x = torch.randn(rows, n, generator=gen)
            times = {name: timed(fn, x, args.budget) for name, fn in ways.items()}
            results.append({"n": n, "construction": construction, "m": m, "p": p, "rows": rows,
                            "median_ms": times, "max_abs_error": errors})
            print(f"n = {n} = {m} x {p}, rows = {rows}: " + ", ".join(f"{k} {v:.4g} ms" for k, v in times.items()),
                  flush=True)

    headers = ["n", "construction", "m x p", "rows", *(f"{name} ms" for name in ways), "op / two matmuls", "op / dense"]
    table = [[r["n"], r["construction"], f"{r['m']} x {r['p']}", r["rows"], *(f"{t:.4g}" for t in r["median_ms"].values()),
              f"{r['median_ms']['dyq op'] / r['median_ms']['torch two matmuls']:.3g}",
              f"{r['median_ms']['dyq op'] / r['median_ms']['dense x @ R']:.3g}"] for r in results]
    env = environment()
    state = "LOADED by other jobs: indicative only" if args.loaded else "not known to be loaded"
    print_table(headers, table, title=f"x R on float32 rows, {args.threads} thread(s), {env['cpu']} "
                                      f"({env['cpu_isa']}); machine {state}")
    record = {
        "benchmark": "hadamard_transform_cpu",
        "environment": env,
        "threads": args.threads,
        "machine_loaded": args.loaded,
        "note": ("timings taken while other jobs shared the machine's cores: medians are indicative, not clean "
                 "speedups") if args.loaded else "",
        "dtype": "float32",
        "results": results,
    }
    print(f"\nwrote {write_json(args.out, record)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
