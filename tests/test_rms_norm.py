"""dyq.ops.rms_norm, DyQRMSNorm and fuse_rms_norms: the fused RMSNorm against the plain PyTorch reference
(dyq.reference.rms_norm, transformers' LlamaRMSNorm formula) and a float64 one, on fresh random inputs."""
import copy
import io
import math

import pytest
import torch
from torch import nn

import dyq
from dyq.core.norm import DyQRMSNorm, fuse_rms_norms

DTYPES = (torch.float32, torch.bfloat16, torch.float16)
ROUNDING_STEP = {torch.float32: 2.0 ** -23, torch.bfloat16: 2.0 ** -7, torch.float16: 2.0 ** -10}
SHAPES = ((1,), (256,), (1, 1, 256), (3, 7, 100), (2, 4097), (256, 768))


def random_input(shape, dtype, rng):
    x = 3 * torch.randn(*shape, generator=rng)
    weight = 0.5 + torch.rand(shape[-1], generator=rng)
    return x.to(dtype), weight.to(dtype)


def relative_steps(got: torch.Tensor, expected: torch.Tensor) -> torch.Tensor:
    """|got - expected| in units of the dtype's rounding step at the larger of the two."""
    got, expected = got.double(), expected.double()
    scale = torch.maximum(got.abs(), expected.abs()).clamp_min(1e-30)
    return (got - expected).abs() / (scale * ROUNDING_STEP[got.dtype if got.dtype in ROUNDING_STEP else torch.float32])


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("shape", SHAPES)
def test_matches_the_reference_to_one_rounding_step(shape, dtype, rng):
    """The kernel and the reference differ only in the order of the sum of squares, which may move the
    normalized value by one step of its dtype, rarely, and the product with the weight by up to two."""
    x, weight = random_input(shape, dtype, rng)
    got = dyq.ops.rms_norm(x, weight, 1e-6)
    expected = dyq.reference.rms_norm(x, weight, 1e-6)
    assert got.dtype == dtype and got.shape == x.shape
    steps = (got.double() - expected.double()).abs() / (
        torch.maximum(got.double().abs(), expected.double().abs()).clamp_min(1e-30) * ROUNDING_STEP[dtype])
    assert steps.max() <= (8 if dtype == torch.float32 else 2)
    if dtype != torch.float32:
        assert (got == expected).float().mean() >= 0.98


@pytest.mark.parametrize("shape", SHAPES)
def test_fp32_matches_float64(shape, rng):
    x, weight = random_input(shape, torch.float32, rng)
    x64 = x.double()
    expected = weight.double() * x64 / torch.sqrt(x64.pow(2).mean(-1, keepdim=True) + 1e-5)
    torch.testing.assert_close(dyq.ops.rms_norm(x, weight, 1e-5).double(), expected, rtol=2e-6, atol=0)


def test_eps_enters_the_root(rng):
    """Rows of tiny values: eps dominates the mean square."""
    x = 1e-4 * torch.randn(4, 64, generator=rng)
    weight = torch.ones(64)
    for eps in (0.0, 1e-6, 1e-2):
        torch.testing.assert_close(dyq.ops.rms_norm(x, weight, eps), dyq.reference.rms_norm(x, weight, eps),
                                   rtol=1e-6, atol=0)


def test_non_contiguous_input_is_read_as_its_values(rng):
    x, weight = random_input((64, 5), torch.float32, rng)
    view = x.t()  # [5, 64], strides (1, 5)
    assert not view.is_contiguous()
    got = dyq.ops.rms_norm(view, weight[:5].repeat(13)[:64].contiguous(), 1e-6)
    assert torch.equal(got, dyq.ops.rms_norm(view.contiguous(), weight[:5].repeat(13)[:64].contiguous(), 1e-6))


def test_nan_and_inf_spread_as_in_the_formula(rng):
    x, weight = random_input((3, 32), torch.float32, rng)
    x[0, 4] = float("nan")
    x[1, 7] = float("inf")
    got, expected = dyq.ops.rms_norm(x, weight, 1e-6), dyq.reference.rms_norm(x, weight, 1e-6)
    assert torch.isnan(got[0]).all() and torch.isnan(got[1, 7])
    assert torch.equal(got[1, :7], expected[1, :7]) and (got[1, :7] == 0).all()
    assert torch.isfinite(got[2]).all()


