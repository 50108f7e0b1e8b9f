"""``load_scene``: detect the input format, read it, undistort/resize images into the cache, normalise.

Auto-detection (``reader="auto"``), first match wins:
1. ``transforms_train.json`` or ``transforms.json`` in the folder -> "transforms" (instant-ngp / LOM);
2. a COLMAP model (``.``, ``sparse/0``, ``sparse``, ``colmap_sparse/0``, ...) -> "colmap";
3. photos in ``images/`` (or the ``images`` folder given), ``low/``, or directly in the folder -> "sfm" (pycolmap
   SfM, cached in ``<scene>/retinexgs_sfm``).

Caches (the only files written into the scene folder; ``cache_dir=`` moves them elsewhere):
``<scene>/retinexgs_cache/{undistorted,downscaled}/...`` for processed images and
``<scene>/retinexgs_sfm/`` (or ``<cache_dir>/sfm``) for the SfM model.

Camera raw photos (docs/raw.md, "Raw scenes"): a view whose image is a raw file is read as a float sRGB photo
(:func:`retinexgs.data.images.read_image_float`), divided by its exposure relative to the median of its folder's
raw files. Refused, one line each: raw and other photos in one split; raw photos of different cameras
(EXIF make/model) or sizes in one split (a bare folder's raw files by :func:`retinexgs.data.sfm.run_sfm`,
before SfM: the views after it are only the photos it registered). Printed: one line with the exposure factors'
range, one warning naming the raw files without exposure metadata (taken at the median). A bare folder of
RAW + JPEG pairs gets its poses from the JPEGs (SfM) and trains on the raw files.

A bare folder goes through SfM (``sfm_options``, e.g. ``min_registered``): the photos it did not register are
named in a warning, and too few registered is refused (:func:`retinexgs.data.sfm.check_registration`).

Without input points (a transforms JSON with no COLMAP model), initial points are random: points along
random train-camera rays at depths uniform in [0.05, 2.5] (normalised units, i.e. up to 2.5 times the
largest camera distance from the rig centre), kept only when inside the frustum of at least two train
views (of all, if fewer); colour mid-grey.
"""
from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple, Union

import numpy as np
import torch

from retinexgs.data.camera import Intrinsics
from retinexgs.data.capture import capture_of_files
from retinexgs.data.images import image_size, is_raw_file, list_images, no_images_reason
from retinexgs.data.declared import DeclaredScene, DeclaredView
from retinexgs.data.scene import Normalization, Scene, View, warn
from retinexgs.data.undistort import output_camera, plan_paths, process_all
from retinexgs.errors import UserError
from retinexgs.data.colmap import find_model_dir
from retinexgs.data.transforms_json import has_transforms
from retinexgs.data.transforms_json import read_transforms_scene
from retinexgs.data.colmap import read_colmap_scene
from retinexgs.data.sfm import PreviewDenoise, raw_jpeg_pairs, run_sfm

READERS = ("auto", "transforms", "colmap", "sfm")
PathLike = Union[str, Path]


def detect_reader(root: Path, images: Optional[PathLike] = None) -> str:
    """The reader that fits ``root`` (see the module docstring); UserError when none does."""

    if has_transforms(root):
        return "transforms"
    if find_model_dir(root) is not None:
        return "colmap"
    if _sfm_image_dir(root, images) is not None:
        return "sfm"
    if images is not None:
        d = Path(images) if Path(images).is_absolute() else root / images
        raise UserError(f"no photos in {d}: {no_images_reason(d)}")
    raise UserError(f"{root} holds no photos (in it, images/ or low/), transforms_*.json or COLMAP model; nothing "
                    f"to load: {no_images_reason(root)}")


def _sfm_image_dir(root: Path, images: Optional[PathLike]) -> Optional[Path]:
    if images is not None:
        d = Path(images) if Path(images).is_absolute() else root / images
        return d if list_images(d) else None
    for d in (root / "images", root / "low", root):
        if list_images(d):
            return d
    return None


