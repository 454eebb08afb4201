"""Gradients through frozen INT4 weights: x.grad is that of x W^T + b with the dequantized weight
(straight-through over the activation quantization), so adapters train on a dyq model."""
import warnings

import pytest
import torch
from helpers import DTYPES, random_activations, random_weight

import dyq


def float64_grad(layer, x, grad_out):
    """d(sum(grad_out * y))/dx by autograd through the float64 dequantized layer."""
    x64 = x.detach().double().requires_grad_()
    y64 = x64 @ layer.dequantized_weight().double().T
    (y64 * grad_out.double()).sum().backward()
    return x64.grad


@pytest.mark.parametrize("act_bits", dyq.VALID_BITS)
@pytest.mark.parametrize("in_features", (128, 576, 97))
def test_input_gradient_is_that_of_the_dequantized_layer(act_bits, in_features, rng):
    linear = torch.nn.Linear(in_features, 24)
    with torch.no_grad():
        linear.weight.copy_(random_weight(24, in_features, rng))
    layer = dyq.DyQLinear.from_linear(linear, group_size=64, act_bits=act_bits)
    x = random_activations((3, 5, in_features), rng).requires_grad_()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "autograd kernel was not registered" warning
        y = layer(x)
        grad_out = torch.randn(y.shape, generator=rng)
        y.backward(grad_out)
    expected = float64_grad(layer, x, grad_out)
    bound = grad_out.double().abs().reshape(-1, 24) @ layer.dequantized_weight().double().abs()
    assert ((x.grad.double() - expected).abs() <= 1e-6 * bound.reshape(expected.shape) + 1e-30).all()


@pytest.mark.parametrize("dtype", DTYPES)
def test_gradient_has_the_input_dtype_and_flows_through_the_flag_op(dtype, rng):
    flag = dyq.PrecisionFlag(4)
    layer = dyq.DyQLinear.from_linear(torch.nn.Linear(128, 16), group_size=128, flag=flag)
    x = random_activations((4, 128), rng, dtype).requires_grad_()
    layer(x).sum().backward()
    assert x.grad.dtype == dtype and x.grad.shape == x.shape
    expected = float64_grad(layer, x, torch.ones(4, 16))
    assert torch.allclose(x.grad.double(), expected, rtol=2e-2, atol=1e-2)


def test_bias_gets_its_gradient_when_asked(rng):
    qweight, scales = dyq.ops.quantize_weight(random_weight(8, 64, rng), 64)
    bias = torch.zeros(8, requires_grad=True)
    dyq.ops.gemm(torch.randn(3, 64), qweight, scales, 64, 8, bias).sum().backward()
    assert torch.equal(bias.grad, torch.full((8,), 3.0))


def test_bias_gets_its_gradient_through_the_flag_op_too(rng):
    qweight, scales = dyq.ops.quantize_weight(random_weight(8, 64, rng), 64)
    bias = torch.zeros(8, requires_grad=True)
    x = torch.randn(5, 64, generator=rng, requires_grad=True)
    grad_out = torch.randn(5, 8, generator=rng)
    dyq.ops.gemm(x, qweight, scales, 64, dyq.PrecisionFlag(2).tensor, bias).backward(grad_out)
    assert torch.allclose(bias.grad, grad_out.sum(0))
    assert x.grad is not None and x.grad.shape == x.shape


def test_a_gradient_of_the_packed_weights_is_a_clear_error(rng):
    qweight, scales = dyq.ops.quantize_weight(random_weight(8, 64, rng), 64)
    with pytest.raises(RuntimeError, match="INT4 weights are frozen"):
        dyq.ops.gemm(torch.randn(3, 64), qweight, scales.requires_grad_(), 64, 4)


class LoRALinear(torch.nn.Module):
    """A frozen DyQLinear plus a trainable low-rank update B A, as PEFT's LoRA adds it."""

    def __init__(self, base: dyq.DyQLinear, rank: int = 4):
        super().__init__()
        self.base = base
        self.lora_a = torch.nn.Parameter(torch.randn(rank, base.in_features) * 0.01)
        self.lora_b = torch.nn.Parameter(torch.zeros(base.out_features, rank))

    def forward(self, x):
        return self.base(x) + x @ self.lora_a.T @ self.lora_b.T


@pytest.mark.parametrize("act_bits", (4, 16))
def test_lora_adapters_train_on_a_quantized_model(act_bits):
    gen = torch.Generator().manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(64, 96), torch.nn.GELU(), torch.nn.Linear(96, 8))
    dyq.quantize_model(model, group_size=32, skip=(), act_bits=act_bits)
    model[0], model[2] = LoRALinear(model[0]), LoRALinear(model[2])
    x = torch.randn(64, 64, generator=gen)
    target = torch.randn(64, 8, generator=gen)
    trainable = [p for p in model.parameters() if p.requires_grad]
    assert len(trainable) == 4  # only the adapters
    optimizer = torch.optim.Adam(trainable, lr=1e-2)
    losses = []
    for _ in range(60):
        optimizer.zero_grad()
        loss = torch.nn.functional.mse_loss(model(x), target)
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < 0.7 * losses[0]


@pytest.mark.parametrize("shape", [(64,), (2, 3, 64), (1, 1, 1, 64)])
def test_input_gradient_has_the_inputs_shape_at_any_rank(shape, rng):
    qweight, scales = dyq.ops.quantize_weight(random_weight(8, 64, rng), 64)
    x = random_activations(shape, rng).requires_grad_()
    grad_out = torch.randn(shape[:-1] + (8,), generator=rng)
    dyq.ops.gemm(x, qweight, scales, 64, 8).backward(grad_out)
    weight = dyq.ops.dequantize_weight(qweight, scales, 64).double()
    assert x.grad.shape == x.shape
    torch.testing.assert_close(x.grad.double(), grad_out.double() @ weight, rtol=1e-6, atol=1e-6)
