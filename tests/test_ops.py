"""torch.ops.dyq on CPU tensors against the float64 reference of docs/numerics.md."""
import pytest
import torch
from helpers import DTYPES, assert_gemm_close, bf16_fallback, random_activations, random_weight

import dyq
from dyq import reference

ACT_BITS = dyq.VALID_BITS  # every registered width
GROUP_SIZES = dyq.GROUP_SIZES
QUANTIZED_BITS = dyq.core.precision.QUANTIZED_BITS


@pytest.mark.parametrize("group_size", GROUP_SIZES)
def test_quantize_weight_matches_reference_codes_and_scales(group_size, rng):
    n, k = 37, group_size * 3
    w = random_weight(n, k, rng)
    qweight, scales = dyq.ops.quantize_weight(w, group_size)
    codes, ref_scales = reference.quantize_weight(w, group_size)
    assert qweight.dtype == torch.uint8 and qweight.shape == (n, k // 2)
    assert torch.equal(qweight, reference.pack_int4(codes))
    assert torch.equal(scales, ref_scales)


@pytest.mark.parametrize("dtype", DTYPES)
def test_quantize_weight_accepts_low_precision_weights(dtype, rng):
    w = random_weight(8, 128, rng, dtype)
    qweight, scales = dyq.ops.quantize_weight(w, 64)
    codes, ref_scales = reference.quantize_weight(w.float(), 64)
    assert torch.equal(qweight, reference.pack_int4(codes)) and torch.equal(scales, ref_scales)


def test_dequantize_weight_is_scale_times_code(rng):
    w = random_weight(19, 256, rng)
    qweight, scales = dyq.ops.quantize_weight(w, 128)
    out = dyq.ops.dequantize_weight(qweight, scales, 128)
    assert torch.equal(out, reference.dequantize_weight(qweight, scales, 128))
    # INT4 error: at most half a step of each group's scale.
    step = scales.repeat_interleave(128, dim=1)
    assert ((out - w).abs() <= step / 2 + 1e-7).all()


def test_all_zero_weight_group_dequantizes_to_zero(rng):
    w = random_weight(4, 128, rng)
    w[1, 64:] = 0
    qweight, scales = dyq.ops.quantize_weight(w, 64)
    assert scales[1, 1] == 1.0
    assert torch.equal(dyq.ops.dequantize_weight(qweight, scales, 64)[1, 64:], torch.zeros(64))


@pytest.mark.parametrize("act_bits", QUANTIZED_BITS)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("group_size", GROUP_SIZES)
def test_quantize_activations_is_bit_identical_to_reference(act_bits, dtype, group_size, rng):
    x = random_activations((3, 5, group_size * 2), rng, dtype)
    packed, scales, zeros = dyq.ops.quantize_activations(x, group_size, act_bits)
    codes, ref_scales, ref_zeros = reference.quantize_activations(x, group_size, act_bits)
    assert packed.shape == (3, 5, group_size * 2 * act_bits // 8)
    assert torch.equal(packed, reference.pack_activations(codes, act_bits))
    assert torch.equal(scales, ref_scales)
    assert torch.equal(zeros, ref_zeros)


@pytest.mark.parametrize("act_bits", ACT_BITS)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("group_size", GROUP_SIZES)
def test_gemm_matches_reference(act_bits, dtype, group_size, rng):
    m = int(torch.randint(1, 40, (), generator=rng)) | 1          # odd M
    n = int(torch.randint(1, 70, (), generator=rng)) * 8 + 3      # N not a multiple of 8
    k = group_size * int(torch.randint(2, 5, (), generator=rng))  # several groups
    w = random_weight(n, k, rng)
    qweight, scales = dyq.ops.quantize_weight(w, group_size)
    x = random_activations((m, k), rng, dtype)
    bias = torch.randn(n, generator=rng).to(dtype)
    for b in (None, bias):
        out = dyq.ops.gemm(x, qweight, scales, group_size, act_bits, b)
        assert out.dtype == dtype and out.shape == (m, n)
        assert_gemm_close(out, x, qweight, scales, group_size, act_bits, b)


@pytest.mark.parametrize("act_bits", ACT_BITS)
def test_gemm_keeps_leading_batch_dimensions(act_bits, rng):
    w = random_weight(24, 128, rng)
    qweight, scales = dyq.ops.quantize_weight(w, 64)
    x = random_activations((2, 3, 5, 128), rng)
    out = dyq.ops.gemm(x, qweight, scales, 64, act_bits)
    assert out.shape == (2, 3, 5, 24)
    flat = dyq.ops.gemm(x.reshape(30, 128), qweight, scales, 64, act_bits)
    assert torch.equal(out.reshape(30, 24), flat)


@pytest.mark.parametrize("act_bits", ACT_BITS)
def test_gemm_with_flag_equals_gemm_at_the_flag_value(act_bits, rng):
    w = random_weight(40, 256, rng)
    qweight, scales = dyq.ops.quantize_weight(w, 128)
    x = random_activations((7, 256), rng)
    flag = dyq.PrecisionFlag(act_bits)
    assert torch.equal(dyq.ops.gemm(x, qweight, scales, 128, flag.tensor),
                       dyq.ops.gemm(x, qweight, scales, 128, act_bits))


@pytest.mark.parametrize("floor", ACT_BITS)
def test_a_floor_raises_the_flag_to_it(floor, rng):
    """gemm_with_flag(..., min_act_bits) runs at max(flag, floor); so does gemm with a fixed width."""
    qweight, scales = dyq.ops.quantize_weight(random_weight(24, 256, rng), 128)
    x = random_activations((5, 256), rng)
    flag = dyq.PrecisionFlag(2)
    for bits in ACT_BITS:
        flag.bits = bits
        expected = dyq.ops.gemm(x, qweight, scales, 128, max(bits, floor))
        assert torch.equal(dyq.ops.gemm(x, qweight, scales, 128, flag.tensor, None, floor), expected)
        assert torch.equal(dyq.ops.gemm(x, qweight, scales, 128, bits, None, floor), expected)
    before = dyq.ops.width_counts()
    flag.bits = 2
    dyq.ops.gemm(x, qweight, scales, 128, flag.tensor, None, floor)
    after = dyq.ops.width_counts()
    assert after[max(2, floor)] == before[max(2, floor)] + 1  # the width it ran at is the one counted


def test_a_floor_that_is_not_a_width_is_refused(rng):
    qweight, scales = dyq.ops.quantize_weight(random_weight(8, 64, rng), 32)
    x = random_activations((2, 64), rng)
    with pytest.raises(RuntimeError, match="min_act_bits must be"):
        torch.ops.dyq.gemm_with_flag(x, qweight, scales, 32, dyq.PrecisionFlag(4).tensor, None, 6)
    with pytest.raises(ValueError, match="min_act_bits must be one of"):
        dyq.ops.gemm(x, qweight, scales, 32, 4, None, 6)


def test_gemm_handles_empty_batch(rng):
    qweight, scales = dyq.ops.quantize_weight(random_weight(16, 64, rng), 32)
    out = dyq.ops.gemm(torch.empty(0, 64), qweight, scales, 32, 4)
    assert out.shape == (0, 16)
    assert dyq.ops.gemm(torch.empty(2, 0, 64), qweight, scales, 32, 16).shape == (2, 0, 16)


def test_gemm_accepts_non_contiguous_activations(rng):
    qweight, scales = dyq.ops.quantize_weight(random_weight(16, 64, rng), 32)
    x = random_activations((64, 10), rng).t()  # [10, 64], strided
    assert not x.is_contiguous()
    assert torch.equal(dyq.ops.gemm(x, qweight, scales, 32, 8), dyq.ops.gemm(x.contiguous(), qweight, scales, 32, 8))


def test_all_zero_activation_group_contributes_exactly_zero(rng):
    w = random_weight(8, 128, rng)
    qweight, scales = dyq.ops.quantize_weight(w, 64)
    x = random_activations((3, 128), rng)
    x[1, :64] = 0
    packed, s, z = dyq.ops.quantize_activations(x, 64, 4)
    assert s[1, 0] == 1.0 and z[1, 0] == 0 and torch.equal(packed[1, :32], torch.zeros(32, dtype=torch.uint8))
    for bits in ACT_BITS:
        assert_gemm_close(dyq.ops.gemm(x, qweight, scales, 64, bits), x, qweight, scales, 64, bits)


@pytest.mark.parametrize("act_bits", ACT_BITS)
@pytest.mark.parametrize("bad", (float("nan"), float("inf")))
def test_non_finite_input_row_gives_nan_row_and_leaves_others_finite(act_bits, bad, rng):
    qweight, scales = dyq.ops.quantize_weight(random_weight(12, 128, rng), 64)
    x = random_activations((4, 128), rng)
    x[2, 5] = bad
    out = dyq.ops.gemm(x, qweight, scales, 64, act_bits)
    assert torch.isfinite(out[[0, 1, 3]]).all()
    assert not torch.isfinite(out[2]).any()
    if act_bits != 16:
        assert out[2].isnan().all()


def test_error_shrinks_as_bits_grow_on_realistic_inputs(rng):
    """Relative error against the float64 product with the dequantized weight: A2 > A4 > A8 > A16."""
    w = random_weight(256, 1024, rng)
    qweight, scales = dyq.ops.quantize_weight(w, 128)
    x = random_activations((32, 1024), rng)
    exact = x.double() @ reference.dequantize_weight(qweight, scales, 128).double().t()
    errors = {b: ((dyq.ops.gemm(x, qweight, scales, 128, b).double() - exact).norm() / exact.norm()).item()
              for b in ACT_BITS}
    assert errors[2] > errors[4] > errors[8] > errors[16]
    # bf16 dot products round x to bf16 (relative error at most 2^-8); fp32 ones keep it.
    assert errors[16] < (2.0**-8 if bf16_fallback(32, 1024, 128) else 1e-5) and errors[8] < 0.02 and errors[2] < 1.0


@pytest.mark.parametrize("act_bits", ACT_BITS)
def test_opcheck_gemm(act_bits, rng):
    qweight, scales = dyq.ops.quantize_weight(random_weight(24, 128, rng), 64)
    x = random_activations((3, 5, 128), rng)
    bias = torch.randn(24, generator=rng)
    torch.library.opcheck(torch.ops.dyq.gemm.default, (x, qweight, scales, 64, act_bits, bias))
    torch.library.opcheck(torch.ops.dyq.gemm.default, (x.bfloat16(), qweight, scales, 64, act_bits, None))


def test_opcheck_gemm_with_flag(rng):
    qweight, scales = dyq.ops.quantize_weight(random_weight(24, 128, rng), 64)
    x = random_activations((5, 128), rng)
    torch.library.opcheck(torch.ops.dyq.gemm_with_flag.default,
                          (x, qweight, scales, 64, dyq.PrecisionFlag(4).tensor, None))
    torch.library.opcheck(torch.ops.dyq.gemm_with_flag.default,
                          (x, qweight, scales, 64, dyq.PrecisionFlag(4).tensor, None, 8))


def test_opcheck_quantizers(rng):
    w = random_weight(24, 128, rng)
    torch.library.opcheck(torch.ops.dyq.quantize_weight.default, (w, 64))
    qweight, scales = dyq.ops.quantize_weight(w, 64)
    torch.library.opcheck(torch.ops.dyq.dequantize_weight.default, (qweight, scales, 64))
    for bits in QUANTIZED_BITS:
        torch.library.opcheck(torch.ops.dyq.quantize_activations.default,
                              (random_activations((2, 3, 128), rng), 64, bits))


def test_ops_trace_with_meta_tensors():
    x = torch.empty(4, 7, 256, device="meta", dtype=torch.bfloat16)
    qweight = torch.empty(96, 128, device="meta", dtype=torch.uint8)
    scales = torch.empty(96, 2, device="meta", dtype=torch.float32)
    out = torch.ops.dyq.gemm(x, qweight, scales, 128, 4)
    assert out.shape == (4, 7, 96) and out.dtype == torch.bfloat16 and out.device.type == "meta"


def test_gemm_with_flag_compiles_once_for_every_flag_value(rng):
    """The flag is data, not a constant: torch.compile traces once and follows every later write."""
    qweight, scales = dyq.ops.quantize_weight(random_weight(32, 128, rng), 64)
    x = random_activations((3, 128), rng)
    flag = dyq.PrecisionFlag(16)
    compiled = torch.compile(lambda inp: dyq.ops.gemm(inp, qweight, scales, 64, flag.tensor) * 2,
                             backend="eager", fullgraph=True)
    for bits in (16, 2, 8, 4):
        flag.bits = bits
        assert torch.equal(compiled(x), dyq.ops.gemm(x, qweight, scales, 64, bits) * 2)


@pytest.mark.parametrize("act_bits", ACT_BITS)
def test_gemm_with_no_input_features_is_the_bias(act_bits, rng):
    qweight, scales = dyq.ops.quantize_weight(torch.empty(6, 0), 32)
    bias = torch.randn(6, generator=rng)
    assert torch.equal(dyq.ops.gemm(torch.randn(3, 0), qweight, scales, 32, act_bits, bias), bias.expand(3, 6))
    assert torch.equal(dyq.ops.gemm(torch.randn(3, 0), qweight, scales, 32, act_bits), torch.zeros(3, 6))
    for x in (torch.randn(3, 0), torch.empty(0, 0)):  # the reference check takes them too (no rows to reshape)
        assert_gemm_close(dyq.ops.gemm(x, qweight, scales, 32, act_bits, bias), x, qweight, scales, 32, act_bits, bias)


# K that the group size does not divide: the last group of each row holds the remainder.
REMAINDER_K = (576, 960, 130, 30, 6)


@pytest.mark.parametrize("k", REMAINDER_K)
@pytest.mark.parametrize("group_size", GROUP_SIZES)
def test_weight_quantization_of_a_remainder_group_matches_reference(k, group_size, rng):
    w = random_weight(11, k, rng)
    qweight, scales = dyq.ops.quantize_weight(w, group_size)
    codes, ref_scales = reference.quantize_weight(w, group_size)
    assert scales.shape == (11, -(-k // group_size))
    assert torch.equal(qweight, reference.pack_int4(codes)) and torch.equal(scales, ref_scales)
    assert torch.equal(dyq.ops.dequantize_weight(qweight, scales, group_size),
                       reference.dequantize_weight(qweight, scales, group_size))


@pytest.mark.parametrize("act_bits", QUANTIZED_BITS)
@pytest.mark.parametrize("k", (576, 960, 132, 36, 4))
def test_activation_quantization_of_a_remainder_group_is_bit_identical(act_bits, k, rng):
    for group_size in GROUP_SIZES:
        x = random_activations((3, k), rng)
        packed, scales, zeros = dyq.ops.quantize_activations(x, group_size, act_bits)
        codes, ref_scales, ref_zeros = reference.quantize_activations(x, group_size, act_bits)
        assert torch.equal(packed, reference.pack_activations(codes, act_bits))
        assert torch.equal(scales, ref_scales) and torch.equal(zeros, ref_zeros)


@pytest.mark.parametrize("act_bits", ACT_BITS)
@pytest.mark.parametrize("k", REMAINDER_K)
def test_gemm_with_a_remainder_group_matches_reference(act_bits, k, rng):
    for group_size in GROUP_SIZES:
        for m in (1, 5, 13, 40):  # the row kernels and the panel path
            for dtype in DTYPES:
                w = random_weight(21, k, rng)
                qweight, scales = dyq.ops.quantize_weight(w, group_size)
                x = random_activations((m, k), rng, dtype)
                bias = torch.randn(21, generator=rng).to(dtype)
                assert_gemm_close(dyq.ops.gemm(x, qweight, scales, group_size, act_bits, bias), x, qweight, scales,
                                  group_size, act_bits, bias)


@pytest.mark.parametrize("act_bits", ACT_BITS)
@pytest.mark.parametrize("magnitude", (1e37, 1e38, 3e38))
def test_activations_near_the_fp32_range_give_the_reference_answer(act_bits, magnitude, rng):
    """Finite inputs with a finite product give finite outputs: no scale or sum overflows."""
    # Small weights keep the true product within fp32 (an out-of-range product is an error, tested elsewhere).
    qweight, scales = dyq.ops.quantize_weight(random_weight(24, 256, rng) * 1e-3, 64)
    x = (torch.rand(13, 256, generator=rng) * 2 - 1) * magnitude
    x[0, :64] = magnitude  # a group whose range hi - lo exceeds FLT_MAX
    x[0, 64:128] = -magnitude
    for rows in (x[:3], x):
        out = dyq.ops.gemm(rows, qweight, scales, 64, act_bits)
        assert torch.isfinite(out).all()
        assert_gemm_close(out, rows, qweight, scales, 64, act_bits)
    if act_bits != 16:
        _, act_scales, _ = dyq.ops.quantize_activations(x, 64, act_bits)
        assert torch.isfinite(act_scales).all()
        assert torch.equal(act_scales, reference.quantize_activations(x, 64, act_bits)[1])


# Rows on either side of the CPU's switch from the row kernels (decode) to the panel path (4 or 5 rows on
# the AVX2 path, by the width; 2, 5 or 6 on AVX-512, by K and the width) and to the AMX tiles (4 rows at
# W4A16, 16 at the integer widths); dyq.cpu_gemm_kernel names the kernel of a call.
PANEL_THRESHOLD_ROWS = (1, 2, 3, 4, 5, 6, 7, 8, 9, 15, 16, 17, 31)


@pytest.mark.parametrize("act_bits", ACT_BITS)
@pytest.mark.parametrize("group_size", GROUP_SIZES)
def test_gemm_around_the_panel_threshold_matches_reference(act_bits, group_size, rng):
    """N not a multiple of the panels' 16 outputs, K not a multiple of the group size, fresh inputs per M."""
    n, k = 16 * 3 + 5, 4 * group_size + 34
    for m in PANEL_THRESHOLD_ROWS:
        qweight, scales = dyq.ops.quantize_weight(random_weight(n, k, rng), group_size)
        x = random_activations((m, k), rng)
        bias = torch.randn(n, generator=rng)
        assert_gemm_close(dyq.ops.gemm(x, qweight, scales, group_size, act_bits, bias), x, qweight, scales,
                          group_size, act_bits, bias)


@pytest.mark.parametrize("act_bits", ACT_BITS)
@pytest.mark.parametrize("threads", (1, 2, 3))
def test_gemm_matches_reference_at_every_thread_count(act_bits, threads, rng):
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for m in (1, 5, 16, 40):
            qweight, scales = dyq.ops.quantize_weight(random_weight(83, 640, rng), 128)
            x = random_activations((m, 640), rng, torch.bfloat16)
            assert_gemm_close(dyq.ops.gemm(x, qweight, scales, 128, act_bits), x, qweight, scales, 128, act_bits)
    finally:
        torch.set_num_threads(previous)
