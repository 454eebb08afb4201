"""Time dyq's CUDA GEMM paths against cuBLAS bf16, torch's INT4 weight-only kernel and bitsandbytes.

    python bench/bench_cuda.py [--quick] [--out bench/results]

For every (N, K) of the Llama-2-7B linear layers and every M, times `torch.ops.dyq.gemm` at 2, 4, 8
and 16 activation bits, `torch.matmul` in bf16 (cuBLAS) and `torch._weight_int4pack_mm` (where this
torch has it), bitsandbytes' NF4 and LLM.int8() layers (where it is installed:
bench/bitsandbytes_peers.py) with CUDA events, each call on one of several weight copies in rotation so that
M = 1 measures DRAM, not L2. Two times per call, medians after a warm-up:

- ``ms``: the device's time, calls queued back to back behind a spin kernel (dyq.results.cuda_device_median_ms),
  as a CUDA graph or a busy stream runs them. The table, the bandwidth and the TOPS come from it.
- ``eager_ms``: a lone call on an idle stream, the host's launch included (dyq.results.cuda_median_ms): what
  one eager call costs a Python caller. Small calls measure the host here, not the kernel.

Then whole control steps of a 0.5 B Llama-shaped decoder in plain torch (bench/decoder_step.py: a GPU machine
may have no transformers), bf16 against dyq at each width and bitsandbytes, eager (``control_step``).

Reports, at M = 1, the achieved bandwidth (bytes of weights + scales + activations + output over time) as a
percentage of a measured device-to-device copy, and at M = 512 the rate in TOPS. Prints a table and writes
bench/results/cuda_<device>.json with the device, driver, versions, shapes and medians.
"""
from __future__ import annotations

import argparse
import copy
import re
import statistics
import sys
import time
from pathlib import Path

import torch

import dyq
from dyq.results import HostSynchronizes, cuda_device_median_ms, cuda_median_ms, environment, \
    interleaved_median_ms, write_json

from bitsandbytes_peers import INPUT_DTYPES as BITSANDBYTES_INPUT_DTYPES, PEERS as BITSANDBYTES_PEERS, \
    bitsandbytes_layers, bitsandbytes_version, model_bytes, replace_linear_layers
from decoder_step import HALF_BILLION, Decoder, control_step as decoder_control_step

SHAPES = ((4096, 4096), (12288, 4096), (22016, 4096), (4096, 11008))  # (N, K): qkv/o, fused qkv, gate+up, down
ROWS = (1, 4, 8, 16, 64, 256, 512)
GROUP_SIZE = 128


def copy_bandwidth_gbs(warmup: int, repeats: int) -> float:
    """Device-to-device copy of 1 GiB, counting bytes read plus bytes written."""
    src = torch.empty(1 << 30, dtype=torch.uint8, device="cuda")
    dst = torch.empty_like(src)
    ms = cuda_device_median_ms(lambda: dst.copy_(src), warmup=warmup, repeats=repeats, calls=2)
    return 2 * src.numel() / ms / 1e6


