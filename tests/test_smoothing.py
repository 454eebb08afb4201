"""SmoothQuant-style smoothing: exact in float, scales as documented, calibrated on the inputs given."""
import pytest
import torch

transformers = pytest.importorskip("transformers")

import dyq  # noqa: E402
from dyq.smoothing import activation_maxima, smooth_llama, smoothing_scales  # noqa: E402


def llama(seed=0):
    torch.manual_seed(seed)
    config = transformers.LlamaConfig(vocab_size=300, hidden_size=128, intermediate_size=256, num_hidden_layers=2,
                                      num_attention_heads=4, num_key_value_heads=4, max_position_embeddings=64)
    return transformers.LlamaForCausalLM(config).eval()


def test_scales_follow_the_formula():
    torch.manual_seed(1)
    x_max = torch.rand(16) * 10
    w1, w2 = torch.randn(8, 16), torch.randn(4, 16)
    alpha = 0.6
    expected = x_max.double() ** alpha / torch.cat([w1, w2]).abs().amax(0).double() ** (1 - alpha)
    torch.testing.assert_close(smoothing_scales(x_max, [w1, w2], alpha).double(), expected, rtol=1e-5, atol=0)


def test_maxima_are_the_channel_maxima_of_the_calibration_inputs():
    layer = torch.nn.Sequential(torch.nn.Linear(6, 3))
    x = torch.randn(2, 5, 6)
    maxima = activation_maxima(layer, lambda: layer(x))
    torch.testing.assert_close(maxima["0"], x.abs().reshape(-1, 6).amax(0))
    with pytest.raises(ValueError, match="ran no nn.Linear"):
        activation_maxima(layer, lambda: None)


def test_smoothed_float_model_computes_the_same_function():
    model = llama()
    calibration = torch.randint(0, 300, (4, 20))
    test_ids = torch.randint(0, 300, (3, 17))  # disjoint from the calibration batch
    with torch.no_grad():
        before = model(test_ids).logits
        maxima = activation_maxima(model, lambda: model(calibration))
        assert smooth_llama(model, maxima, alpha=0.5) == 2 * 7
        after = model(test_ids).logits
    torch.testing.assert_close(after, before, rtol=1e-4, atol=1e-4)


def test_smoothing_moves_outlier_channels_into_the_weights():
    model = llama()
    with torch.no_grad():
        # An outlier input channel of q/k/v, as real models have after their RMSNorm.
        model.model.layers[0].input_layernorm.weight[5] = 40.0
        ids = torch.randint(0, 300, (4, 20))
        maxima = activation_maxima(model, lambda: model(ids))
        spread_before = maxima["model.layers.0.self_attn.q_proj"].max() / maxima["model.layers.0.self_attn.q_proj"].median()
        smooth_llama(model, maxima, alpha=0.5)
        smoothed = activation_maxima(model, lambda: model(ids))["model.layers.0.self_attn.q_proj"]
    assert smoothed.max() / smoothed.median() < spread_before / 4


def test_smoothing_survives_quantization():
    model = llama()
    ids = torch.randint(0, 300, (2, 12))
    with torch.no_grad():
        maxima = activation_maxima(model, lambda: model(ids))
        smooth_llama(model, maxima)
        flag = dyq.PrecisionFlag(4)
        dyq.quantize_model(model, group_size=128, flag=flag)
        logits = model(ids).logits
    assert torch.isfinite(logits).all()


def test_rejects_bad_alpha_and_non_llama_models():
    model = llama()
    with pytest.raises(ValueError, match="alpha"):
        smooth_llama(model, {}, alpha=1.5)
    with pytest.raises(ValueError, match="decoder layers"):
        smooth_llama(torch.nn.Linear(4, 4), {})
