"""torch.ops.dyq on CUDA tensors against the CPU ops and the float64 reference (docs/numerics.md, docs/cuda.md).

Every test draws fresh random inputs. The BF16 fallback (act_bits = 16) rounds fp32 and fp16 inputs to
bf16 on CUDA (docs/cuda.md), so its expected value is computed from the bf16-rounded input.
"""
import pytest
import torch
from helpers import DTYPES, assert_gemm_close, random_activations, random_weight

import dyq
from dyq import reference
from dyq.rotation import OnlineRotation

pytestmark = pytest.mark.cuda

ACT_BITS = dyq.VALID_BITS  # every registered width
GROUP_SIZES = dyq.GROUP_SIZES
QUANTIZED_BITS = dyq.core.precision.QUANTIZED_BITS
ROWS = (1, 3, 8, 9, 17, 128, 300)  # decode (<= 8) and prefill (> 8) paths, with partial tiles
N_ODD = 200                      # not a multiple of the 16-row decode block or the 128-column prefill tile


def quantized_layer(n, k, group_size, gen):
    w = random_weight(n, k, gen)
    qweight, scales = torch.ops.dyq.quantize_weight(w, group_size)  # CPU op
    return qweight, scales


def as_cuda_input(x, act_bits):
    """The input the CUDA kernel effectively multiplies: bf16-rounded at act_bits = 16."""
    return x.to(torch.bfloat16).to(x.dtype) if act_bits == 16 else x


def pinned_flag(bits):
    flag = torch.empty(1, dtype=torch.int32, pin_memory=True)
    flag[0] = bits
    return flag


# ---- weights --------------------------------------------------------------------------------------

@pytest.mark.parametrize("group_size", GROUP_SIZES)
def test_quantize_weight_is_identical_to_cpu(group_size, rng):
    w = random_weight(45, group_size * 5, rng)
    qweight, scales = torch.ops.dyq.quantize_weight(w.cuda(), group_size)
    cpu_qweight, cpu_scales = torch.ops.dyq.quantize_weight(w, group_size)
    assert torch.equal(qweight.cpu(), cpu_qweight)
    assert torch.equal(scales.cpu(), cpu_scales)


def test_quantize_weight_keeps_zero_groups_exact(rng):
    w = random_weight(4, 256, rng)
    w[1, 128:] = 0
    qweight, scales = torch.ops.dyq.quantize_weight(w.cuda(), 128)
    assert scales[1, 1].item() == 1.0
    assert torch.equal(qweight[1, 64:].cpu(), torch.zeros(64, dtype=torch.uint8))


def test_quantize_weight_rejects_nonfinite_weights(rng):
    w = random_weight(4, 128, rng)
    w[2, 5] = float("inf")
    with pytest.raises(RuntimeError, match="NaN or Inf"):
        torch.ops.dyq.quantize_weight(w.cuda(), 64)


@pytest.mark.parametrize("group_size", GROUP_SIZES)
def test_dequantize_weight_is_identical_to_cpu(group_size, rng):
    qweight, scales = quantized_layer(33, group_size * 4, group_size, rng)
    out = torch.ops.dyq.dequantize_weight(qweight.cuda(), scales.cuda(), group_size)
    assert torch.equal(out.cpu(), torch.ops.dyq.dequantize_weight(qweight, scales, group_size))


# ---- activations ----------------------------------------------------------------------------------

