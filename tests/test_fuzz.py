"""Fuzzing dyq's public surface: random shapes, dtypes, devices (meta included), group sizes, bit-widths,
strides and extreme values through every op, DyQLinear, quantize_model, the dispatcher and the runtime.

Every case must end in the reference's answer or in a clear exception: a ValueError, TypeError or
RuntimeError whose message names the argument at fault. Never a crash, a hang or a silently wrong answer.
The fast part runs in-process (a few seconds); ``test_ops_fuzz_in_a_subprocess`` (slow) repeats the op
fuzz with many more examples in a child process, so that a crash (a signal) is reported as a failure.
"""
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from helpers import assert_gemm_close
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import dyq
from dyq import reference

CLEAR_ERRORS = (ValueError, TypeError, RuntimeError)
EXAMPLES = int(os.environ.get("DYQ_FUZZ_EXAMPLES", "60"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck), derandomize=False)

GROUP_SIZES = (0, 16, 32, 48, 64, 128, 256)
BITS = (-1, 0, 1, 2, 3, 4, 8, 16, 32)
DTYPES = (torch.float32, torch.bfloat16, torch.float16, torch.float64, torch.int32, torch.complex64)
VALUES = ("normal", "zeros", "tiny", "huge", "nan", "inf")


def values(shape, kind, gen):
    base = torch.randn(shape, generator=gen)
    if kind == "zeros":
        return torch.zeros(shape)
    if kind == "tiny":
        return base * 1e-40
    if kind == "huge":
        return base.clamp(-1, 1) * 3e38
    if kind in ("nan", "inf") and base.numel():
        base.view(-1)[torch.randint(0, base.numel(), (1,), generator=gen)] = float(kind)
    return base


def expect_clear_error(error, *names):
    """The exception is one of the clear kinds and its message names one of ``names``."""
    assert isinstance(error, CLEAR_ERRORS), f"{type(error).__name__}: {error}"
    message = str(error)
    assert any(name in message for name in names), f"message names none of {names}: {message}"


def run(fn):
    try:
        return fn(), None
    except CLEAR_ERRORS as error:  # anything else propagates and fails the test
        return None, error


gemm_cases = st.fixed_dictionaries({
    "m": st.integers(0, 20), "n": st.integers(0, 40), "k": st.integers(0, 300),
    "group_size": st.sampled_from(GROUP_SIZES), "act_bits": st.sampled_from(BITS),
    "dtype": st.sampled_from(DTYPES), "device": st.sampled_from(("cpu", "meta", "mixed")),
    "values": st.sampled_from(VALUES), "bias": st.sampled_from(("none", "same", "wrong_dtype", "wrong_shape")),
    "flag": st.booleans(), "x_stride": st.sampled_from(("contiguous", "transposed", "sliced")),
    "qweight": st.sampled_from(("ok", "non_contiguous", "rank3", "int8")), "seed": st.integers(0, 2**31 - 1),
})


