"""DyQLinear as a drop-in nn.Linear."""
import io

import pytest
import torch
from helpers import DTYPES, assert_gemm_close, bf16_fallback, random_activations

import dyq
from dyq import reference


def make_linear(k, n, bias, dtype, gen):
    linear = torch.nn.Linear(k, n, bias=bias)
    with torch.no_grad():
        linear.weight.copy_(torch.randn(n, k, generator=gen) * 0.05)
        if bias:
            linear.bias.copy_(torch.randn(n, generator=gen))
    return linear.to(dtype)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("bias", (True, False))
@pytest.mark.parametrize("act_bits", (2, 4, 8, 16))
def test_from_linear_forward_matches_reference(dtype, bias, act_bits, rng):
    linear = make_linear(256, 45, bias, dtype, rng)
    layer = dyq.DyQLinear.from_linear(linear, group_size=64, act_bits=act_bits)
    x = random_activations((2, 9, 256), rng, dtype)
    out = layer(x)
    assert out.dtype == dtype and out.shape == (2, 9, 45)
    assert_gemm_close(out, x, layer.qweight, layer.scales, 64, act_bits, layer.bias)


def test_fallback_precision_is_close_to_the_float_layer(rng):
    linear = make_linear(512, 64, True, torch.float32, rng)
    layer = dyq.DyQLinear.from_linear(linear, act_bits=16)
    x = random_activations((8, 512), rng)
    # Where the CPU's W4A16 runs on bf16 dot products, x is rounded to bf16 first, and where it multiplies
    # by the dequantized weights (the AMX tiles from 4 rows), they are rounded too (docs/numerics.md).
    x_used = x.bfloat16().float() if bf16_fallback(8, 512, layer.group_size) else x
    weight = layer.dequantized_weight()
    if "dequantized" in dyq.cpu_gemm_kernel(8, 512, layer.group_size, 16):
        weight = weight.bfloat16().float()
    expected = x_used @ weight.t() + linear.bias
    assert torch.allclose(layer(x), expected, rtol=1e-5, atol=1e-5)
    # Round-to-nearest INT4 of Gaussian weights: about 12 % RMS error per weight.
    with torch.no_grad():
        rel = (layer(x) - linear(x)).norm() / linear(x).norm()
    assert rel < 0.15


def test_quantized_weight_is_the_reference_quantization(rng):
    linear = make_linear(128, 20, False, torch.bfloat16, rng)
    layer = dyq.DyQLinear.from_linear(linear, group_size=32)
    codes, scales = reference.quantize_weight(linear.weight.float(), 32)
    assert torch.equal(layer.qweight, reference.pack_int4(codes)) and torch.equal(layer.scales, scales)


def test_state_dict_round_trip(rng):
    layer = dyq.DyQLinear.from_linear(make_linear(128, 24, True, torch.bfloat16, rng), group_size=64, act_bits=4)
    buffer = io.BytesIO()
    torch.save(layer.state_dict(), buffer)
    buffer.seek(0)
    fresh = dyq.DyQLinear(128, 24, bias=True, group_size=64, act_bits=4, dtype=torch.bfloat16)
    fresh.load_state_dict(torch.load(buffer))
    assert set(layer.state_dict()) == {"qweight", "scales", "bias"}
    x = random_activations((5, 128), rng, torch.bfloat16)
    assert torch.equal(fresh(x), layer(x))


def test_shared_flag_switches_every_layer(rng):
    flag = dyq.PrecisionFlag(16)
    layers = [dyq.DyQLinear.from_linear(make_linear(128, 128, True, torch.float32, rng), flag=flag)
              for _ in range(3)]
    x = random_activations((4, 128), rng)
    for bits in (2, 4, 8, 16):
        flag.bits = bits
        for layer in layers:
            assert layer.precision == bits
            expected = dyq.ops.gemm(x, layer.qweight, layer.scales, 128, bits, layer.bias)
            assert torch.equal(layer(x), expected)


def test_set_precision_writes_the_flag_when_bound(rng):
    flag = dyq.PrecisionFlag(16)
    layer = dyq.DyQLinear.from_linear(make_linear(128, 8, False, torch.float32, rng), flag=flag)
    layer.set_precision(2)
    assert flag.bits == 2 and layer.act_bits == 16
    layer.bind_flag(None)
    layer.set_precision(8)
    assert layer.act_bits == 8 and flag.bits == 2


