"""The packed weights of CPU layers on huge pages (dyq.core.host_memory): the same values, in memory that
starts on a 2 MiB boundary and that the kernel sees advised for huge pages, through conversion, deep copies,
pickling and loading."""
import copy
import os
import pickle
import subprocess
import sys

import pytest
import torch

import dyq
from dyq.core import ops
from dyq.core.host_memory import HUGE_PAGE_BYTES, huge_page_empty, huge_pages_available, on_huge_pages

needs_huge_pages = pytest.mark.skipif(not huge_pages_available(), reason="no transparent huge pages here")


def mapping_fields(tensor: torch.Tensor) -> dict:
    """The /proc/self/smaps fields of the mapping that holds the tensor's first byte."""
    address, fields, inside = tensor.data_ptr(), {}, False
    with open("/proc/self/smaps") as smaps:
        for line in smaps:
            head = line.split()[0]
            if "-" in head and ":" not in head:  # a mapping's first line: "start-end perms ..."
                start, end = (int(bound, 16) for bound in head.split("-"))
                inside = start <= address < end
            elif inside:
                fields[head.rstrip(":")] = line.split()[1]
    return fields


def assert_on_huge_pages(tensor: torch.Tensor) -> None:
    assert tensor.data_ptr() % HUGE_PAGE_BYTES == 0
    fields = mapping_fields(tensor)
    assert int(fields["Size"]) * 1024 >= tensor.numel() * tensor.element_size()
    if "THPeligible" in fields:  # the kernel's own word that this mapping may take huge pages
        assert fields["THPeligible"] == "1"


