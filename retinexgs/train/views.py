"""Training views on the device: :class:`TrainView` (a view's camera and loss targets), and the two ways the
trainer holds them (``train.stream_views``, ``train.views_on_device_gb``):

- **preloaded** (small scenes): every view's targets stay on the device for the whole run, float32 (S, R, L:
  28 B per pixel; 44 B/px once :meth:`TrainView.pack` has built the packed targets with the depth prior's
  edge maps);
- **streamed** (big captures): the photos and 2D priors live on the host in one memory-mapped file, a
  :class:`ViewStore` (photo uint8, or uint16 for 16-bit sources, R and L float16: 11 B/px), and
  :class:`StreamedViews` moves each step's view to the device into one of a few reused buffers, converts it
  to float32 and packs it there, prefetching the next view of the trainer's order while the current step
  runs (on CUDA: a worker thread fills a pinned staging buffer and copies it on a side stream; the main stream
  waits on an event). Device memory no longer grows with the view count; host memory is the OS page cache,
  except that a store up to ``train.views_pinned_gb`` is read once into pinned memory and copied from there.

The store is lossless: the decomposition cache holds R and L as float16 (what a preloaded run reads back as
float32), and an 8- or 16-bit photo read as float32 is k / 255 or k / 65535 exactly (a photo that is neither
is stored as float32). Streamed views are therefore bit-identical to preloaded ones, and so are the set-up
statistics (:class:`ViewStatistics`, computed on the device from the same float32 maps, one view at a time).
"""
from __future__ import annotations

import errno
import hashlib
import json
import os
import struct
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, Iterable, Iterator, List, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

from retinexgs.errors import UserError
from retinexgs.fileio import atomic_write, free_bytes
from retinexgs.render import Camera, cuda_graphs
from retinexgs.retinex import enhance_for_viewing
from retinexgs.train import losses


def _bchw(x: Tensor) -> Tensor:
    return x.permute(2, 0, 1).unsqueeze(0)


# ---- a view on the device -----------------------------------------------------------------------------------

@dataclass
class TrainView:
    """A training view on the device: camera, low-light image S and its 2D priors / baseline target."""

    camera: Camera
    S: Tensor                   # [H,W,3]
    R: Optional[Tensor] = None  # [H,W,3]
    L: Optional[Tensor] = None  # [H,W,1]
    target: Optional[Tensor] = None  # [H,W,3], baselines
    center: Optional[Tensor] = None  # [3] the camera centre on the device (the renderer's view directions)
    packed: Optional[Tensor] = None  # [H,W,K] the loss's targets in one tensor (the CUDA graphs' input)
    edges: Optional[Tuple[Tensor, Tensor]] = None  # ([1,1,H,W-1], [1,1,H-1,W]) the depth prior's edge weights

    def edge_weights(self, edge: float) -> Tuple[Tensor, Tensor]:
        """:func:`losses.edge_weights` of the view's reflectance prior R (of S without priors), built once."""
        if self.edges is None:
            self.edges = losses.edge_weights(_bchw(self.R if self.R is not None else self.S), edge)
        return self.edges

    def pack(self, decomposed: bool, depth_edge: Optional[float] = None, out: Optional[Tensor] = None) -> Tensor:
        """The loss's targets as one contiguous [H,W,K] tensor, built once: S (+ R, L) or the baselines' target
        (one copy into a captured graph's input instead of three). With ``depth_edge`` (the depth prior is on)
        the prior's edge weights follow as the last two channels (:func:`pad_edges`). ``out``: a contiguous
        [H,W,K] tensor to build it in (a streamed view's reused buffer) instead of a new one."""
        if self.packed is None:
            if not decomposed:
                self.packed = self.target.contiguous() if out is None else out.copy_(self.target)
                return self.packed
            maps = [self.S] if self.R is None else [self.S, self.R, self.L]
            if depth_edge is not None:
                maps.append(pad_edges(*self.edge_weights(depth_edge)))
            if len(maps) == 1:
                self.packed = self.S.contiguous() if out is None else out.copy_(self.S)
                return self.packed
            self.packed = torch.cat(maps, dim=-1) if out is None else torch.cat(maps, dim=-1, out=out)
            # The view's maps become views of the packed tensor: no second copy on the device.
            same_target = self.target is self.S
            S, R, L = unpack_targets(self.packed, True, depth_edge is not None)
            self.S = S
            if self.R is not None:
                self.R, self.L = R, L
            if same_target:
                self.target = self.S
        return self.packed


