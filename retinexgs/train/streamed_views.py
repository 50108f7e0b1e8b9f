"""The training views streamed from a :class:`~retinexgs.train.view_store.ViewStore` to the device
(:class:`StreamedViews`): a few reused device slots, the next view prefetched on a side stream while the
current step runs, its conversion to float32 captured as a CUDA graph; a small store is held whole in pinned
host memory (:func:`hold_whole`), a larger one read view by view by a worker thread.
"""
from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

from retinexgs.render import Camera, cuda_graphs
from retinexgs.train.view_store import PHOTO_LEVELS, ViewStore, photo_table
from retinexgs.train.views import TrainView, gib, make_train_view, packed_channels, unpack_edges


# ---- streaming to the device --------------------------------------------------------------------------------

class _Inline:
    """An executor that runs each job at once in the calling thread (the CPU's path: no copy to overlap)."""

    def submit(self, fn, *args) -> Future:
        fut: Future = Future()
        try:
            fut.set_result(fn(*args))
        except BaseException as exc:  # handed to whoever asks for the result, as a worker thread's would be
            fut.set_exception(exc)
        return fut

    def shutdown(self, wait: bool = True) -> None:
        pass


def available_host_bytes() -> Optional[int]:
    """The host memory the OS could give now (Linux ``MemAvailable``), or None where it cannot be read."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def hold_whole(store: ViewStore, limit: int, pinned: bool,
               log: Optional[Callable[[str], None]] = None) -> Optional[Tensor]:
    """The whole store read into one host tensor (page-locked if ``pinned``) when it is at most ``limit`` bytes
    and at most half the host memory available now; else None (views are then read one at a time). A pinned
    allocation the driver refuses falls back to None, with one line to ``log``."""
    n = store.nbytes
    avail = available_host_bytes()
    if n > limit or (avail is not None and n > avail // 2):
        return None
    try:
        whole = torch.empty(n, dtype=torch.uint8, pin_memory=pinned)
    except RuntimeError as err:  # e.g. page-locked memory exhausted
        if log is not None:
            log(f"views: could not hold the view store in pinned memory ({gib(n)}: {err}); reading it view by view")
        return None
    store.read_into(whole.numpy())
    return whole


@dataclass
class _SlotGraph:
    """One device slot's conversion of one view layout, captured: ``replay()`` refills the slot's packed
    buffer from its compact device bytes (the graph's static input and output); ``view`` is what the captured
    conversion left, its maps views of the slot's buffer (a load hands on a copy with the view's camera)."""

    replay: Callable[[], None]
    view: TrainView


# Distinct view layouts (size, photo type) whose conversion is captured; further ones convert eagerly.
MAX_GRAPHED_LAYOUTS = 8


class StreamedViews(Sequence):
    """The training views as a sequence of :class:`TrainView`, streamed from a :class:`ViewStore`: ``views[i]``
    brings view i to the device (at once if it was not prefetched), then starts the next views that
    ``upcoming()`` names (the trainer's order, nearest first) on their way, to arrive while the caller trains on
    view i: the next one is copied to the device and converted there, the one after is read from the memory map
    into a staging buffer by a worker thread.

    At most ``slots`` views are on the device, in buffers allocated once for the largest view and reused: the
    packed targets [H,W,K] (and the depth prior's edge maps) in float32, and on CUDA the view's compact bytes
    (the copy's destination) beside them. The host side is ``slots`` staging buffers of one view's compact
    bytes (pinned on CUDA). A view returned stays valid until ``slots - 1`` more views have been fetched (the
    trainer uses each for one step).

    A store of at most ``resident_bytes`` (``train.views_pinned_gb``) is instead read whole into one (pinned)
    host buffer at the start: a view's copy then starts from it, with no staging and no worker thread.

    The worker thread only copies host memory (no CUDA call: a CUDA graph captured meanwhile on the main thread
    is safe). The main thread, between steps, queues on a side stream the non-blocking copy of a staged view to
    the device, its conversion to float32 (the photo through its bit depth's lookup table, the reader's
    values) and packing as :meth:`TrainView.pack` does, and an event; ``views[i]`` makes the current stream wait
    on it. A device slot is overwritten only after an event recorded on the current stream when its view was
    last handed on (the step that used it is queued before it); a staging buffer only after its copy's event.
    On the CPU the same code converts from the staging buffer directly, and host reads run in the calling
    thread unless ``threaded`` (a test's choice; on CUDA the default).

    The conversion as a CUDA graph (``graphs``, the trainer's ``train.cuda_graphs``): the step is launch-bound,
    and the eager conversion is ~20 small kernels and their Python (lookup table, float16 to float32, the edge
    maps, packing) per view. Its input (the slot's device bytes) and output (the slot's packed buffer) are
    allocated once, and for one layout (size, photo type, offsets: the same for every view of that size) it
    is the same kernels on the same addresses every time, so each (slot, layout) is captured once and then
    replayed: one launch, the same kernels, so the same values. The first view of a layout converts eagerly
    (the capture's warm-up); the next load of it into each slot captures, on the side stream, in
    ``thread_local`` mode (a live viewer renders from another thread between steps; this runs between steps,
    outside the trainer's own captures, on the main thread like them), then replays. The graphs share one
    memory pool (their intermediates, kept: ~50 B per pixel of the largest layout, 0.1 GB at 1920x1080):
    replays are serialised on the side stream and leave nothing in the pool that outlives them. The event waits and
    records and the host-to-device copy stay outside the graph (a capture cannot wait on an event recorded
    outside it; the staging buffer varies). A capture that fails leaves that layout eager, with one line to
    ``log``; ``emulate_graphs`` runs the same bookkeeping on the CPU (the "graph" re-runs the eager conversion
    on the static buffers), for tests.
    """

    def __init__(self, store: ViewStore, cameras: Sequence[Camera], centers: Sequence[Tensor],
                 device: torch.device, method: str, depth_edge: Optional[float],
                 upcoming: Optional[Callable[[], Sequence[int]]] = None, slots: int = 3,
                 threaded: Optional[bool] = None, graphs: bool = True, emulate_graphs: bool = False,
                 log: Optional[Callable[[str], None]] = None, resident_bytes: int = 0) -> None:
        if len(store) != len(cameras):
            raise ValueError(f"the view store has {len(store)} views, the scene {len(cameras)}")
        if slots < 3:
            raise ValueError("StreamedViews needs at least 3 slots (the current view, the next, the one after)")
        self.store, self.cameras, self.centers = store, list(cameras), list(centers)
        self.device, self.method, self.depth_edge = torch.device(device), method, depth_edge
        self.upcoming = upcoming
        self.decomposed = method == "retinexgs"
        self.K = packed_channels(self.decomposed, store.priors, depth_edge is not None)
        cuda = self.device.type == "cuda"
        self._cuda = cuda
        px = [v.height * v.width for v in store.views]
        edge_px = [v.height * (v.width - 1) + (v.height - 1) * v.width for v in store.views]
        self._slot_numel = max(p * self.K + (e if depth_edge is not None else 0) + (p * 3 if method == "pre" else 0)
                               for p, e in zip(px, edge_px))
        span = max(v.nbytes for v in store.views)
        self._slots = [torch.empty(self._slot_numel, dtype=torch.float32, device=self.device)
                       for _ in range(slots)]
        # A store of at most ``resident_bytes`` is read once into (pinned) host memory: each view's copy then
        # starts from it directly, with no staging and no worker thread, which cost a launch-bound step ~0.3 ms
        # of host time (fox-dark, H100: docs/benchmarks.md, Scale).
        self._resident = hold_whole(store, resident_bytes, cuda, log)
        self._staging = [] if self._resident is not None else \
            [torch.empty(span, dtype=torch.uint8, pin_memory=cuda) for _ in range(slots)]
        self._staging_np = [t.numpy() for t in self._staging]  # what the worker thread writes
        # Graphed conversion: on CUDA (``graphs``), or emulated on the CPU (a test's choice).
        self._emulate = bool(emulate_graphs) and not cuda
        self._graphed = (cuda and bool(graphs)) or self._emulate
        self._bytes = [torch.empty(span, dtype=torch.uint8, device=self.device) for _ in range(slots)] \
            if cuda or self._emulate else self._staging
        self._graphs: Dict[tuple, _SlotGraph] = {}  # per (slot,) + layout
        self._graph_layouts: set = set()  # layouts converted once eagerly: their captures may follow
        self.graph_failures: Dict[tuple, str] = {}  # layouts whose capture failed (they convert eagerly)
        self._pool = None  # the graphs' shared memory pool
        self._log = log
        self._tables = {dtype: torch.from_numpy(photo_table(dtype)).to(self.device)
                        for dtype in sorted({v.photo_dtype for v in store.views} & set(PHOTO_LEVELS))}
        # Device slots: the view each holds, its TrainView, when each was last handed out or filled.
        self._holds: List[Optional[int]] = [None] * slots
        self._views: Dict[int, TrainView] = {}
        self._used = [0] * slots
        self._current: Optional[int] = None  # the slot handed out last
        # Staging buffers: the view each holds (read, or being read: its job), when each was last assigned.
        self._staged: Dict[int, Tuple[int, Future]] = {}
        self._staging_used = [0] * slots
        self._clock = 0
        self.loads: List[Tuple[int, bool]] = []  # (view, prefetched) of every device load, in order
        self.hits = self.misses = 0  # views handed out that were already on the device / loaded then
        if cuda:
            self._side = torch.cuda.Stream(device=self.device)
            self._ready = [torch.cuda.Event() for _ in range(slots)]
            self._released = [torch.cuda.Event() for _ in range(slots)]
            self._copied = [torch.cuda.Event() for _ in range(slots)]  # per staging buffer
        threaded = (cuda if threaded is None else threaded) and self._resident is None
        self._executor = ThreadPoolExecutor(1, thread_name_prefix="retinexgs-views") if threaded else _Inline()

    # -- the sequence ---------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.store)

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        return self.get(int(i))

    def get(self, i: int, prefetch: bool = True) -> TrainView:
        """View ``i`` on the device (ready for the current stream); with ``prefetch`` the views ``upcoming()``
        names start on their way."""
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(f"view {i} of {len(self)}")
        if i in self._holds:
            self.hits += 1
            slot = self._holds.index(i)
        else:
            self.misses += 1
            slot = self._load_into_free_slot(i, False)
        if self._cuda:
            stream = torch.cuda.current_stream(self.device)
            stream.wait_event(self._ready[slot])
            if self._current is not None and self._current != slot:
                # Everything queued so far that read the previous view is before this event.
                self._released[self._current].record(stream)
        self._current = slot
        self._touch(self._used, slot)
        tv = self._views[slot]
        if prefetch and self.upcoming is not None:
            ahead = [int(j) for j in self.upcoming()][:2]
            if ahead and ahead[0] not in self._holds:
                self._load_into_free_slot(ahead[0], True)
            for j in ahead[1:] if self._resident is None else ():
                if j not in self._holds:
                    self._stage(j)
        return tv

    def close(self) -> None:
        """Wait for the host reads in flight and stop the worker thread."""
        try:
            for _, job in list(self._staged.values()):
                job.result()
        finally:
            self._executor.shutdown(wait=True)

    @property
    def resident_bytes(self) -> int:
        """Host bytes of the store held in (pinned) memory: all of it, or 0 (read view by view)."""
        return 0 if self._resident is None else int(self._resident.numel())

    @property
    def slot_bytes(self) -> int:
        """Device bytes of the reused buffers (all slots)."""
        return sum(t.numel() * t.element_size() for t in self._slots) + \
            (sum(t.numel() for t in self._bytes) if self._bytes is not self._staging else 0)

    # -- internals ------------------------------------------------------------------------------------------
    def _touch(self, used: List[int], k: int) -> None:
        self._clock += 1
        used[k] = self._clock

    def _load_into_free_slot(self, i: int, prefetched: bool) -> int:
        """Load view ``i`` into the least recently used device slot other than the current one."""
        slot = min((s for s in range(len(self._slots)) if s != self._current), key=lambda s: self._used[s])
        self._holds[slot] = None
        self._views.pop(slot, None)
        self._views[slot] = self._load(i, slot, prefetched)
        self._holds[slot] = i
        self._touch(self._used, slot)
        return slot

    def _stage(self, i: int) -> int:
        """The staging buffer that holds (or is being given) view ``i``'s bytes; starts the host read."""
        if i in self._staged:
            return self._staged[i][0]
        busy = {b for b, _ in self._staged.values()}
        free = [b for b in range(len(self._staging)) if b not in busy]
        if not free:  # every buffer holds a staged view: drop the oldest
            oldest = min(self._staged, key=lambda v: self._staging_used[self._staged[v][0]])
            self._staged.pop(oldest)[1].result()
            free = [b for b in range(len(self._staging)) if b not in {b for b, _ in self._staged.values()}]
        b = min(free, key=lambda k: self._staging_used[k])
        if self._cuda:
            self._copied[b].synchronize()  # its last copy to the device has left it (long since, as a rule)
        self._touch(self._staging_used, b)
        self._staged[i] = (b, self._executor.submit(self._read, i, b))
        return b

    def _read(self, i: int, b: int) -> None:
        """Host read (the worker thread's whole job: numpy only, the GIL released while it copies)."""
        rec = self.store.views[i]
        np.copyto(self._staging_np[b][:rec.nbytes], self.store.span(i))

    def _load(self, i: int, slot: int, prefetched: bool) -> TrainView:
        """View ``i`` into ``slot``: its staged bytes (read now if they are not), on CUDA copied to the device
        and converted on the side stream (the slot's ready event after it). Returns its TrainView."""
        self.loads.append((i, prefetched))
        rec = self.store.views[i]
        n = rec.nbytes
        if self._resident is not None:
            b, src = None, self._resident[rec.start:rec.start + n]
        else:
            b = self._stage(i)
            self._staged.pop(i)[1].result()
            src = self._staging[b][:n]
        if not self._cuda:
            if not self._emulate:
                return self._convert(i, slot, src)
            dev = self._bytes[slot][:n]
            dev.copy_(src)
            return self._convert_graphed(i, slot, dev)
        with torch.cuda.stream(self._side):
            self._side.wait_event(self._released[slot])  # the last step that read this slot is done
            dev = self._bytes[slot][:n]
            dev.copy_(src, non_blocking=True)
            if b is not None:
                self._copied[b].record(self._side)
            tv = self._convert_graphed(i, slot, dev) if self._graphed else self._convert(i, slot, dev)
            self._ready[slot].record(self._side)
        return tv

    def _convert_graphed(self, i: int, slot: int, data: Tensor) -> TrainView:
        """:meth:`_convert` through the slot's captured graph of the view's layout (captured now if this layout
        was converted before, eagerly while it is new or its capture failed). ``data``: the slot's device bytes
        (the start of ``self._bytes[slot]``, the graph's static input); on CUDA the side stream is current."""
        rec = self.store.views[i]
        layout = (rec.height, rec.width, rec.photo_dtype, rec.photo, rec.R, rec.L, rec.nbytes)
        g = self._graphs.get((slot,) + layout)
        if g is None:
            if layout in self.graph_failures or layout not in self._graph_layouts:
                if len(self._graph_layouts) < MAX_GRAPHED_LAYOUTS:
                    self._graph_layouts.add(layout)  # the eager run before its first capture: the warm-up
                return self._convert(i, slot, data)
            try:
                g = self._capture(i, slot, data)
            except Exception as err:  # e.g. an op that cannot be captured: this layout converts eagerly
                why = f"{type(err).__name__}: {err}"
                self.graph_failures[layout] = why
                if self._log is not None:
                    self._log(f"CUDA graph capture of a streamed view's conversion failed for {rec.width}x"
                              f"{rec.height} views ({why}); they convert eagerly")
                return self._convert(i, slot, data)
            self._graphs[(slot,) + layout] = g
        g.replay()
        # A new TrainView (its own lazily built fields, e.g. a baseline's edge maps) on the captured maps.
        v = g.view
        return TrainView(self.cameras[i], v.S, v.R, v.L, v.target, self.centers[i], v.packed, v.edges)

    def _capture(self, i: int, slot: int, data: Tensor) -> _SlotGraph:
        """Capture :meth:`_convert` of view ``i``'s layout from ``data`` into ``slot`` (not run: replay it)."""
        if self._emulate:  # the CPU's stand-in: the same conversion re-run on the same static buffers
            view = self._convert(i, slot, data)
            replay: Callable[[], None] = lambda: self._convert(i, slot, data)
            pool = None
        else:
            graph = torch.cuda.CUDAGraph()
            # thread_local: only this thread's unsafe calls break the capture (a live viewer's frames may
            # allocate meanwhile); the side stream is the current one (its copy is queued before).
            with cuda_graphs.capture(graph, pool=self._pool, stream=self._side, capture_error_mode="thread_local"):
                view = self._convert(i, slot, data)
            replay, pool = graph.replay, graph.pool()
        # Every map handed on must be in the slot's buffer: the graph rewrites only that (its intermediates
        # live in the pool and are overwritten by the next replay of any graph).
        storage = self._slots[slot].untyped_storage().data_ptr()
        maps = [view.S, view.R, view.L, view.target, view.packed, *(view.edges or ())]
        if any(t is not None and t.untyped_storage().data_ptr() != storage for t in maps):
            raise RuntimeError("a converted map is not in the slot's buffer")
        if self._pool is None:  # the first graph's pool, shared by the next captures
            self._pool = pool
        return _SlotGraph(replay, view)

    def _convert(self, i: int, slot: int, data: Tensor) -> TrainView:
        """The view's float32 maps from its compact bytes ``data`` (on the device), packed into the slot."""
        rec = self.store.views[i]
        H, W = rec.height, rec.width
        px = H * W
        dtype = rec.photo_dtype
        raw = data[rec.photo:rec.photo + px * 3 * np.dtype(dtype).itemsize]
        if dtype == "uint8":
            S = self._tables[dtype][raw.view(H, W, 3).to(torch.int32)]
        elif dtype == "uint16":
            S = self._tables[dtype][raw.view(torch.int16).view(H, W, 3).to(torch.int32) & 0xFFFF]
        elif dtype == "float16":  # a camera raw view's target (View.load_target rounds it so: exact)
            S = raw.view(torch.float16).view(H, W, 3).float()
        else:
            S = raw.view(torch.float32).view(H, W, 3).clone()
        R = L = None
        if rec.R >= 0:
            R = data[rec.R:rec.R + px * 6].view(torch.float16).view(H, W, 3).float()
            L = data[rec.L:rec.L + px * 2].view(torch.float16).view(H, W, 1).float()
        buf = self._slots[slot]
        tv = make_train_view(self.cameras[i], self.centers[i], S, R, L, self.method)
        packed = buf[:px * self.K].view(H, W, self.K)
        at = px * self.K
        tv.pack(self.decomposed, self.depth_edge, out=packed)
        if not self.decomposed:
            tv.target = tv.packed
            if self.method == "pre":  # the photo beside the target (nothing trains on the priors)
                tv.S = buf[at:at + px * 3].view(H, W, 3).copy_(S)
                tv.R = tv.L = None
            else:
                tv.S = tv.packed
        elif tv.packed.shape[-1] == 3:  # S alone (no priors, no depth prior)
            tv.S = tv.target = tv.packed
        if self.depth_edge is not None and self.decomposed:
            # The edge maps as contiguous tensors of the slot (the eager depth loss reads them as the
            # preloaded view's own), copied from the packed channels (the same values).
            wx, wy = unpack_edges(tv.packed)
            ex = buf[at:at + H * (W - 1)].view(1, 1, H, W - 1)
            ey = buf[at + H * (W - 1):at + H * (W - 1) + (H - 1) * W].view(1, 1, H - 1, W)
            tv.edges = (ex.copy_(wx), ey.copy_(wy))
        return tv



__all__ = ["StreamedViews", "hold_whole", "available_host_bytes", "MAX_GRAPHED_LAYOUTS"]
