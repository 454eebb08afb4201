"""dyq.ops.hadamard_transform, the online rotation of down_proj's input: ``(x * signs) (left (x) H_p) / sqrt(p)``
against the dense float64 product with OnlineRotation.matrix(), on fresh random inputs."""
import math

import pytest
import torch
from helpers import OUTPUT_RTOL

import dyq
from dyq.rotation import OnlineRotation, hadamard_factors

# n = m x p: m = 1 (a power of two), the Paley orders 12, 20, 28, 36, 44, 60 and their multiples by 2^k.
HADAMARD_SIZES = (1, 8, 12, 96, 160, 448, 576, 960, 1536, 2816)
LEADING_SHAPES = ((), (5,), (2, 3))


def kernel_arguments(rotation):
    return rotation.signs.float(), rotation.left.float()


def raises(match):
    return pytest.raises(RuntimeError, match=match)


@pytest.mark.parametrize("n", HADAMARD_SIZES)
@pytest.mark.parametrize("lead", LEADING_SHAPES)
def test_fp32_equals_the_dense_rotation(n, lead, rng):
    rotation = OnlineRotation(n, seed=torch.randint(0, 1000, (), generator=rng).item())
    assert rotation.hadamard
    x = torch.randn(*lead, n, generator=rng)
    expected = x.double() @ rotation.matrix()
    got = dyq.ops.hadamard_transform(x, *kernel_arguments(rotation))
    assert got.shape == x.shape and got.dtype == torch.float32
    # fp32 rounding of log2(p) butterfly adds and m multiply-adds on unit-variance rows.
    torch.testing.assert_close(got.double(), expected, rtol=0, atol=2e-5)


def test_llama_7b_intermediate_size(rng):
    """11008 = 344 x 32, 344 Paley's order over GF(7^3); against the float64 factored product (the dense
    matrix would be 11008^2 doubles)."""
    rotation = OnlineRotation(11008, seed=1)
    assert rotation.hadamard and rotation.left.shape == (344, 344)
    x = torch.randn(3, 11008, generator=rng)
    expected = rotation(x.double())  # float64: (x * signs) viewed as [344, 32], A^T X B in torch
    got = dyq.ops.hadamard_transform(x, *kernel_arguments(rotation))
    torch.testing.assert_close(got.double(), expected, rtol=0, atol=2e-5)


@pytest.mark.parametrize("dtype", (torch.bfloat16, torch.float16))
def test_half_precision_rounds_the_fp32_result_once(dtype, rng):
    rotation = OnlineRotation(1536, seed=2)
    x = torch.randn(4, 1536, generator=rng).to(dtype)
    expected = x.double() @ rotation.matrix()
    got = dyq.ops.hadamard_transform(x, *kernel_arguments(rotation))
    assert got.dtype == dtype
    torch.testing.assert_close(got.double(), expected, rtol=2 * OUTPUT_RTOL[dtype], atol=1e-4)


@pytest.mark.parametrize(("m", "p"), [(1, 1), (3, 4), (12, 64), (7, 32)])
def test_any_left_factor_is_applied_as_given(m, p, rng):
    left = torch.randn(m, m, generator=rng)
    signs = torch.randn(m * p, generator=rng)  # not only +-1: the kernel applies what it is given
    sylvester = hadamard_factors(p)[1] if p > 1 else torch.ones(1, 1, dtype=torch.float64)
    rotation = torch.kron(left.double(), sylvester) / math.sqrt(p)
    x = torch.randn(6, m * p, generator=rng)
    expected = (x.double() * signs.double()) @ rotation
    torch.testing.assert_close(dyq.ops.hadamard_transform(x, signs, left).double(), expected, rtol=0,
                               atol=1e-5 * max(1.0, expected.abs().max().item()))


def test_a_non_contiguous_x_is_read_as_its_values(rng):
    rotation = OnlineRotation(96, seed=0)
    x = torch.randn(96, 8, generator=rng).T  # [8, 96], strided
    assert not x.is_contiguous()
    got = dyq.ops.hadamard_transform(x, *kernel_arguments(rotation))
    assert torch.equal(got, dyq.ops.hadamard_transform(x.contiguous(), *kernel_arguments(rotation)))