@pytest.mark.parametrize("dtype", (torch.float32, torch.float64))
def test_gradients_match_autograd_through_the_reference(dtype, rng):
    """grad_x and grad_w of the op against torch's autograd through the formula (both in float64 where the op
    runs fp32: the kernel's backward computes in fp32)."""
    x, weight = random_input((2, 3, 48), torch.float32, rng)
    grad = torch.randn(2, 3, 48, generator=rng)
    x1, w1 = x.clone().requires_grad_(), weight.clone().requires_grad_()
    dyq.ops.rms_norm(x1, w1, 1e-5).backward(grad)
    x2, w2 = x.to(dtype).requires_grad_(), weight.to(dtype).requires_grad_()
    (w2 * x2 * torch.rsqrt(x2.pow(2).mean(-1, keepdim=True) + 1e-5)).backward(grad.to(dtype))
    torch.testing.assert_close(x1.grad.double(), x2.grad.double(), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(w1.grad.double(), w2.grad.double(), rtol=1e-4, atol=1e-5)


def test_no_gradient_recorded_without_grad_mode(rng):
    x, weight = random_input((2, 16), torch.float32, rng)
    with torch.no_grad():
        out = dyq.ops.rms_norm(x.requires_grad_(), weight, 1e-6)
    assert out.grad_fn is None


def test_opcheck(rng):
    for dtype in DTYPES:
        x, weight = random_input((2, 5, 96), dtype, rng)
        torch.library.opcheck(torch.ops.dyq.rms_norm.default, (x, weight, 1e-5))
    x, weight = random_input((4, 32), torch.float32, rng)
    torch.library.opcheck(torch.ops.dyq.rms_norm.default, (x.requires_grad_(), weight.requires_grad_(), 1e-5))


def test_meta_tensors_give_the_shape():
    out = dyq.ops.rms_norm(torch.empty(3, 9, 64, device="meta", dtype=torch.bfloat16),
                           torch.empty(64, device="meta", dtype=torch.bfloat16), 1e-6)
    assert out.shape == (3, 9, 64) and out.dtype == torch.bfloat16 and out.is_meta


@pytest.mark.parametrize("args, match", [
    (lambda: (torch.randn(2, 8), torch.ones(8, dtype=torch.bfloat16), 1e-6), "weight must have x's dtype"),
    (lambda: (torch.randn(2, 8), torch.ones(7), 1e-6), r"weight must have shape \[n\] = \[8\]"),
    (lambda: (torch.randn(2, 8), torch.ones(2, 8), 1e-6), r"weight must have shape \[n\]"),
    (lambda: (torch.randn(2, 8), torch.ones(8), -1.0), "eps must be a finite number >= 0"),
    (lambda: (torch.randn(2, 8), torch.ones(8), float("nan")), "eps must be a finite number >= 0"),
    (lambda: (torch.randn(2, 8), torch.ones(8), float("inf")), "eps must be a finite number >= 0"),
    (lambda: (torch.randint(0, 5, (2, 8)), torch.ones(8, dtype=torch.int64), 1e-6), "x must be float32, bfloat16"),
    (lambda: (torch.tensor(1.0), torch.ones(1), 1e-6), "at least one dimension"),
    (lambda: (torch.randn(2, 0), torch.ones(0), 1e-6), "at least one feature"),
    (lambda: (torch.randn(2, 8), torch.ones(8, device="meta"), 1e-6), "weight is on meta but x is on cpu"),
])
def test_bad_arguments_are_named(args, match):
    with pytest.raises(RuntimeError, match=match):
        dyq.ops.rms_norm(*args())


# ---- DyQRMSNorm and fuse_rms_norms ------------------------------------------------------------------------

def llama(dtype=torch.float32, layers=2):
    from transformers import LlamaConfig, LlamaForCausalLM

    config = LlamaConfig(hidden_size=128, intermediate_size=256, num_hidden_layers=layers, num_attention_heads=4,
                         vocab_size=256, rms_norm_eps=1e-5)
    torch.manual_seed(torch.randint(0, 2**31 - 1, ()).item())
    model = LlamaForCausalLM(config).eval().to(dtype)
    for name, parameter in model.named_parameters():
        if name.endswith("norm.weight"):
            nn.init.uniform_(parameter, 0.5, 1.5)  # not all ones: a dropped weight would show
    return model


@pytest.mark.parametrize("dtype", DTYPES)
def test_fused_llama_norm_matches_transformers(dtype, rng):
    model = llama(dtype, layers=1)
    norm = model.model.layers[0].input_layernorm
    x = (3 * torch.randn(2, 5, 128, generator=rng)).to(dtype)
    with torch.no_grad():
        expected = norm(x)
        fused, left = fuse_rms_norms(norm)
        got = norm(x)
    assert fused == ["LlamaRMSNorm"] and not left and isinstance(norm, DyQRMSNorm)
    assert norm.eps == 1e-5
    assert relative_steps(got, expected).max() <= (8 if dtype == torch.float32 else 2)


def test_fuse_rms_norms_converts_every_llama_norm_and_keeps_the_outputs(rng):
    model = llama()
    keys = set(model.state_dict())
    ids = torch.randint(0, 256, (2, 11), generator=rng)
    with torch.inference_mode():
        expected = model(ids).logits
    fused, left = fuse_rms_norms(model)
    assert len(fused) == 2 * 2 + 1 and not left
    assert all(isinstance(model.get_submodule(name), DyQRMSNorm) for name in fused)
    assert set(model.state_dict()) == keys
    with torch.inference_mode():
        torch.testing.assert_close(model(ids).logits, expected, rtol=1e-4, atol=1e-5)
    assert fuse_rms_norms(model) == ([], {})  # a second call finds nothing left to convert


def test_fused_model_survives_deepcopy_and_pickle(rng):
    model = llama(layers=1)
    fuse_rms_norms(model)
    ids = torch.randint(0, 256, (1, 6), generator=rng)
    buffer = io.BytesIO()
    torch.save(model, buffer)
    buffer.seek(0)
    loaded = torch.load(buffer, weights_only=False)
    with torch.inference_mode():
        expected = model(ids).logits
        torch.testing.assert_close(copy.deepcopy(model)(ids).logits, expected, rtol=0, atol=0)
        torch.testing.assert_close(loaded(ids).logits, expected, rtol=0, atol=0)


class GemmaStyleRMSNorm(nn.Module):
    """Gemma's formula: (1 + weight) and the product in float32."""

    def __init__(self, n):
        super().__init__()
        self.weight = nn.Parameter(torch.zeros(n))
        self.eps = 1e-6

    def forward(self, x):
        h = x.float() * torch.rsqrt(x.float().pow(2).mean(-1, keepdim=True) + self.eps)
        return (h * (1.0 + self.weight.float())).to(x.dtype)


class Float32OutRMSNorm(nn.Module):
    """A norm that returns float32 whatever its input."""

    def __init__(self, n):
        super().__init__()
        self.weight = nn.Parameter(torch.ones(n, dtype=torch.bfloat16))
        self.variance_epsilon = 1e-6

    def forward(self, x):
        h = x.float() * torch.rsqrt(x.float().pow(2).mean(-1, keepdim=True) + self.variance_epsilon)
        return self.weight.float() * h


class NoEpsilonRMSNorm(nn.Module):
    def __init__(self, n):
        super().__init__()
        self.weight = nn.Parameter(torch.ones(n))

    def forward(self, x):
        return x


def test_norms_of_other_formulas_are_left_with_the_reason():
    model = nn.ModuleDict({"gemma": GemmaStyleRMSNorm(32), "fp32_out": Float32OutRMSNorm(32),
                           "no_eps": NoEpsilonRMSNorm(32)})
    fused, left = fuse_rms_norms(model)
    assert fused == []
    assert "differs from the kernel's formula" in left["gemma"]
    assert "differs from the kernel's formula" in left["fp32_out"]
    assert "no finite epsilon" in left["no_eps"]
    assert type(model["gemma"]) is GemmaStyleRMSNorm


def test_a_norm_shared_by_two_parents_is_converted_once():
    norm = llama(layers=1).model.norm
    model = nn.ModuleDict({"a": norm, "b": norm})
    fused, left = fuse_rms_norms(model)
    assert fused == ["a"] and not left and model["b"] is norm and isinstance(norm, DyQRMSNorm)


def test_dyq_rms_norm_module_computes_mixed_dtypes_as_llama_does(rng):
    """A float32 input into a bfloat16 norm (LlamaRMSNorm's type promotion gives float32)."""
    norm = DyQRMSNorm(64, eps=1e-6, dtype=torch.bfloat16)
    nn.init.uniform_(norm.weight, 0.5, 1.5)
    x = torch.randn(3, 64, generator=rng)
    got = norm(x)
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, dyq.reference.rms_norm(x, norm.weight, 1e-6), rtol=0, atol=0)