@FUZZ
@given(gemm_cases)
def test_gemm_is_the_reference_or_a_clear_error(case):
    gen = torch.Generator().manual_seed(case["seed"])
    m, n, k, group_size, act_bits = case["m"], case["n"], case["k"], case["group_size"], case["act_bits"]
    packing = group_size if group_size in dyq.GROUP_SIZES else 32
    weight_k = k + k % 2
    qweight, scales = dyq.ops.quantize_weight(torch.randn(n, weight_k, generator=gen) * 0.05, packing)
    x = values((m, k), case["values"], gen)
    if case["dtype"].is_floating_point or case["dtype"].is_complex:
        x = x.to(case["dtype"])
    else:
        x = x.nan_to_num().clamp(-100, 100).to(case["dtype"])
    if case["x_stride"] == "transposed":
        x = x.T.contiguous().T
    elif case["x_stride"] == "sliced":
        x = torch.cat([x, x], dim=-1)[:, ::2] if k else x
    bias = {"none": None, "same": torch.randn(n, generator=gen).to(x.dtype),
            "wrong_dtype": torch.randn(n, generator=gen, dtype=torch.float64),
            "wrong_shape": torch.randn(n + 1, generator=gen).to(x.dtype)}[case["bias"]]
    qweight_arg = {"ok": qweight, "non_contiguous": torch.cat([qweight, qweight], dim=1)[:, ::2],
                   "rank3": qweight.reshape(1, *qweight.shape), "int8": qweight.view(torch.int8)}[case["qweight"]]
    if case["device"] == "meta":
        x, qweight_arg, scales_arg = x.to("meta"), qweight_arg.to("meta"), scales.to("meta")
        bias = bias.to("meta") if bias is not None else None
    elif case["device"] == "mixed":
        scales_arg = scales.to("meta")
    else:
        scales_arg = scales
    bits = torch.tensor([act_bits], dtype=torch.int32) if case["flag"] else act_bits
    out, error = run(lambda: dyq.ops.gemm(x, qweight_arg, scales_arg, group_size, bits, bias))

    # A flag's value is data, read when a kernel runs: a meta (or traced) call cannot check it.
    bits_known = not (case["flag"] and case["device"] == "meta")
    valid = (group_size in dyq.GROUP_SIZES and (act_bits in dyq.VALID_BITS or not bits_known)
             and x.dtype in helpers_dtypes()
             and case["qweight"] in ("ok", "non_contiguous") and k == weight_k
             and case["bias"] in ("none", "same") and case["device"] != "mixed")
    if not qweight_arg.is_contiguous():
        valid = False
    if error is not None:
        assert not valid or case["values"] in ("huge",), f"valid case rejected: {error}"
        expect_clear_error(error, "x", "qweight", "scales", "group_size", "act_bits", "bias", "out of the range")
        return
    assert valid, f"invalid case accepted: {case}"
    assert out.shape == (m, n) and out.dtype == x.dtype and out.device == x.device
    if case["device"] == "cpu":
        reference_bits = act_bits
        expected = reference.gemm(x, qweight, scales, group_size, reference_bits, bias)
        if torch.isfinite(expected).all() and torch.isfinite(x.float()).all():
            assert torch.isfinite(out).all(), "finite inputs with a finite answer gave Inf or NaN"
        assert_gemm_close(out, x, qweight, scales, group_size, reference_bits, bias)


def helpers_dtypes():
    return (torch.float32, torch.bfloat16, torch.float16)


@FUZZ
@given(st.integers(0, 9), st.integers(0, 200), st.sampled_from(GROUP_SIZES), st.sampled_from(DTYPES),
       st.sampled_from(VALUES), st.sampled_from(("cpu", "meta")), st.integers(0, 2**31 - 1))
