"""Training set-up from the scene: the training views on the device (preloaded or streamed from the view store,
:mod:`retinexgs.train.views`) with their 2D priors from the per-scene decomposition cache, the statistics the model's
levels start from (the illumination reference, the mean background), the near plane and the scene's extent."""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterator, List, Optional, Sequence, Tuple

import torch

from retinexgs.data import Scene, View
from retinexgs.errors import UserError
from retinexgs.model.near_plane import MIN_POINTS, content_depth
from retinexgs.data.capture import PHOTO_BLOTCH_MIN, capture_of_files
from retinexgs.retinex.cache import entry_dir, iter_decompositions, produced_ahead, scene_cache_root
from retinexgs.retinex.denoise import DenoiseParams, DenoiseSpec, NoiseModel, noise_model
from retinexgs.run.render import view_camera
from retinexgs.config.schema import Config
from retinexgs.train.noise import measure_capture_noise
from retinexgs.train.colour_blotches import previews_chroma_blotch
from retinexgs.train.streamed_views import StreamedViews
from retinexgs.train.view_store import (ViewStore, check_store_space, store_fingerprint, store_path, store_tag,
                                        store_size_estimate)
from retinexgs.train.views import (TrainView, ViewStatistics, check_prior_size, choose_streaming, gib,
                                   make_train_view, preload_bytes_per_pixel, stream_set_up)


def scene_extent(scene: Scene) -> float:
    """1.1 x the largest distance of a train camera from the centroid of the train cameras (3DGS)."""
    centers = torch.stack([v.camera_center for v in scene.train]).float()
    return float(1.1 * (centers - centers.mean(0)).norm(dim=-1).max().clamp_min(1e-3))


# The line that says photos go through the denoiser by ``auto`` (PhotoCapture.auto_denoise: blotchy colour noise).
BLOTCH_NOTE = ("note: these photos' colour noise is blotchy (σ {blotch:.3f} on 4x4-pixel averages > {gate:g}): they are "
               "decomposed after the chroma denoiser (night camera JPEGs: +0.04 to +0.35 SSIM; "
               "--set decomposer.denoise=none turns it off)")


def denoise_params(cfg: Config, views_per_point: Optional[float],
                   note: Optional[Callable[[str], None]] = None) -> DenoiseParams:
    """The denoiser's settings for this scene: ``decomposer.denoise_params`` over the defaults, the luma's strength
    then set by the views that see each point (:meth:`DenoiseParams.for_views`, ``decomposer.denoise_luma_views``;
    ``views_per_point``: :meth:`Scene.views_per_point`). ``note``: told where the luma is lightened (one line)."""
    base = DenoiseParams.from_mapping(cfg.decomposer.denoise_params)
    params = base.for_views(views_per_point, cfg.decomposer.denoise_luma_views)
    if note is not None and params.h_luma != base.h_luma:
        note(f"denoiser: luma NLM at {params.h_luma:.2f} σ ({views_per_point:g} training views see a point; "
             f"{base.h_luma:g} σ up to decomposer.denoise_luma_views={cfg.decomposer.denoise_luma_views:g})")
    return params


