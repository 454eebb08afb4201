"""quantize_model(method=...): every method writes the documented format, the clipping search finds the
optimum of its grid, AWQ keeps the float function and beats round-to-nearest where activations have
outliers, and bad arguments are refused by name. The checks use plain float64 re-implementations, not
the code under test."""
import copy
import itertools
import json
import math

import pytest
import torch
from helpers import assert_gemm_close

import dyq
from dyq import reference
from dyq.core import weight_methods
from dyq.core.weight_methods import (CLIP_RATIOS, awq_channel_scales, clipped_weight, collect_hessians, gptq_weight,
                                     search_awq_scales)

transformers = pytest.importorskip("transformers")


def tiny_llama(seed=0, kv_heads=2):
    torch.manual_seed(seed)
    config = transformers.LlamaConfig(vocab_size=200, hidden_size=64, intermediate_size=96, num_hidden_layers=1,
                                      num_attention_heads=4, num_key_value_heads=kv_heads, max_position_embeddings=64)
    model = transformers.LlamaForCausalLM(config).eval()
    with torch.no_grad():  # an outlier channel in the residual stream, as trained Llamas have
        model.model.embed_tokens.weight[:, 5] *= 30
    return model


def brute_force_group(w, h, ratios):
    """The smallest sum h (w - s q)^2 over s = c absmax / 7, c in ratios: float64, one group, by enumeration."""
    absmax = max(abs(v) for v in w)
    best = (math.inf, None)
    for c in ratios:
        s = float(torch.tensor(c * absmax, dtype=torch.float32) / 7) if absmax else 1.0
        codes = [min(7, max(-8, round(v / s))) for v in w]
        error = sum(hk * (v - s * q) ** 2 for v, q, hk in zip(w, codes, h))
        if error < best[0]:
            best = (error, s)
    return best


