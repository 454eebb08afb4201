"""Host memory for the packed INT4 weights: 2 MiB pages where Linux offers them.

A decode on the CPU streams every packed weight byte once per token. In 4 KiB pages the 8 MiB of a
4096 x 4096 layer span 2048 pages, and the stream misses the TLB every 4 KiB; in Linux's transparent
huge pages (2 MiB) it misses once per 512 of those. Most distributions ship them in ``madvise`` mode,
where only memory advised ``MADV_HUGEPAGE`` gets them, and torch's allocator does not advise its
allocations (unless ``THP_MEM_ALLOC_ENABLE=1`` is set before torch starts). On the AMD EPYC of the README,
one thread, W4A8 on 4096 x 4096 weights rotated through four times the last-level cache took 0.33 to
0.41 ms a call on huge pages against 0.42 to 0.56 ms on 4 KiB pages (four alternating runs), and 11008 x
4096 0.87 to 0.96 ms against 1.06 to 1.27 (three).

So a :class:`~dyq.DyQLinear` on the CPU keeps its packed weights and scales, where they fill at least one
huge page, in a private anonymous mapping aligned to 2 MiB and advised for huge pages (``on_huge_pages``).
The values are the same bytes: only where they live changes. The tensor owns its mapping (it is unmapped
with the tensor's storage), and copies of it (``copy.deepcopy``, ``.clone()``, ``.to``) are ordinary
torch memory, which :class:`~dyq.DyQLinear` moves back after a deep copy or an unpickling.
``DYQ_HUGE_PAGES=0`` keeps everything in torch's own memory.
"""
from __future__ import annotations

import functools
import mmap
import os

import torch

HUGE_PAGE_BYTES = 2 << 20
_THP_SETTING = "/sys/kernel/mm/transparent_hugepage/enabled"


@functools.lru_cache(maxsize=None)
def huge_pages_available() -> bool:
    """Whether this platform can advise memory for transparent huge pages, the kernel has not turned them
    off (``never``) and ``DYQ_HUGE_PAGES=0`` is not set (read once, at the first conversion)."""
    if os.environ.get("DYQ_HUGE_PAGES", "1") == "0":
        return False
    if not hasattr(mmap, "MADV_HUGEPAGE") or not hasattr(mmap, "MAP_PRIVATE"):
        return False
    try:
        with open(_THP_SETTING) as setting:
            return "[never]" not in setting.read()
    except OSError:
        return False


def huge_page_empty(shape, dtype: torch.dtype) -> torch.Tensor:
    """A zero-filled contiguous CPU tensor of ``shape`` and ``dtype`` whose memory starts on a 2 MiB
    boundary and is advised for huge pages (``torch.zeros`` where :func:`huge_pages_available` is False).
    The whole 2 MiB stretches of it get huge pages, its tail ordinary ones."""
    shape = torch.Size(shape)
    if not huge_pages_available():
        return torch.zeros(shape, dtype=dtype)
    nbytes = shape.numel() * dtype.itemsize
    if nbytes == 0:
        return torch.zeros(shape, dtype=dtype)
    # One huge page more than needed, so that a 2 MiB boundary lies within the first one; the untouched
    # rest of the mapping never gets physical memory.
    try:
        mapping = mmap.mmap(-1, nbytes + HUGE_PAGE_BYTES, flags=mmap.MAP_PRIVATE)
        start = (-torch.frombuffer(mapping, dtype=torch.uint8, count=1).data_ptr()) % HUGE_PAGE_BYTES
        advised = -(-nbytes // mmap.PAGESIZE) * mmap.PAGESIZE
        mapping.madvise(mmap.MADV_HUGEPAGE, start, advised)
    except OSError:  # no mapping to be had (a limit on mappings, say): torch's own memory serves as well
        return torch.zeros(shape, dtype=dtype)
    # The tensor's storage is exactly its bytes (torch.save and copies take no more), and holds the mapping.
    return torch.frombuffer(mapping, dtype=torch.uint8, count=nbytes, offset=start).view(dtype).view(shape)


def on_huge_pages(tensor: torch.Tensor) -> torch.Tensor:
    """``tensor`` copied onto huge pages (:func:`huge_page_empty`) when it is a plain CPU tensor of at least
    one huge page, without gradient history; otherwise ``tensor`` itself (subclasses too: a fake tensor of
    a tracing mode has no memory to move)."""
    if (type(tensor) is not torch.Tensor or tensor.device.type != "cpu" or tensor.requires_grad
            or tensor.numel() * tensor.element_size() < HUGE_PAGE_BYTES or not huge_pages_available()):
        return tensor
    placed = huge_page_empty(tensor.shape, tensor.dtype)
    placed.copy_(tensor)
    return placed
