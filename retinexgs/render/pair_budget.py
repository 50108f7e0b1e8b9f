"""Sizing the tile-pair buffer of a binning that never waits for the GPU (issue 65).

Binning's exact path copies the pair count M to the host and waits for it, because the pair buffers are sized
by M; the GPU then idles while the host launches the rest of the step. :class:`PairBudget` sizes the buffer from
the counts of earlier steps instead, learning each step's M one step late from a copy the GPU made long ago.
"""
from __future__ import annotations

import math
from typing import Callable, Dict, Hashable, Optional, Tuple

import torch
from torch import Tensor

# Starts reading an int64 [1] count tensor (on its device, in stream order) and returns the function that finishes
# the read and gives the value; called again only after that function.
LateReader = Callable[[Tensor], Callable[[], int]]

MAX_CAPACITY = 2 ** 31 - 1  # pair indices are int32


class _CudaLateRead:
    """The GPU's late read: a non-blocking copy into pinned host memory and an event after it. Finishing
    waits on that event, which the GPU passed a step ago: no stall in practice."""

    def __init__(self) -> None:
        self._host: Optional[Tensor] = None
        self._event: Optional[torch.cuda.Event] = None

    def __call__(self, count: Tensor) -> Callable[[], int]:
        if self._host is None:  # one pinned buffer: each read is finished before the next one starts
            self._host = torch.empty(1, dtype=torch.int64, pin_memory=True)
            self._event = torch.cuda.Event()
        self._host.copy_(count, non_blocking=True)
        self._event.record(torch.cuda.current_stream(count.device))
        return self._finish

    def _finish(self) -> int:
        self._event.synchronize()
        return int(self._host[0])


class PairBudget:
    """The capacity of each sync-free binning (:func:`retinexgs.render.functions.bin_gaussians` with a
    ``capacity``), for a loop that renders the same Gaussians again and again (training).

    Why: knowing the pair count M before sizing the buffer costs a host sync every render (issue 65); the
    counts of the last renders, times a margin, bound the next one almost always, and the M that a sync-free
    binning writes on the device is read a render later, when the GPU is long past it.

    :meth:`plan` gives the capacity for the next render: ``ceil(margin * max M seen since the last reset)``, or
    None (bin with the exact, synced path and pass its M to :meth:`observe_synced`) on the first call, after
    :meth:`reset`, when the Gaussian count N changed since the last call (densification: re-measure), for an
    image size not rendered since (counts are kept per size: the coarse-to-fine ``train.resolution`` changes M
    about k² fold with no change of N, and a capture may mix sizes), after an overflow (a late-read M above the
    capacity its render used: that render dropped pairs; counted in ``overflows``), with ``margin`` 0, and for
    CPU tensors (the CPU pays no sync) unless a ``reader`` is given. After a sync-free binning,
    :meth:`observe` starts the late read of its ``count``.

    Counters for the log: ``steps`` (renders planned), ``synced`` (of them, binned with the synced path),
    ``overflows`` (renders that dropped pairs)."""

    def __init__(self, margin: float = 1.5, reader: Optional[LateReader] = None) -> None:
        """``margin``: the capacity over the largest recent count (>= 1), or 0 for always synced (exact) binning.
        ``reader``: how a device count is read late (default: a pinned copy and a CUDA event, CUDA tensors only);
        a given reader (tests) is used on any device, the CPU included."""
        if isinstance(margin, bool) or not isinstance(margin, (int, float)) or not (
                margin == 0 or 1 <= margin < math.inf):
            raise ValueError(f"margin must be 0 (always synced) or a finite number >= 1, got {margin!r}")
        self.margin = float(margin)
        self._reader = reader
        self._cuda_reader: Optional[_CudaLateRead] = None
        self.steps = self.synced = self.overflows = 0
        self._max_seen: Dict[Hashable, int] = {}  # the largest M since the last reset, per image size
        self._n: Optional[int] = None  # the Gaussian count of the last plan
        self._epoch = 0  # bumped by every reset: a read started before it measured the old set
        # (finish, capacity used, epoch, size)
        self._pending: Optional[Tuple[Callable[[], int], int, int, Hashable]] = None
        self._size: Hashable = None  # the size of the last plan

    def reset(self) -> None:
        """Forget the counts seen: the next render bins synced and measures again."""
        self._max_seen = {}
        self._epoch += 1

    def plan(self, n: int, device: torch.device, size: Hashable = None) -> Optional[int]:
        """The capacity for the next render of ``n`` Gaussians on ``device`` at image ``size`` (e.g. (W, H)),
        or None: bin synced (then :meth:`observe_synced`; else :meth:`observe`)."""
        self.steps += 1
        overflowed = self._settle()
        if n != self._n:  # another set of Gaussians: its counts are not the old ones'
            self._n = n
            self.reset()
        self._size = size
        seen = self._max_seen.get(size)
        on_cpu_by_default = self._reader is None and torch.device(device).type != "cuda"
        if self.margin == 0 or seen is None or overflowed or on_cpu_by_default:
            self.synced += 1
            return None
        return min(MAX_CAPACITY, math.ceil(self.margin * seen))

    def observe_synced(self, pairs: int) -> None:
        """The exact M of a synced binning (the length of its ids) of the render just planned."""
        self._see(int(pairs), self._size)

    def observe(self, count: Tensor, capacity: int) -> None:
        """Start the late read of a sync-free binning's device ``count``, binned with ``capacity``."""
        if self._reader is not None:
            reader = self._reader
        else:
            if self._cuda_reader is None:
                self._cuda_reader = _CudaLateRead()
            reader = self._cuda_reader
        self._pending = (reader(count), int(capacity), self._epoch, self._size)

    def summary(self) -> Optional[str]:
        """One line for the end of a run if any render dropped pairs, else None (finishes the last read)."""
        self._settle()
        if not self.overflows:
            return None
        return (f"{self.overflows} of {self.steps} renders dropped tile pairs: their pair count outgrew the "
                f"sync-free binning's buffer (train.pair_margin {self.margin:g} x the largest recent count); "
                "each was followed by a synced render")

    def _settle(self) -> bool:
        """Finish the pending late read: fold its M into the counts seen; True if its render overflowed."""
        if self._pending is None:
            return False
        finish, capacity, epoch, size = self._pending
        self._pending = None
        m = finish()
        if epoch == self._epoch:
            self._see(m, size)
        if m > capacity:
            self.overflows += 1
            return True
        return False

    def _see(self, m: int, size: Hashable) -> None:
        self._max_seen[size] = max(self._max_seen.get(size, m), m)