def _fit_camera(view: DeclaredView) -> Intrinsics:
    """The view's camera adjusted to the actual image size (same aspect ratio), else UserError."""
    w, h = image_size(view.image)
    cam = view.camera
    pw, ph = image_size(view.paired) if view.paired is not None else (w, h)
    odd = ((1, 0), (0, 1), (1, 1))
    if is_raw_file(Path(view.image)) and (
            ((pw - w, ph - h) in odd and (cam.width, cam.height) in ((pw, ph), (w, h)))
            or ((pw, ph) == (w, h) and (cam.width - w, cam.height - h) in odd)):
        # A raw file's odd last row/column is dropped (whole 2x2 colour quads): its view is the top-left w x h of
        # the sensor, so the camera keeps its focal length and centre and the truth is cropped alike
        # (View.paired_image). The same for a camera of the uncropped size without a truth (a RAW + JPEG pair posed
        # from its JPEG): rescaling it instead stretched one axis (1 x 0.9973), two camera models for one photo.
        return Intrinsics(w, h, cam.fx, cam.fy, cam.cx, cam.cy, cam.dist)
    if view.paired is not None and (pw, ph) != (w, h):
        raise UserError(f"paired images differ in size: {view.image} is {w}x{h}, "
                        f"{view.paired} is {image_size(view.paired)[0]}x{image_size(view.paired)[1]}")
    if (w, h) == (cam.width, cam.height):
        return cam
    if abs(w / h - cam.width / cam.height) > 0.01 * cam.width / cam.height:
        raise UserError(f"image {view.image} is {w}x{h} pixels but its camera is {cam.width}x{cam.height}")
    return cam.scaled(w, h)


def _shown(root: Path, path: Path) -> str:
    """``path`` relative to the scene folder when it lies inside it (as the user listed it)."""
    try:
        return str(Path(path).relative_to(root))
    except ValueError:
        return str(path)


def _split_label(raw: DeclaredScene, split: str) -> str:
    """Where a split's views are listed: the transforms JSON file, else 'the <split> split'."""
    if raw.reader == "transforms":
        return (f"transforms_{split}.json" if (Path(raw.root) / "transforms_train.json").is_file()
                else "transforms.json")
    return f"the {split} split"


def _check_views(raw: DeclaredScene) -> None:
    """Refuse what cannot train, warn about what is doubtful:

    * fewer than 2 training views: UserError (one photo has no parallax, so no 3D to reconstruct);
    * one image file listed twice in a split: a warning when both frames have the same pose (the view just
      counts twice), a UserError when the poses differ (one photo cannot be taken from two places);
    * test views whose image is also a training view: a warning (the test metrics are not held-out; the
      evaluation records the count in metrics.json as ``test_in_train``).
    """
    root = Path(raw.root)
    if len(raw.train) < 2:
        got = (f"only 1 training view ({_shown(root, raw.train[0].image)})" if raw.train
               else "no training views")
        raise UserError(f"{root} has {got}; a 3D reconstruction needs at least 2 views of the scene from "
                        "different positions (in practice a dozen or more): add photos, or list more frames as "
                        "training views")
    for split in ("train", "test", "val"):
        first: Dict[Path, int] = {}
        for i, v in enumerate(getattr(raw, split)):
            key = Path(v.image).resolve()
            if key not in first:
                first[key] = i
                continue
            j = first[key]
            other = getattr(raw, split)[j]
            label = _split_label(raw, split)
            which = (f"{label} frames {j} and {i} both list {_shown(root, v.image)}" if raw.reader == "transforms"
                     else f"{label} lists {_shown(root, v.image)} twice")
            scale = 1.0 + float(np.abs(other.c2w[:3, 3]).max())
            if not np.allclose(other.c2w, v.c2w, atol=1e-6 * scale):
                raise UserError(f"{which} with different camera poses; one photo has one pose: remove the "
                                "wrong frame")
            warn(f"{which} (same pose): the view counts twice{' in training' if split == 'train' else ''}; "
                 "remove the duplicate frame")
    train = {Path(v.image).resolve() for v in raw.train}
    shared = [v for v in raw.test if Path(v.image).resolve() in train]
    if shared:
        names = ", ".join(_shown(root, v.image) for v in shared[:3]) + (" ..." if len(shared) > 3 else "")
        warn(f"{len(shared)} of {len(raw.test)} test views are also training views ({names}): the test metrics "
             "are not held-out (recorded as test_in_train in metrics.json); list them in one split only")


