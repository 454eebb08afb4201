"""``dyq demo``: quantize a small OpenVLA-shaped policy and run it in a control loop under the dispatcher.

The policy is a Llama backbone built from a config (nothing is downloaded) that, like OpenVLA, reads a
prompt and greedily decodes 7 action tokens from the last 256 ids of its vocabulary. The demo

1. converts every linear layer but the LM head to INT4 (``dyq.quantize_model``) and reports the memory;
2. measures, at each activation precision, how often the quantized policy picks the same action tokens
   as the float policy, and the error of its action logits;
3. replays a synthetic trajectory (coarse transit, fine rotation-heavy manipulation, carry) through
   ``dyq.DyQRuntime``: the dispatcher runs on a worker thread during each step's prefill and publishes
   the bit-width that the 7-token decode then runs at;
4. prints the per-precision step counts, switches, dispatcher cost and the time the model waited.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from ..control.dispatch import DispatchConfig, KinematicDispatcher, synthetic_trajectory
from ..control.flag import PrecisionFlag
from ..control.runtime import DyQRuntime
from ..core.precision import VALID_BITS
from ..core.quantize import quantize_model
from ..sim.policy import cache_keyword
from .usage import int_at_least, output_file, positive_int, require

ACTION_TOKENS = 7
ACTION_BINS = 256


def build_policy(vocab_size: int = 32000, hidden_size: int = 256, layers: int = 4, seed: int = 0):
    """A small Llama with OpenVLA's vocabulary and action-token layout, randomly initialized."""
    from transformers import LlamaConfig, LlamaForCausalLM

    config = LlamaConfig(vocab_size=vocab_size, hidden_size=hidden_size, intermediate_size=hidden_size * 8 // 3 // 128 * 128,
                         num_hidden_layers=layers, num_attention_heads=max(1, hidden_size // 64),
                         num_key_value_heads=max(1, hidden_size // 64), max_position_embeddings=512)
    torch.manual_seed(seed)
    return LlamaForCausalLM(config).eval()


def prefill(model, prompt: torch.Tensor):
    """The prompt through the model: (logits of its last position, the KV cache that the decode extends)."""
    from transformers import DynamicCache

    cache = DynamicCache()
    with torch.inference_mode():
        out = model(prompt, use_cache=True, **{cache_keyword(): cache})
    return out.logits[:, -1], cache


def decode_actions(model, prompt: torch.Tensor, prefilled=None) -> torch.Tensor:
    """Greedy decode of 7 action tokens, restricted to the action bins (OpenVLA's last 256 ids).

    ``prefilled`` is :func:`prefill` of ``prompt`` when the caller already ran it."""
    vocab = model.config.vocab_size
    keyword = cache_keyword()
    logits, cache = prefill(model, prompt) if prefilled is None else prefilled
    tokens = []
    with torch.inference_mode():
        for _ in range(ACTION_TOKENS):
            token = logits[:, vocab - ACTION_BINS:].argmax(dim=-1, keepdim=True) + vocab - ACTION_BINS
            tokens.append(token)
            logits = model(token, use_cache=True, **{keyword: cache}).logits[:, -1]  # the cache grows in place
    return torch.cat(tokens, dim=1)


def action_logits(model, prompts: torch.Tensor) -> torch.Tensor:
    with torch.inference_mode():
        return model(prompts).logits[:, -1, -ACTION_BINS:].float()


def run(steps: int = 80, prompt_tokens: int = 48, seed: int = 0, json_path: str | None = None) -> dict:
    torch.manual_seed(seed)
    float_policy = build_policy(seed=seed)
    policy = build_policy(seed=seed)
    flag = PrecisionFlag(16)
    report = quantize_model(policy, group_size=128, flag=flag)
    print(report)

    # 1) Fidelity of each precision against the float policy.
    gen = torch.Generator().manual_seed(seed + 1)
    prompts = torch.randint(0, policy.config.vocab_size - ACTION_BINS, (8, prompt_tokens), generator=gen)
    reference_logits = action_logits(float_policy, prompts)
    reference_tokens = decode_actions(float_policy, prompts)
    fidelity = {}
    for bits in VALID_BITS[::-1]:
        flag.bits = bits
        logits = action_logits(policy, prompts)
        tokens = decode_actions(policy, prompts)
        fidelity[bits] = {
            "action_logit_rel_error": ((logits - reference_logits).norm() / reference_logits.norm()).item(),
            "action_token_agreement": (tokens == reference_tokens).float().mean().item(),
        }
    print("\nprecision  action-logit error vs float  action tokens equal to float")
    for bits, f in fidelity.items():
        name = "W4A16" if bits == 16 else f"W4A{bits}"
        print(f"{name:>9}  {100 * f['action_logit_rel_error']:26.2f} %  {100 * f['action_token_agreement']:27.1f} %")
    print("(the policy is randomly initialized, so its action logits are nearly flat and the INT4 weights alone\n"
          " change many argmax choices; the logit error is the steadier measure of each precision)")

    # 2) A control loop under the dispatcher.
    trajectory = synthetic_trajectory(steps, seed)
    flag.bits = 16
    dispatcher = KinematicDispatcher(DispatchConfig())
    step_ms = {bits: [] for bits in VALID_BITS}
    with DyQRuntime(dispatcher, flag) as runtime:
        previous = None
        for t in range(steps):
            prompt = torch.randint(0, policy.config.vocab_size - ACTION_BINS, (1, prompt_tokens), generator=gen)
            start = time.perf_counter()

            runtime.step(previous, lambda: prefill(policy, prompt),
                         lambda prefilled: decode_actions(policy, prompt, prefilled=prefilled))
            step_ms[runtime.stats[-1].bits].append((time.perf_counter() - start) * 1e3)
            previous = trajectory[t]
        summary = runtime.summary()

    print(f"\ncontrol loop: {steps} steps of prefill ({prompt_tokens} tokens) + {ACTION_TOKENS} decoded action tokens")
    print("bits  steps  median step ms")
    for bits in VALID_BITS:
        times = step_ms[bits]
        median = f"{statistics.median(times):15.1f}" if times else f"{'-':>15}"
        print(f"{bits:>4}  {len(times):5d}  {median}")
    print(f"switches {summary['switches']}, mean bits {summary['mean_bits']:.2f}, "
          f"dispatcher {summary['dispatcher_us_median']:.1f} us median, "
          f"model waited {summary['wait_us_median']:.1f} us median ({summary['wait_us_max']:.1f} us max)")

    result = {
        "converted_layers": len(report.converted),
        "linear_bytes_before": report.linear_bytes_before,
        "linear_bytes_after": report.linear_bytes_after,
        "fidelity": {str(b): f for b, f in fidelity.items()},
        "control_loop": {k: v for k, v in summary.items() if k != "steps_per_bits"}
        | {"steps_per_bits": {str(b): n for b, n in summary["steps_per_bits"].items()}},
        "median_step_ms": {str(b): statistics.median(v) for b, v in step_ms.items() if v},
    }
    if json_path:
        with open(json_path, "w", encoding="utf-8") as f:
            json.dump(result, f, indent=2)
        print(f"\nwrote {json_path}")
    return result


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # The synthetic trajectory needs 10 steps (control.dispatch.synthetic_trajectory).
    parser.add_argument("--steps", type=int_at_least(10), default=80, help="control steps in the loop (default 80)")
    parser.add_argument("--prompt-tokens", type=positive_int, default=48, help="prompt length of each step (default 48)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=output_file(".json"), help="also write the results as JSON")


def main(args: argparse.Namespace) -> int:
    require("transformers", "dyq demo (its Llama policy)")
    run(steps=args.steps, prompt_tokens=args.prompt_tokens, seed=args.seed, json_path=args.json)
    return 0