def denoise_spec(views: List[View], cfg: Config, device: str,
                 note: Optional[Callable[[str], None]] = None,
                 views_per_point: Optional[Callable[[], Optional[float]]] = None) -> Optional[DenoiseSpec]:
    """What ``decomposer.denoise`` reads the views through (None when ``none``): the method and the views' noise in
    the light of the images decomposed, as training measures it: a raw scene's :class:`RawNoise` (DNG NoiseProfile
    or the mosaic's estimate), a photo scene's :class:`CaptureNoise` (already at the training resolution);
    ``data.downscale`` and the white balance applied. UserError (one line) when it cannot be measured. ``note``:
    where ``auto`` denoises photos (their colour noise is blotchy), it is told so (one line). ``views_per_point``:
    the scene's :meth:`Scene.views_per_point` (the method, called only where the views are denoised), which sets the
    luma's strength (:func:`denoise_params`)."""
    capture = capture_of_files([v.user_path for v in views])
    method = auto = cfg.decomposer.denoise
    sources = [v.source_path if v.source_path is not None and Path(v.source_path).is_file() else v.image_path
               for v in views]
    measured: List[float] = []  # the photos' blotches, where auto read them
    if auto == "auto":  # the capture's choice (raw: chroma; photos: chroma where their colour noise is blotchy)
        def blotch() -> float:
            measured.append(previews_chroma_blotch(sources, float(cfg.data.downscale)) if sources else 0.0)
            return measured[-1]

        method = capture.auto_denoise(blotch)
    if method == "none" or not views:
        return None
    noise = _measured_noise(views, cfg, device)
    try:
        model = None if noise is None else _noise_model(noise, views, cfg)
    except UserError:
        if auto != "auto":  # a named denoiser the measured noise cannot drive: its own one-line reason
            raise
        model = None
    if model is None and auto == "auto":  # nothing flat to measure the noise on (or no shot noise read): as before
        return None
    if auto == "auto" and measured and note is not None:  # photos denoised by auto's own reading: said once
        note(BLOTCH_NOTE.format(blotch=measured[-1], gate=PHOTO_BLOTCH_MIN))
    if model is None:
        raise UserError(f"decomposer.denoise={method}: the views' noise could not be measured (no flat area in any "
                        "view): set decomposer.denoise=none")
    # Where the views are decomposed (decomposer.device, else training's): the denoiser runs there too.
    n = views_per_point() if views_per_point is not None else None
    return DenoiseSpec(method, model, denoise_params(cfg, n, note),
                       device=str(cfg.decomposer.device or device),
                       backend=cfg.decomposer.denoise_backend)


def _measured_noise(views: List[View], cfg: Config, device: str):
    """The views' measured noise (a raw scene's :class:`RawNoise`, a photo scene's :class:`CaptureNoise`) or None."""
    capture = capture_of_files([v.user_path for v in views])
    sources = [v.source_path if v.source_path is not None and Path(v.source_path).is_file() else v.image_path
               for v in views]
    return capture.noise(sources, lambda paths: measure_capture_noise(paths, cfg.data.downscale, torch.device(device)))


def _noise_model(noise, views: List[View], cfg: Config) -> NoiseModel:
    """``noise`` in the light training reads: ``data.downscale`` and the white balance applied."""
    capture = capture_of_files([v.user_path for v in views])
    return noise_model(noise, views[0].balance, capture.noise_downscale(float(cfg.data.downscale)))


def views_noise(views: List[View], cfg: Config, device: str) -> Optional[NoiseModel]:
    """The views' Poisson–Gaussian noise in the light training reads, or None where nothing could be measured;
    UserError (one line) when what was measured cannot be used."""
    noise = _measured_noise(views, cfg, device)
    return None if noise is None else _noise_model(noise, views, cfg)


def decompose_views(views: List[View], cfg: Config, device: str, progress: bool, scene_root: Path,
                    denoise: Optional[DenoiseSpec]) -> Iterator:
    """(R, L) per view, one view at a time, from the per-scene cache (computed and written where missing;
    ``retinexgs decompose`` fills the same cache, see :func:`retinexgs.retinex.cache.scene_cache_root`). Run it
    to its end: the cache's sweep of other photos' entries follows the last view. ``denoise``: the views'
    :func:`denoise_spec` (None: the views as they are)."""

    dcfg = cfg.decomposer
    priors = iter_decompositions([v.image_path for v in views], dcfg.method, dict(dcfg.params) or None,
                                 cache_dir=scene_cache_root(scene_root, cfg.data.cache_dir),
                                 device=dcfg.device or device, progress=progress,
                                 cache_hint="--set data.cache_dir=DIR", sweep=True, scene=str(scene_root),
                                 raw_denoise=dcfg.raw.preview_denoise, balance=views[0].balance if views else None,
                                 names=[v.source_path or v.image_path for v in views],  # errors name the user's photo
                                 denoise=denoise)
    # On a GPU, a view ahead on a thread: the next photo's LR3M (a 12 MP one ~2 s) while this one's maps are stored.
    # On the CPU the decomposition has every core already, and one photo may take minutes (a Ctrl-C waits for it).
    on_gpu = torch.device(dcfg.device or device).type == "cuda"
    return produced_ahead(priors) if on_gpu else priors