def pad_edges(wx: Tensor, wy: Tensor) -> Tensor:
    """The depth prior's edge weights ([1,1,H,W-1], [1,1,H-1,W]) as one [H,W,2] map, zero in the last column
    (x) and row (y), to travel with a view's packed targets; :func:`unpack_edges` inverts it."""
    H, W = wy.shape[-2] + 1, wx.shape[-1] + 1
    out = wx.new_zeros(H, W, 2)
    out[:, :-1, 0] = wx[0, 0]
    out[:-1, :, 1] = wy[0, 0]
    return out


def unpack_edges(packed: Tensor) -> Tuple[Tensor, Tensor]:
    """(wx [1,1,H,W-1], wy [1,1,H-1,W]) from the last two channels of a view's packed targets (views)."""
    return packed[None, None, :, :-1, -2], packed[None, None, :-1, :, -1]


def unpack_targets(packed: Tensor, decomposed: bool, edges: bool = False
                   ) -> Tuple[Tensor, Optional[Tensor], Optional[Tensor]]:
    """(S or the target, R, L) from :meth:`TrainView.pack` (views, no copies); ``edges``: it was packed with
    the depth prior's edge weights."""
    if not decomposed:
        return packed, None, None
    if packed.shape[-1] - (2 if edges else 0) == 3:
        return (packed[..., :3] if edges else packed), None, None
    return packed[..., :3], packed[..., 3:6], packed[..., 6:7]


def make_train_view(camera: Camera, center: Tensor, S: Tensor, R: Optional[Tensor], L: Optional[Tensor],
                    method: str) -> TrainView:
    """A view's :class:`TrainView` from its device maps (S [H,W,3], priors R, L or None) as the trainer
    trains ``method`` on it: the pre-enhancement baseline's target is the priors' enhancement, the others'
    is S."""
    tv = TrainView(camera, S, R, L, center=center)
    tv.target = enhance_for_viewing(R, L) if method == "pre" else S
    return tv


# ---- how much, and which way --------------------------------------------------------------------------------

STREAM_MODES = ("auto", "always", "never")


def packed_channels(decomposed: bool, priors: bool, depth_prior: bool) -> int:
    """K of a view's packed targets [H,W,K] (:meth:`TrainView.pack`)."""
    if not decomposed:
        return 3
    return 3 + (4 if priors else 0) + (2 if depth_prior else 0)


def preload_bytes_per_pixel(method: str, priors: bool, depth_prior: bool) -> int:
    """Device bytes per view-pixel of a preloaded view once trained on (packed targets, and the depth prior's
    edge maps kept beside them): 44 for RetinexGS with priors and the depth prior, 28 without the depth prior,
    40 for the pre-enhancement baseline (S, R, L and its target), 12 for the others (S)."""
    if method == "pre":
        return 4 * (3 + 3 + 1 + 3)
    decomposed = method == "retinexgs"
    return 4 * packed_channels(decomposed, priors, depth_prior) + (8 if decomposed and depth_prior else 0)


def choose_streaming(mode: str, preload_bytes: float, budget_gb: float) -> bool:
    """Stream the views (True) or preload them (False): ``mode`` always / never, or auto: stream when the
    preloaded views would take more than ``budget_gb`` GB (10^9 bytes) of device memory."""
    if mode not in STREAM_MODES:
        raise ValueError(f"train.stream_views must be one of {', '.join(STREAM_MODES)}, got {mode!r}")
    if mode != "auto":
        return mode == "always"
    return preload_bytes > budget_gb * 1e9


# ---- set-up statistics --------------------------------------------------------------------------------------

class ViewStatistics:
    """What set-up needs from every view, gathered one view at a time on the device (the same float32 maps and
    operations as when every view sat on the device at once, so the same values): the illumination reference
    (per view the ``quantile`` of L, or of S's max-RGB without priors; their median over views) and the mean
    background (the views' mean R and L, or S and its max-RGB)."""

    def __init__(self, quantile: Optional[float]) -> None:
        self.quantile = quantile
        self._refs: List[Tensor] = []
        self._mean_r: List[Tensor] = []
        self._mean_l: List[Tensor] = []

    def __len__(self) -> int:
        return len(self._mean_r)

    def add(self, S: Tensor, R: Optional[Tensor], L: Optional[Tensor]) -> None:
        """One view's maps (contiguous copies are taken of views into a packed tensor: same reduction order)."""
        light = (L if L is not None else S.amax(dim=-1, keepdim=True)).contiguous()
        if self.quantile is not None:
            flat = light.reshape(-1).float()
            k = min(flat.numel(), max(1, round(float(self.quantile) * flat.numel())))
            self._refs.append(flat.kthvalue(k).values)
        refl = (R if R is not None else S).contiguous()
        self._mean_r.append(refl.reshape(-1, refl.shape[-1]).float().mean(0))
        self._mean_l.append(light.reshape(-1, 1).float().mean(0))

    def illumination_reference(self) -> float:
        """The median over views of each view's ``quantile`` of L (at least 1e-3); 1.0 without a quantile."""
        if self.quantile is None:
            return 1.0
        return float(torch.stack(self._refs).median().clamp_min(1e-3))

    def mean_background(self) -> Tensor:
        """[6]: the views' mean R (3 channels), then their mean L repeated over 3."""
        R = torch.stack(self._mean_r).mean(0)
        L = torch.stack(self._mean_l).mean(0)
        return torch.cat([R, L.expand(3)])


