"""Hadamard rotation (dyq.rotation): orthogonal, exact in float on a Llama model, spreads outliers, and
survives save and load."""
import copy

import pytest
import torch

import dyq
from dyq.rotation import OnlineRotation, hadamard_matrix, rotate_llama

transformers = pytest.importorskip("transformers")


def outlier_llama(seed=0, tied=True):
    """Sizes that are not powers of two (48 = 4 x 12, 96 = 8 x 12, head_dim 12), grouped-query attention,
    norm weights away from 1, and an outlier channel in the residual stream."""
    torch.manual_seed(seed)
    config = transformers.LlamaConfig(vocab_size=200, hidden_size=48, intermediate_size=96, num_hidden_layers=2,
                                      num_attention_heads=4, num_key_value_heads=2, max_position_embeddings=64,
                                      tie_word_embeddings=tied)
    model = transformers.LlamaForCausalLM(config).eval()
    with torch.no_grad():
        for name, p in model.named_parameters():
            if "norm" in name:
                p.uniform_(0.5, 1.5)
        model.model.embed_tokens.weight[:, 7] *= 40
    return model


@pytest.mark.parametrize("n", [1, 2, 12, 20, 28, 36, 48, 64, 576, 960, 1536])
def test_hadamard_matrices_are_hadamard(n):
    h = hadamard_matrix(n)
    assert h is not None and h.shape == (n, n)
    assert torch.equal(h.abs(), torch.ones(n, n))
    assert torch.equal(h @ h.T, n * torch.eye(n, dtype=torch.float64))


@pytest.mark.parametrize("n", [12, 96, 576, 7, 22])
def test_online_rotation_is_orthogonal_and_applies_its_matrix(n):
    """7 and 22 have no Hadamard construction here: the fallback is a random orthogonal matrix."""
    rotation = OnlineRotation(n, seed=3)
    r = rotation.matrix()
    torch.testing.assert_close(r @ r.T, torch.eye(n, dtype=torch.float64), rtol=0, atol=1e-12)
    if hadamard_matrix(n) is not None:  # every entry +-1/sqrt(n): an outlier is spread over all channels
        torch.testing.assert_close(r.abs(), torch.full((n, n), n ** -0.5, dtype=torch.float64))
    x = torch.randn(3, 5, n, dtype=torch.float64)
    torch.testing.assert_close(rotation(x), x @ r, rtol=0, atol=1e-12)


@pytest.mark.parametrize("tied", [True, False])
def test_rotated_float_model_computes_the_same_function(tied):
    model = outlier_llama(tied=tied)
    ids = torch.randint(0, 200, (2, 19))
    with torch.no_grad():
        expected = model(ids).logits
        rotated = copy.deepcopy(model)
        assert rotate_llama(rotated, seed=5) == {"kind": "hadamard", "seed": 5}
        got = rotated(ids).logits
    # fp32 rounding of sums of about a hundred terms, relative to the logits' scale.
    torch.testing.assert_close(got, expected, rtol=0, atol=2e-5 * expected.abs().max().item())
    assert rotated.lm_head.weight is not rotated.model.embed_tokens.weight
    assert torch.equal(rotated.model.norm.weight, torch.ones(48))


def test_the_online_rotation_runs_the_hadamard_kernel(monkeypatch):
    """down_proj's input (96 = 12 x 8) is rotated by dyq.ops.hadamard_transform, once per layer and call;
    float64 inputs and sizes without a Hadamard construction take the two torch matrix products."""
    calls = []
    kernel = dyq.ops.hadamard_transform
    monkeypatch.setattr(dyq.ops, "hadamard_transform", lambda *args: calls.append(args[0].shape) or kernel(*args))
    model = outlier_llama()
    rotate_llama(model)
    with torch.no_grad():
        model(torch.randint(0, 200, (2, 7)))
    assert calls == [(2, 7, 96)] * 2
    calls.clear()
    OnlineRotation(96)(torch.randn(3, 96, dtype=torch.float64))
    OnlineRotation(22)(torch.randn(3, 22))
    assert calls == []


def test_rotation_spreads_the_outlier_channel():
    model = outlier_llama()
    rotated = copy.deepcopy(model)
    rotate_llama(rotated)
    ids = torch.randint(0, 200, (2, 16))
    seen = {}

    def peak_to_rms(key):
        def hook(_module, inputs):
            x = inputs[0]
            seen[key] = (x.abs().amax(-1) / x.pow(2).mean(-1).sqrt()).mean().item()
        return hook

    for key, m in (("plain", model), ("rotated", rotated)):
        handle = m.model.layers[1].self_attn.q_proj.register_forward_pre_hook(peak_to_rms(key))
        with torch.no_grad():
            m(ids)
        handle.remove()
    assert seen["rotated"] < 0.5 * seen["plain"]


def test_a_rotated_quantized_model_saves_and_loads(tmp_path):
    model, flag = outlier_llama(), dyq.PrecisionFlag(4)
    rotate_llama(model, seed=1)
    dyq.quantize_model(model, group_size=32, flag=flag, method="mse")
    dyq.save_quantized(model, tmp_path)
    fresh = transformers.LlamaForCausalLM(outlier_llama().config)
    loaded = dyq.load_quantized(fresh, tmp_path)
    assert loaded.dyq_rotation == {"kind": "hadamard", "seed": 1}
    ids = torch.randint(0, 200, (1, 11))
    with torch.no_grad():
        torch.testing.assert_close(loaded(ids).logits, model(ids).logits)


def test_bad_arguments_are_refused_by_name():
    with pytest.raises(ValueError, match="seed must be"):
        rotate_llama(outlier_llama(), seed=-1)
    with pytest.raises(ValueError, match="model must be a Hugging Face Llama-style"):
        rotate_llama(torch.nn.Linear(4, 4))
    rotated = outlier_llama()
    rotate_llama(rotated)
    with pytest.raises(ValueError, match="already rotated"):
        rotate_llama(rotated)
    quantized = outlier_llama()
    dyq.quantize_model(quantized, group_size=32)
    with pytest.raises(ValueError, match="before quantize_model"):
        rotate_llama(quantized)
    with pytest.raises(ValueError, match="n must be an int"):
        OnlineRotation(0)