def test_quantize_weight_is_the_reference_or_a_clear_error(n, k, group_size, dtype, kind, device, seed):
    gen = torch.Generator().manual_seed(seed)
    w = values((n, k), kind, gen)
    w = w.to(dtype) if dtype.is_floating_point or dtype.is_complex else w.nan_to_num().to(dtype)
    result, error = run(lambda: dyq.ops.quantize_weight(w.to(device), group_size))
    finite = bool(torch.isfinite(w.to(torch.complex64) if dtype.is_complex else w.double()).all())
    valid = group_size in dyq.GROUP_SIZES and dtype.is_floating_point and k % 2 == 0
    if error is not None:
        assert not valid or (not finite and device == "cpu"), f"valid case rejected: {error}"
        expect_clear_error(error, "weight", "group_size")
        return
    assert valid and (finite or device == "meta")
    qweight, scales = result
    assert qweight.shape == (n, k // 2) and scales.shape == (n, -(-k // group_size))
    if device == "cpu":
        codes, ref_scales = reference.quantize_weight(w.float(), group_size)
        assert torch.equal(qweight, reference.pack_int4(codes)) and torch.equal(scales, ref_scales)


@FUZZ
@given(st.integers(0, 6), st.integers(0, 200), st.sampled_from(GROUP_SIZES), st.sampled_from(BITS),
       st.sampled_from(DTYPES), st.sampled_from(VALUES), st.sampled_from(("cpu", "meta")), st.integers(0, 2**31 - 1))
def test_quantize_activations_is_the_reference_or_a_clear_error(m, k, group_size, act_bits, dtype, kind, device,
                                                                seed):
    gen = torch.Generator().manual_seed(seed)
    x = values((m, k), kind, gen)
    x = x.to(dtype) if dtype.is_floating_point or dtype.is_complex else x.nan_to_num().clamp(-9, 9).to(dtype)
    result, error = run(lambda: dyq.ops.quantize_activations(x.to(device), group_size, act_bits))
    valid = (group_size in dyq.GROUP_SIZES and act_bits in (2, 4, 8) and dtype in helpers_dtypes()
             and (k * act_bits) % 8 == 0)
    if error is not None:
        assert not valid, f"valid case rejected: {error}"
        expect_clear_error(error, "x", "group_size", "act_bits")
        return
    assert valid
    if device == "cpu":
        packed, scales, zeros = result
        codes, ref_scales, ref_zeros = reference.quantize_activations(x, group_size, act_bits)
        assert torch.equal(packed, reference.pack_activations(codes, act_bits))
        assert torch.equal(scales, ref_scales, ) or torch.equal(scales.isnan(), ref_scales.isnan())
        assert torch.equal(zeros, ref_zeros)
        finite_groups = ~ref_scales.isnan()
        assert torch.isfinite(scales[finite_groups]).all()


@FUZZ
@given(st.integers(1, 200), st.integers(1, 20), st.sampled_from(GROUP_SIZES), st.sampled_from(BITS),
       st.booleans(), st.sampled_from(("lead", "flat", "wrong_k", "double")), st.integers(0, 2**31 - 1))
def test_dyq_linear_and_quantize_model(in_features, out_features, group_size, act_bits, use_flag, shape, seed):
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    model = torch.nn.Sequential(torch.nn.Linear(in_features, out_features), torch.nn.Linear(out_features, 3))
    flag = dyq.PrecisionFlag() if use_flag else None
    report, error = run(lambda: dyq.quantize_model(model, group_size=group_size, skip=(), act_bits=act_bits,
                                                   flag=flag))
    if error is not None:
        assert group_size not in dyq.GROUP_SIZES or act_bits not in dyq.VALID_BITS
        expect_clear_error(error, "group_size", "act_bits", "bits")
        return
    assert len(report.converted) == 2 and all(isinstance(layer, dyq.DyQLinear) for layer in model)
    x = torch.randn({"lead": (2, 3, in_features), "flat": (4, in_features), "wrong_k": (2, in_features + 1),
                     "double": (2, in_features)}[shape], generator=gen)
    if shape == "double":
        x = x.double()
    out, error = run(lambda: model(x))
    if error is not None:
        assert shape in ("wrong_k", "double")
        expect_clear_error(error, "in_features", "input")
        return
    assert out.shape == (*x.shape[:-1], 3) and torch.isfinite(out).all()
    assert "already quantized" in str(dyq.quantize_model(model, group_size=group_size, skip=()))


actions = st.one_of(
    st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=0, max_size=9).map(np.array),
    st.lists(st.floats(-1e308, 1e308), min_size=7, max_size=7).map(np.array),
    st.lists(st.complex_numbers(max_magnitude=10), min_size=7, max_size=7).map(np.array),
    st.sampled_from([None, "abcdefg", [[1.0] * 7], torch.zeros(7), torch.zeros(7, device="meta")]),
)