def prepare_views(cfg: Config, scene: Scene, device: torch.device, depth_prior: bool, dist, progress: bool,
                  log: Callable[[str], None], upcoming: Callable[[], List[int]]
                  ) -> Tuple[Sequence[TrainView], bool, Optional[ViewStatistics]]:
    """The training views on the device: preloaded (a list of :class:`TrainView`) or streamed from the scene's
    view store (:class:`StreamedViews`), as ``train.stream_views`` and ``train.views_on_device_gb`` decide. Either
    way the photos and priors are read one view at a time, and the set-up statistics are gathered as they pass.
    Returns (views, whether they are streamed, the statistics or None where a reused store skipped them).
    ``dist``: this rank among several (rank 0 alone writes a shared view store), or None; ``upcoming``: the
    rank's next views (what the streamed views prefetch)."""
    method = cfg.method
    dev = device
    needs_priors = method in ("retinexgs", "pre") and cfg.decomposer.method != "none"
    if method == "pre" and cfg.decomposer.method == "none":
        raise UserError("the pre-enhancement baseline needs a decomposer (decomposer.method lr3m or lime)")
    train = scene.train
    cameras = [view_camera(v) for v in train]
    # Once, not every step: the camera centre is computed on the host and copied to the device.
    centers = [cam.center.to(dev, torch.float32) for cam in cameras]
    pixels = sum(v.width * v.height for v in train)
    preload = pixels * preload_bytes_per_pixel(method, needs_priors, depth_prior)
    tcfg = cfg.train
    streamed = choose_streaming(tcfg.stream_views, preload, tcfg.views_on_device_gb)
    if streamed and tcfg.views_per_rank > 1:
        # A streamed view stays valid on the device for one step; a batch of several views on one rank would
        # need them all at once. Several ranks with one view each stream as they are.
        raise UserError(f"train.views_per_rank={tcfg.views_per_rank} needs the training views on the device, "
                        f"but they are streamed ({gib(preload)} preloaded would exceed train.views_on_device_gb="
                        f"{tcfg.views_on_device_gb:g}, or train.stream_views=always): use several ranks with "
                        "one view each (--gpus N), or train.stream_views=never if they fit")
    # What set-up needs from every view (the illumination reference, the mean background): RetinexGS's.
    stats = ViewStatistics(cfg.model.enhancement.ref_quantile) if method == "retinexgs" else None
    priors: Optional[Iterator] = None
    spec = None
    if needs_priors:
        log(f"2D priors: {cfg.decomposer.method} on {len(train)} views (cached per scene)")
        spec = denoise_spec(train, cfg, str(dev), note=log, views_per_point=scene.views_per_point)
    if not streamed:
        log(f"views: preloaded on the device ({gib(preload)} for {len(train)} views; streamed above "
                 f"train.views_on_device_gb={tcfg.views_on_device_gb:g})")
        if needs_priors:
            priors = decompose_views(train, cfg, str(dev), progress, scene.root, spec)
        views: List[TrainView] = []
        for i, v in enumerate(train):
            S = v.load_target().to(dev)
            v.release_images()  # the device copy is the one kept (on the CPU: the same tensor)
            R = L = None
            if priors is not None:
                R, L = next(priors)
                check_prior_size(R, S)
                R, L = R.to(dev), L.to(dev)
            tv = make_train_view(cameras[i], centers[i], S, R, L, method)
            if stats is not None:
                stats.add(tv.S, tv.R, tv.L)
            views.append(tv)
        for _ in priors or ():  # the cache's sweep runs once the last view has gone by
            pass
        release_set_up_memory(dev)
        return views, streamed, stats
    root = scene_cache_root(scene.root, cfg.data.cache_dir)
    dcfg = cfg.decomposer
    tag = store_tag(entry_dir(root, dcfg.method, dict(dcfg.params) or None).name if needs_priors else "none",
                    needs_priors and scene.capture.preview_denoise(dcfg) and spec is None,
                    train[0].balance if train else None)
    if spec is not None:  # priors of the denoised views: another store than the plain priors'
        tag = f"{tag}-dn{spec.recipe[:8]}"
    paths = [v.image_path for v in train]
    sizes = [(v.height, v.width) for v in train]
    path = store_path(root, paths, tag)
    fingerprint = store_fingerprint(paths, sizes, tag)
    shared = dist is not None and dist.enabled  # ranks on one machine share the store file: rank 0 writes it
    if shared and dist.rank != 0:
        dist.barrier("the view store, which rank 0 writes")
    store = ViewStore.open(path, fingerprint)
    fresh: Optional[ViewStatistics] = None  # gathered only when the store is written now
    hint = "put it elsewhere with --set data.cache_dir=DIR, or preload with --set train.stream_views=never"
    if store is None:
        check_store_space(path, store_size_estimate(sizes, needs_priors), hint)
        log(f"views: streamed ({gib(preload)} preloaded would exceed train.views_on_device_gb="
                 f"{tcfg.views_on_device_gb:g}); writing the view store {path}")
        if needs_priors:
            priors = decompose_views(train, cfg, str(dev), progress, scene.root, spec)
        items = stream_set_up(train, priors, dev, stats)
        store = ViewStore.build(path, fingerprint, needs_priors, items, "--set data.cache_dir=DIR")
        fresh = stats
        release_set_up_memory(dev)
    else:
        log(f"views: streamed from the view store {path} ({gib(store.nbytes)})")
    if shared and dist.rank == 0:
        dist.barrier("the view store, which rank 0 writes")
    views = StreamedViews(store, cameras, centers, dev, method,
                          cfg.loss.depth_edge if depth_prior else None,
                          upcoming=upcoming, graphs=bool(tcfg.cuda_graphs), log=log,
                          resident_bytes=int(tcfg.views_pinned_gb * 1e9))
    log(f"views: {gib(views.slot_bytes)} of reused buffers on the device" +
             (f"; the store held in {'pinned ' if dev.type == 'cuda' else ''}host memory ({gib(views.resident_bytes)}"
              f" <= train.views_pinned_gb={tcfg.views_pinned_gb:g})" if views.resident_bytes else ""))
    return views, streamed, fresh


