"""The precision flag: one int32 that selects the activation bit-width of a whole model.

A quantized model binds every DyQ linear layer to the same :class:`PrecisionFlag`, so a single host
write switches all of them. The GEMM ``dyq.ops.gemm(..., flag.tensor, ...)`` (``dyq::gemm_with_flag``) reads
the int32 at run time, never at trace or capture time: a CUDA graph captured once serves every
precision.

Memory
------
With CUDA available the int32 lives in pinned (page-locked) host memory allocated by torch's
``cudaHostAlloc``-backed allocator. Under unified virtual addressing such memory is mapped into the
device address space with the same pointer, so a kernel reads the flag directly (zero-copy) and no
host-to-device transfer is ever enqueued. Without CUDA the flag is ordinary host memory and the CPU
kernels read it the same way.

Memory ordering
---------------
The flag is read by kernels when they *run*, not when they are enqueued. A write is therefore safe
only when no kernel that may read the old value is still pending:

* the host writes the flag, then launches (or replays the graph of) the decode; the kernel launch
  orders the earlier host store before the kernel's reads;
* the host must not write the flag while kernels that should see the previous value are queued or
  running (for example a prefill that was enqueued asynchronously). :class:`dyq.DyQRuntime`
  synchronizes before any write that changes the value, and publishes b*_t before it signals the
  decode.
* kernels read the flag once per launch with an uncached (volatile, ``__ldcv``) load so that no copy
  cached by an earlier kernel is used.

Writes go through a numpy view of the tensor's storage: a plain store (about 0.5 microseconds through
the property), with no torch dispatch and no allocation.
"""

from __future__ import annotations

import torch

from ..core.precision import check_bits


class PrecisionFlag:
    """One int32 holding the activation bit-width (2, 4, 8 or 16) that a whole model runs at.

    A flag pickles and deep-copies as its value and pinning: the copy owns a new int32 (a process that
    unpickles a model gets flags of its own), and layers that shared a flag share the copy.

    Args:
        bits: initial bit-width, one of :data:`dyq.VALID_BITS` (default 16, full precision).
        pin_memory: allocate the int32 in pinned host memory; by default pinned exactly when
            ``torch.cuda.is_available()``.
    """

    __slots__ = ("_tensor", "_view")

    def __init__(self, bits: int = 16, *, pin_memory: bool | None = None):
        bits = check_bits(bits)
        if pin_memory is None:
            pin_memory = torch.cuda.is_available()
        self._tensor = torch.empty(1, dtype=torch.int32, pin_memory=bool(pin_memory))
        self._view = self._tensor.numpy()  # shares the tensor's storage
        self._view[0] = bits

    # Copied field by field, the tensor and its numpy view would become two separate buffers.
    def __getstate__(self) -> dict:
        return {"bits": self.bits, "pinned": self.is_pinned}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["bits"], pin_memory=state["pinned"] and torch.cuda.is_available())

    @property
    def bits(self) -> int:
        """The bit-width the next kernels will read."""
        return int(self._view[0])

    @bits.setter
    def bits(self, bits: int) -> None:
        self._view[0] = check_bits(bits)

    @property
    def tensor(self) -> torch.Tensor:
        """The one-element int32 CPU tensor the GEMM ops read; the same object for the flag's life."""
        return self._tensor

    @property
    def is_pinned(self) -> bool:
        """Whether the int32 lives in pinned host memory (readable by the GPU without a copy)."""
        return self._tensor.is_pinned()

    def __repr__(self) -> str:
        return f"PrecisionFlag(bits={self.bits}, pinned={self.is_pinned})"


def capture_cuda_graph(forward):
    """Captures ``forward()`` (CUDA work, such as a decode step of layers bound to a :class:`PrecisionFlag`)
    into a CUDA graph and returns ``(graph, output)``: each ``graph.replay()`` reruns it and refills
    ``output`` in place, at the width the flag holds when the replay runs. ``forward`` first runs once on a
    side stream outside the capture, as torch requires, so that lazy initializations are not captured."""
    if not torch.cuda.is_available():
        raise RuntimeError("dyq.capture_cuda_graph needs CUDA: torch.cuda.is_available() is False")
    stream = torch.cuda.Stream()
    stream.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(stream):
        forward()
    torch.cuda.current_stream().wait_stream(stream)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        output = forward()
    return graph, output