def _check_raw_views(raw: DeclaredScene) -> None:
    """Camera raw views (see the module docstring): one split is all raw or all not, of one camera and one
    size; one line gives the exposure factors' range and one warning names the files without exposure
    metadata. Reads only the raw files' headers (:func:`retinexgs.data.camera_raw.folder_exposure`)."""
    from retinexgs.data.camera_raw import folder_exposure

    root = Path(raw.root)
    factors: Dict[Path, float] = {}
    missing: List[str] = []
    for split in ("train", "test", "val"):
        views = getattr(raw, split)
        raws = [v for v in views if is_raw_file(Path(v.image))]
        if not raws:
            continue
        label = _split_label(raw, split)
        others = [v for v in views if not is_raw_file(Path(v.image))]
        if others:
            raise UserError(f"{label} mixes camera raw files and other photos ({_shown(root, raws[0].image)}, "
                            f"{_shown(root, others[0].image)}): one split's photos must all be raw or all not "
                            f"(they are read differently); list one kind")
        cameras: Dict[str, Path] = {}
        sizes: Dict[Tuple[int, int], Path] = {}
        for v in raws:
            img = Path(v.image)
            fe = folder_exposure(img.parent)
            head = fe.headers[img.name]
            factors[img.resolve()] = fe.factors[img.name]
            if img.name in fe.missing:
                missing.append(_shown(root, img))
            if head.camera:
                cameras.setdefault(head.camera, img)
            sizes.setdefault((head.width, head.height), img)
        if len(cameras) > 1:
            (a, pa), (b, pb) = list(cameras.items())[:2]
            raise UserError(f"{label} holds raw photos of different cameras: {_shown(root, pa)} is a {a}, "
                            f"{_shown(root, pb)} a {b}; one scene is one camera's (its colour and noise): "
                            f"train them as separate scenes")
        if len(sizes) > 1:
            (a, pa), (b, pb) = list(sizes.items())[:2]
            raise UserError(f"{label} holds raw photos of different sizes: {_shown(root, pa)} is {a[0]}x{a[1]}, "
                            f"{_shown(root, pb)} {b[0]}x{b[1]}; shoot one format (no crop modes) or train them "
                            f"as separate scenes")
    if not factors:
        return
    lo, hi = min(factors.values()), max(factors.values())
    print(f"raw photos: {len(factors)} camera raw views read as float sRGB (demosaiced, as-shot white balance), "
          f"each divided by its exposure relative to its folder's median: factors {lo:.3g} .. {hi:.3g}",
          file=sys.stderr, flush=True)
    if missing:
        shown = ", ".join(sorted(set(missing))[:5]) + (" ..." if len(set(missing)) > 5 else "")
        warn(f"{len(set(missing))} raw photo{'s have' if len(set(missing)) > 1 else ' has'} no exposure time, ISO "
             f"or f-number in the metadata ({shown}): their exposure is assumed equal to the median (factor 1)")


def _raw_for_jpeg(raw: DeclaredScene, pairs: Dict[Path, Path]) -> None:
    """A RAW + JPEG folder's scene (poses from the JPEGs): each view reads the raw file beside its JPEG."""
    by_jpeg = {jpeg.name: raw_file for raw_file, jpeg in pairs.items()}
    for v in raw.train + raw.test + raw.val:
        partner = by_jpeg.get(Path(v.image).name)
        if partner is not None:
            v.image = partner