def test_half_and_bfloat16_conversion_keeps_float32_scales(rng):
    layer = dyq.DyQLinear.from_linear(make_linear(128, 8, True, torch.float32, rng))
    scales = layer.scales.clone()
    layer.half()
    assert layer.scales.dtype == torch.float32 and torch.equal(layer.scales, scales)
    assert layer.bias.dtype == torch.float16 and layer.qweight.dtype == torch.uint8
    layer.to(torch.bfloat16)
    assert torch.equal(layer.scales, scales)


def test_repr_names_the_format(rng):
    layer = dyq.DyQLinear.from_linear(make_linear(128, 8, True, torch.float32, rng), group_size=32, act_bits=4)
    text = repr(layer)
    assert "in_features=128" in text and "out_features=8" in text and "group_size=32" in text
    assert "act_bits=4" in text and "int4" in text


def test_misuse_is_reported(rng):
    with pytest.raises(ValueError, match="in_features must be an int >= 1"):
        dyq.DyQLinear(0, 8, group_size=64)
    with pytest.raises(ValueError, match="group_size must be one of"):
        dyq.DyQLinear(128, 8, group_size=100)
    with pytest.raises(ValueError, match="act_bits must be one of"):
        dyq.DyQLinear(128, 8, act_bits=3)
    with pytest.raises(TypeError, match="must be a torch.nn.Linear"):
        dyq.DyQLinear.from_linear(torch.nn.Conv1d(4, 4, 1))
    layer = dyq.DyQLinear(128, 8)
    with pytest.raises(TypeError, match="DyQLinear input must be one of"):
        layer(torch.zeros(2, 128, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"input must have shape \[\.\.\., in_features = 128\]"):
        layer(torch.zeros(2, 96))
    with pytest.raises(ValueError, match="bits must be one of"):
        layer.set_precision(5)
    with pytest.raises(TypeError, match="flag must be a dyq.PrecisionFlag"):
        layer.bind_flag(4)


def test_a_linear_on_the_meta_device_is_refused_with_the_way_out():
    meta = torch.nn.Linear(128, 8, device="meta")
    with pytest.raises(ValueError, match="linear.weight is on the meta device"):
        dyq.DyQLinear.from_linear(meta)
    with pytest.raises(ValueError, match=r"convert_in_place\(linear, quantize=False\)"):
        dyq.quantize_model(torch.nn.Sequential(meta))
    assert type(meta) is torch.nn.Linear  # refused before the class changed
    shell = dyq.DyQLinear.convert_in_place(meta, quantize=False)
    assert shell.qweight.is_meta and shell.qweight.shape == (8, 64)


@pytest.mark.parametrize("reparametrize", ["weight_norm", "spectral_norm", "hook_weight_norm"])
def test_a_weight_computed_on_access_is_quantized_at_its_current_value(reparametrize):
    """weight_norm / spectral_norm layers keep no `weight` parameter: their current weight is what is
    quantized, as a plain layer of that weight would be."""
    import warnings

    torch.manual_seed(0)
    linear = torch.nn.Linear(192, 48)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)  # the hook-based weight_norm is deprecated
        wrapped = {"weight_norm": torch.nn.utils.parametrizations.weight_norm,
                   "spectral_norm": torch.nn.utils.parametrizations.spectral_norm,
                   "hook_weight_norm": torch.nn.utils.weight_norm}[reparametrize](linear)
    wrapped.eval()
    plain = torch.nn.Linear(192, 48)
    with torch.no_grad():
        plain.weight.copy_(wrapped.weight)
        plain.bias.copy_(wrapped.bias)
    expected = dyq.DyQLinear.from_linear(plain, act_bits=8)
    model = torch.nn.Sequential(wrapped)
    report = dyq.quantize_model(model, act_bits=8, skip=())
    assert report.converted == ["0"] and isinstance(model[0], dyq.DyQLinear)
    assert torch.equal(model[0].qweight, expected.qweight) and torch.equal(model[0].scales, expected.scales)
    x = torch.randn(3, 192)
    assert torch.equal(model(x), expected(x))


def test_a_lazy_layer_not_yet_initialized_is_refused():
    with pytest.raises(ValueError, match="0 is a lazy layer whose weight is not initialized yet: run one forward"):
        dyq.quantize_model(torch.nn.Sequential(torch.nn.LazyLinear(32)))