def release_set_up_memory(device: torch.device) -> None:
    """Hand the cached blocks of the set-up's GPU work back to the driver before the first step. LR3M solves a 12 MP
    photo whole in ~15 GB where they fit; kept by torch's caching allocator, they stay reserved beside training's own
    blocks (the 12 MP raw scene peaked at 32.5 GB reserved for 17.8 GB allocated), which a 24 GB card lacks."""
    if torch.device(device).type == "cuda":
        torch.cuda.empty_cache()


def view_statistics(cfg: Config, views: Sequence[TrainView], gathered: Optional[ViewStatistics]) -> ViewStatistics:
    """Every training view's contribution to the illumination reference and the mean background: ``gathered`` at
    set-up as the views were read, or (a reused view store) now, one view at a time."""
    if gathered is not None:
        return gathered
    stats = ViewStatistics(cfg.model.enhancement.ref_quantile)
    for i in range(len(views)):
        tv = views.get(i, prefetch=False) if isinstance(views, StreamedViews) else views[i]
        stats.add(tv.S, tv.R, tv.L)
    return stats


def near_plane(cfg: Config, scene: Scene, log: Callable[[str], None]) -> float:
    """``model.near_fraction`` times the training views' nearest content depth (:func:`content_depth` of the
    scene's initial points); logged. 0 (no plane) where no view sees enough points."""
    depth = content_depth(scene.points, [view_camera(v) for v in scene.train])
    near = float(cfg.model.near_fraction) * depth
    log(f"near plane: {near:.4g} ({cfg.model.near_fraction:g} x the training views' nearest content "
        f"depth {depth:.4g})" if near > 0 else
        f"near plane: none (no training view sees {MIN_POINTS} initial points)")
    return near