def _warn_rescaled(raw: DeclaredScene, cams: Dict[int, Intrinsics]) -> None:
    """One warning per camera size that disagrees with its images' size (the intrinsics are rescaled)."""
    seen: Dict[Tuple[int, int, int, int], List[DeclaredView]] = {}
    for v in raw.train + raw.test + raw.val:
        declared, fitted = v.camera, cams[id(v)]
        cropped = (declared.fx, declared.fy, declared.cx, declared.cy) == (fitted.fx, fitted.fy, fitted.cx, fitted.cy)
        if (declared.width, declared.height) != (fitted.width, fitted.height) and not cropped:
            seen.setdefault((declared.width, declared.height, fitted.width, fitted.height), []).append(v)
    source = "the transforms JSON gives w x h =" if raw.reader == "transforms" else "the COLMAP camera is"
    for (cw, ch, w, h), views in seen.items():
        sx, sy = w / cw, h / ch
        factor = f"{sx:.4g}" if abs(sx - sy) < 1e-3 * sx else f"{sx:.4g} x {sy:.4g}"
        warn(f"{source} {cw}x{ch} but the image{'s are' if len(views) > 1 else ' is'} {w}x{h} "
             f"({len(views)} view{'s' if len(views) > 1 else ''}, e.g. {_shown(Path(raw.root), views[0].image)}): "
             f"the intrinsics (focal length, principal point) are rescaled by {factor} to fit the images")


def _normalization(train: List[DeclaredView]) -> Normalization:
    centres = np.stack([v.c2w[:3, 3] for v in train])
    centre = centres.mean(0)
    radius = float(np.linalg.norm(centres - centre, axis=1).max())
    scale = 1.0 / radius if radius > 1e-12 else 1.0
    return Normalization(torch.tensor(centre, dtype=torch.float64), scale)


def random_frustum_points(views: List[View], n: int, seed: int = 0) -> np.ndarray:
    """``n`` random points seen by at least min(2, len(views)) views (see the module docstring)."""
    rng = np.random.default_rng(seed)
    need = min(2, len(views))
    kept: List[np.ndarray] = []
    total = 0
    for _ in range(20):
        m = max(4 * n, 1000)
        idx = rng.integers(0, len(views), m)
        pts = np.empty((m, 3))
        for i in np.unique(idx):
            sel = idx == i
            v = views[i]
            k = int(sel.sum())
            u = rng.uniform(0, v.width, k)
            w = rng.uniform(0, v.height, k)
            d = rng.uniform(0.05, 2.5, k)
            cam = np.stack([(u - v.cx) / v.fx * d, (w - v.cy) / v.fy * d, d], -1)
            c2w = v.camera_to_world.numpy()
            pts[sel] = cam @ c2w[:3, :3].T + c2w[:3, 3]
        seen = np.zeros(m, dtype=np.int64)
        for v in views:
            uvz = v.project(pts).numpy()
            seen += ((uvz[:, 2] > 1e-6) & (uvz[:, 0] >= 0) & (uvz[:, 0] < v.width)
                     & (uvz[:, 1] >= 0) & (uvz[:, 1] < v.height))
        good = pts[seen >= need]
        kept.append(good)
        total += len(good)
        if total >= n:
            break
    out = np.concatenate(kept)[:n]
    return out


# Smallest image side a downscaled view may have: the evaluation's SSIM window is 11x11 (the decomposers
# need 8x8), and fewer pixels train nothing useful.
MIN_IMAGE_SIDE = 11
# How each entry point spells "put the caches elsewhere", for the read-only-scene message.
CACHE_HINT = "cache_dir=DIR"