@FUZZ
@given(st.lists(actions, min_size=1, max_size=40), st.sampled_from(("action", "pose")))
def test_dispatcher_answers_a_width_or_a_clear_error(sequence, input_kind):
    dispatcher = dyq.KinematicDispatcher(dyq.DispatchConfig(warmup=2, input=input_kind))
    for action in sequence:
        steps = dispatcher.steps
        bits, error = run(lambda: dispatcher.step(action))
        if error is not None:
            expect_clear_error(error, "action")
            assert dispatcher.steps == steps  # a rejected action leaves the state alone
            continue
        assert bits in dyq.VALID_BITS
        sensitivity = dispatcher.sensitivity
        assert math.isnan(sensitivity) or sensitivity >= 0
        if not math.isfinite(sensitivity):
            assert dispatcher.target_bits == 16  # never less than full precision on what it cannot judge
        for proxy in dispatcher._proxies.values():
            assert all(math.isfinite(v) for v in proxy._scale._sorted) and all(map(math.isfinite, proxy._window))


@FUZZ
@given(st.dictionaries(st.sampled_from(("delay_window", "history", "warmup", "percentile", "fusion_weight",
                                        "macro_window", "theta_fp", "xyz_slice")),
                       st.one_of(st.integers(-5, 10**12), st.floats(allow_nan=True), st.none(),
                                 st.tuples(st.integers(-3, 10**9), st.integers(-3, 10**9))), max_size=4))
def test_dispatch_config_is_valid_or_a_clear_error(changes):
    config, error = run(lambda: dyq.DispatchConfig(**changes))
    if error is not None:
        expect_clear_error(error, *changes)
        return
    dispatcher = dyq.KinematicDispatcher(config)
    assert dispatcher.state_bytes < 8 * 2**20  # no config allocates more than a few MiB


@FUZZ
@given(st.lists(st.sampled_from(("ok", "prefill", "decode", "barrier", "bad_action")), min_size=1, max_size=25))
def test_runtime_recovers_from_every_failure(events):
    calls = {"barrier": 0}
    fail_barrier = {"now": False}

    def barrier():
        calls["barrier"] += 1
        if fail_barrier["now"]:
            raise RuntimeError("barrier failed")

    def failing(_=None):
        raise RuntimeError("model failed")

    trajectory = dyq.control.dispatch.synthetic_trajectory(max(len(events) + 1, 10), seed=0)
    with dyq.DyQRuntime(dyq.KinematicDispatcher(dyq.DispatchConfig(warmup=2, delay_window=1)), dyq.PrecisionFlag(),
                        barrier=barrier) as runtime:
        for t, event in enumerate(events):
            fail_barrier["now"] = event == "barrier"
            action = np.full(7, np.nan) if event == "bad_action" else trajectory[t]
            prefill = failing if event == "prefill" else (lambda: None)
            decode = failing if event == "decode" else (lambda _: None)
            _, error = run(lambda: runtime.step(action, prefill, decode))
            if event == "ok" or (event == "barrier" and error is None):  # an unchanged flag skips the barrier
                assert error is None
            elif error is not None:
                expect_clear_error(error, "failed", "action")
        fail_barrier["now"] = False
        runtime.step(trajectory[-1], lambda: None, lambda _: None)  # the next step runs normally
        assert runtime.stats[-1].bits == runtime.flag.bits == runtime.dispatcher.bits


@pytest.mark.slow
def test_ops_fuzz_in_a_subprocess():
    """The op fuzz with many more examples, isolated: a crash of the process (a signal) fails here."""
    env = dict(os.environ, DYQ_FUZZ_EXAMPLES="600")
    tests = ["test_fuzz.py::test_gemm_is_the_reference_or_a_clear_error",
             "test_fuzz.py::test_quantize_weight_is_the_reference_or_a_clear_error",
             "test_fuzz.py::test_quantize_activations_is_the_reference_or_a_clear_error"]
    result = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *tests],
                            cwd=os.path.dirname(__file__), env=env, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