@pytest.mark.parametrize("act_bits", QUANTIZED_BITS)
@pytest.mark.parametrize("group_size", GROUP_SIZES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_quantize_activations_is_identical_to_cpu(act_bits, group_size, dtype, rng):
    x = random_activations((2, 150, group_size * 7), rng, dtype)
    x[0, 3] = 0                      # an all-zero row: scale 1, zero point 0
    x[1, 7, 5] = float("nan")        # a non-finite group: NaN scale, codes 0
    packed, scales, zeros = torch.ops.dyq.quantize_activations(x.cuda(), group_size, act_bits)
    cpu_packed, cpu_scales, cpu_zeros = torch.ops.dyq.quantize_activations(x, group_size, act_bits)
    assert torch.equal(packed.cpu(), cpu_packed)
    assert torch.equal(zeros.cpu(), cpu_zeros)
    torch.testing.assert_close(scales.cpu(), cpu_scales, rtol=0, atol=0, equal_nan=True)


def test_quantize_activations_matches_reference(rng):
    x = random_activations((5, 256), rng)
    packed, scales, zeros = torch.ops.dyq.quantize_activations(x.cuda(), 64, 4)
    codes, ref_scales, ref_zeros = reference.quantize_activations(x, 64, 4)
    assert torch.equal(packed.cpu(), reference.pack_activations(codes, 4))
    assert torch.equal(scales.cpu(), ref_scales) and torch.equal(zeros.cpu(), ref_zeros)


# ---- GEMM ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("m", ROWS)
@pytest.mark.parametrize("act_bits", ACT_BITS)
@pytest.mark.parametrize("group_size", GROUP_SIZES)
def test_gemm_matches_reference_and_cpu(m, act_bits, group_size, rng):
    k = group_size * 5  # several groups; for G < 128 not a multiple of the 128-column tile
    qweight, scales = quantized_layer(N_ODD, k, group_size, rng)
    x = random_activations((m, k), rng)
    out = torch.ops.dyq.gemm(x.cuda(), qweight.cuda(), scales.cuda(), group_size, act_bits)
    assert out.shape == (m, N_ODD) and out.dtype == x.dtype
    assert_gemm_close(out.cpu(), as_cuda_input(x, act_bits), qweight, scales, group_size, act_bits)
    if act_bits != 16:  # same integer codes and sums as the CPU op: equal up to fp32 summation order
        cpu = torch.ops.dyq.gemm(x, qweight, scales, group_size, act_bits)
        bound = reference.gemm_error_bound(x, qweight, scales, group_size, act_bits)
        assert ((out.cpu().double() - cpu.double()).abs() <= 8 * 4e-7 * bound + 1e-30).all()


@pytest.mark.parametrize("m", (1, 5, 16, 40))
@pytest.mark.parametrize("act_bits", ACT_BITS)
def test_gemm_long_k_crosses_chunks_and_tiles(m, act_bits, rng):
    k, group_size = 4096 + 3 * 128 + 64, 64  # several decode chunks, a partial last one
    qweight, scales = quantized_layer(70, k, group_size, rng)
    x = random_activations((m, k), rng)
    out = torch.ops.dyq.gemm(x.cuda(), qweight.cuda(), scales.cuda(), group_size, act_bits)
    assert_gemm_close(out.cpu(), as_cuda_input(x, act_bits), qweight, scales, group_size, act_bits)


@pytest.mark.parametrize("m", (2, 300))
@pytest.mark.parametrize("act_bits", ACT_BITS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_gemm_dtypes_and_bias(m, act_bits, dtype, rng):
    qweight, scales = quantized_layer(130, 384, 128, rng)
    x = random_activations((m, 384), rng, dtype)
    bias = torch.randn(130, generator=rng).to(dtype)
    out = torch.ops.dyq.gemm(x.cuda(), qweight.cuda(), scales.cuda(), 128, act_bits, bias.cuda())
    assert out.dtype == dtype
    assert_gemm_close(out.cpu(), as_cuda_input(x, act_bits), qweight, scales, 128, act_bits, bias)


@pytest.mark.parametrize("m", (1, 64))
def test_gemm_leading_dims_and_noncontiguous_input(m, rng):
    qweight, scales = quantized_layer(96, 256, 64, rng)
    x = random_activations((2, m, 512), rng)[..., ::2]  # a strided view
    out = torch.ops.dyq.gemm(x.cuda(), qweight.cuda(), scales.cuda(), 64, 8)
    assert out.shape == (2, m, 96)
    assert_gemm_close(out.cpu(), x, qweight, scales, 64, 8)


@pytest.mark.parametrize("m", (1, 40))
@pytest.mark.parametrize("act_bits", ACT_BITS)
def test_nonfinite_input_row_gives_nan_row_only(m, act_bits, rng):
    qweight, scales = quantized_layer(64, 256, 128, rng)
    x = random_activations((m, 256), rng)
    x[m - 1, 17] = float("nan")
    out = torch.ops.dyq.gemm(x.cuda(), qweight.cuda(), scales.cuda(), 128, act_bits).cpu()
    assert torch.isnan(out[m - 1]).all()
    assert torch.isfinite(out[: m - 1]).all()


def test_gemm_empty_batch(rng):
    qweight, scales = quantized_layer(32, 128, 128, rng)
    out = torch.ops.dyq.gemm(torch.empty(0, 128, device="cuda"), qweight.cuda(), scales.cuda(), 128, 4)
    assert out.shape == (0, 32)


# ---- the precision flag ---------------------------------------------------------------------------

@pytest.mark.parametrize("m", (1, 17))
@pytest.mark.parametrize("act_bits", ACT_BITS)
@pytest.mark.parametrize("flag_on_gpu", (False, True))
def test_gemm_with_flag_equals_gemm_at_that_precision(m, act_bits, flag_on_gpu, rng):
    qweight, scales = quantized_layer(N_ODD, 256, 64, rng)
    x = random_activations((m, 256), rng).cuda()
    flag = pinned_flag(act_bits)
    if flag_on_gpu:
        flag = flag.cuda()
    out = torch.ops.dyq.gemm_with_flag(x, qweight.cuda(), scales.cuda(), 64, flag)
    expected = torch.ops.dyq.gemm(x, qweight.cuda(), scales.cuda(), 64, act_bits)
    assert torch.equal(out, expected)


@pytest.mark.parametrize("m", (1, 17))
@pytest.mark.parametrize("value", (0, 3, 32, -1))
@pytest.mark.parametrize("floor", (2, 8))
def test_invalid_flag_value_gives_nan_output(m, value, floor, rng):
    """A floor does not turn an invalid value into a valid width."""
    qweight, scales = quantized_layer(40, 128, 32, rng)
    x = random_activations((m, 128), rng).cuda()
    out = torch.ops.dyq.gemm_with_flag(x, qweight.cuda(), scales.cuda(), 32, pinned_flag(value), None, floor)
    assert torch.isnan(out).all()


def test_pageable_cpu_flag_is_rejected(rng):
    qweight, scales = quantized_layer(16, 128, 128, rng)
    flag = torch.tensor([8], dtype=torch.int32)  # not pinned
    with pytest.raises(RuntimeError, match="pinned"):
        torch.ops.dyq.gemm_with_flag(torch.randn(1, 128, device="cuda"), qweight.cuda(), scales.cuda(), 128, flag)


def test_flag_of_wrong_dtype_is_rejected(rng):
    qweight, scales = quantized_layer(16, 128, 128, rng)
    flag = torch.tensor([8], dtype=torch.int64).pin_memory()
    with pytest.raises(RuntimeError, match="int32"):
        torch.ops.dyq.gemm_with_flag(torch.randn(1, 128, device="cuda"), qweight.cuda(), scales.cuda(), 128, flag)


@pytest.mark.parametrize("m", (1, 3, 64))
def test_cuda_graph_replays_at_the_precision_the_flag_holds(m, rng):
    """Three chained layers captured once; each replay follows the flag's current value."""
    k = 256
    layers = [tuple(t.cuda() for t in quantized_layer(k, k, 128, rng)) for _ in range(3)]
    x = random_activations((m, k), rng).to(torch.bfloat16).cuda()
    flag = pinned_flag(16)

    def forward():
        h = x
        for qweight, scales in layers:
            h = torch.ops.dyq.gemm_with_flag(h, qweight, scales, 128, flag)
        return h

    graph, captured = dyq.capture_cuda_graph(forward)

    for bits in (2, 8, 16, 4, 16, 2):
        flag[0] = bits
        graph.replay()
        torch.cuda.synchronize()
        h = x
        for qweight, scales in layers:
            h = torch.ops.dyq.gemm(h, qweight, scales, 128, bits)
        assert torch.equal(captured, h), f"replay at {bits} bits differs from eager"


@pytest.mark.parametrize("m", (1, 64))
def test_an_exported_program_on_cuda_reads_the_pinned_flag_passed_to_it(m, rng, tmp_path):
    """dyq.export of a CUDA model: the program, also saved and loaded, takes the pinned host flag as its first
    input and follows each write, as the eager model does."""
    model = torch.nn.Sequential(torch.nn.Linear(256, 512), torch.nn.GELU(), torch.nn.Linear(512, 256)).cuda().eval()
    flag = dyq.PrecisionFlag(16, pin_memory=True)
    dyq.quantize_model(model, skip=(), flag=flag)
    x = random_activations((m, 256), rng).to(torch.bfloat16).cuda()
    torch.export.save(dyq.export(model, (x,)), tmp_path / "program.pt2")
    program = torch.export.load(tmp_path / "program.pt2").module()
    for bits in (16, 2, 8, 4, 16):
        flag.bits = bits
        with torch.no_grad():
            assert torch.equal(program(flag.tensor, x), model(x)), f"at {bits} bits"


@pytest.mark.parametrize("capture_bits", (2, 16))
def test_cuda_graph_keeps_a_layers_floor_under_every_flag_value(capture_bits, rng):
    """The middle layer never runs below A8 (min_act_bits = 8): the kernel applies the floor where it reads
    the flag, whichever value the flag held at capture."""
    k = 256
    layers = [tuple(t.cuda() for t in quantized_layer(k, k, 128, rng)) for _ in range(3)]
    floors = (2, 8, 2)
    x = random_activations((3, k), rng).to(torch.bfloat16).cuda()
    flag = pinned_flag(capture_bits)

    def forward():
        h = x
        for (qweight, scales), floor in zip(layers, floors):
            h = torch.ops.dyq.gemm_with_flag(h, qweight, scales, 128, flag, None, floor)
        return h

    graph, captured = dyq.capture_cuda_graph(forward)

    for bits in (2, 4, 8, 16, 2):
        flag[0] = bits
        graph.replay()
        torch.cuda.synchronize()
        h = x
        for (qweight, scales), floor in zip(layers, floors):
            h = torch.ops.dyq.gemm(h, qweight, scales, 128, max(bits, floor))
        assert torch.equal(captured, h), f"replay at {bits} bits differs from eager with the floor"


# ---- bad inputs -----------------------------------------------------------------------------------

def test_wrong_dtypes_are_rejected(rng):
    qweight, scales = (t.cuda() for t in quantized_layer(16, 128, 64, rng))
    x = torch.randn(2, 128, device="cuda")
    with pytest.raises(RuntimeError, match="qweight must be uint8"):
        torch.ops.dyq.gemm(x, qweight.to(torch.int8), scales, 64, 4)
    with pytest.raises(RuntimeError, match="scales must be float32"):
        torch.ops.dyq.gemm(x, qweight, scales.half(), 64, 4)
    with pytest.raises(RuntimeError, match="x must be float32"):
        torch.ops.dyq.gemm(x.to(torch.int32), qweight, scales, 64, 4)


def test_bad_sizes_and_bits_are_rejected(rng):
    qweight, scales = (t.cuda() for t in quantized_layer(16, 128, 64, rng))
    x = torch.randn(2, 128, device="cuda")
    with pytest.raises(RuntimeError, match="act_bits"):
        torch.ops.dyq.gemm(x, qweight, scales, 64, 3)
    with pytest.raises(RuntimeError, match="group_size"):
        torch.ops.dyq.gemm(x, qweight, scales, 48, 4)
    with pytest.raises(RuntimeError, match="features"):
        torch.ops.dyq.gemm(torch.randn(2, 64, device="cuda"), qweight, scales, 64, 4)


def test_weights_on_another_device_are_rejected(rng):
    qweight, scales = quantized_layer(16, 128, 64, rng)
    with pytest.raises(RuntimeError, match="qweight is on"):
        torch.ops.dyq.gemm(torch.randn(2, 128, device="cuda"), qweight, scales.cuda(), 64, 4)


# ---- K that the group size does not divide ----------------------------------------------------------

@pytest.mark.parametrize("m", ROWS)
@pytest.mark.parametrize("act_bits", ACT_BITS)
@pytest.mark.parametrize("k", (576, 960, 4096 + 96))
def test_gemm_with_a_remainder_group_matches_reference_and_cpu(m, act_bits, k, rng):
    """The last group of each row holds the remainder (576: SmolLM2's hidden size, 960: SmolVLA's)."""
    for group_size in GROUP_SIZES:
        qweight, scales = quantized_layer(N_ODD, k, group_size, rng)
        x = random_activations((m, k), rng)
        out = torch.ops.dyq.gemm(x.cuda(), qweight.cuda(), scales.cuda(), group_size, act_bits)
        assert_gemm_close(out.cpu(), as_cuda_input(x, act_bits), qweight, scales, group_size, act_bits)


@pytest.mark.parametrize("k", (576, 960, 96))
def test_quantizers_with_a_remainder_group_are_identical_to_cpu(k, rng):
    for group_size in GROUP_SIZES:
        w = random_weight(33, k, rng)
        qweight, scales = torch.ops.dyq.quantize_weight(w.cuda(), group_size)
        cpu_qweight, cpu_scales = torch.ops.dyq.quantize_weight(w, group_size)
        assert torch.equal(qweight.cpu(), cpu_qweight) and torch.equal(scales.cpu(), cpu_scales)
        assert torch.equal(torch.ops.dyq.dequantize_weight(qweight, scales, group_size).cpu(),
                           torch.ops.dyq.dequantize_weight(cpu_qweight, cpu_scales, group_size))
        x = random_activations((5, k), rng)
        for act_bits in QUANTIZED_BITS:
            cuda = torch.ops.dyq.quantize_activations(x.cuda(), group_size, act_bits)
            cpu = torch.ops.dyq.quantize_activations(x, group_size, act_bits)
            assert all(torch.equal(a.cpu(), b) for a, b in zip(cuda, cpu))


def test_k_not_a_multiple_of_32_is_rejected_on_cuda(rng):
    with pytest.raises(RuntimeError, match="CUDA kernels need K a multiple of 32"):
        torch.ops.dyq.quantize_weight(random_weight(4, 578, rng).cuda(), 64)
    qweight, scales = quantized_layer(4, 578, 64, rng)
    with pytest.raises(RuntimeError, match="CUDA kernels need K a multiple of 32"):
        torch.ops.dyq.gemm(torch.randn(2, 578, device="cuda"), qweight.cuda(), scales.cuda(), 64, 4)


@pytest.mark.parametrize("act_bits", ACT_BITS)
def test_activations_near_the_fp32_range_are_finite_on_cuda(act_bits, rng):
    qweight, scales = quantized_layer(24, 256, 64, rng)
    x = torch.full((3, 256), 3e38)
    x[:, ::2] = -3e38  # hi - lo exceeds FLT_MAX
    _, act_scales, _ = torch.ops.dyq.quantize_activations(x.cuda(), 64, 4)
    assert torch.isfinite(act_scales).all()


# ---- the online Hadamard rotation ------------------------------------------------------------------

@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("n", [1, 8, 96, 1536, 2816, 11008, 16384])
def test_hadamard_transform_matches_the_cpu_op(n, dtype, rng):
    """One block per row, the butterfly in shared memory (11008 = 344 x 32 and 16384 need more than 48 KiB).
    The CPU op is tested against the dense float64 rotation (test_hadamard_transform.py)."""
    rotation = OnlineRotation(n, seed=3)
    signs, left = rotation.signs.float(), rotation.left.float()
    x = torch.randn(5, n, generator=rng).to(dtype)
    got = dyq.ops.hadamard_transform(x.cuda(), signs.cuda(), left.cuda())
    assert got.dtype == dtype
    expected = dyq.ops.hadamard_transform(x.float(), signs, left)  # fp32 on the CPU, then one rounding
    rtol = {torch.float32: 0.0, torch.bfloat16: 2**-7, torch.float16: 2**-10}[dtype]
    torch.testing.assert_close(got.cpu().float(), expected, rtol=rtol, atol=2e-5 if dtype == torch.float32 else 1e-4)


def test_hadamard_transform_opcheck(rng):
    rotation = OnlineRotation(96, seed=1)
    x = torch.randn(2, 5, 96, generator=rng).cuda()
    torch.library.opcheck(torch.ops.dyq.hadamard_transform.default,
                          (x, rotation.signs.float().cuda(), rotation.left.float().cuda()))


# ---- RMSNorm ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("n", [1, 100, 256, 4096, 11008])
def test_rms_norm_matches_the_reference(n, dtype, rng):
    """One block per row: the block's sum of squares, then the two roundings (test_rms_norm.py tests the CPU
    op the same way)."""
    x = (3 * torch.randn(7, n, generator=rng)).to(dtype)
    weight = (0.5 + torch.rand(n, generator=rng)).to(dtype)
    got = dyq.ops.rms_norm(x.cuda(), weight.cuda(), 1e-6)
    assert got.dtype == dtype
    expected = dyq.reference.rms_norm(x, weight, 1e-6)
    step = {torch.float32: 2e-6, torch.bfloat16: 2**-7, torch.float16: 2**-10}[dtype]
    torch.testing.assert_close(got.cpu().double(), expected.double(), rtol=step, atol=1e-30)


def test_rms_norm_opcheck(rng):
    x = torch.randn(2, 5, 96, generator=rng).cuda()
    torch.library.opcheck(torch.ops.dyq.rms_norm.default, (x, torch.rand(96, generator=rng).cuda(), 1e-5))