# ---- compact photos -----------------------------------------------------------------------------------------

_PHOTO_LEVELS = {"uint8": 255, "uint16": 65535}


def photo_table(dtype: str) -> np.ndarray:
    """float32 [levels + 1]: the value of each integer sample as the image reader scales it (k / 255 or
    k / 65535 in float32, :func:`retinexgs.data.images.read_image_float`)."""
    n = _PHOTO_LEVELS[dtype]
    return np.arange(n + 1, dtype=np.int64).astype(np.float32) / float(n)


def compact_photo(image: Tensor) -> np.ndarray:
    """A photo read as float32 [H,W,3] in its smallest exact form: uint8 when every value is k / 255, uint16
    when k / 65535, else float32 (a reader that scales otherwise)."""
    a = np.ascontiguousarray(image.detach().cpu().numpy(), dtype=np.float32)
    for name in ("uint8", "uint16"):
        n = _PHOTO_LEVELS[name]
        k = np.clip(np.rint(a * n), 0, n).astype(name)
        if np.array_equal(photo_table(name)[k], a):
            return k
    return a


# ---- the host store -----------------------------------------------------------------------------------------

_MAGIC = b"RGSVIEWS"
_FORMAT = 1
_PREFIX = struct.Struct("<8sIQQ")  # magic, format, header offset, header length
_PAGE = 4096  # each view starts on a page
_ALIGN = 256  # each array within a view


def _up(n: int, a: int) -> int:
    return (n + a - 1) // a * a


@dataclass
class StoredView:
    """Where one view lies in a :class:`ViewStore`: its span [start, start + nbytes) of the file and, within
    it, the photo (``photo_dtype`` [H,W,3]) and the priors R (float16 [H,W,3]) and L (float16 [H,W,1]) at
    byte offsets (-1: no priors)."""

    name: str
    height: int
    width: int
    photo_dtype: str
    start: int
    nbytes: int
    photo: int
    R: int
    L: int


def _layout(height: int, width: int, photo_dtype: str, priors: bool) -> Tuple[int, int, int, int]:
    """(photo, R, L offsets within a view's span, span bytes)."""
    px = height * width
    photo_bytes = px * 3 * np.dtype(photo_dtype).itemsize
    r = _up(photo_bytes, _ALIGN) if priors else -1
    l = r + _up(px * 3 * 2, _ALIGN) if priors else -1
    end = l + px * 2 if priors else photo_bytes
    return 0, r, l, end


def store_size_estimate(sizes: Sequence[Tuple[int, int]], priors: bool) -> int:
    """Bytes of a store of views of these (height, width), 8-bit photos."""
    return _PAGE + sum(_up(_layout(h, w, "uint8", priors)[3], _PAGE) for h, w in sizes) + 65536


