"""dyq.ops.width_counts: GEMM calls per activation width, counted in C++ where the width is resolved."""
import copy
import multiprocessing
import pickle

import pytest
import torch
from helpers import random_activations, random_weight

import dyq


@pytest.fixture
def layer(rng):
    qweight, scales = dyq.ops.quantize_weight(random_weight(16, 128, rng), 64)
    return qweight, scales, random_activations((3, 128), rng)


def zero_counts():
    return {bits: 0 for bits in dyq.VALID_BITS}


def test_keys_are_every_registered_width_and_reset_zeroes_them(layer):
    qweight, scales, x = layer
    dyq.ops.gemm(x, qweight, scales, 64, 4)
    dyq.ops.reset_width_counts()
    assert dyq.ops.width_counts() == zero_counts()


def test_a_known_sequence_of_fixed_widths_is_counted(layer):
    qweight, scales, x = layer
    dyq.ops.reset_width_counts()
    for bits in (2, 4, 4, 8, 16, 16, 16):
        dyq.ops.gemm(x, qweight, scales, 64, bits)
    dyq.ops.gemm(torch.empty(0, 128), qweight, scales, 64, 8)  # an empty call resolves its width too
    assert dyq.ops.width_counts() == {2: 1, 4: 2, 8: 2, 16: 3}


def test_rejected_calls_are_not_counted(layer):
    qweight, scales, x = layer
    dyq.ops.reset_width_counts()
    with pytest.raises(RuntimeError):
        dyq.ops.gemm(x, qweight, scales, 64, 3)
    with pytest.raises(RuntimeError):
        dyq.ops.gemm(x, qweight, scales, 64, torch.tensor([5], dtype=torch.int32))
    assert dyq.ops.width_counts() == zero_counts()


def test_a_flag_is_counted_at_the_value_it_holds_at_each_call(layer):
    qweight, scales, x = layer
    model = torch.nn.Sequential(torch.nn.Linear(128, 128), torch.nn.Linear(128, 64))
    flag = dyq.PrecisionFlag(16)
    dyq.quantize_model(model, group_size=64, flag=flag)
    dyq.ops.reset_width_counts()
    for bits in (16, 2, 8, 2):
        flag.bits = bits
        model(x)
    assert dyq.ops.width_counts() == {2: 4, 4: 0, 8: 2, 16: 2}


def _count_in_child(payload: bytes, queue) -> None:
    model, flag = pickle.loads(payload)
    x = torch.randn(2, 128)
    for bits in (4, 4, 2):
        flag.bits = bits
        model(x)
    queue.put(dyq.ops.width_counts())


def _model_and_flag():
    model = torch.nn.Sequential(torch.nn.Linear(128, 128), torch.nn.Linear(128, 64))
    flag = dyq.PrecisionFlag(16)
    dyq.quantize_model(model, group_size=64, flag=flag)
    return model, flag


def test_a_deepcopied_model_drives_its_own_flag():
    model, flag = _model_and_flag()
    model_copy, flag_copy = copy.deepcopy((model, flag))
    assert all(layer.flag is flag_copy for layer in model_copy if isinstance(layer, dyq.DyQLinear))
    dyq.ops.reset_width_counts()
    flag_copy.bits = 2
    model_copy(torch.randn(2, 128))
    assert flag.bits == 16 and flag_copy.tensor.item() == 2
    assert dyq.ops.width_counts() == {2: 2, 4: 0, 8: 0, 16: 0}


@pytest.mark.slow
def test_a_spawned_child_with_a_pickled_model_counts_its_own_calls():
    model, flag = _model_and_flag()
    dyq.ops.reset_width_counts()
    model(torch.randn(2, 128))  # the parent's calls stay in the parent
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    child = context.Process(target=_count_in_child, args=(pickle.dumps((model, flag)), queue))
    child.start()
    counts = queue.get(timeout=120)
    child.join(timeout=60)
    assert child.exitcode == 0
    assert counts == {2: 2, 4: 4, 8: 0, 16: 0}
    assert dyq.ops.width_counts() == {2: 0, 4: 0, 8: 0, 16: 2}