def rotation_count(weight_bytes: int) -> int:
    """Enough weight copies to exceed L2 several times over."""
    l2 = torch.cuda.get_device_properties(0).L2_cache_size
    return max(2, min(16, 4 * l2 // max(weight_bytes, 1) + 1))


class Rotating:
    """Calls fn(i) for i cycling over the copies, so consecutive runs touch different weights."""

    def __init__(self, fn, copies: int):
        self.fn, self.copies, self.i = fn, copies, 0

    def __call__(self):
        self.fn(self.i)
        self.i = (self.i + 1) % self.copies


def int4pack_available() -> bool:
    return hasattr(torch, "_weight_int4pack_mm") and hasattr(torch.ops.aten, "_convert_weight_to_int4pack")


def torch_int4_layer(w_bf16: torch.Tensor):
    """torch's tinygemm layout: uint8 [N, K/2] codes in 0..15 (asymmetric, group scale and zero)."""
    n, k = w_bf16.shape
    wg = w_bf16.float().reshape(n, k // GROUP_SIZE, GROUP_SIZE)
    lo, hi = wg.amin(-1), wg.amax(-1)
    scale = ((hi - lo) / 15).clamp(min=1e-6)
    codes = torch.round((wg - lo.unsqueeze(-1)) / scale.unsqueeze(-1)).clamp(0, 15).to(torch.int32).reshape(n, k)
    packed = (codes[:, ::2] << 4 | codes[:, 1::2]).to(torch.uint8)
    weight = torch.ops.aten._convert_weight_to_int4pack(packed, 8)
    zero = lo + 8 * scale  # tinygemm dequantizes (q - 8) * scale + zero
    scales_and_zeros = torch.stack([scale, zero], dim=-1).transpose(0, 1).contiguous().to(torch.bfloat16)
    return weight, scales_and_zeros


def time_call(entry: dict, key: str, fn, warmup: int, repeats: int) -> None:
    """entry["ms"][key]: the device's time of a call; entry["eager_ms"][key]: a lone call's, launch included. A
    call that waits for the GPU has no device time of its own: its eager time stands in, and the reason is
    recorded."""
    entry.setdefault("eager_ms", {})[key] = cuda_median_ms(fn, warmup=warmup, repeats=repeats)
    try:
        # 10 calls a sample: a quarter of the lone calls' repeats gives as many calls, a tenth of the spins.
        entry["ms"][key] = cuda_device_median_ms(fn, warmup=0, repeats=max(5, repeats // 4))
    except HostSynchronizes as error:
        entry["ms"][key] = entry["eager_ms"][key]
        entry.setdefault("device_time_unavailable", {})[key] = str(error)
        print(f"  {key} at M = {entry['m']}: {error}; its eager time stands in")


def bench_shape(n: int, k: int, rows, warmup: int, repeats: int, copy_gbs: float, results: list, table: list):
    w = (torch.randn(n, k, device="cuda") * 0.02).to(torch.bfloat16)
    qweight, scales = torch.ops.dyq.quantize_weight(w, GROUP_SIZE)
    copies = rotation_count(qweight.numel() + scales.numel() * 4)
    dyq_layers = [(qweight.clone(), scales.clone()) for _ in range(copies)]
    bf16_layers = [w.clone() for _ in range(rotation_count(w.numel() * 2))]
    int4_layers = []
    if int4pack_available():
        try:
            int4_layers = [torch_int4_layer(w) for _ in range(copies)]
        except RuntimeError as err:  # layout requirements differ between torch versions
            print(f"  torch INT4 weight-only kernel unavailable here: {err}")
    bnb_layers = [bitsandbytes_layers(w) for _ in range(copies)]
    if isinstance(bnb_layers[0], str):
        bnb_layers = []
    for m in rows:
        x = torch.randn(m, k, device="cuda").to(torch.bfloat16)
        entry = {"n": n, "k": k, "m": m, "group_size": GROUP_SIZE, "ms": {}}
        for bits in dyq.VALID_BITS:
            fn = Rotating(lambda i, b=bits: torch.ops.dyq.gemm(x, *dyq_layers[i], GROUP_SIZE, b), copies)
            time_call(entry, f"dyq_a{bits}", fn, warmup, repeats)
        fn = Rotating(lambda i: torch.matmul(x, bf16_layers[i].t()), len(bf16_layers))
        time_call(entry, "cublas_bf16", fn, warmup, repeats)
        if int4_layers:
            fn = Rotating(lambda i: torch._weight_int4pack_mm(x, int4_layers[i][0], GROUP_SIZE, int4_layers[i][1]),
                          copies)
            time_call(entry, "torch_int4_weight_only", fn, warmup, repeats)
        for peer in BITSANDBYTES_PEERS if bnb_layers else ():
            fn = Rotating(lambda i, p=peer, xp=x.to(BITSANDBYTES_INPUT_DTYPES[peer]): bnb_layers[i][p](xp), copies)
            try:  # a peer failing on this device must not cost the rest of the run
                time_call(entry, peer, fn, warmup, repeats)
            except Exception as error:  # noqa: BLE001
                entry.setdefault("peer_errors", {})[peer] = f"{type(error).__name__}: {error}"
                print(f"  {peer} failed at M = {m}: {entry['peer_errors'][peer]}")
        dyq_bytes = qweight.numel() + scales.numel() * 4 + x.numel() * 2 + m * n * 2
        if m == 1:
            entry["dyq_bandwidth_pct_of_copy"] = {
                key: dyq_bytes / ms / 1e6 / copy_gbs * 100 for key, ms in entry["ms"].items() if key.startswith("dyq")}
        entry["tops"] = {key: 2 * m * n * k / ms / 1e9 for key, ms in entry["ms"].items()}
        results.append(entry)
        row = [f"{n}x{k}", str(m)] + [f"{entry['ms'].get(c, float('nan')) * 1e3:9.1f}" for c in COLUMNS]
        if m == 1:
            row.append(f"{entry['dyq_bandwidth_pct_of_copy']['dyq_a4']:5.1f}% BW (a4); a lone eager call: "
                       f"a4 {entry['eager_ms']['dyq_a4'] * 1e3:.1f}, cuBLAS {entry['eager_ms']['cublas_bf16'] * 1e3:.1f}")
        elif m == 512:
            row.append(f"{entry['tops']['dyq_a8']:6.1f} TOPS (a8)")
        table.append(row)
        print("  ".join(row), flush=True)


COLUMNS = tuple(f"dyq_a{bits}" for bits in dyq.VALID_BITS) + ("cublas_bf16", "torch_int4_weight_only") + BITSANDBYTES_PEERS


def graph_flag_switching(m: int, n: int, k: int, layers: int, warmup: int, repeats: int) -> dict:
    """A chain of `layers` flag-routed layers captured once in a CUDA graph and replayed as a control loop
    would: write the pinned flag, replay, synchronize. Times steps under each fixed flag value and steps
    whose flag changes every time (cycling through the widths); the difference is what switching costs.
    Also checks that a replay under each value equals the eager layers at that width."""
    flag = torch.empty(1, dtype=torch.int32, pin_memory=True)
    flag[0] = 16
    chain = []
    for _ in range(layers):
        w = (torch.randn(n, k, device="cuda") * 0.02).to(torch.bfloat16)
        chain.append(torch.ops.dyq.quantize_weight(w, GROUP_SIZE))
    x = torch.randn(m, k, device="cuda").to(torch.bfloat16)

    def forward():
        h = x
        for qweight, scales in chain:
            h = torch.ops.dyq.gemm_with_flag(h, qweight, scales, GROUP_SIZE, flag)
        return h

    graph, captured = dyq.capture_cuda_graph(forward)

    matches = {}
    for bits in dyq.VALID_BITS:
        flag[0] = bits
        graph.replay()
        torch.cuda.synchronize()
        h = x
        for qweight, scales in chain:
            h = torch.ops.dyq.gemm(h, qweight, scales, GROUP_SIZE, bits)
        matches[bits] = bool(torch.equal(captured, h))

    def step_ms(bit_sequence) -> float:
        times = []
        for i, bits in enumerate(bit_sequence):
            start = time.perf_counter()
            flag[0] = bits
            graph.replay()
            torch.cuda.synchronize()
            if i >= warmup:
                times.append((time.perf_counter() - start) * 1e3)
        return statistics.median(times)

    count = warmup + repeats
    fixed = {bits: step_ms([bits] * count) for bits in dyq.VALID_BITS}
    switching = step_ms([dyq.VALID_BITS[i % len(dyq.VALID_BITS)] for i in range(count)])
    return {"m": m, "n": n, "k": k, "layers": layers, "replay_equals_eager": matches,
            "fixed_flag_step_ms": fixed, "switching_flag_step_ms": switching}


def control_step_section(warmup: int, repeats: int, device: str = "cuda", config: dict = HALF_BILLION,
                         prompt: int = 64) -> dict:
    """Whole control steps (a prefill of ``prompt`` tokens, then 7 greedily decoded tokens over a KV cache) of
    bench/decoder_step.py's plain-torch decoder in bf16: torch (cuBLAS) against dyq at each width (the LM head
    in bf16) and bitsandbytes' layers where installed. Eager calls, as a Python control loop makes them: each
    step's wall time to its last token, the device synchronized. Models in turns, each repeat in a shuffled
    order."""
    torch.manual_seed(0)
    bf16 = Decoder(**config).to(device, torch.bfloat16).eval()
    flag = dyq.PrecisionFlag(16, pin_memory=device == "cuda")
    quantized = copy.deepcopy(bf16)
    dyq.quantize_model(quantized, flag=flag)
    models = {"bf16": (None, bf16), **{f"dyq_a{bits}": ((lambda bits=bits: setattr(flag, "bits", bits)), quantized)
                                       for bits in dyq.VALID_BITS}}
    errors = {}
    for peer in BITSANDBYTES_PEERS:
        try:
            model = copy.deepcopy(bf16)
            replace_linear_layers(model, peer)
            models[peer] = (None, model)
        except Exception as error:  # noqa: BLE001  (not installed, or no kernel for this device)
            errors[peer] = f"{type(error).__name__}: {error}"
    prompt_ids = torch.randint(0, config["vocab"], (1, prompt), device=device)
    synchronize = torch.cuda.synchronize if device == "cuda" else (lambda: None)

    def step(model):
        decoder_control_step(model, prompt_ids)
        synchronize()

    candidates = {name: (prepare, lambda model=model: step(model)) for name, (prepare, model) in models.items()}
    step_ms = interleaved_median_ms(candidates, warmup=warmup, repeats=repeats)
    return {"config": config, "parameters": sum(p.numel() for p in bf16.parameters()), "prompt_tokens": prompt,
            "decoded_tokens": 7, "timing": "eager steps in turns, wall time to the last token", "step_ms": step_ms,
            "model_bytes": {name: model_bytes(model) for name, (_, model) in models.items()},
            "peer_errors": errors}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="first shape only, fewer repeats")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    args = parser.parse_args()
    if not torch.cuda.is_available():
        print("bench_cuda: no CUDA device; nothing to time.")
        return 0
    warmup, repeats = (5, 20) if args.quick else (20, 100)
    info = environment()
    copy_gbs = copy_bandwidth_gbs(warmup, repeats)
    print(f"{info['gpu']} (sm_{info['capability'].replace('.', '')}), driver {info['driver']}, "
          f"torch {info['torch']}, CUDA {info['cuda']}; device-to-device copy {copy_gbs:.0f} GB/s")
    print("device time per call in microseconds (median; calls queued back to back, launches not counted)")
    header = ["N x K", "M"] + [f"{c:>9}" for c in COLUMNS]
    print("  ".join(header))
    results, table = [], []
    shapes = SHAPES[:1] if args.quick else SHAPES
    name = re.sub(r"[^A-Za-z0-9]+", "_", info["gpu"]).strip("_").lower()
    probe = bitsandbytes_layers(torch.randn(256, 256, device="cuda").to(torch.bfloat16))
    bitsandbytes = {"version": bitsandbytes_version(), "peers": list(BITSANDBYTES_PEERS) if isinstance(probe, dict) else [],
                    "unavailable": probe if isinstance(probe, str) else None}
    print(f"bitsandbytes: {bitsandbytes['version'] or 'not installed'}"
          + (f" ({bitsandbytes['unavailable']})" if bitsandbytes["unavailable"] else ""))
    report = {"benchmark": "cuda", "environment": info, "bitsandbytes": bitsandbytes, "copy_gbs": copy_gbs, "warmup": warmup,
              "repeats": repeats, "group_size": GROUP_SIZE, "shapes": [list(s) for s in shapes],
              "rows": list(ROWS), "results": results}
    for n, k in shapes:
        bench_shape(n, k, ROWS, warmup, repeats, copy_gbs, results, table)
        path = write_json(args.out / f"cuda_{name}.json", report)  # after each shape: a cut-off run keeps it
    print("CUDA graph of 4 flag-routed 4096 x 4096 layers: write flag, replay, synchronize (median ms per step)")
    report["graph_flag_switching"] = []
    for m in (1, 64):
        entry = graph_flag_switching(m, 4096, 4096, 4, warmup, repeats)
        report["graph_flag_switching"].append(entry)
        fixed = "  ".join(f"a{b} {t:.4f}" for b, t in entry["fixed_flag_step_ms"].items())
        print(f"  M = {m}: fixed flag {fixed}; flag switched every step {entry['switching_flag_step_ms']:.4f}; "
              f"replay equals eager at {entry['replay_equals_eager']}")
    path = write_json(args.out / f"cuda_{name}.json", report)
    try:  # last, and on its own: the kernel tables above are already written
        step = control_step_section(3, 10 if args.quick else 30)
        report["control_step"] = step
        print(f"control step of a {step['parameters'] / 1e9:.2f} B decoder "
              f"(prefill {step['prompt_tokens']}, {step['decoded_tokens']} decoded tokens), eager, median ms: "
              + "  ".join(f"{key} {ms:.2f}" for key, ms in step["step_ms"].items())
              + "".join(f"; {peer}: {error}" for peer, error in step["peer_errors"].items()))
    except Exception as error:  # noqa: BLE001
        report["control_step"] = {"error": f"{type(error).__name__}: {error}"}
        print(f"control step failed: {report['control_step']['error']}")
    path = write_json(args.out / f"cuda_{name}.json", report)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
