"""The CPU benchmarks run end to end on tiny settings and write the JSON their docstrings promise.

Only the structure is checked (every row, every peer, positive medians, the kernel each call ran): speed
is measured by the benchmarks themselves, never asserted in a test.
"""
import json
import subprocess
import sys
from pathlib import Path

import pytest

import dyq

ROOT = Path(__file__).resolve().parents[1]


def run_bench(script: str, *args: str) -> None:
    subprocess.run([sys.executable, str(ROOT / "bench" / script), *args], check=True, cwd=ROOT,
                   stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=600)


def test_bench_linear_times_every_peer_and_width(tmp_path):
    out = tmp_path / "linear.json"
    run_bench("bench_linear.py", "--shape", "256x512", "--batches", "1", "8", "--threads", "1", "--modes", "hot",
              "--repeats", "2", "--out", str(out))
    result = json.loads(out.read_text())
    assert result["environment"]["cpu_isa"] == dyq.cpu_info()["isa"]
    assert result["dyq_input_dtype"] == "bfloat16"
    (run,) = result["runs"]
    assert run["threads"] == 1 and run["stream_read_gbps"] > 0
    assert [(r["m"], r["n"], r["k"], r["mode"]) for r in run["results"]] == [(1, 256, 512, "hot"), (8, 256, 512, "hot")]
    for r in run["results"]:
        assert set(r["median_ms"]) >= {"fp32", "bf16", "int8_dynamic", "w4a16", "w4a8", "w4a4", "w4a2"}
        assert all(t > 0 for t in r["median_ms"].values())
        assert r["dyq_kernel"]["w4a8"] == dyq.cpu_gemm_kernel(r["m"], r["k"], 128, 8)


def test_bench_policy_step_times_a_control_step_at_every_width(tmp_path):
    pytest.importorskip("transformers")
    out = tmp_path / "step.json"
    run_bench("bench_policy_step.py", "--config", "policy", "--prompt", "8", "--repeats", "1", "--threads", "1",
              "--out", str(out))
    result = json.loads(out.read_text())
    (step,) = result["results"]
    # dyq on the bf16 and the fp32 model where the CPU computes in bf16, on the fp32 one elsewhere.
    expected_bases = ["bf16", "fp32"] if dyq.cpu_info()["isa"] in ("avx512_bf16", "amx") else ["fp32"]
    assert step["dyq_base_dtypes"] == expected_bases
    dyq_labels = {f"w4a{bits}/{base}" for bits in (16, 8, 4, 2) for base in expected_bases}
    labels = {"fp32", "bf16"} | dyq_labels
    assert set(step["step_ms"]) == labels and set(step["prefill_ms"]) == labels
    assert all(t > 0 for t in [*step["step_ms"].values(), *step["prefill_ms"].values()])
    assert step["prompt_tokens"] == 8 and step["decoded_tokens"] == 7
    assert step["prefill_logits"] == "last position"
    assert set(step["dyq_gemm_share"]) == dyq_labels
    assert all(0 < share < 1 for share in step["dyq_gemm_share"].values())
    # Every model's step split into the same parts, each a time, the linear layers and attention never empty.
    breakdown = step["step_breakdown_ms"]
    assert set(breakdown) == labels
    for label, parts in breakdown.items():
        assert set(parts) == {"linear layers", "LM head", "attention", "MLP activation", "norms", "embeddings",
                              "layers' own code", "outside the modules"}
        assert all(ms >= 0 for ms in parts.values())
        assert parts["linear layers"] > 0 and parts["attention"] > 0 and parts["LM head"] > 0
    for label, share in step["dyq_gemm_share"].items():
        assert share == pytest.approx(breakdown[label]["linear layers"] / sum(breakdown[label].values()))
    assert step["dyq_kernel"]["w4a2/fp32"]["decode"] == dyq.cpu_gemm_kernel(1, step["settings"]["hidden_size"], 128, 2)
    # Memory from the config alone: every linear but the LM head becomes INT4 codes (half a byte a weight)
    # and one fp32 scale per 128 inputs; the rest stays in the base dtype.
    settings = step["settings"]
    hidden, inner, layers = settings["hidden_size"], settings["intermediate_size"], settings["num_hidden_layers"]
    linears = [(hidden, hidden)] * 4 + [(inner, hidden)] * 2 + [(hidden, inner)]
    linear_weights = layers * sum(n * k for n, k in linears)
    int4_bytes = layers * sum(n * k // 2 + n * -(-k // 128) * 4 for n, k in linears)
    memory = step["model_bytes"]
    other_fp32 = memory["fp32"] - 4 * linear_weights  # embeddings, norms, LM head, rotary buffers
    assert other_fp32 > 0
    assert memory["bf16"] == 2 * linear_weights + other_fp32 // 2
    for base in expected_bases:
        assert memory[f"dyq/{base}"] == int4_bytes + other_fp32 // 4 * (2 if base == "bf16" else 4)


def test_bench_cuda_without_a_gpu_says_so_and_exits_cleanly():
    if torch_cuda_available():
        pytest.skip("a GPU is here: bench_cuda.py runs in scripts/device_check.sh")
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "bench_cuda.py"), "--quick"], check=True, cwd=ROOT,
                         capture_output=True, text=True, timeout=300).stdout
    assert "no CUDA device; nothing to time" in out


