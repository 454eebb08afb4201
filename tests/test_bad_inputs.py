"""Every misuse is a clear error that names the argument and what was expected."""
import contextlib

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
    with raises("group_size must be 32, 64 or 128"):
        dyq.ops.gemm(x, qweight, scales, 0, 4)


def test_k_must_fill_whole_bytes(rng):
    """K need not be a multiple of the group size, only fill whole bytes of packed codes."""
    with raises("K must be even"):
        dyq.ops.quantize_weight(random_weight(4, 97, rng), 64)
    with raises("K must be a multiple of 4"):
        dyq.ops.quantize_activations(random_activations((2, 98), rng), 64, 2)
    with raises("K must be a multiple of 2"):
        dyq.ops.quantize_activations(random_activations((2, 97), rng), 64, 4)
    dyq.ops.quantize_activations(random_activations((2, 97), rng), 64, 8)  # one code per byte: any K


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
    # Finite in float64 but beyond float32: not called NaN or Inf.
    w = random_weight(4, 128, rng).double()
    w[1, 7] = 1e300
    with raises(r"weight has values beyond float32's range \(\|w\| above 3.4e38\)"):
        dyq.ops.quantize_weight(w, 64)


@pytest.mark.cuda
def test_device_mismatch_is_rejected(layer):
    qweight, scales, x = layer
    with raises("qweight is on cpu"):
        dyq.ops.gemm(x.cuda(), qweight, scales.cuda(), 64, 4)


def test_meta_tensors_mixed_with_cpu_tensors_are_rejected(layer):
    qweight, scales, x = layer
    with raises("qweight is on meta but x is on cpu"):
        dyq.ops.gemm(x, qweight.to("meta"), scales.to("meta"), 64, 4)
    with raises("scales is on cpu but x is on meta"):
        dyq.ops.gemm(x.to("meta"), qweight.to("meta"), scales, 64, 4)
    with raises("bias is on meta but x is on cpu"):
        dyq.ops.gemm(x, qweight, scales, 64, 4, torch.zeros(16, device="meta"))
    with raises("scales is on meta but x is on cpu"):
        dyq.ops.dequantize_weight(qweight, scales.to("meta"), 64)
    # A meta flag would send real inputs to the fake kernel, whose output is never computed.
    with raises(r"act_bits_flag must be a CPU \(host\) tensor or on x's device \(cpu\), got meta"):
        dyq.ops.gemm(x, qweight, scales, 64, torch.tensor([8], dtype=torch.int32, device="meta"))
    # On meta inputs a meta flag is the shape computation it looks like.
    out = dyq.ops.gemm(x.to("meta"), qweight.to("meta"), scales.to("meta"), 64,
                       torch.tensor([8], dtype=torch.int32, device="meta"))
    assert out.device.type == "meta" and out.shape == (3, 16)


def test_group_size_must_be_an_int(rng):
    """A float such as 64.0 compares equal to 64, but no tensor shape takes it: refused by name."""
    with pytest.raises(TypeError, match="group_size must be an int in"):
        dyq.DyQLinear(128, 4, group_size=64.0)
    with pytest.raises(TypeError, match="group_size must be an int in"):
        dyq.DyQLinear.from_linear(torch.nn.Linear(128, 4), group_size=64.0)
    assert dyq.DyQLinear(128, 4, group_size=64).group_size == 64


