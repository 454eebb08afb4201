"""Hadamard rotation (dyq.rotation): orthogonal, exact in float on a Llama model, spreads outliers, and
survives save and load."""
import copy
import json

import pytest
import torch

import dyq
from dyq.rotation import HADAMARD_CONSTRUCTION, OnlineRotation, _jacobsthal, hadamard_factors, hadamard_matrix, rotate_llama

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


@pytest.mark.parametrize("n", [1, 2, 12, 20, 28, 36, 48, 52, 64, 576, 688, 960, 1536])
def test_hadamard_matrices_are_hadamard(n):
    h = hadamard_matrix(n)
    assert h is not None and h.shape == (n, n)
    assert torch.equal(h.abs(), torch.ones(n, n))
    assert torch.equal(h @ h.T, n * torch.eye(n, dtype=torch.float64))


@pytest.mark.parametrize("q", [3, 5, 9, 25, 27, 49, 81, 125, 343])
def test_jacobsthal_matrices_over_prime_power_fields(q):
    """The defining properties of the Jacobsthal matrix of GF(q), which make Paley's constructions Hadamard:
    Q Q^T = q I - J, zero row sums, a zero diagonal, symmetric for q = 1 mod 4 and antisymmetric for 3 mod 4."""
    jacobsthal = _jacobsthal(q)
    ones = torch.ones(q, q, dtype=torch.float64)
    assert torch.equal(jacobsthal @ jacobsthal.T, q * torch.eye(q, dtype=torch.float64) - ones)
    assert torch.equal(jacobsthal.sum(1), torch.zeros(q, dtype=torch.float64))
    assert torch.equal(jacobsthal.diagonal(), torch.zeros(q, dtype=torch.float64))
    assert torch.equal(jacobsthal.T, jacobsthal if q % 4 == 1 else -jacobsthal)


def test_prime_power_fields_shrink_the_dense_factor():
    """Llama-2-7B's intermediate 11008 = 32 * (7^3 + 1): a dense factor of order 344, where prime fields alone
    (construction 1) leave 2 * 5504. 52 (= 2 (5^2 + 1)) and 688 (= 2 * 344) have no prime-field split."""
    left, right = hadamard_factors(11008)
    assert (left.shape[0], right.shape[0]) == (344, 32)
    assert torch.equal(left @ left.T, 344 * torch.eye(344, dtype=torch.float64))
    assert hadamard_factors(52, construction=1) is None and hadamard_factors(688, construction=1) is None
    # Orders a prime field already covers keep that field's matrix.
    for n in (12, 28, 96, 576, 960, 1536):
        assert torch.equal(hadamard_matrix(n, construction=1), hadamard_matrix(n, construction=2))
    with pytest.raises(ValueError, match="construction must be one of"):
        hadamard_factors(12, construction=3)


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
        assert rotate_llama(rotated, seed=5) == {"kind": "hadamard", "seed": 5, "construction": HADAMARD_CONSTRUCTION}
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
    assert loaded.dyq_rotation == {"kind": "hadamard", "seed": 1, "construction": HADAMARD_CONSTRUCTION}
    ids = torch.randint(0, 200, (1, 11))
    with torch.no_grad():
        torch.testing.assert_close(loaded(ids).logits, model(ids).logits)


def test_a_rotated_quantized_model_round_trips_through_save_pretrained(tmp_path):
    """quantize_model's config carries the rotation, from_pretrained attaches down_proj's run-time rotation
    again (a tied model untied by the rotation stays untied)."""
    from helpers import hf_quantizer_unavailable

    if hf_quantizer_unavailable() is not None:
        pytest.skip(hf_quantizer_unavailable())
    model, flag = outlier_llama(), dyq.PrecisionFlag(8)
    rotate_llama(model, seed=4)
    dyq.quantize_model(model, group_size=32, flag=flag)
    assert model.config.quantization_config.rotation == model.dyq_rotation
    model.save_pretrained(tmp_path / "dyq")
    loaded = transformers.LlamaForCausalLM.from_pretrained(tmp_path / "dyq")
    assert loaded.dyq_rotation == {"kind": "hadamard", "seed": 4, "construction": HADAMARD_CONSTRUCTION}
    assert loaded.lm_head.weight.data_ptr() != loaded.model.embed_tokens.weight.data_ptr()
    ids = torch.randint(0, 200, (1, 11))
    with torch.no_grad():
        assert torch.equal(loaded(ids).logits, model(ids).logits)
    # A float checkpoint is not rotated on load.
    outlier_llama().save_pretrained(tmp_path / "float")
    with pytest.raises(ValueError, match="not rotated on load"):
        transformers.LlamaForCausalLM.from_pretrained(
            tmp_path / "float", quantization_config=dyq.DyQConfig(rotation=dict(model.dyq_rotation)))


def test_a_file_without_a_construction_is_rebuilt_with_the_first(tmp_path):
    """A model saved before the construction was recorded ran construction 1. Its intermediate size 104 is
    104 x 1 (Paley I over GF(103)) under construction 1 and 52 x 2 under 2: loading it with the current
    construction would rotate down_proj's input by a matrix its weights were not folded with."""
    config = transformers.LlamaConfig(vocab_size=200, hidden_size=48, intermediate_size=104, num_hidden_layers=2,
                                      num_attention_heads=4, num_key_value_heads=2, max_position_embeddings=64)
    torch.manual_seed(3)
    model = transformers.LlamaForCausalLM(config).eval()
    rotate_llama(model, seed=2, construction=1)
    dyq.quantize_model(model, group_size=32, flag=dyq.PrecisionFlag(16))
    dyq.save_quantized(model, tmp_path)
    state_file = tmp_path / "dyq_config.json"
    state = json.loads(state_file.read_text())
    del state["rotation"]["construction"]
    state_file.write_text(json.dumps(state))
    ids = torch.randint(0, 200, (1, 9))
    with torch.no_grad():
        expected = model(ids).logits
        loaded = dyq.load_quantized(transformers.LlamaForCausalLM(config), tmp_path)
        assert loaded.model.layers[0].mlp.down_proj_rotation.left.shape == (104, 104)
        torch.testing.assert_close(loaded(ids).logits, expected)
        state["rotation"]["construction"] = 2  # the other matrix: a different function
        state_file.write_text(json.dumps(state))
        wrong = dyq.load_quantized(transformers.LlamaForCausalLM(config), tmp_path)
        assert (wrong(ids).logits - expected).abs().max() > 1e-3
        state["rotation"]["construction"] = 7
        state_file.write_text(json.dumps(state))
        with pytest.raises(ValueError, match="uses rotation"):
            dyq.load_quantized(transformers.LlamaForCausalLM(config), tmp_path)


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