def _check_downscale(downscale: float, cams: Dict[int, Intrinsics], views: List[DeclaredView]) -> None:
    """UserError, before anything is written, when ``downscale`` leaves a view too small to use."""
    for v in views:
        cam = cams[id(v)]
        w, h = max(1, int(round(cam.width / downscale))), max(1, int(round(cam.height / downscale)))
        if min(w, h) < MIN_IMAGE_SIDE:
            largest = min(cam.width, cam.height) / (MIN_IMAGE_SIDE - 0.5)
            raise UserError(f"downscale {downscale:g} shrinks {v.image} ({cam.width}x{cam.height}) to {w}x{h} "
                            f"pixels; images need at least {MIN_IMAGE_SIDE} pixels a side (use a downscale of at "
                            f"most {max(1.0, float(int(largest * 10) / 10)):g})")


def build_scene(raw: DeclaredScene, downscale: float = 1, cache_dir: Optional[PathLike] = None,
                normalize: bool = True, num_random_points: int = 50_000, seed: int = 0,
                cache_hint: str = CACHE_HINT) -> Scene:
    """Turn a reader's :class:`DeclaredScene` into a :class:`Scene` (images processed into the cache).

    Every image's size is checked before the cache is touched; the cache's files of one call appear
    together or not at all. ``cache_hint`` is how the caller's interface spells moving the caches
    (e.g. ``--set data.cache_dir=DIR``), named when the scene folder is not writable.
    """
    if not downscale >= 1:
        raise UserError(f"downscale must be >= 1, got {downscale}")
    root = Path(raw.root)
    cache = Path(cache_dir) if cache_dir is not None else root / "retinexgs_cache"
    jobs: List[Tuple[Path, Path, Intrinsics, Intrinsics]] = []
    split_views: Dict[str, List[View]] = {}
    _check_views(raw)
    _check_raw_views(raw)
    all_raw = raw.train + raw.test + raw.val
    cams = {id(v): _fit_camera(v) for v in all_raw}
    _warn_rescaled(raw, cams)
    _check_downscale(downscale, cams, all_raw)
    norm = _normalization(raw.train) if normalize else Normalization.identity()
    for split, rv in (("train", raw.train), ("test", raw.test), ("val", raw.val)):
        views = []
        for v in rv:
            cam = cams[id(v)]
            srcs = [v.image] + ([v.paired] if v.paired is not None else [])
            mapping = plan_paths(srcs, root, cache, cam, downscale, jobs)
            oc = output_camera(cam, downscale)
            c2w = norm.pose_to_normalized(torch.tensor(v.c2w, dtype=torch.float64))
            views.append(View(v.name, mapping[v.image], oc.fx, oc.fy, oc.cx, oc.cy, oc.width, oc.height, c2w,
                              mapping[v.paired] if v.paired is not None else None, v.image))
        split_views[split] = views
    if jobs:
        created = not cache.exists()
        try:
            cache.mkdir(parents=True, exist_ok=True)
            probe = tempfile.TemporaryFile(dir=cache)  # an existing but read-only cache fails here too
            probe.close()
        except OSError as exc:
            raise UserError(f"cannot write the image cache folder {cache}: {exc.strerror or exc}; "
                            f"put the caches elsewhere with {cache_hint}") from None
        try:
            process_all(jobs, cache, elsewhere=cache_hint)
        except BaseException:
            if created:  # nothing of a failed first load stays in the user's scene folder
                shutil.rmtree(cache, ignore_errors=True)
            raise
    if raw.points is not None and len(raw.points):
        pts = norm.to_normalized(np.asarray(raw.points, np.float64))
        points = torch.tensor(pts, dtype=torch.float32)
        colors = torch.tensor(np.asarray(raw.colors, np.float32) / 255.0)
        source = raw.points_source
    else:
        pts = random_frustum_points(split_views["train"], num_random_points, seed)
        points = torch.tensor(pts, dtype=torch.float32)
        colors = torch.full_like(points, 0.5)
        source = "random"
    return Scene(root, raw.reader, split_views["train"], split_views["test"], points, colors, norm, source,
                 split_views["val"], capture_of_files([v.user_path for v in split_views["train"]]))


