"""The precision registry (csrc/common/precision.h, read through dyq.core.precision) agrees with the
reference's own formulas, and every registered width runs through every op, the flag and the CLI."""
import json

import pytest
import torch
from helpers import assert_gemm_close, random_activations, random_weight

import dyq
from dyq import reference
from dyq.apps import cli
from dyq.core import precision


def test_registry_lists_the_reference_widths_and_group_sizes():
    assert dyq.VALID_BITS == reference.ACT_BITS
    assert dyq.GROUP_SIZES == reference.GROUP_SIZES
    assert dyq.FALLBACK_BITS == 16 and precision.QUANTIZED_BITS == tuple(b for b in reference.ACT_BITS if b != 16)
    assert list(dyq.VALID_BITS) == sorted(dyq.VALID_BITS)


@pytest.mark.parametrize("bits", precision.QUANTIZED_BITS)
def test_registry_traits_agree_with_the_reference_formulas(bits):
    traits = precision.TRAITS[bits]
    assert traits.quantized and traits.bits == bits
    # levels: the largest code the reference quantizer produces (Eq. 2).
    x = torch.linspace(-1, 1, 128).reshape(1, 128)
    codes, _, _ = reference.quantize_activations(x, 32, bits)
    assert int(codes.max()) == traits.levels
    # codes per byte: how many codes the reference packs into one byte.
    assert reference.pack_activations(codes, bits).shape[-1] * traits.codes_per_byte == 128


def test_the_fallback_has_no_codes():
    assert precision.TRAITS[dyq.FALLBACK_BITS] == precision.ActivationTraits(16, False, 0, 0)


@pytest.mark.parametrize("bits", dyq.VALID_BITS)
def test_every_width_runs_through_every_op_and_the_flag(bits, rng):
    qweight, scales = dyq.ops.quantize_weight(random_weight(24, 128, rng), 64)
    x = random_activations((5, 128), rng)
    out = dyq.ops.gemm(x, qweight, scales, 64, bits)
    assert_gemm_close(out, x, qweight, scales, 64, bits)
    flag = dyq.PrecisionFlag(bits)
    assert torch.equal(dyq.ops.gemm(x, qweight, scales, 64, flag.tensor), out)
    layer = dyq.DyQLinear(128, 24, act_bits=bits, group_size=64)
    assert layer(x).shape == (5, 24)
    if bits in precision.QUANTIZED_BITS:
        packed, _, _ = dyq.ops.quantize_activations(x, 64, bits)
        assert packed.shape == (5, 128 // precision.TRAITS[bits].codes_per_byte)
    else:
        with pytest.raises(RuntimeError, match=f"act_bits must be {precision.spelled_out(precision.QUANTIZED_BITS)}"):
            dyq.ops.quantize_activations(x, 64, bits)


def test_error_messages_list_the_registered_widths(rng):
    qweight, scales = dyq.ops.quantize_weight(random_weight(8, 64, rng), 32)
    with pytest.raises(RuntimeError, match=f"act_bits must be {precision.spelled_out(dyq.VALID_BITS)}, got 3"):
        dyq.ops.gemm(torch.randn(2, 64), qweight, scales, 32, 3)
    with pytest.raises(RuntimeError, match=f"group_size must be {precision.spelled_out(dyq.GROUP_SIZES)}"):
        dyq.ops.gemm(torch.randn(2, 64), qweight, scales, 48, 4)


def test_every_registered_width_appears_in_the_cli_summary(tmp_path, capsys):
    trajectory, trace = tmp_path / "traj.npz", tmp_path / "trace.json"
    assert cli.main(["dispatch", "demo", str(trajectory), "--steps", "60"]) == 0
    assert cli.main(["dispatch", "replay", str(trajectory), "--json", str(trace)]) == 0
    summary = json.loads(trace.read_text())["summary"]
    assert [int(b) for b in summary["steps_per_bits"]] == list(dyq.VALID_BITS)
    printed = capsys.readouterr().out
    for bits in dyq.VALID_BITS:
        assert f"\n{bits:>4}  " in printed
