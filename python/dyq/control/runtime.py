"""The per-step runtime: overlaps the dispatcher with the prefill and publishes b*_t before the decode.

Timeline of one control step t (paper Sec. V-B)::

    host:    begin_step(a_{t-1}) ─► prefill() ──────────────► publish(): wait, [sync], flag ← b*_t ─► decode()
    worker:       dispatcher.step(a_{t-1}) ─► b*_t (microseconds)
    device:                       prefill kernels ............ decode kernels read the flag

* The dispatcher runs on one persistent worker thread while the prefill runs, so the host normally
  finds b*_t ready when the prefill returns: ``wait_us`` in the statistics measures what is left.
* Prefill precision: by default (``prefill_bits="previous"``) the prefill runs at the flag's current
  value, i.e. b*_{t-1}, the precision of the previous step's decode; the flag is written once per
  step. ``prefill_bits=16`` (or 2, 4, 8) pins the prefill to a fixed precision instead.
* Memory ordering: the flag is read by kernels when they execute. Before a write that changes the
  flag, the runtime calls ``barrier`` (by default ``torch.cuda.synchronize`` when the flag is pinned,
  nothing on a CPU-only build) so that no pending prefill kernel reads the decode's value; writes
  that keep the value skip it. The flag is written before ``decode`` is called.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import math
import statistics
import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable, Iterator

from ..core.precision import VALID_BITS, check_bits
from .dispatch import KinematicDispatcher
from .flag import PrecisionFlag


@dataclasses.dataclass
class StepStats:
    """What one control step did.

    Attributes:
        step: index since the runtime's last reset.
        bits: the bit-width published for the decode (the forced one under ``force_precision``).
        dispatched_bits: b*_t as the dispatcher chose it.
        target_bits: b^_t, the dispatcher's target before hysteresis.
        sensitivity: S_t (NaN during warm-up).
        switched: whether ``bits`` differs from the previous step's decode precision (the flag's
            value when the runtime was built or reset, for the first step).
        forced: whether ``force_precision`` overrode the dispatcher.
        dispatcher_us: time the worker spent in ``dispatcher.step``.
        wait_us: time the host waited for the dispatcher after the prefill (ideally ~0).
        barrier_us: time spent in the barrier before a flag change (0 when the flag kept its value).
        prefill_ms, decode_ms: wall time of the callables (NaN when ``begin_step``/``publish`` are
            used directly).
    """

    step: int
    bits: int
    dispatched_bits: int
    target_bits: int
    sensitivity: float
    switched: bool
    forced: bool
    dispatcher_us: float
    wait_us: float
    barrier_us: float
    prefill_ms: float = math.nan
    decode_ms: float = math.nan


def _default_barrier(flag: PrecisionFlag) -> Callable[[], None] | None:
    if flag.is_pinned:
        import torch

        if torch.cuda.is_available():
            return torch.cuda.synchronize
    return None


class DyQRuntime:
    """Runs a :class:`~dyq.KinematicDispatcher` beside the model and drives a
    :class:`~dyq.PrecisionFlag`.

    Args:
        dispatcher: the kinematic dispatcher (its config decides action or pose input).
        flag: the flag the quantized model is bound to.
        prefill_bits: ``"previous"`` (prefill at b*_{t-1}, the flag's current value) or a fixed
            bit-width in {2, 4, 8, 16} written before each prefill.
        barrier: called before any write that changes the flag; ``"auto"`` picks
            ``torch.cuda.synchronize`` for a pinned flag on a CUDA build and nothing otherwise;
            ``None`` disables it (the caller guarantees no pending kernel reads the flag).
        max_stats: how many recent :class:`StepStats` are kept.

    Use ``step(previous_action, prefill, decode)`` in a control loop, or ``begin_step`` +
    ``publish`` around a model call of one's own. Close it (or use it as a context manager) to stop
    the worker thread.
    """

    def __init__(
        self,
        dispatcher: KinematicDispatcher,
        flag: PrecisionFlag,
        *,
        prefill_bits: int | str = "previous",
        barrier: Callable[[], Any] | str | None = "auto",
        max_stats: int = 100_000,
    ):
        if not isinstance(dispatcher, KinematicDispatcher):
            raise TypeError(f"dispatcher must be a KinematicDispatcher, got {type(dispatcher).__name__}")
        if not isinstance(flag, PrecisionFlag):
            raise TypeError(f"flag must be a PrecisionFlag, got {type(flag).__name__}")
        if prefill_bits != "previous":
            prefill_bits = check_bits(prefill_bits, "prefill_bits")
        if barrier == "auto":
            barrier = _default_barrier(flag)
        elif barrier is not None and not callable(barrier):
            raise TypeError(f"barrier must be a callable, 'auto' or None, got {barrier!r}")
        if isinstance(max_stats, bool) or not isinstance(max_stats, int) or max_stats < 1:
            raise ValueError(f"max_stats must be an int >= 1, got {max_stats!r}")
        self.dispatcher = dispatcher
        self.flag = flag
        self.prefill_bits = prefill_bits
        self.barrier = barrier
        self._stats: collections.deque[StepStats] = collections.deque(maxlen=max_stats)
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dyq-dispatch")
        self._pending: Future | None = None
        self._forced: int | None = None
        self._step_index = 0
        self._last_decode_bits = flag.bits
        self._closed = False

    # -- control loop -------------------------------------------------------------------------

    def step(self, kinematics, prefill: Callable[[], Any], decode: Callable[[Any], Any]) -> Any:
        """One control step: dispatch on ``kinematics`` while ``prefill()`` runs, publish b*_t, then
        return ``decode(prefill_output)``.

        ``kinematics`` is what the arm executed at step t-1 (an action, or a pose when the
        dispatcher's config says ``input="pose"``), or ``None`` when there is none yet (the first
        step of an episode): the dispatcher is then not advanced and its current b* (16 after a
        reset) is published.
        """
        for function, expected in ((prefill, "prefill must be a callable of no argument"),
                                   (decode, "decode must be a callable of the prefill's output")):
            if not callable(function):
                raise TypeError(f"{expected}, got {type(function).__name__}")
        self.begin_step(kinematics)
        start = time.perf_counter()
        try:
            prefill_output = prefill()
        except BaseException:
            self._abandon()
            raise
        prefill_ms = (time.perf_counter() - start) * 1e3
        self.publish()
        stats = self._stats[-1]
        stats.prefill_ms = prefill_ms
        start = time.perf_counter()
        try:
            return decode(prefill_output)
        finally:
            stats.decode_ms = (time.perf_counter() - start) * 1e3

    def begin_step(self, kinematics) -> None:
        """Start step t: hand ``kinematics`` to the worker and, with a fixed ``prefill_bits``, set
        the prefill's precision. Call before launching the prefill.

        If the barrier or the flag write fails, the exception reaches the caller and the step is
        dropped (the dispatcher still sees ``kinematics``): the next ``begin_step`` starts normally."""
        if self._closed:
            raise RuntimeError("DyQRuntime is closed; create a new one")
        if self._pending is not None:
            raise RuntimeError("begin_step called twice without publish(); publish the previous step first")
        self._pending = self._executor.submit(self._dispatch, kinematics)
        if self.prefill_bits != "previous" and self._forced is None:
            try:
                self._write(self.prefill_bits)
            except BaseException:
                self._abandon()
                raise

    def publish(self) -> int:
        """Wait for b*_t, write it (or the forced precision) into the flag, record the step's
        statistics and return the bits the decode will run at. Call after the prefill, before the
        decode.

        A failure of the dispatcher, the barrier or the flag write reaches the caller; the step is then
        dropped (no statistics) and the next ``begin_step`` starts normally."""
        if self._pending is None:
            raise RuntimeError("publish called without begin_step")
        start = time.perf_counter()
        try:
            dispatched, target, sensitivity, dispatcher_us = self._pending.result()
        finally:
            self._pending = None
        wait_us = (time.perf_counter() - start) * 1e6
        forced = self._forced is not None
        bits = self._forced if forced else dispatched
        barrier_us = self._write(bits)
        self._stats.append(
            StepStats(
                step=self._step_index,
                bits=bits,
                dispatched_bits=dispatched,
                target_bits=target,
                sensitivity=sensitivity,
                switched=bits != self._last_decode_bits,
                forced=forced,
                dispatcher_us=dispatcher_us,
                wait_us=wait_us,
                barrier_us=barrier_us,
            )
        )
        self._step_index += 1
        self._last_decode_bits = bits
        return bits

    def _dispatch(self, kinematics) -> tuple[int, int, float, float]:
        dispatcher = self.dispatcher
        start = time.perf_counter()
        if kinematics is not None:
            dispatcher.step(kinematics)
        elapsed_us = (time.perf_counter() - start) * 1e6
        return dispatcher.bits, dispatcher.target_bits, dispatcher.sensitivity, elapsed_us

    def _abandon(self) -> None:
        """Drop a pending step after a failed prefill (the dispatcher still saw its input)."""
        if self._pending is not None:
            with contextlib.suppress(Exception):
                self._pending.result()
            self._pending = None

    def _write(self, bits: int) -> float:
        """Write ``bits`` into the flag, calling the barrier first if the value changes; returns the
        barrier's time in microseconds."""
        if bits == self.flag.bits:
            return 0.0
        barrier_us = 0.0
        if self.barrier is not None:
            start = time.perf_counter()
            self.barrier()
            barrier_us = (time.perf_counter() - start) * 1e6
        self.flag.bits = bits
        return barrier_us

    # -- episodes and statistics --------------------------------------------------------------

    def reset(self, *, keep_history: bool = False) -> None:
        """New episode: reset the dispatcher (see ``KinematicDispatcher.reset``) and write its
        initial precision (16) into the flag unless a precision is forced. Statistics are kept
        (``clear_stats`` drops them)."""
        self._abandon()
        self.dispatcher.reset(keep_history=keep_history)
        self._step_index = 0
        if self._forced is None:
            self._write(self.dispatcher.bits)
        self._last_decode_bits = self.flag.bits

    @property
    def stats(self) -> list[StepStats]:
        """Statistics of the most recent steps (at most ``max_stats``), oldest first."""
        return list(self._stats)

    def clear_stats(self) -> None:
        self._stats.clear()

    def summary(self) -> dict[str, Any]:
        """Aggregates over the kept statistics: steps per bit-width, switches, mean bits and the
        median / max of dispatcher time and wait time (microseconds)."""
        stats = self._stats
        if not stats:
            return {"steps": 0}
        dispatcher_us = [s.dispatcher_us for s in stats]
        wait_us = [s.wait_us for s in stats]
        return {
            "steps": len(stats),
            "steps_per_bits": {bits: sum(s.bits == bits for s in stats) for bits in VALID_BITS},
            "mean_bits": statistics.fmean(s.bits for s in stats),
            "switches": sum(s.switched for s in stats),
            "forced_steps": sum(s.forced for s in stats),
            "dispatcher_us_median": statistics.median(dispatcher_us),
            "dispatcher_us_max": max(dispatcher_us),
            "wait_us_median": statistics.median(wait_us),
            "wait_us_max": max(wait_us),
        }

    # -- lifetime -----------------------------------------------------------------------------

    def close(self) -> None:
        """Stop the worker thread (pending work finishes first)."""
        self._abandon()
        self._closed = True
        self._executor.shutdown(wait=True)

    def __enter__(self) -> "DyQRuntime":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def __reduce_ex__(self, protocol):
        # copy.copy, copy.deepcopy and pickle all come here; a copy would share or lose the worker thread and
        # the step in flight (they had failed on an internal queue, naming neither).
        raise TypeError("a DyQRuntime cannot be copied or pickled: it owns a worker thread and the step in flight; "
                        "make one per control loop, DyQRuntime(dispatcher, flag), or copy the dispatcher's "
                        "config (dispatcher.config)")

    def __repr__(self) -> str:
        forced = f", forced={self._forced}" if self._forced is not None else ""
        return f"DyQRuntime(flag={self.flag!r}, prefill_bits={self.prefill_bits!r}, steps={self._step_index}{forced})"


def force_precision(target: PrecisionFlag | DyQRuntime, bits: int) -> contextlib.AbstractContextManager:
    """Run everything inside the block at ``bits`` (2, 4, 8 or 16), for ablations.

    On a :class:`DyQRuntime` the dispatcher keeps running (its state stays current and its choices
    are still recorded as ``dispatched_bits``) but the flag holds ``bits`` for prefill and decode;
    the flag is written through the runtime's barrier. On a bare :class:`PrecisionFlag` the value is
    written directly (no kernel reading the flag may be pending). Either way the flag gets back the
    value it held on entry; blocks nest. Arguments are checked at the call, before the block.
    """
    bits = check_bits(bits)
    if not isinstance(target, (DyQRuntime, PrecisionFlag)):
        raise TypeError(f"force_precision target must be a PrecisionFlag or DyQRuntime, got {type(target).__name__}")
    return _forced_precision(target, bits)


@contextlib.contextmanager
def _forced_precision(target: PrecisionFlag | DyQRuntime, bits: int) -> Iterator[PrecisionFlag | DyQRuntime]:
    if isinstance(target, DyQRuntime):
        previous_forced, previous_bits = target._forced, target.flag.bits
        target._write(bits)  # a failing barrier or write leaves the runtime as it was
        target._forced = bits
        try:
            yield target
        finally:
            target._forced = previous_forced
            target._write(previous_bits)
    else:
        previous_bits = target.bits
        target.bits = bits
        try:
            yield target
        finally:
            target.bits = previous_bits