@pytest.mark.parametrize("method", ["rtn", "mse", "awq", "gptq"])
@pytest.mark.parametrize("in_features,group_size", [(64, 32), (80, 32), (71, 64)])
def test_every_method_writes_the_documented_format(method, in_features, group_size):
    """Codes in [-8, 7], fp32 scales [N, ceil(K/G)] (the last group the remainder, an odd K padded with a zero
    column), and the kernels' forward equal to the float64 reference GEMM on those buffers."""
    torch.manual_seed(1)
    model = torch.nn.Sequential(torch.nn.Linear(in_features, 24))
    calibration = torch.randn(16, in_features) if method in ("awq", "gptq") else None
    dyq.quantize_model(model, group_size=group_size, skip=(), method=method, calibration=calibration)
    layer = model[0]
    k = in_features + in_features % 2
    assert layer.qweight.shape == (24, k // 2) and layer.qweight.dtype == torch.uint8
    assert layer.scales.shape == (24, -(-k // group_size)) and layer.scales.dtype == torch.float32
    codes = reference.unpack_int4(layer.qweight)
    assert codes.min() >= -8 and codes.max() <= 7
    if in_features % 2:
        assert (codes[:, -1] == 0).all()
    torch.testing.assert_close(layer.dequantized_weight(),
                               reference.dequantize_weight(layer.qweight, layer.scales, group_size)[:, :in_features])
    x = torch.randn(5, in_features)
    for bits in (16, 4):
        layer.set_precision(bits)
        xk = torch.nn.functional.pad(x, (0, k - in_features))
        # The float64 reference GEMM on those buffers, within the kernels' documented rounding (on CPUs with
        # AVX512-BF16 the W4A16 fallback rounds x to bf16: docs/numerics.md).
        assert_gemm_close(layer(x), xk, layer.qweight, layer.scales, group_size, bits, layer.bias)


def test_clipping_finds_the_known_optimum_of_a_group():
    """A group on the grid s* q (q in [-7, 7]) plus one outlier at 8.75 s*: clipping at c = 0.8 gives the
    scale s* exactly, every inlier error-free, and beats every other ratio of the grid."""
    s_star = 0.01
    inliers = torch.tensor([q for q in range(-7, 8) for _ in range(4)] + [3, -2, 5], dtype=torch.float32) * s_star
    group = torch.cat([inliers, torch.tensor([8.75 * s_star])])
    assert group.numel() == 64
    codes, scales = clipped_weight(group[None], 64)
    torch.testing.assert_close(scales, torch.tensor([[s_star]]), rtol=1e-6, atol=0)
    assert torch.equal(codes[0, :-1].float(), torch.round(inliers / s_star))
    assert codes[0, -1] == 7  # the outlier is clipped
    _, rtn_scales = reference.quantize_weight(group[None], 64)
    assert not torch.allclose(rtn_scales, scales)


@pytest.mark.parametrize("block_elements", (None, 4 * 96, 1))  # one block; blocks of 4 rows and a ragged one; rows
def test_clipping_matches_a_brute_force_search_and_never_loses_to_round_to_nearest(block_elements, monkeypatch):
    if block_elements is not None:
        monkeypatch.setattr(weight_methods, "MSE_BLOCK_ELEMENTS", block_elements)
    gen = torch.Generator().manual_seed(2)
    weight = torch.randn(6, 96, generator=gen) * torch.rand(6, 96, generator=gen) ** 3  # heavy-tailed
    channel_weight = torch.rand(96, generator=gen) * 4
    for h in (None, channel_weight):
        codes, scales = clipped_weight(weight, 32, h)
        hw = [1.0] * 96 if h is None else h.double().tolist()
        for n, g in itertools.product(range(6), range(3)):
            w = weight[n, 32 * g:32 * g + 32].double().tolist()
            best_error, best_scale = brute_force_group(w, hw[32 * g:32 * g + 32], CLIP_RATIOS)
            rtn_error, _ = brute_force_group(w, hw[32 * g:32 * g + 32], (1.0,))
            mine = scales[n, g].item() * codes[n, 32 * g:32 * g + 32].double()
            error = sum(hk * (v - m) ** 2 for v, m, hk in zip(w, mine.tolist(), hw[32 * g:32 * g + 32]))
            assert error == pytest.approx(best_error, rel=1e-6, abs=1e-12)
            assert error <= rtn_error * (1 + 1e-9)


def test_an_all_zero_group_keeps_scale_one_and_zero_codes():
    weight = torch.zeros(2, 64)
    weight[1, :32] = torch.linspace(-1, 1, 32)
    codes, scales = clipped_weight(weight, 32)
    assert scales[0].tolist() == [1.0, 1.0] and scales[1, 1] == 1.0
    assert (codes[0] == 0).all() and (codes[1, 32:] == 0).all()


def awq_objective_float64(x, weight, scales, group_size, bits):
    """Independent float64 version of the AWQ objective for one layer."""
    x, weight, scales = x.double(), weight.double(), scales.double()
    target = x @ weight.T
    ws = weight * scales
    absmax = ws.reshape(ws.shape[0], -1, group_size).abs().amax(-1, keepdim=True).float().double()
    step = (absmax.float() / 7).double()
    wq = (torch.round(ws.reshape(ws.shape[0], -1, group_size) / step).clamp(-8, 7) * step).reshape(ws.shape)
    total = 0.0
    for b in bits:
        xs = (x / scales).float()
        if b == 16:
            xq = xs.double()
        else:
            g = xs.reshape(xs.shape[0], -1, group_size)
            lo, hi = g.amin(-1, keepdim=True).clamp(max=0), g.amax(-1, keepdim=True).clamp(min=0)
            s = (hi - lo) / (2**b - 1)
            z = torch.round(-lo / s).clamp(0, 2**b - 1)
            xq = ((torch.round(g / s) + z).clamp(0, 2**b - 1) - z).double() * s.double()
            xq = xq.reshape(xs.shape)
        total += math.log(((xq @ wq.T - target) ** 2).sum().item())
    return total / len(bits)


def test_awq_search_finds_the_best_alpha_of_an_independent_objective():
    """Activations with two outlier channels: the alpha the search returns minimises a float64
    re-implementation of the objective over the same grid, and that minimum is below alpha = 0 (RTN)."""
    gen = torch.Generator().manual_seed(3)
    x = torch.randn(128, 64, generator=gen)
    x[:, [3, 40]] *= 25
    weight = torch.randn(32, 64, generator=gen) * 0.05
    bits = (16, 8, 4, 2)
    scales, alpha = search_awq_scales(x, x.abs().mean(0), [weight], 32, bits)
    values = {a: awq_objective_float64(x, weight, awq_channel_scales(x.abs().mean(0), a), 32, bits)
              for a in weight_methods.ALPHAS}
    best = min(values, key=values.get)
    assert values[alpha] <= values[best] + 1e-6
    assert values[alpha] < values[0.0] - 0.1
    torch.testing.assert_close(scales, awq_channel_scales(x.abs().mean(0), alpha))
    assert scales.double().log().mean().abs() < 1e-5  # geometric mean 1


def test_awq_folding_keeps_the_float_function():
    model = tiny_llama(kv_heads=4)  # every head its own value head: the v -> o fold is exercised too
    calibration, test_ids = torch.randint(0, 200, (2, 24)), torch.randint(0, 200, (2, 17))
    with torch.no_grad():
        expected = model(test_ids).logits
    weight_methods.awq_prepare(model, calibration, 32, (16, 4), targets=lambda linear: True)
    with torch.no_grad():
        torch.testing.assert_close(model(test_ids).logits, expected, rtol=1e-4, atol=1e-4)
    assert not torch.allclose(model.model.layers[0].input_layernorm.weight, torch.ones(64))


def test_awq_folding_keeps_the_float_function_of_a_rotated_model():
    """After rotate_llama, down_proj's input is rotated at run time, so no scale is folded across it."""
    from dyq.rotation import rotate_llama

    model = tiny_llama(kv_heads=4)
    rotate_llama(model)
    calibration, test_ids = torch.randint(0, 200, (2, 24)), torch.randint(0, 200, (2, 17))
    with torch.no_grad():
        expected = model(test_ids).logits
    down = model.model.layers[0].mlp.down_proj.weight.clone()
    weight_methods.awq_prepare(model, calibration, 32, (16, 4), targets=lambda linear: True)
    with torch.no_grad():
        torch.testing.assert_close(model(test_ids).logits, expected, rtol=1e-4, atol=1e-4)
    assert torch.equal(model.model.layers[0].mlp.down_proj.weight, down)


def test_awq_beats_round_to_nearest_at_low_widths_on_outlier_activations():
    model = tiny_llama()
    calibration, test_ids = torch.randint(0, 200, (4, 24)), torch.randint(0, 200, (2, 24))
    with torch.no_grad():
        expected = model(test_ids).logits
    errors = {}
    for method in ("rtn", "awq"):
        quantized, flag = copy.deepcopy(model), dyq.PrecisionFlag(4)
        dyq.quantize_model(quantized, group_size=32, flag=flag, method=method,
                           calibration=calibration if method == "awq" else None)
        with torch.no_grad():
            errors[method] = ((quantized(test_ids).logits - expected) ** 2).mean().item()
    assert errors["awq"] < errors["rtn"]


def test_the_method_is_reported_and_saved(tmp_path):
    model, flag = tiny_llama(), dyq.PrecisionFlag(8)
    report = dyq.quantize_model(model, group_size=32, flag=flag, method="mse")
    assert report.method == "mse" and "method=mse" in str(report)
    dyq.save_quantized(model, tmp_path)
    assert json.loads((tmp_path / "dyq_config.json").read_text())["weight_method"] == "mse_clip_int4_symmetric"
    loaded = dyq.load_quantized(transformers.LlamaForCausalLM(model.config), tmp_path)
    ids = torch.randint(0, 200, (1, 9))
    with torch.no_grad():
        torch.testing.assert_close(loaded(ids).logits, model(ids).logits)
    assert {m.weight_method for m in loaded.modules() if isinstance(m, dyq.DyQLinear)} == {"mse"}


@pytest.mark.parametrize("kwargs,match", [
    ({"method": "spinquant"}, "method must be one of"),
    ({"method": "awq"}, "needs calibration"),
    ({"method": "gptq"}, "needs calibration"),
    ({"method": "gptq", "calibration": torch.randn(2, 4)}, "calibration does not fit the model"),
    ({"method": "mse", "calibration": torch.zeros(1, 4, dtype=torch.long)}, "calibration is only used"),
    ({"method": "awq", "calibration": torch.zeros(0, 4, dtype=torch.long)}, "calibration is an empty tensor"),
    ({"method": "awq", "calibration": torch.randn(2, 4)}, "calibration does not fit the model"),
    ({"method": "awq", "calibration": [torch.zeros(1, 4, dtype=torch.long), "text"]}, r"calibration\[1\] must be"),
    ({"method": "awq", "calibration": []}, "calibration is empty"),
    ({"method": "awq", "calibration": torch.zeros(1, 4, dtype=torch.long), "calibration_bits": (16, 3)},
     "calibration_bits"),
    ({"method": "awq", "calibration": torch.zeros(1, 4, dtype=torch.long), "calibration_bits": ()},
     "calibration_bits"),
])
def test_bad_arguments_are_refused_by_name(kwargs, match):
    model = tiny_llama()
    with pytest.raises((ValueError, TypeError), match=match):
        dyq.quantize_model(model, group_size=32, **kwargs)


@pytest.mark.parametrize("method", ["awq", "gptq"])
def test_calibration_that_gives_a_layer_nan_inputs_is_refused_by_layer(method):
    """One NaN in the calibration data would make every clipping error NaN (AWQ kept scale 1 everywhere)."""
    model = torch.nn.Sequential(torch.nn.Linear(64, 64), torch.nn.ReLU(), torch.nn.Linear(64, 8))
    calibration = torch.randn(32, 64, generator=torch.Generator().manual_seed(5))
    calibration[3, 5] = float("nan")
    before = copy.deepcopy(model.state_dict())
    with pytest.raises(ValueError, match="the calibration data gives layer '0' NaN or Inf inputs"):
        dyq.quantize_model(model, group_size=64, skip=(), method=method, calibration=calibration)
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())


def test_bad_channel_weight_shape_is_refused():
    with pytest.raises(ValueError, match="channel_weight must have shape"):
        clipped_weight(torch.randn(4, 64), 32, torch.ones(63))


# ---- GPTQ ---------------------------------------------------------------------------------------------------

def correlated_inputs(tokens, features, generator):
    """Inputs whose channels are strongly correlated (a random mixing of a few latent factors plus noise)
    and of unequal magnitude, as a layer's real inputs are."""
    latent = torch.randn(tokens, features // 4, generator=generator, dtype=torch.float64)
    mixing = torch.randn(features // 4, features, generator=generator, dtype=torch.float64)
    noise = 0.1 * torch.randn(tokens, features, generator=generator, dtype=torch.float64)
    return (latent @ mixing + noise) * torch.linspace(0.2, 3, features, dtype=torch.float64)


def hessian_of(x):
    return 2 * x.T @ x / x.shape[0]


def gptq_float64(weight, hessian, group_size, damping=0.01):
    """GPTQ in its Optimal Brain Surgeon form, one column at a time, float64, no Cholesky: quantize column q,
    move its error onto the later columns by ``-err / [H^-1]_qq * [H^-1]_{q,:}``, then remove q from the
    inverse Hessian (``H^-1 -= H^-1[:, q] H^-1[q, :] / [H^-1]_qq``). A group's scale: the clipping search
    (weighted by diag H) on the group's weights when q enters it."""
    w = weight.double().clone()
    h = hessian.double().clone()
    h += damping * h.diagonal().mean() * torch.eye(h.shape[0], dtype=torch.float64)
    h_inverse = torch.linalg.inv(h)
    k = w.shape[1]
    codes = torch.zeros_like(w)
    scales = torch.zeros(w.shape[0], -(-k // group_size), dtype=torch.float64)
    for q in range(k):
        if q % group_size == 0:
            _, group_scale = clipped_weight(w[:, q:q + group_size], group_size, h.diagonal()[q:q + group_size].float())
            scales[:, q // group_size] = group_scale[:, 0].double()
        s = scales[:, q // group_size]
        codes[:, q] = torch.round(w[:, q] / s).clamp(-8, 7)
        error = (w[:, q] - s * codes[:, q]) / h_inverse[q, q]
        w[:, q:] -= error[:, None] * h_inverse[q, q:][None, :]
        h_inverse -= torch.outer(h_inverse[:, q], h_inverse[q, :]) / h_inverse[q, q]
    return codes, scales


def dequantized(codes, scales, group_size):
    grouped = reference._grouped(codes.double(), group_size) * scales.double()[..., None]
    return reference._ungrouped(grouped, codes.shape[1])


@pytest.mark.parametrize("in_features,group_size,block", [(96, 32, 128), (200, 64, 64), (150, 32, 40)])
def test_gptq_equals_the_column_by_column_float64_form(in_features, group_size, block):
    """The blocked Cholesky implementation (a partial last group and, for block 40, blocks rounded up to a
    multiple of the group) quantizes exactly as the OBS form of the algorithm does."""
    gen = torch.Generator().manual_seed(4)
    x = correlated_inputs(512, in_features, gen)
    weight = torch.randn(24, in_features, generator=gen, dtype=torch.float64).float()
    codes, scales = gptq_weight(weight, hessian_of(x), group_size, block=block)
    expected_codes, expected_scales = gptq_float64(weight, hessian_of(x), group_size)
    torch.testing.assert_close(scales.double(), expected_scales, rtol=1e-6, atol=0)
    assert torch.equal(codes.double(), expected_codes)
    assert codes.dtype == torch.int8 and scales.dtype == torch.float32


def test_gptq_beats_round_to_nearest_on_fresh_correlated_inputs():
    """On a least-squares toy problem the output error ||X W^T - X Wq^T|| on *new* inputs from the same
    distribution is clearly below round-to-nearest's and the clipping search's."""
    gen = torch.Generator().manual_seed(5)
    k, group_size = 128, 32
    weight = torch.randn(64, k, generator=gen, dtype=torch.float64).float()
    mixing = torch.randn(k // 4, k, generator=gen, dtype=torch.float64)
    column_scale = torch.linspace(0.2, 3, k, dtype=torch.float64)

    def draw(tokens, seed):  # the same mixing and scaling, new tokens
        g = torch.Generator().manual_seed(seed)
        latent = torch.randn(tokens, k // 4, generator=g, dtype=torch.float64)
        return (latent @ mixing + 0.1 * torch.randn(tokens, k, generator=g, dtype=torch.float64)) * column_scale

    calibration, test = draw(1024, 7), draw(1024, 8)
    target = test @ weight.double().T
    errors = {}
    codes, scales = gptq_weight(weight, hessian_of(calibration), group_size)
    errors["gptq"] = (test @ dequantized(codes, scales, group_size).T - target).norm().item()
    codes, scales = reference.quantize_weight(weight, group_size)
    errors["rtn"] = (test @ dequantized(codes, scales, group_size).T - target).norm().item()
    codes, scales = clipped_weight(weight, group_size)
    errors["mse"] = (test @ dequantized(codes, scales, group_size).T - target).norm().item()
    assert errors["gptq"] < 0.7 * errors["rtn"] and errors["gptq"] < 0.7 * errors["mse"], errors


def test_gptq_with_a_diagonal_hessian_is_the_weighted_clipping_search():
    """Uncorrelated inputs (H diagonal): no error can be moved to another column, so GPTQ is exactly the
    clipping search weighted by H's damped diagonal."""
    gen = torch.Generator().manual_seed(9)
    weight = torch.randn(16, 96, generator=gen)
    diagonal = torch.rand(96, generator=gen, dtype=torch.float64) * 3 + 0.1
    codes, scales = gptq_weight(weight, torch.diag(diagonal), 32)
    expected_codes, expected_scales = clipped_weight(weight, 32, (diagonal + 0.01 * diagonal.mean()).float())
    assert torch.equal(codes, expected_codes)
    torch.testing.assert_close(scales, expected_scales, rtol=0, atol=0)


def test_gptq_of_a_single_group_column_pair_has_the_closed_form_update():
    """Two columns, one group: column 0 is rounded, and column 1 receives exactly
    ``-err0 * [H^-1]_01 / [H^-1]_00`` before it is rounded (the least-squares optimum for column 1 given
    column 0's rounding), in plain float64 arithmetic."""
    h = torch.tensor([[2.0, 1.2], [1.2, 1.0]], dtype=torch.float64)
    weight = torch.tensor([[0.33, -0.71], [0.9, 0.05]])
    codes, scales = gptq_weight(weight, h, 32, damping=1e-12)
    h_inverse = torch.linalg.inv(h + 1e-12 * h.diagonal().mean() * torch.eye(2, dtype=torch.float64))
    for row in range(2):
        s = scales[row, 0].item()
        w0, w1 = weight[row].double().tolist()
        q0 = max(-8, min(7, round(w0 / s)))
        w1_updated = w1 - (w0 - s * q0) * h_inverse[0, 1].item() / h_inverse[0, 0].item()
        assert codes[row].tolist() == [q0, max(-8, min(7, round(w1_updated / s)))]


def test_gptq_zeroes_columns_no_input_reaches():
    gen = torch.Generator().manual_seed(10)
    x = correlated_inputs(256, 64, gen)
    x[:, 7] = 0
    codes, _ = gptq_weight(torch.randn(8, 64, generator=gen), hessian_of(x), 32)
    assert (codes[:, 7] == 0).all()


def test_collect_hessians_is_two_x_transpose_x_over_n_of_the_float_inputs():
    torch.manual_seed(11)
    model = torch.nn.Sequential(torch.nn.Linear(12, 8), torch.nn.ReLU(), torch.nn.Linear(8, 4))
    batches = [torch.randn(5, 12), torch.randn(3, 12)]
    hessians = collect_hessians(model, batches)
    x = torch.cat(batches).double()
    torch.testing.assert_close(hessians[id(model[0])], hessian_of(x))
    with torch.no_grad():
        hidden = torch.relu(model[0](torch.cat(batches))).double()
    torch.testing.assert_close(hessians[id(model[2])], hessian_of(hidden), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("kwargs,match", [
    ({"hessian": torch.eye(63)}, "hessian must have shape"),
    ({"hessian": torch.full((64, 64), float("nan"))}, "hessian contains NaN"),
    ({"hessian": -torch.eye(64)}, "positive semi-definite"),
    ({"hessian": 3 * torch.ones(64, 64) - 2 * torch.eye(64)}, "positive semi-definite"),  # indefinite
    ({"hessian": torch.eye(64), "damping": 0.0}, "damping must be > 0"),
    ({"hessian": torch.eye(64), "weight": torch.randn(64)}, "weight must be 2-D"),
])
def test_gptq_bad_inputs_are_refused_by_name(kwargs, match):
    arguments = {"weight": torch.randn(4, 64), "group_size": 32, **kwargs}
    with pytest.raises(ValueError, match=match):
        gptq_weight(**arguments)


def test_gptq_on_a_llama_beats_round_to_nearest_and_saves(tmp_path):
    model = tiny_llama()
    calibration, test_ids = torch.randint(0, 200, (4, 24)), torch.randint(0, 200, (2, 24))
    with torch.no_grad():
        expected = model(test_ids).logits
    errors = {}
    for method in ("rtn", "gptq"):
        quantized, flag = copy.deepcopy(model), dyq.PrecisionFlag(16)
        dyq.quantize_model(quantized, group_size=32, flag=flag, method=method,
                           calibration=calibration if method == "gptq" else None)
        with torch.no_grad():
            errors[method] = ((quantized(test_ids).logits - expected) ** 2).mean().item()
    assert errors["gptq"] < errors["rtn"]
    dyq.save_quantized(quantized, tmp_path)
    assert json.loads((tmp_path / "dyq_config.json").read_text())["weight_method"] == "gptq_int4_symmetric"
