"""Every misuse is a clear error that names the argument and what was expected."""
import pytest
import torch
from helpers import random_activations, random_weight

import dyq


@pytest.fixture
def layer(rng):
    qweight, scales = dyq.ops.quantize_weight(random_weight(16, 128, rng), 64)
    return qweight, scales, random_activations((3, 128), rng)


def raises(match):
    return pytest.raises((RuntimeError, ValueError, TypeError), match=match)


def test_activation_dtype_is_checked(layer):
    qweight, scales, x = layer
    with raises("x must be float32, bfloat16 or float16"):
        dyq.ops.gemm(x.double(), qweight, scales, 64, 4)
    with raises("x must be float32, bfloat16 or float16"):
        dyq.ops.gemm(x.to(torch.int32), qweight, scales, 64, 4)


def test_weight_dtypes_are_checked(layer):
    qweight, scales, x = layer
    with raises("qweight must be uint8"):
        dyq.ops.gemm(x, qweight.to(torch.int8), scales, 64, 4)
    with raises("scales must be float32"):
        dyq.ops.gemm(x, qweight, scales.half(), 64, 4)


def test_shapes_are_checked(layer):
    qweight, scales, x = layer
    with raises("x has 96 features"):
        dyq.ops.gemm(x[:, :96], qweight, scales, 64, 4)
    with raises("scales must have shape"):
        dyq.ops.gemm(x, qweight, scales[:, :1].contiguous(), 64, 4)
    with raises("qweight must have shape"):
        dyq.ops.gemm(x, qweight.reshape(-1), scales, 64, 4)
    with raises("bias must have shape"):
        dyq.ops.gemm(x, qweight, scales, 64, 4, torch.zeros(15))
    with raises("bias must have the dtype of x"):
        dyq.ops.gemm(x, qweight, scales, 64, 4, torch.zeros(16, dtype=torch.float16))


def test_group_size_is_checked(layer, rng):
    qweight, scales, x = layer
    with raises("group_size must be 32, 64 or 128"):
        dyq.ops.gemm(x, qweight, scales, 48, 4)
    with raises("group_size must be 32, 64 or 128"):
        dyq.ops.quantize_weight(random_weight(4, 96, rng), 16)
    with raises("not a multiple of group_size"):
        dyq.ops.quantize_weight(random_weight(4, 96, rng), 64)
    with raises("not a multiple of group_size"):
        dyq.ops.quantize_activations(random_activations((2, 96), rng), 64, 4)


@pytest.mark.parametrize("bits", (0, 1, 3, 6, 12, 32, -4))
def test_bit_width_is_checked(layer, bits):
    qweight, scales, x = layer
    with raises("act_bits must be 2, 4, 8 or 16"):
        dyq.ops.gemm(x, qweight, scales, 64, bits)
    flag = torch.tensor([bits], dtype=torch.int32)
    with raises("act_bits_flag holds"):
        dyq.ops.gemm(x, qweight, scales, 64, flag)
    with raises("act_bits must be"):
        dyq.ops.quantize_activations(x, 64, 16 if bits == 0 else bits)


def test_flag_tensor_is_checked(layer):
    qweight, scales, x = layer
    with raises("act_bits_flag must be an int32"):
        dyq.ops.gemm(x, qweight, scales, 64, torch.tensor([4], dtype=torch.int64))
    with raises("exactly one element"):
        dyq.ops.gemm(x, qweight, scales, 64, torch.tensor([4, 4], dtype=torch.int32))


def test_non_contiguous_packed_weight_is_rejected(layer, rng):
    qweight, scales, x = layer
    wide, wide_scales = dyq.ops.quantize_weight(random_weight(16, 256, rng), 64)
    with raises("qweight must be contiguous"):
        dyq.ops.gemm(x, wide[:, ::2], wide_scales[:, ::2].contiguous(), 64, 4)
    with raises("scales must be contiguous"):
        dyq.ops.gemm(x, qweight, wide_scales[:, ::2], 64, 4)


def test_non_finite_weight_is_rejected(rng):
    w = random_weight(4, 128, rng)
    w[2, 3] = float("nan")
    with raises("weight contains NaN or Inf"):
        dyq.ops.quantize_weight(w, 64)
    w[2, 3] = float("inf")
    with raises("weight contains NaN or Inf"):
        dyq.ops.quantize_weight(w, 64)


@pytest.mark.cuda
def test_device_mismatch_is_rejected(layer):
    qweight, scales, x = layer
    with raises("qweight is on cpu"):
        dyq.ops.gemm(x.cuda(), qweight, scales.cuda(), 64, 4)