@needs_huge_pages
@pytest.mark.parametrize("dtype", (torch.uint8, torch.float32))
def test_on_huge_pages_keeps_the_values_in_advised_memory(dtype, rng):
    shape = (3 * HUGE_PAGE_BYTES // 1024, 1024 // torch.empty((), dtype=dtype).element_size())  # 3 MiB
    tensor = (torch.randint(0, 256, shape, generator=rng, dtype=torch.uint8) if dtype == torch.uint8
              else torch.randn(shape, generator=rng))
    placed = on_huge_pages(tensor)
    assert placed is not tensor and placed.dtype == dtype and placed.shape == tensor.shape
    assert placed.is_contiguous() and torch.equal(placed, tensor)
    assert_on_huge_pages(placed)
    # The storage is exactly the tensor's bytes: saving or copying it takes no slack of the mapping.
    assert placed.untyped_storage().nbytes() == tensor.numel() * tensor.element_size()
    placed.add_(1)  # writable memory, independent of the source
    assert not torch.equal(placed, tensor)


def test_on_huge_pages_leaves_small_and_other_tensors_alone():
    small = torch.zeros(HUGE_PAGE_BYTES - 1, dtype=torch.uint8)
    assert on_huge_pages(small) is small
    meta = torch.empty(4 * HUGE_PAGE_BYTES, dtype=torch.uint8, device="meta")
    assert on_huge_pages(meta) is meta
    with_grad = torch.zeros(HUGE_PAGE_BYTES, requires_grad=True)
    assert on_huge_pages(with_grad) is with_grad
    from torch._subclasses.fake_tensor import FakeTensorMode

    with FakeTensorMode():
        fake = torch.zeros(4 * HUGE_PAGE_BYTES, dtype=torch.uint8)
        assert on_huge_pages(fake) is fake
        assert dyq.DyQLinear(4096, 4096).qweight.device.type == "cpu"  # built under the mode, nothing moved


@needs_huge_pages
def test_huge_page_empty_is_zero_filled():
    tensor = huge_page_empty((5, HUGE_PAGE_BYTES // 8), torch.float64)
    assert tensor.shape == (5, HUGE_PAGE_BYTES // 8) and tensor.dtype == torch.float64
    assert not tensor.any()
    assert_on_huge_pages(tensor)


def random_layer(rng) -> tuple[torch.nn.Linear, "dyq.DyQLinear"]:
    """A random 4096 x 1024 nn.Linear and its W4A8 DyQLinear: 2 MiB of codes, 128 KiB of scales (too small
    to move)."""
    linear = torch.nn.Linear(1024, 4096)
    with torch.no_grad():
        linear.weight.copy_(torch.randn(4096, 1024, generator=rng) * 0.05)
    return linear, dyq.DyQLinear.from_linear(linear, act_bits=8)


@needs_huge_pages
def test_dyqlinear_packed_weights_stay_on_huge_pages(rng):
    linear, layer = random_layer(rng)
    assert_on_huge_pages(layer.qweight)
    qweight, scales = ops.quantize_weight(linear.weight.detach(), 128)
    assert torch.equal(layer.qweight, qweight) and torch.equal(layer.scales, scales)
    x = torch.randn(3, 1024, generator=rng)
    expected = ops.gemm(x, qweight, scales, 128, 8, linear.bias.detach())
    assert torch.equal(layer(x), expected)  # the same bytes, the same kernel: the same outputs

    # Copies land in ordinary memory; the layer moves them back.
    for other in (copy.deepcopy(layer), pickle.loads(pickle.dumps(layer))):
        assert_on_huge_pages(other.qweight)
        assert torch.equal(other.qweight, layer.qweight) and torch.equal(other(x), expected)

    # A layer converted in place, and a shell filled by a state dict, as loading does.
    in_place = dyq.DyQLinear.convert_in_place(copy.deepcopy(linear), act_bits=8)
    assert_on_huge_pages(in_place.qweight)
    assert torch.equal(in_place.qweight, qweight)
    shell = dyq.DyQLinear.convert_in_place(torch.nn.Linear(1024, 4096), quantize=False)
    assert_on_huge_pages(shell.qweight)
    shell.load_state_dict(layer.state_dict())
    assert_on_huge_pages(shell.qweight)
    shell.set_precision(8)
    assert torch.equal(shell(x), expected)


def test_dyq_huge_pages_0_turns_them_off():
    script = ("import torch, dyq; from dyq.core.host_memory import on_huge_pages, huge_pages_available; "
              "t = torch.ones(4 << 20, dtype=torch.uint8); "
              "assert not huge_pages_available() and on_huge_pages(t) is t; "
              "assert dyq.cpu_info()['huge_pages'] is False; print('off')")
    result = subprocess.run([sys.executable, "-c", script], env={**os.environ, "DYQ_HUGE_PAGES": "0"},
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and result.stdout.strip() == "off", result.stderr


@needs_huge_pages
def test_without_a_mapping_torch_memory_serves(monkeypatch):
    import mmap
    import types

    import dyq.core.host_memory as host_memory

    def refuse(*args, **kwargs):
        raise OSError(12, "Cannot allocate memory")

    fake = types.SimpleNamespace(mmap=refuse, MAP_PRIVATE=mmap.MAP_PRIVATE, PAGESIZE=mmap.PAGESIZE,
                                 MADV_HUGEPAGE=mmap.MADV_HUGEPAGE)
    monkeypatch.setattr(host_memory, "mmap", fake)
    tensor = torch.arange(HUGE_PAGE_BYTES, dtype=torch.int32)
    placed = host_memory.on_huge_pages(tensor)
    assert placed is not tensor and torch.equal(placed, tensor)  # a copy in torch's memory, same values


def test_cpu_info_and_benchmarks_say_whether_huge_pages_are_used():
    from dyq.results import environment

    assert dyq.cpu_info()["huge_pages"] is huge_pages_available()
    assert environment()["cpu_huge_pages"] is huge_pages_available()


@needs_huge_pages
def test_moves_onto_the_cpu_land_on_huge_pages_and_no_other_apply_copies(rng):
    _, layer = random_layer(rng)
    x = torch.randn(2, 1024, generator=rng)
    expected = layer(x)

    # New CPU tensors from an _apply (as a move back from a GPU makes them) go onto huge pages.
    moved = copy.deepcopy(layer)._apply(lambda t: t.clone())
    assert_on_huge_pages(moved.qweight)
    assert torch.equal(moved.qweight, layer.qweight) and torch.equal(moved(x), expected)
    with torch.device("meta"):
        shell = dyq.DyQLinear(1024, 4096)
    shell.to_empty(device="cpu")
    assert_on_huge_pages(shell.qweight)
    shell.load_state_dict(layer.state_dict())
    shell.set_precision(8)
    assert_on_huge_pages(shell.qweight)
    assert torch.equal(shell(x), expected)

    # What an _apply returns unchanged stays put: no copy for .float() or .cpu(), and share_memory() keeps
    # the shared storage it moved the codes into.
    qweight = layer.qweight
    assert layer.float().qweight is qweight and layer.cpu().qweight is qweight
    assert layer.to(torch.bfloat16).qweight is qweight and layer.scales.dtype == torch.float32
    shared = copy.deepcopy(layer).share_memory()
    assert shared.qweight.is_shared() and torch.equal(shared.qweight, qweight)
