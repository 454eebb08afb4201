"""One OpenVLA-style control step on the CPU: a prefill of the prompt, then 7 greedily decoded action
tokens, each one forward with the KV cache, for torch fp32 and bf16 against dyq at every width.

Two Llama configs with random weights (transformers' LlamaConfig, nothing downloaded): the closed-loop
policy's (python/dyq/sim/policies/*/policy.json) and one of about 0.5 B parameters. The prefill computes
the logits of its last position only (``logits_to_keep=1`` where transformers has it), as ``generate`` and
dyq's own policy do: the first action token needs no others.

dyq runs ``dyq.quantize_model`` on a copy of the model in a base dtype (its LM head and everything outside
the linear layers stay in that dtype; its RMSNorm layers run through dyq's fused norm, as quantize_model does
by default, and ``dyq_fused_norms`` counts them) and then sets the width with ``dyq.set_precision``; the label
``w4a8/bf16`` is W4A8 on the bf16 model. Where the CPU computes in bf16 (dyq's ``avx512_bf16`` and ``amx``
paths) dyq is timed on both bases: on the bf16 one, as in the bf16 baseline, and on the fp32 one, as dyq's
own policy runs (what dyq leaves alone is then computed in fp32: torch's bf16 attention over one query is
slower than its fp32 one, but the fp32 embeddings and LM head read twice the bytes). Elsewhere only on fp32:
on a CPU without bf16 dot products oneDNN emulates bf16, and a user would not run the rest of the model in it
(``--dyq-base`` chooses). The models are timed in turns (each repeat runs every one once, in a shuffled
order), so that a drift of a shared machine reaches all of them alike, first the whole steps and then the
prefills alone.
Beside the median step times, instrumented steps (forward hooks around every module, up to 5 per model, in
turns) split each model's step into its parts (``step_breakdown_ms``): the linear layers (dyq's GEMMs, or
torch's), the LM head, attention (its own code: rotary position, the KV cache, scaled dot-product
attention), the MLP's activation, the norms, the embeddings, the layers' and the model's own code, and the
time outside every module; ``dyq_gemm_share`` is the linear layers' share of dyq's instrumented step. Each
model's memory is the bytes of its parameters and buffers (``model_bytes``): dyq's holds the INT4 codes,
their fp32 scales and the parts it does not convert (embeddings, norms, the LM head) in its base dtype.

    python bench/bench_policy_step.py                  # both configs
    python bench/bench_policy_step.py --config policy --prompt 256
    python bench/bench_policy_step.py --config policy --prompt 16 --repeats 1 --out /tmp/step.json  # smoke

With ``--bitsandbytes`` the bf16 model is also timed with every linear layer but the LM head replaced by
bitsandbytes' NF4 (``bnb_nf4``) and LLM.int8() (``bnb_int8``) layers, as ``load_in_4bit`` and
``load_in_8bit`` would (bench/bitsandbytes_peers.py); their ``model_bytes`` count the statistics those layers
keep outside their parameters.
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import statistics
import time
from pathlib import Path

import torch

import dyq
from dyq.results import environment, interleaved_median_ms, print_table, write_json
from dyq.sim.policy import cached_forward

from bitsandbytes_peers import PEERS as BITSANDBYTES_PEERS, bitsandbytes_version, model_bytes, \
    replace_linear_layers

ACTION_TOKENS = 7
BITS = [16, 8, 4, 2]
BF16_PATHS = ("avx512_bf16", "amx")  # dyq's CPU paths whose CPUs have bf16 dot products


def policy_config() -> dict:
    path = sorted((Path(dyq.__file__).parent / "sim" / "policies").glob("*/policy.json"))[0]
    config = json.loads(path.read_text())
    return {"hidden_size": config["hidden_size"], "intermediate_size": config["intermediate_size"],
            "num_hidden_layers": config["layers"], "num_attention_heads": config["heads"], "vocab_size": 512,
            "source": str(path.relative_to(Path(dyq.__file__).parent))}


CONFIGS = {
    "policy": policy_config,
    # About 0.5 B parameters: 20 layers of hidden 1280, MLP 3456, a 32000-token vocabulary.
    "0.5b": lambda: {"hidden_size": 1280, "intermediate_size": 3456, "num_hidden_layers": 20,
                     "num_attention_heads": 20, "vocab_size": 32000},
}
DEFAULT_PROMPT = {"policy": 256, "0.5b": 64}


def build_model(settings: dict, prompt: int):
    from transformers import LlamaConfig, LlamaForCausalLM

    fields = {key: value for key, value in settings.items() if key != "source"}
    config = LlamaConfig(**fields, num_key_value_heads=fields["num_attention_heads"],
                         max_position_embeddings=prompt + ACTION_TOKENS + 8, tie_word_embeddings=False)
    torch.manual_seed(0)
    return LlamaForCausalLM(config).eval()


def prefill(model, prompt_ids: torch.Tensor):
    """The prompt's forward into a new KV cache (as in dyq's policy); returns the output and the cache."""
    return cached_forward(model, prompt_ids)


def control_step(model, prompt_ids: torch.Tensor) -> torch.Tensor:
    out, cache = prefill(model, prompt_ids)
    token = out.logits[:, -1:].argmax(-1)
    tokens = []
    for _ in range(ACTION_TOKENS):
        out, cache = cached_forward(model, token, cache)
        token = out.logits[:, -1:].argmax(-1)
        tokens.append(token)
    return torch.cat(tokens, dim=1)


PARTS = ("linear layers", "LM head", "attention", "MLP activation", "norms", "embeddings", "layers' own code",
         "outside the modules")


def part_of(name: str, module) -> str | None:
    """The part of the step a module's own time counts towards (None: its parent's)."""
    kind = type(module).__name__
    if name.endswith("lm_head"):
        return "LM head"
    if isinstance(module, (dyq.DyQLinear, torch.nn.Linear)):
        return "linear layers"
    if kind.endswith("Attention"):
        return "attention"
    if kind.endswith("MLP"):
        return "MLP activation"
    if kind.endswith("RMSNorm"):
        return "norms"
    if isinstance(module, torch.nn.Embedding) or kind.endswith("RotaryEmbedding"):
        return "embeddings"
    if kind.endswith(("DecoderLayer", "Model", "ForCausalLM")):
        return "layers' own code"
    return None


def step_breakdown(model, step) -> dict[str, float]:
    """Milliseconds of one step by part, from forward hooks around every module: each module's own time
    (its wall time less its children's) counts towards its part, a module of no part's towards its
    parent's, and the step's time outside every module (sampling the token, the cache's bookkeeping between
    calls) is "outside the modules". The hooks' own cost falls mostly on the parents ("layers' own code"),
    so the parts add up to the instrumented step, a little longer than an uninstrumented one; "linear
    layers" are dyq's GEMMs (DyQLinear) or torch's nn.Linear, the LM head apart."""
    own = dict.fromkeys(PARTS, 0.0)
    stack = []  # [part, start, children's time]

    def before(part):
        def hook(module, _):
            stack.append([part, time.perf_counter(), 0.0])
        return hook

    def after(module, _, __):
        part, start, children = stack.pop()
        spent = time.perf_counter() - start
        if stack:
            stack[-1][2] += spent
        own[part] += spent - children

    handles = []
    for name, module in model.named_modules():
        part = part_of(name, module)
        if part is None:  # its time stays with the parent
            continue
        handles += [module.register_forward_pre_hook(before(part)), module.register_forward_hook(after)]
    try:
        start = time.perf_counter()
        step()
        total = time.perf_counter() - start
    finally:
        for handle in handles:
            handle.remove()
    own["outside the modules"] = total - sum(own.values())
    return {part: 1e3 * seconds for part, seconds in own.items()}


def default_dyq_bases() -> list[str]:
    return ["bf16", "fp32"] if dyq.cpu_info()["isa"] in BF16_PATHS else ["fp32"]


def dyq_label(bits: int, base: str) -> str:
    """dyq at ``bits`` on the model in ``base``, e.g. ``w4a8/bf16``."""
    return f"w4a{bits}/{base}"


def time_config(name: str, prompt: int, repeats: int, dyq_bases: list[str], bitsandbytes: bool = False) -> dict:
    settings = CONFIGS[name]()
    fp32 = build_model(settings, prompt)
    parameters = sum(p.numel() for p in fp32.parameters())
    bf16 = copy.deepcopy(fp32).to(torch.bfloat16)
    quantized = {base: copy.deepcopy(bf16 if base == "bf16" else fp32) for base in dyq_bases}
    fused_norms = {base: len(dyq.quantize_model(model).fused_norms) for base, model in quantized.items()}
    peers = {peer: copy.deepcopy(bf16) for peer in (BITSANDBYTES_PEERS if bitsandbytes else ())}
    for peer, model in peers.items():
        replace_linear_layers(model, peer)
    memory = {"fp32": model_bytes(fp32), "bf16": model_bytes(bf16),
              **{f"dyq/{base}": model_bytes(model) for base, model in quantized.items()},
              **{peer: model_bytes(model) for peer, model in peers.items()}}
    prompt_ids = torch.randint(3, settings["vocab_size"], (1, prompt))
    # Every model in turns (interleaved_median_ms), dyq's widths each set right before its call.
    models = {"fp32": (None, fp32), "bf16": (None, bf16), **{peer: (None, model) for peer, model in peers.items()}}
    for base, model in quantized.items():
        for bits in BITS:
            models[dyq_label(bits, base)] = ((lambda bits=bits, model=model: dyq.set_precision(model, bits)), model)

    def candidates(run):
        return {label: (prepare, lambda model=model: run(model, prompt_ids))
                for label, (prepare, model) in models.items()}

    shares, kernels, breakdowns = {}, {}, {}
    with torch.inference_mode():
        timings = interleaved_median_ms(candidates(control_step), warmup=1, repeats=repeats)
        prefill_ms = interleaved_median_ms(candidates(prefill), warmup=1, repeats=repeats)
        # The instrumented passes: each model's median part by part over a few steps, in turns.
        passes = {label: [] for label in models}
        for _ in range(max(1, min(repeats, 5))):
            for label, (prepare, model) in models.items():
                if prepare is not None:
                    prepare()
                passes[label].append(step_breakdown(model, lambda model=model: control_step(model, prompt_ids)))
        for label, runs in passes.items():
            breakdowns[label] = {part: statistics.median(run[part] for run in runs) for part in PARTS}
        for base in dyq_bases:
            for bits in BITS:
                label = dyq_label(bits, base)
                shares[label] = breakdowns[label]["linear layers"] / sum(breakdowns[label].values())
                kernels[label] = {"prefill": dyq.cpu_gemm_kernel(prompt, settings["hidden_size"], 128, bits),
                                  "decode": dyq.cpu_gemm_kernel(1, settings["hidden_size"], 128, bits)}
    return {"config": name, "settings": settings, "parameters": parameters, "prompt_tokens": prompt,
            "decoded_tokens": ACTION_TOKENS, "prefill_logits": "last position", "dyq_base_dtypes": dyq_bases,
            "timing": "interleaved: each repeat runs every model once, in a shuffled order",
            "step_ms": timings, "prefill_ms": prefill_ms, "dyq_gemm_share": shares, "step_breakdown_ms": breakdowns,
            "dyq_kernel": kernels, "dyq_fused_norms": fused_norms, "model_bytes": memory}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", choices=sorted(CONFIGS), action="append", help="configs to run (repeatable)")
    parser.add_argument("--prompt", type=int, help="prompt tokens (default: 256 for policy, 64 for 0.5b)")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--dyq-base", choices=["bf16", "fp32"], action="append",
                        help="dtype of the model dyq converts (repeatable; default: both on CPUs with bf16 dot "
                             "products, else fp32)")
    parser.add_argument("--bitsandbytes", action="store_true",
                        help="also time the bf16 model on bitsandbytes' NF4 and LLM.int8() layers")
    parser.add_argument("--out", default="policy_step_cpu.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()
    dyq_bases = list(dict.fromkeys(args.dyq_base)) if args.dyq_base else default_dyq_bases()
    results = [time_config(name, args.prompt or DEFAULT_PROMPT[name], args.repeats, dyq_bases, args.bitsandbytes)
               for name in args.config or ["policy", "0.5b"]]
    peers = list(BITSANDBYTES_PEERS) if args.bitsandbytes else []
    labels = ["fp32", "bf16"] + peers + [dyq_label(b, base) for base in dyq_bases for b in BITS]
    rows = []
    for r in results:
        for label in labels:
            step, pre = r["step_ms"][label], r["prefill_ms"][label]
            share = r["dyq_gemm_share"].get(label)
            memory = r["model_bytes"]["dyq/" + label.split("/")[1] if label.startswith("w4a") else label]
            rows.append([f"{r['config']} ({r['parameters'] / 1e6:.0f} M)", r["prompt_tokens"], label, f"{step:.1f}",
                         f"{pre:.1f}", f"{step - pre:.1f}", f"{r['step_ms']['fp32'] / step:.2f}x",
                         f"{r['step_ms']['bf16'] / step:.2f}x",
                         "" if share is None else f"{100 * share:.0f} %", f"{memory / 2**20:.1f}"])
    print_table(["config", "prompt", "model", "step ms", "prefill ms", "decode ms", "fp32 / this", "bf16 / this",
                 "in dyq GEMMs", "model MiB"],
                rows, title=f"One control step (prefill + {ACTION_TOKENS} decoded tokens), {args.threads} thread(s), "
                            f"w4aB/base: dyq at B bits on the model in that dtype, CPU path {dyq.cpu_info()['isa']}")
    rows = [[r["config"], label, *(f"{r['step_breakdown_ms'][label][part]:.1f}" for part in PARTS),
             f"{sum(r['step_breakdown_ms'][label].values()):.1f}"]
            for r in results for label in labels]
    print()
    print_table(["config", "model", *PARTS, "instrumented step"], rows,
                title="Where one step's time goes (ms, median of instrumented steps; each module's own time)")
    load_after = os.getloadavg()
    print(f"load average (1, 5, 15 min): {load_before} before, {load_after} after")
    path = write_json(args.out, {"benchmark": "policy_step_cpu", "environment": environment(),
                                 "threads": args.threads, "bitsandbytes": bitsandbytes_version() if peers else None,
                                 "load_average_before": load_before,
                                 "load_average_after": load_after, "results": results})
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
