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

This module holds the view on the device and the choice between the two; the store is
:mod:`retinexgs.train.view_store`, the streaming :mod:`retinexgs.train.streamed_views`.
"""
from __future__ import annotations

import os
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Deque, Iterable, Iterator, List, Optional, Tuple

import numpy as np
import torch
from torch import Tensor

from retinexgs.errors import UserError
from retinexgs.kth_value import kth_smallest
from retinexgs.render import Camera
from retinexgs.retinex import enhance_for_viewing
from retinexgs.train import losses
from retinexgs.train.view_store import compact_photo


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
            self._refs.append(kth_smallest(flat, k))
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


def _read_compact(view) -> Tuple[Tensor, np.ndarray]:
    """A view's photo as the trainer reads it (float32 [H,W,3]) and in its compact stored form."""
    image = view.load_target()
    return image, compact_photo(image)


def read_ahead_workers() -> int:
    """Threads that decode photos ahead of the store's writer: PIL's decoder and numpy release the GIL, so a
    1080p JPEG's ~0.1 s of decoding and compacting runs in parallel; at most 8, so that host memory stays at a
    few photos (up to threads + 2 at once, 15 B/px each once read: float32 and the compact copy)."""
    return max(1, min(8, (os.cpu_count() or 1) - 1))


def stream_set_up(views: Iterable, priors: Optional[Iterator], device: torch.device,
                  stats: Optional[ViewStatistics], workers: Optional[int] = None
                  ) -> Iterator[Tuple[str, np.ndarray, Optional[np.ndarray], Optional[np.ndarray]]]:
    """The items of :meth:`ViewStore.build` from the scene's views (each photo read, then released) and
    their priors (an iterator of (R, L) float32 CPU tensors, run to its end; None: no priors), gathering
    ``stats`` on ``device`` from the same float32 maps a preloaded run trains on.

    The photos are decoded ``workers`` views ahead (default :func:`read_ahead_workers`) on threads, in order;
    the items and the statistics are those of reading them one at a time. An unreadable photo raises its
    error when its turn comes."""
    workers = read_ahead_workers() if workers is None else max(1, int(workers))
    queue: Deque[Tuple[object, Future]] = deque()
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="retinexgs-read")
    it = iter(views)

    def submit() -> bool:
        v = next(it, None)
        if v is None:
            return False
        v.release_images()
        queue.append((v, pool.submit(_read_compact, v)))
        return True

    try:
        while len(queue) <= workers and submit():  # one more than the threads: the next is ready
            pass
        while queue:
            v, job = queue.popleft()
            image, photo = job.result()
            submit()
            R = L = None
            if priors is not None:
                R, L = next(priors)
                check_prior_size(R, image)
            if stats is not None:
                stats.add(image.to(device), None if R is None else R.to(device), None if L is None else L.to(device))
            del image
            yield (v.name, photo, None if R is None else R.numpy().astype(np.float16),
                   None if L is None else L.numpy().astype(np.float16))
    finally:
        for _, job in queue:
            job.cancel()
        pool.shutdown(wait=True)
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
           "preload_bytes_per_pixel", "choose_streaming", "ViewStatistics", "stream_set_up", "read_ahead_workers",
           "check_prior_size", "gib",
           "STREAM_MODES"]