def torch_cuda_available() -> bool:
    import torch

    return torch.cuda.is_available()


def test_bitsandbytes_peers_compute_the_layer_they_quantize():
    """The peers of bench_cuda.py and bench_linear.py --bitsandbytes, on the CPU: each computes x W^T within
    its format's error (NF4 is 4-bit, LLM.int8() 8-bit), on its own input dtype."""
    pytest.importorskip("bitsandbytes")
    import torch

    sys.path.insert(0, str(ROOT / "bench"))
    try:
        from bitsandbytes_peers import INPUT_DTYPES, PEERS, bitsandbytes_layers
    finally:
        sys.path.pop(0)
    generator = torch.Generator().manual_seed(3)
    weight = (torch.randn(192, 256, generator=generator) * 0.02).bfloat16()
    x = torch.randn(5, 256, generator=generator)
    layers = bitsandbytes_layers(weight)
    assert set(layers) == set(PEERS), layers
    expected = x.double() @ weight.double().T
    for peer, bound in (("bnb_nf4", 0.15), ("bnb_int8", 0.02)):
        with torch.inference_mode():
            y = layers[peer](x.to(INPUT_DTYPES[peer]))
        assert y.shape == (5, 192) and y.dtype == INPUT_DTYPES[peer]
        rel = ((y.double() - expected).norm() / expected.norm()).item()
        assert 1e-4 < rel < bound, (peer, rel)  # quantized (not the float layer), and within the format's error


def test_bench_linear_times_bitsandbytes_when_asked(tmp_path):
    pytest.importorskip("bitsandbytes")
    out = tmp_path / "linear.json"
    run_bench("bench_linear.py", "--shape", "256x512", "--batches", "1", "--threads", "1", "--modes", "hot",
              "--repeats", "2", "--bitsandbytes", "--out", str(out))
    result = json.loads(out.read_text())
    assert result["peers"][-2:] == ["bnb_nf4", "bnb_int8"] and result["bitsandbytes"]
    (r,) = result["runs"][0]["results"]
    assert r["median_ms"]["bnb_nf4"] > 0 and r["median_ms"]["bnb_int8"] > 0
    assert 0 < r["weight_bytes"]["bnb_nf4"] < r["weight_bytes"]["bnb_int8"] < r["weight_bytes"]["bf16"]


def test_bench_policy_step_times_the_bitsandbytes_models_when_asked(tmp_path):
    pytest.importorskip("transformers")
    pytest.importorskip("bitsandbytes")
    out = tmp_path / "step.json"
    run_bench("bench_policy_step.py", "--config", "policy", "--prompt", "8", "--repeats", "1", "--threads", "1",
              "--dyq-base", "fp32", "--bitsandbytes", "--out", str(out))
    result = json.loads(out.read_text())
    assert result["bitsandbytes"]
    (step,) = result["results"]
    for peer in ("bnb_nf4", "bnb_int8"):
        assert step["step_ms"][peer] > 0 and step["prefill_ms"][peer] > 0
        assert step["step_breakdown_ms"][peer]["linear layers"] > 0
    # NF4 below LLM.int8() below bf16: the statistics kept outside the layers' parameters are counted.
    memory = step["model_bytes"]
    assert memory["dyq/fp32"] < memory["bf16"] and memory["bnb_nf4"] < memory["bnb_int8"] < memory["bf16"]


def test_bench_cuda_control_step_section_runs_its_models_on_the_cpu():
    """bench_cuda.py's control-step section (a plain-torch decoder, no transformers on a GPU machine), run here
    on the CPU at a small size: every model times a step, dyq's at each width, and the decoder's cached decode
    is the full recompute's."""
    import torch

    sys.path.insert(0, str(ROOT / "bench"))
    try:
        import bench_cuda
        import decoder_step
    finally:
        sys.path.remove(str(ROOT / "bench"))
    config = {"hidden": 256, "layers": 2, "heads": 4, "mlp": 512, "vocab": 300}
    result = bench_cuda.control_step_section(0, 2, device="cpu", config=config, prompt=16)
    expected = {"bf16", *(f"dyq_a{bits}" for bits in dyq.VALID_BITS)}
    assert expected <= set(result["step_ms"]) and all(ms > 0 for ms in result["step_ms"].values())
    assert set(result["step_ms"]) - expected == set(bench_cuda.BITSANDBYTES_PEERS) - set(result["peer_errors"])
    assert result["model_bytes"]["dyq_a8"] < result["model_bytes"]["bf16"]
    torch.manual_seed(0)
    model = decoder_step.Decoder(**config).eval()
    ids = torch.randint(0, 300, (1, 16))
    tokens = decoder_step.control_step(model, ids)
    sequence = ids
    with torch.inference_mode():
        for _ in range(7):
            token = model(sequence, model.new_cache(), 0).argmax(-1)
            sequence = torch.cat([sequence, token], dim=1)
    assert torch.equal(tokens, sequence[:, 16:])