def test_rows_are_transformed_independently(rng):
    rotation = OnlineRotation(576, seed=0)
    x = torch.randn(300, 576, generator=rng)  # enough rows for several threads
    all_rows = dyq.ops.hadamard_transform(x, *kernel_arguments(rotation))
    for row in (0, 150, 299):
        assert torch.equal(all_rows[row], dyq.ops.hadamard_transform(x[row], *kernel_arguments(rotation)))


def test_gradient_is_the_transposed_rotation(rng):
    rotation = OnlineRotation(96, seed=4)
    x = torch.randn(3, 96, generator=rng, requires_grad=True)
    grad_out = torch.randn(3, 96, generator=rng)
    dyq.ops.hadamard_transform(x, *kernel_arguments(rotation)).backward(grad_out)
    torch.testing.assert_close(x.grad.double(), grad_out.double() @ rotation.matrix().T, rtol=0, atol=2e-5)


def test_opcheck(rng):
    rotation = OnlineRotation(96, seed=1)
    for x in (torch.randn(2, 5, 96, generator=rng), torch.randn(4, 96, generator=rng).bfloat16(),
              torch.randn(4, 96, generator=rng).requires_grad_()):
        torch.library.opcheck(torch.ops.dyq.hadamard_transform.default, (x, *kernel_arguments(rotation)))


def test_traces_with_meta_tensors():
    x = torch.empty(4, 7, 1536, device="meta", dtype=torch.bfloat16)
    signs = torch.empty(1536, device="meta")
    left = torch.empty(12, 12, device="meta")
    out = torch.ops.dyq.hadamard_transform(x, signs, left)
    assert out.shape == x.shape and out.dtype == torch.bfloat16 and out.device.type == "meta"


def test_non_finite_values_spread_over_their_row_only():
    rotation = OnlineRotation(96, seed=0)
    x = torch.ones(3, 96)
    x[1, 5] = float("nan")
    out = dyq.ops.hadamard_transform(x, *kernel_arguments(rotation))
    assert out[1].isnan().all() and out[[0, 2]].isfinite().all()


# ---- bad arguments: each names the argument and what was expected ----------------------------------------

@pytest.fixture
def arguments(rng):
    return torch.randn(3, 96, generator=rng), torch.ones(96), torch.eye(12)


def test_dtypes_are_checked(arguments):
    x, signs, left = arguments
    with raises("x must be float32, bfloat16 or float16, got Double"):
        dyq.ops.hadamard_transform(x.double(), signs, left)
    with raises("signs must be float32, got Half"):
        dyq.ops.hadamard_transform(x, signs.half(), left)
    with raises("left must be float32, got Int"):
        dyq.ops.hadamard_transform(x, signs, left.int())


def test_shapes_are_checked(arguments):
    x, signs, left = arguments
    with raises(r"signs must have shape \[n\] = \[96\]"):
        dyq.ops.hadamard_transform(x, signs[:95], left)
    with raises(r"left must be a square matrix \[m, m\]"):
        dyq.ops.hadamard_transform(x, signs, left[:, :6])
    with raises("not a multiple of left's order m = 12"):
        dyq.ops.hadamard_transform(x[:, :90], signs[:90], left)
    with raises("n / m = 3 must be a power of two"):
        dyq.ops.hadamard_transform(x[:, :36], signs[:36], left)
    with raises("x must have at least one dimension"):
        dyq.ops.hadamard_transform(x[0, 0], signs[:1], left[:1, :1])


def test_signs_and_left_must_be_contiguous(arguments):
    x, signs, left = arguments
    with raises("signs must be contiguous"):
        dyq.ops.hadamard_transform(x, torch.ones(192)[::2], left)
    with raises("left must be contiguous"):
        dyq.ops.hadamard_transform(x, signs, torch.randn(12, 12).T)


def test_devices_are_checked(arguments):
    x, signs, left = arguments
    with raises("signs is on meta but x is on cpu"):
        dyq.ops.hadamard_transform(x, signs.to("meta"), left)
    with raises("left is on meta but x is on cpu"):
        dyq.ops.hadamard_transform(x, signs, left.to("meta"))