def test_dyq_rms_norm_refuses_a_bad_eps():
    for eps in (-1.0, float("nan"), "1e-6", True):
        with pytest.raises(ValueError, match="eps must be a finite number >= 0"):
            DyQRMSNorm(8, eps=eps)


def test_quantize_model_fuses_norms_unless_asked_not_to(rng):
    model = llama()
    report = dyq.quantize_model(model)
    assert len(report.fused_norms) == 5 and not report.norms_left
    assert "5 RMSNorm layers run through dyq's fused kernel" in str(report)
    unfused = llama()
    assert dyq.quantize_model(unfused, fuse_norms=False).fused_norms == []
    assert not any(isinstance(m, DyQRMSNorm) for m in unfused.modules())
    with pytest.raises(TypeError, match="fuse_norms must be True or False"):
        dyq.quantize_model(llama(), fuse_norms="yes")


def test_fused_and_unfused_quantized_models_agree(rng):
    model = llama(torch.bfloat16)
    other = copy.deepcopy(model)
    dyq.quantize_model(model, act_bits=8)
    dyq.quantize_model(other, act_bits=8, fuse_norms=False)
    ids = torch.randint(0, 256, (1, 9), generator=rng)
    with torch.inference_mode():
        a, b = model(ids).logits.float(), other(ids).logits.float()
    # A one-step bf16 difference in a norm's output can move an A8 code; the logits stay close.
    assert (a - b).abs().max() <= 0.05 * b.abs().max()
    assert math.isclose((a.argmax(-1) == b.argmax(-1)).float().mean().item(), 1.0, abs_tol=0.25)