class ViewStore:
    """Photos and 2D priors of a scene's training views in one file, memory-mapped read-only. Layout: a
    prefix (magic ``RGSVIEWS``, format, header offset and length), each view's span on a page boundary (photo,
    then R, then L, see :class:`StoredView`), and a JSON header at the end (format, fingerprint, the views).
    Written atomically by :meth:`build` (temporary file, fsync, rename); :meth:`open` trusts a file only when
    its fingerprint (:func:`store_fingerprint`) and size match."""

    def __init__(self, path: Path, header: Dict) -> None:
        self.path = Path(path)
        self.fingerprint: str = header["fingerprint"]
        self.priors: bool = bool(header["priors"])
        self.views = [StoredView(**v) for v in header["views"]]
        self._map = np.memmap(self.path, dtype=np.uint8, mode="r")

    def __len__(self) -> int:
        return len(self.views)

    @property
    def nbytes(self) -> int:
        return int(self._map.shape[0])

    def span(self, i: int) -> np.ndarray:
        """View ``i``'s bytes (a read-only view of the mapping)."""
        v = self.views[i]
        return self._map[v.start:v.start + v.nbytes]

    def read_into(self, out: np.ndarray) -> None:
        """The whole file's bytes into ``out`` (uint8, :attr:`nbytes` long), read in 64 MiB pieces."""
        if out.shape != (self.nbytes,) or out.dtype != np.uint8:
            raise ValueError(f"read_into needs a uint8 array of {self.nbytes} bytes, got {out.dtype} {out.shape}")
        step = 64 << 20
        for at in range(0, self.nbytes, step):
            np.copyto(out[at:at + step], self._map[at:at + step])

    def photo(self, i: int) -> np.ndarray:
        v = self.views[i]
        n = v.height * v.width * 3 * np.dtype(v.photo_dtype).itemsize
        return self.span(i)[v.photo:v.photo + n].view(v.photo_dtype).reshape(v.height, v.width, 3)

    def priors_of(self, i: int) -> Tuple[Optional[np.ndarray], Optional[np.ndarray]]:
        """(R float16 [H,W,3], L float16 [H,W,1]) of view ``i``, or (None, None)."""
        v = self.views[i]
        if v.R < 0:
            return None, None
        px = v.height * v.width
        span = self.span(i)
        R = span[v.R:v.R + px * 6].view(np.float16).reshape(v.height, v.width, 3)
        L = span[v.L:v.L + px * 2].view(np.float16).reshape(v.height, v.width, 1)
        return R, L

    def close(self) -> None:
        mm = getattr(self._map, "_mmap", None)
        self._map = None  # type: ignore[assignment]
        if mm is not None:
            try:
                mm.close()
            except BufferError:  # an array still points into it: the mapping goes with the last one
                pass

    @staticmethod
    def read_header(path: Path) -> Optional[Dict]:
        """The header of a store file, or None when it is missing, cut short or not a store."""
        try:
            with open(path, "rb") as f:
                prefix = f.read(_PREFIX.size)
                if len(prefix) != _PREFIX.size:
                    return None
                magic, fmt, offset, length = _PREFIX.unpack(prefix)
                if magic != _MAGIC or fmt != _FORMAT or offset + length != os.fstat(f.fileno()).st_size:
                    return None
                f.seek(offset)
                header = json.loads(f.read(length).decode("utf-8"))
        except (OSError, ValueError):
            return None
        return header if isinstance(header, dict) and header.get("format") == _FORMAT else None

    @classmethod
    def open(cls, path: Path, fingerprint: str) -> Optional["ViewStore"]:
        """The store at ``path`` when it holds exactly what ``fingerprint`` describes; else None."""
        header = cls.read_header(path)
        if header is None or header.get("fingerprint") != fingerprint:
            return None
        try:
            views = header["views"]
            end = max((v["start"] + v["nbytes"] for v in views), default=0)
            if end > Path(path).stat().st_size:
                return None
            return cls(path, header)
        except (OSError, KeyError, TypeError, ValueError):
            return None

    @classmethod
    def build(cls, path: Path, fingerprint: str, priors: bool,
              items: Iterable[Tuple[str, np.ndarray, Optional[np.ndarray], Optional[np.ndarray]]],
              elsewhere: str = "") -> "ViewStore":
        """Write the store from ``items`` (name, photo [H,W,3] uint8 / uint16 / float32, R float16 [H,W,3],
        L float16 [H,W,1], or None without priors), consumed one at a time, then open it. Atomic: an error or
        a kill leaves no store (at worst a ``.tmp-`` file); a full or read-only disk raises a UserError naming
        ``elsewhere`` (how to put it on another disk)."""
        records: List[Dict] = []

        def write(f) -> None:
            f.write(b"\0" * _PAGE)
            pos = _PAGE
            for name, photo, R, L in items:
                h, w = photo.shape[:2]
                off_photo, off_r, off_l, nbytes = _layout(h, w, photo.dtype.name, priors)
                parts = [(off_photo, photo)] + ([(off_r, R), (off_l, L)] if priors else [])
                at = 0
                for off, arr in parts:
                    if off > at:
                        f.write(b"\0" * (off - at))
                    data = np.ascontiguousarray(arr)
                    f.write(memoryview(data).cast("B"))
                    at = off + data.nbytes
                pad = _up(nbytes, _PAGE) - nbytes
                f.write(b"\0" * pad)
                records.append({"name": name, "height": h, "width": w, "photo_dtype": photo.dtype.name,
                                "start": pos, "nbytes": nbytes, "photo": off_photo, "R": off_r, "L": off_l})
                pos += nbytes + pad
            header = json.dumps({"format": _FORMAT, "fingerprint": fingerprint, "priors": priors,
                                 "views": records}).encode("utf-8")
            f.write(header)
            f.seek(0)
            f.write(_PREFIX.pack(_MAGIC, _FORMAT, pos, len(header)))

        try:
            atomic_write(path, write, elsewhere=elsewhere)
        except OSError as exc:
            if exc.errno not in (errno.EROFS, errno.EACCES, errno.EPERM):
                raise
            where = f"; put it elsewhere with {elsewhere}" if elsewhere else ""
            raise UserError(f"cannot write the view store {path}: {exc.strerror or exc}{where}") from None
        store = cls.open(path, fingerprint)
        if store is None:  # pragma: no cover - what was just written must read back
            raise UserError(f"the view store {path} did not read back after writing it")
        return store