@pytest.mark.parametrize("device", ("meta", "fake"))
def test_fake_kernels_reject_what_the_real_kernels_reject(layer, device):
    """One validation: the meta and fake (torch.compile) kernels run the C++ checks of the real ones."""
    from torch._subclasses.fake_tensor import FakeTensorMode

    qweight, scales, x = layer
    mode = FakeTensorMode() if device == "fake" else contextlib.nullcontext()
    on = "cpu" if device == "fake" else "meta"
    with mode:
        x, qweight, scales = (torch.empty(t.shape, dtype=t.dtype, device=on) for t in (x, qweight, scales))
        with raises("act_bits must be 2, 4, 8 or 16, got 3"):
            dyq.ops.gemm(x, qweight, scales, 64, 3)
        with raises("qweight must have shape"):
            dyq.ops.gemm(x, qweight.reshape(16, 2, 32), scales, 64, 4)
        with raises("group_size must be 32, 64 or 128, got 0"):
            dyq.ops.gemm(x, qweight, scales, 0, 4)
        with raises("x must be float32, bfloat16 or float16"):
            dyq.ops.gemm(x.double(), qweight, scales, 64, 4)
        with raises("act_bits_flag must be an int32"):
            dyq.ops.gemm(x, qweight, scales, 64, torch.empty(1, dtype=torch.int64, device=on))
        with raises("K must be even"):
            dyq.ops.quantize_weight(torch.empty(4, 7, device=on), 64)
        with raises("act_bits must be 2, 4 or 8"):
            dyq.ops.quantize_activations(x, 64, 16)
        assert dyq.ops.gemm(x, qweight, scales, 64, 4).shape == (3, 16)


@pytest.mark.parametrize("layout", ("sparse", "sparse_csr"))
def test_non_dense_layouts_are_rejected(layer, layout):
    qweight, scales, x = layer
    convert = {"sparse": lambda t: t.to_sparse(), "sparse_csr": lambda t: t.to_sparse_csr()}[layout]
    with raises("x must be a dense"):
        dyq.ops.gemm(convert(x), qweight, scales, 64, 4)
    with raises("weight must be a dense"):
        dyq.ops.quantize_weight(convert(torch.randn(4, 64)), 64)


def test_product_out_of_the_output_range_is_an_error(rng):
    """Finite inputs whose true product overflows the dtype are reported, not returned as Inf or NaN."""
    qweight, scales = dyq.ops.quantize_weight(torch.full((4, 64), 60000.0), 64)
    x = torch.full((2, 64), 60000.0, dtype=torch.float16)
    with raises("out of the range of Half"):
        dyq.ops.gemm(x, qweight, scales, 64, 16)
    with raises("out of the range of Half"):
        dyq.ops.gemm(x, qweight, scales, 64, 8)


@pytest.mark.parametrize("dtype", (torch.float16, torch.bfloat16, torch.float32))
@pytest.mark.parametrize("threads", (1, 2))
def test_one_overflowing_output_is_an_error_on_every_kernel(dtype, threads, rng):
    """A single output beyond the dtype's range, wherever it lies, fails the call: the CPU kernels check the
    outputs as each thread writes them (the decode rows, the panels, the threads' shares of rows)."""
    big = 60000.0 if dtype == torch.float16 else 3e38
    name = {torch.float16: "Half", torch.bfloat16: "BFloat16", torch.float32: "Float"}[dtype]
    n, k = 96, 256
    w = random_weight(n, k, rng) * 1e-3
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for m in (1, 3, 7, 40):
            for act_bits in (16, 8):
                row, column = int(torch.randint(m, (1,), generator=rng)), int(torch.randint(n, (1,), generator=rng))
                weight = w.clone()
                weight[column] = 1.0
                qweight, scales = dyq.ops.quantize_weight(weight, 128)
                x = (torch.rand(m, k, generator=rng) - 0.5).to(dtype)
                assert torch.isfinite(dyq.ops.gemm(x, qweight, scales, 128, act_bits)).all()
                x[row] = big  # the true product of that row and weight row is k times beyond the range
                with raises(f"out of the range of {name}"):
                    dyq.ops.gemm(x, qweight, scales, 128, act_bits)
    finally:
        torch.set_num_threads(previous)


def test_cpu_gemm_kernel_refuses_shapes_no_call_has():
    with raises(r"m must be an int >= 0, got -1"):
        dyq.cpu_gemm_kernel(-1, 4096, 128, 8)
    with raises(r"k must be even \(two INT4 codes per byte\), got 4095"):
        dyq.cpu_gemm_kernel(1, 4095, 128, 8)
    assert dyq.cpu_gemm_kernel(0, 4096, 128, 8).startswith(dyq.cpu_info()["isa"] + "/")  # an empty input is a call