def test_load_quantized_fuses_the_norms(tmp_path, rng):
    model = llama()
    dyq.quantize_model(model)
    dyq.save_quantized(model, tmp_path)
    loaded = dyq.load_quantized(llama(), tmp_path)
    assert sum(isinstance(m, DyQRMSNorm) for m in loaded.modules()) == 5
    ids = torch.randint(0, 256, (1, 7), generator=rng)
    with torch.inference_mode():
        torch.testing.assert_close(loaded(ids).logits, model(ids).logits, rtol=0, atol=0)


def test_a_norm_the_kernel_cannot_run_is_left_with_the_reason(monkeypatch):
    """As on a GPU with a dyq built without its CUDA kernels: the probe's call fails, the norm stays."""
    def no_kernel(*args):
        raise NotImplementedError("Could not run 'dyq::rms_norm' with arguments from the 'CUDA' backend.\nmore")

    monkeypatch.setattr(dyq.core.norm, "_RMS_NORM", no_kernel)
    norm = llama(layers=1).model.norm
    fused, left = fuse_rms_norms(norm)
    assert fused == [] and type(norm).__name__ == "LlamaRMSNorm"
    assert left["LlamaRMSNorm"] == ("dyq's rms_norm does not run on cpu: Could not run 'dyq::rms_norm' with "
                                    "arguments from the 'CUDA' backend.")