def store_fingerprint(image_paths: Sequence[Path], sizes: Sequence[Tuple[int, int]], priors_tag: str) -> str:
    """What a store must match to be reused: the format, the priors' settings (``<method>-<key>`` of the
    decomposition cache, or ``none``) and per view its photo file (resolved path, byte size, modification
    time) and size. An edited, regenerated or resized photo, or other settings, make a new store."""
    items = []
    for p, (h, w) in zip(image_paths, sizes):
        st = Path(p).stat()
        items.append([str(Path(p).resolve()), int(st.st_size), int(st.st_mtime_ns), int(h), int(w)])
    blob = json.dumps({"format": _FORMAT, "priors": priors_tag, "views": items}, sort_keys=True)
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()


def store_path(cache_root: Path, image_paths: Sequence[Path], priors_tag: str) -> Path:
    """``<cache root>/views-<priors tag>-<8 hex of the photos' paths>.bin``: one store per scene view list and
    prior settings, replaced in place when its photos change."""
    digest = hashlib.sha256("\n".join(str(Path(p).resolve()) for p in image_paths).encode("utf-8")).hexdigest()
    return Path(cache_root) / f"views-{priors_tag}-{digest[:8]}.bin"


def check_store_space(path: Path, nbytes: int, hint: str) -> None:
    """Refuse, before any decoding, a store that cannot fit on its disk."""
    free = free_bytes(path.parent)
    if free is not None and free < nbytes:
        raise UserError(f"no space left on device for the view store {path}: it needs {nbytes / 2**30:.2f} GiB, "
                        f"{free / 2**30:.2f} GiB are free; {hint}")


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
                        for dtype in sorted({v.photo_dtype for v in store.views} & set(_PHOTO_LEVELS))}
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


def stream_set_up(views: Iterable, priors: Optional[Iterator], device: torch.device,
                  stats: Optional[ViewStatistics]) -> Iterator[Tuple[str, np.ndarray, Optional[np.ndarray],
                                                                     Optional[np.ndarray]]]:
    """The items of :meth:`ViewStore.build` from the scene's views (each photo read, then released) and
    their priors (an iterator of (R, L) float32 CPU tensors, run to its end; None: no priors), gathering
    ``stats`` on ``device`` from the same float32 maps a preloaded run trains on."""
    for v in views:
        image = v.image
        v.release_images()
        R = L = None
        if priors is not None:
            R, L = next(priors)
            check_prior_size(R, image)
        if stats is not None:
            stats.add(image.to(device), None if R is None else R.to(device), None if L is None else L.to(device))
        photo = compact_photo(image)
        del image
        yield (v.name, photo, None if R is None else R.numpy().astype(np.float16),
               None if L is None else L.numpy().astype(np.float16))
    for _ in priors or ():  # e.g. the decomposition cache's sweep, after its last view
        pass


def check_prior_size(R: Tensor, S: Tensor) -> None:
    """A cached decomposition must have the photo's size."""
    if R.shape[:2] != S.shape[:2]:
        raise UserError(f"cached decomposition has size {tuple(R.shape[:2])} but the view is "
                        f"{tuple(S.shape[:2])}; delete the retinex cache")


def gib(nbytes: float) -> str:
    return f"{nbytes / 2**30:.2f} GiB" if nbytes >= 2**28 else f"{nbytes / 2**20:.0f} MiB"


__all__ = ["TrainView", "pad_edges", "unpack_edges", "unpack_targets", "make_train_view", "packed_channels",
           "preload_bytes_per_pixel", "choose_streaming", "ViewStatistics", "compact_photo", "photo_table",
           "ViewStore", "StoredView", "hold_whole", "available_host_bytes", "store_fingerprint", "store_path", "store_size_estimate", "check_store_space",
           "StreamedViews", "stream_set_up", "check_prior_size", "STREAM_MODES"]
