"""Which path the CPU kernels run (``csrc/cpu/cpu_isa.h``).

Every path is compiled into ``dyq._C``; the best one this CPU can execute is chosen on first use, unless
``DYQ_CPU_ISA=amx|avx512_bf16|avx512|avx_vnni|avx2|portable`` forces one (set it before the first dyq op runs).
"""
from __future__ import annotations

import os

import numpy as np

from .. import _C


def cpu_info() -> dict:
    """``isa``: the path in use; ``runnable``: the paths this CPU can execute, best first; ``compiled``:
    the paths in this build; ``forced``: the value of ``DYQ_CPU_ISA``, or None; ``threads``: whose threads
    run the kernels, ``"torch"`` (torch's intra-op pool, the usual case) or ``"dyq"`` (dyq's own pool, in a
    build against a torch that ships no OpenMP runtime); ``huge_pages``: whether CPU layers keep their packed
    weights on transparent huge pages (:mod:`dyq.core.host_memory`).

    Raises ValueError when ``DYQ_CPU_ISA`` names no path or one this CPU cannot execute."""
    from .host_memory import huge_pages_available

    isa, runnable, compiled = _C.cpu_isa()
    return {"isa": isa, "runnable": list(runnable), "compiled": list(compiled),
            "forced": os.environ.get("DYQ_CPU_ISA") or None, "threads": _C.cpu_threads(),
            "huge_pages": huge_pages_available()}


def cpu_gemm_kernel(m: int, k: int, group_size: int, act_bits: int) -> str:
    """The kernel the active CPU path runs for an ``[m, k]`` input at ``act_bits``, as ``"<path>/<kernel>"``
    (e.g. ``"avx512/panel-vnni"``): which instructions do the work, for benchmarks to record."""
    from .precision import check_bits, check_group_size

    check_group_size(group_size)
    for name, value in (("m", m), ("k", k)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
            raise ValueError(f"{name} must be an int >= 0, got {value!r}")
    if k % 2:
        raise ValueError(f"k must be even (two INT4 codes per byte), got {k}")
    return _C.cpu_gemm_kernel(int(m), int(k), int(group_size), check_bits(act_bits, "act_bits"))
