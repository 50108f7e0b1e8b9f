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
from typing import Iterator

import torch

__all__ = ["capture", "capture_lean"]

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
