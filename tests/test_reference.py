"""Properties of the reference numerics itself (docs/numerics.md), for all inputs hypothesis can find."""
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import dyq
from dyq import reference

settings.register_profile("dyq", deadline=None, max_examples=60)
settings.load_profile("dyq")

groups = st.sampled_from((32, 64, 128))
bits = st.sampled_from((2, 4, 8))
seeds = st.integers(0, 2**31 - 1)


@given(st.integers(1, 9), st.integers(1, 4), seeds)
def test_int4_packing_round_trips(rows, pairs, seed):
    codes = torch.randint(-8, 8, (rows, pairs * 2), generator=torch.Generator().manual_seed(seed), dtype=torch.int8)
    packed = reference.pack_int4(codes)
    assert packed.shape == (rows, pairs) and torch.equal(reference.unpack_int4(packed), codes)
    # Byte layout: column 2j in the low nibble.
    assert int(packed[0, 0]) == (int(codes[0, 0]) & 0xF) | ((int(codes[0, 1]) & 0xF) << 4)


@given(bits, st.integers(1, 5), seeds)
def test_activation_packing_round_trips(act_bits, rows, seed):
    codes = torch.randint(0, 2**act_bits, (rows, 64), generator=torch.Generator().manual_seed(seed),
                          dtype=torch.int32).to(torch.uint8)
    packed = reference.pack_activations(codes, act_bits)
    assert packed.shape == (rows, 64 * act_bits // 8)
    assert torch.equal(reference.unpack_activations(packed, act_bits), codes)


@given(bits, groups, seeds, st.floats(1e-3, 1e3))
def test_activation_quantization_error_is_at_most_half_a_step(act_bits, group_size, seed, magnitude):
    x = torch.randn(3, group_size * 2, generator=torch.Generator().manual_seed(seed)) * magnitude
    codes, scales, zeros = reference.quantize_activations(x, group_size, act_bits)
    assert int(codes.max()) <= 2**act_bits - 1
    deq = (codes.float().reshape(3, 2, group_size) - zeros.float().unsqueeze(-1)) * scales.unsqueeze(-1)
    err = (deq.reshape(3, -1) - x).abs().reshape(3, 2, group_size)
    # Half a step, plus the zero point's rounding (at most another half step at the range's ends).
    assert (err <= scales.unsqueeze(-1) * (1 + 1e-4)).all()


@given(bits, groups, seeds)
def test_zero_is_exactly_representable(act_bits, group_size, seed):
    x = torch.randn(2, group_size, generator=torch.Generator().manual_seed(seed))
    x[:, ::3] = 0
    codes, scales, zeros = reference.quantize_activations(x, group_size, act_bits)
    deq = (codes.float() - zeros.float()) * scales
    assert (deq[:, ::3] == 0).all()


@given(groups, seeds)
def test_kernel_packing_matches_reference_for_any_draw(group_size, seed):
    gen = torch.Generator().manual_seed(seed)
    w = torch.randn(5, group_size * 2, generator=gen) * torch.rand(1, generator=gen).item() * 10
    qweight, scales = dyq.ops.quantize_weight(w, group_size)
    codes, ref_scales = reference.quantize_weight(w, group_size)
    assert torch.equal(qweight, reference.pack_int4(codes)) and torch.equal(scales, ref_scales)
    for b in dyq.core.precision.QUANTIZED_BITS:
        packed, s, z = dyq.ops.quantize_activations(w, group_size, b)
        c, rs, rz = reference.quantize_activations(w, group_size, b)
        assert torch.equal(packed, reference.pack_activations(c, b)) and torch.equal(s, rs) and torch.equal(z, rz)


def test_inconsistent_arguments_are_refused(rng):
    """The executable specification fails loudly too: no numbers from arguments no kernel takes."""
    qweight, scales = dyq.ops.quantize_weight(torch.randn(4, 64, generator=rng), 64)
    with pytest.raises(ValueError, match="x has K = 32 columns but qweight packs K = 64"):
        reference.gemm(torch.randn(2, 32, generator=rng), qweight, scales, 64, 8)
    with pytest.raises(ValueError, match=r"scales must have shape \(4, 2\) for K = 64 at group_size 32"):
        reference.gemm(torch.randn(2, 64, generator=rng), qweight, scales, 32, 8)
    for bits in (3, 0):
        with pytest.raises(ValueError, match=rf"act_bits must be an int in \(2, 4, 8, 16\), got {bits}"):
            reference.gemm(torch.randn(2, 64, generator=rng), qweight, scales, 64, bits)
    with pytest.raises(ValueError, match=r"group_size must be an int in \(32, 64, 128\), got 48"):
        reference.quantize_weight(torch.randn(4, 96, generator=rng), 48)
    with pytest.raises(ValueError, match="act_bits 16 is not quantized"):
        reference.quantize_activations(torch.randn(2, 64, generator=rng), 64, 16)
