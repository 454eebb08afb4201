import numpy as np
import pytest
import torch

from dyq import VALID_BITS, PrecisionFlag, capture_cuda_graph
from dyq.core.precision import check_bits


def test_valid_bits_are_the_paper_precisions():
    assert VALID_BITS == (2, 4, 8, 16)


def test_default_is_full_precision():
    assert PrecisionFlag().bits == 16


@pytest.mark.parametrize("bits", VALID_BITS)
def test_bits_round_trip_through_the_tensor(bits):
    flag = PrecisionFlag(16)
    flag.bits = bits
    assert flag.bits == bits
    assert flag.tensor.item() == bits


def test_tensor_is_one_int32_on_the_cpu():
    tensor = PrecisionFlag(4).tensor
    assert tensor.dtype == torch.int32
    assert tensor.shape == (1,)
    assert tensor.device.type == "cpu"


def test_tensor_is_the_same_object_and_storage_across_writes():
    flag = PrecisionFlag(16)
    tensor, pointer = flag.tensor, flag.tensor.data_ptr()
    for bits in (2, 8, 4, 16):
        flag.bits = bits
        assert flag.tensor is tensor
        assert flag.tensor.data_ptr() == pointer
        assert tensor[0].item() == bits


def test_a_write_through_the_tensor_is_read_back_by_bits():
    flag = PrecisionFlag(16)
    flag.tensor.fill_(2)
    assert flag.bits == 2


def test_numpy_integer_bits_are_accepted():
    flag = PrecisionFlag(np.int64(8))
    assert flag.bits == 8 and isinstance(flag.bits, int)


@pytest.mark.parametrize("bits", [0, 1, 3, 6, 12, 32, -4])
def test_out_of_set_bits_are_rejected_naming_bits(bits):
    with pytest.raises(ValueError, match=r"bits must be one of \(2, 4, 8, 16\)"):
        PrecisionFlag(bits)
    flag = PrecisionFlag()
    with pytest.raises(ValueError, match="bits"):
        flag.bits = bits
    assert flag.bits == 16  # a rejected write leaves the flag alone


@pytest.mark.parametrize("bits", [4.0, "4", None, True, torch.tensor(4)])
def test_non_integer_bits_are_rejected_with_type_error(bits):
    with pytest.raises(TypeError, match="bits must be an int"):
        PrecisionFlag().bits = bits


def test_check_bits_names_the_argument():
    with pytest.raises(ValueError, match="target_bits"):
        check_bits(5, "target_bits")


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA build pins the flag")
def test_flag_is_plain_memory_without_cuda():
    flag = PrecisionFlag()
    assert not flag.is_pinned
    assert not flag.tensor.is_pinned()


@pytest.mark.cuda
def test_flag_is_pinned_with_cuda():
    flag = PrecisionFlag()
    assert flag.is_pinned
    assert flag.tensor.is_pinned()


@pytest.mark.cuda
def test_a_kernel_reads_the_value_written_before_its_launch():
    flag = PrecisionFlag(16)
    for bits in VALID_BITS:
        flag.bits = bits
        # A non-blocking copy reads the pinned int32 when the copy runs on the device.
        seen = flag.tensor.to("cuda", non_blocking=True)
        assert seen.item() == bits


def test_repr_shows_bits_and_pinning():
    assert repr(PrecisionFlag(8)) == f"PrecisionFlag(bits=8, pinned={torch.cuda.is_available()})"


@pytest.mark.skipif(torch.cuda.is_available(), reason="the CUDA tests capture graphs with it")
def test_capturing_a_cuda_graph_without_cuda_is_a_clear_error():
    with pytest.raises(RuntimeError, match="capture_cuda_graph needs CUDA"):
        capture_cuda_graph(lambda: None)
