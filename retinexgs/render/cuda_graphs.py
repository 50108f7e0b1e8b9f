"""One way to capture a CUDA graph for every capture site (the trainer's step, the frame renderer, streamed views).

:func:`capture` is ``torch.cuda.graph`` with Python's cyclic garbage collector held off while the graph records.
Why: ``torch.cuda.graph`` no longer runs ``gc.collect()`` on entry (only under
``torch.compiler.config.force_cudagraph_gc``), so a dead reference cycle that holds an older ``CUDAGraph`` (a
finished trainer, a dropped view stream) can be collected by an allocation *during* the capture, and its
destructor resets that graph. The likely source of a capture that failed once at random beside other work with
"operation not permitted when stream is capturing (function reset)" (docs/benchmarks.md, correctness on the
device). Collecting first and pausing the collector leaves the capture only what it records.
"""
from __future__ import annotations

import contextlib
import gc
import threading
from typing import Iterator, Optional

import torch
from torch import Tensor

__all__ = ["Branch", "capture", "capture_lean"]

# Captures may overlap (a live viewer's frame graph on its server thread beside the trainer's): the collector
# is paused by the first and re-enabled by the last, and only if it was on before the first.
_lock = threading.Lock()
_depth = 0
_was_on = True


@contextlib.contextmanager
def _collector_paused() -> Iterator[None]:
    """Python's cyclic collector off until the outermost pause ends (re-enabled only if it was on)."""
    global _depth, _was_on
    with _lock:
        if _depth == 0:
            _was_on = gc.isenabled()
            gc.disable()
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0 and _was_on:
                gc.enable()


@contextlib.contextmanager
def capture_lean(graph: "torch.cuda.CUDAGraph", stream: "torch.cuda.Stream", pool=None) -> Iterator[None]:
    """Record onto ``stream`` (which first waits for the current stream) into ``graph``, sharing ``pool``, with
    the collector paused, and none of ``torch.cuda.graph``'s preparations: no device synchronisation, no full
    collection, no emptying of the device and pinned-host caches. With a GPU-bound step in flight those cost
    most of a density event's 34-44 ms (the host waits for the queue, then cudaFree and cudaMalloc refill the
    cache; experiments/notes/2026-11-26-scale-events.md), and the Gaussians' channels are re-captured at every
    densification, dozens of times a run. For re-captures of work already run eagerly in this process (library
    handles and workspaces exist)."""
    stream.wait_stream(torch.cuda.current_stream(stream.device))
    with _collector_paused(), torch.cuda.stream(stream):
        graph.capture_begin(*(() if pool is None else (pool,)))
        try:
            yield
        finally:
            graph.capture_end()


@contextlib.contextmanager
def capture(graph: "torch.cuda.CUDAGraph", **kwargs) -> Iterator[None]:
    """``with torch.cuda.graph(graph, **kwargs)`` after a full collection and with the collector paused until
    the capture ends (re-enabled only if it was on)."""
    gc.collect()
    with _collector_paused(), torch.cuda.graph(graph, **kwargs):
        yield


class Branch:
    """Work that does not depend on what the current stream runs next, as a parallel branch of the CUDA graph being
    captured: inside ``with branch:`` kernels go to a side stream forked from the current one, and :meth:`join` makes
    the current stream wait for them (their ``outputs`` recorded as used there). A replay then runs the two chains
    side by side: each kernel of a graph waits out its predecessor's latency (≈ 1.5 µs, a fox-dark step's ~300
    kernels: experiments/notes/2026-11-30-step-bound.md), so two chains of small kernels take about the longer's time.
    Autograd runs each backward kernel on its forward kernel's stream, so the branch's backward is a branch too.
    Outside a capture (eager steps, the CPU) it does nothing: the same kernels on the one stream, in the same order."""

    def __init__(self, like: Tensor) -> None:
        self._side: Optional["torch.cuda.Stream"] = None
        if like.is_cuda and torch.cuda.is_current_stream_capturing():
            self._main = torch.cuda.current_stream(like.device)
            self._side = torch.cuda.Stream(device=like.device)
            self._ctx = torch.cuda.stream(self._side)

    def __enter__(self) -> "Branch":
        if self._side is not None:
            self._side.wait_stream(self._main)
            self._ctx.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self._side is not None:
            self._ctx.__exit__(*exc)

    def join(self, *outputs: Tensor) -> None:
        """The current stream waits for the branch; ``outputs`` (made on the branch, read after the join) are
        recorded as used on it, so their memory is not handed to the branch again while the capture reads them."""
        if self._side is None:
            return
        self._main.wait_stream(self._side)
        for t in outputs:
            if t.is_cuda:
                t.record_stream(self._main)