def load_scene(path: PathLike, reader: str = "auto", downscale: float = 1, *, images: Optional[PathLike] = None,
               cache_dir: Optional[PathLike] = None, normalize: bool = True, test_every: int = 0,
               num_random_points: int = 50_000, seed: int = 0, sfm_options: Optional[dict] = None,
               progress: Optional[Callable[[str], None]] = None, cache_hint: str = CACHE_HINT,
               sfm_denoise: Optional[Callable[[Path], Optional[PreviewDenoise]]] = None) -> Scene:
    """Load a scene folder in any supported format (see the module docstring).

    ``reader``: "auto", "transforms", "colmap" or "sfm". ``downscale``: resize factor (>= 1) applied to
    images and intrinsics. ``images``: image folder for the colmap/sfm readers (relative to ``path`` or
    absolute). ``test_every``: for colmap/sfm scenes without split.json, hold out every N-th view.
    ``sfm_options``: keyword arguments for :func:`retinexgs.data.sfm.run_sfm`. ``cache_hint``: how the
    caller spells ``cache_dir`` (for the message when the scene folder cannot be written). ``sfm_denoise``: (the
    folder of photos SfM reads) -> the denoiser of its previews (``data.sfm_denoise``, built above this layer by
    :func:`retinexgs.train.sfm_preview.scene_sfm_denoise`); called only when the scene is posed by SfM.
    """
    root = Path(path)
    if not root.exists():
        raise UserError(f"scene folder {root} does not exist")
    if not root.is_dir():
        raise UserError(f"{root} is not a folder; pass the scene folder")
    if reader not in READERS:
        raise UserError(f"unknown reader {reader!r}; choose one of {', '.join(READERS)}")
    if reader == "auto":
        reader = detect_reader(root, images)
    if reader == "transforms":
        raw = read_transforms_scene(root)
    elif reader == "colmap":
        raw = read_colmap_scene(root, images=images, test_every=test_every)
    else:
        image_dir = _sfm_image_dir(root, images)
        if image_dir is None:
            if images is not None:
                d = Path(images) if Path(images).is_absolute() else root / images
                raise UserError(f"no photos in {d}: {no_images_reason(d)}")
            raise UserError(f"no photos found in {root}, {root / 'images'} or {root / 'low'}: "
                            f"{no_images_reason(root)}")
        if downscale >= 1:  # refuse a useless downscale before SfM writes its model
            listed = list_images(image_dir)
            pairs = raw_jpeg_pairs(listed)  # also refuses raw and other photos that do not pair up
            photos = [DeclaredView(p.name, p, Intrinsics(*image_size(p), 1.0, 1.0, 0.0, 0.0), np.eye(4))
                      for p in (sorted(pairs) if pairs else listed)]
            _check_downscale(downscale, {id(v): v.camera for v in photos}, photos)
        out = Path(cache_dir) / "sfm" if cache_dir is not None else root / "retinexgs_sfm"
        kwargs = dict(sfm_options or {})
        if progress is not None:
            kwargs.setdefault("progress", progress)
        if sfm_denoise is not None:
            kwargs["denoise"] = sfm_denoise(image_dir)
        result = run_sfm(image_dir, out, **kwargs)
        raw = read_colmap_scene(root, result.model_dir, images=image_dir.resolve(), test_every=test_every,
                                reader="sfm")
        raw.points_source = "sfm"
        pairs = raw_jpeg_pairs(list_images(image_dir))
        if pairs:  # RAW + JPEG: SfM posed the JPEGs (run_sfm said so); the views read the raw files
            _raw_for_jpeg(raw, pairs)
            print(f"raw photos: {len(pairs)} RAW + JPEG pairs in {image_dir}: poses from the JPEGs, training on "
                  f"the raw files", file=sys.stderr, flush=True)
    return build_scene(raw, downscale, cache_dir, normalize, num_random_points, seed, cache_hint)
