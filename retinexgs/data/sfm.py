"""Structure-from-motion on a plain folder of photos with pycolmap, cached on disk.

Pipeline: SIFT extraction (one shared camera, SIMPLE_RADIAL by default, when all photos have one size),
exhaustive matching for up to ``EXHAUSTIVE_MAX`` photos else sequential matching (overlap 15), incremental
mapping; the largest model is kept. Dark folders (median luma < 0.25) are first copied to
``<out>/enhanced/`` brightened and denoised (:mod:`retinexgs.data.enhance`) and features are extracted
from those copies; the mapper reads point colours from the originals.

Output folder (default ``<scene>/retinexgs_sfm``): ``sparse/0`` (binary model), ``database.db``,
``enhanced/`` and ``retinexgs_sfm.json`` (the inputs and options of the run; also the mark that the folder's
COLMAP files are this command's). A later call with the same photos (names and contents, by SHA-256) and
options reuses the model. COLMAP files (``database.db``, ``sparse/``) in the output folder without that mark are
the user's: they are replaced only with ``force``. The model and database are built in a temporary folder
(``.tmp-sfm-<pid>-<host>-*``) and moved into place with ``os.replace``. A call that fails (or is interrupted)
removes what it made: the output folder when it made it, else the ``enhanced/`` folder when it made that; the
temporary folders of killed runs (their process gone) are removed by the next call. Enhanced copies are reused
when their source's content digest and the enhancement method match ``.retinexgs_enhanced.json``.

Camera raw photos (issue #52 stage 3a, docs/raw.md): COLMAP cannot read them, so a folder of raw files ALWAYS
goes through copies: each raw file's full-size preview (:func:`retinexgs.data.camera_raw.preview_srgb`, bright
and denoised), written into ``enhanced/`` under the raw file's own name as PNG bytes (COLMAP reads the bytes, not
the name), and the mapper takes its point colours from those copies. A folder of RAW + JPEG pairs (every raw
file with a photo of the same stem beside it, as a camera writes them) uses the JPEGs for SfM, as they are (one
log line says so); the loader then trains on the raw files (:func:`raw_jpeg_pairs`). Raw and other photos that
do not pair up are refused (one line), and so are raw files of different sizes (training refuses them, and SfM
posed only the photos of one size: the check on the registered views never saw the others).

Dropped photos (issue 62): the photos SfM did not register are named in one ``warning:`` line; when fewer than
``min_registered`` of them (a share, :data:`MIN_REGISTERED_SHARE` by default) are registered, UserError: the model
is kept (a lower ``min_registered``, e.g. ``--min-registered 0``, then uses it without running SfM again).

Denoised previews (issue 62 item 3, issue 64 item 5): with a :class:`PreviewDenoise` (``sfm --denoise``, built by
:mod:`retinexgs.train.sfm_preview`, since the denoiser lives in a layer above this one; ``train`` on a bare folder
too, ``data.sfm_denoise``) the previews of dark photos and raw files are denoised in linear light, under their noise
model, before they are brightened: a raw file by its own noise (:func:`retinexgs.data.raw_noise.view_noise`), a
photo by the capture's (``PreviewDenoise.photo_noise``). The recipe is part of the copies' cache key and of the
cached model's signature (absent without a denoiser, so models cached before it still match). ``denoise_cached``:
a finished run read back (eval, render, export) cannot build the denoiser (it lives above this layer and the run
layer), so it takes the cached model whichever recipe made it: the one its training made.

Night settings (issue 64 item 5, ``sfm --night``): with denoised previews (``night`` "auto") SIFT and the mapper take
:data:`NIGHT_SIFT`, :data:`NIGHT_MAPPER` and :data:`NIGHT_TRIANGULATION` (why: beside them), and photos posed on
loose matches are dropped from the model (:data:`NIGHT_GUARD`, named as not registered), and where that model leaves
photos out two more are mapped from looser matches and one is used only if its camera centres agree with the first's
and with the other looser mapping's (:data:`NIGHT_AGREE`, one ``night check:`` line says which and why); they are part
of the cached model's signature only when used.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import socket
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, List, Optional, Sequence, Tuple, Union

import numpy as np

from retinexgs.data.camera import COLMAP_MODELS
from retinexgs.data.images import (HEIF_EXTENSIONS, image_size, is_raw_file, list_images, read_image,
                                   write_image_atomic)
from retinexgs.errors import UserError
from retinexgs.fileio import atomic_write_text, content_digest, is_out_of_space, out_of_space_error
from retinexgs.data.colmap import keep_python_sigterm
from retinexgs.data.enhance import METHOD as enhance_method
from retinexgs.data.enhance import enhance_for_features, folder_is_dark

EXHAUSTIVE_MAX = 100
SEQUENTIAL_OVERLAP = 15
Progress = Callable[[str], None]
META_NAME = "retinexgs_sfm.json"
ENHANCED_MANIFEST = ".retinexgs_enhanced.json"
TMP_PREFIX = ".tmp-sfm-"
# A temporary folder of another host, or of the old unnamed kind, is taken as abandoned after this long.
STALE_TMP_SECONDS = 24 * 3600
# The least share of the photos SfM must register for the model to be used (``--min-registered``, the config's
# data.min_registered): below half, most of the capture is missing from the scene (a night capture at 1000 e-
# registered 2 of 25 photos and trained on 2 views without a word); 0 accepts any model.
MIN_REGISTERED_SHARE = 0.5
# Dropped photos named in the warning / error before "... (N more)".
SHOWN_NAMES = 20
# Night settings (issue 64 item 5; experiments/notes/2026-11-28-sfm-night.md), used where the previews are noisy
# enough to be denoised (``night`` "auto": a PreviewDenoise is given, under ``--denoise auto`` σ > 0.08). SIFT:
# no upsampled first octave (on a denoised night preview it holds the denoiser's blotches and the noise left, not
# the scene's detail) and domain-size pooling (descriptors pooled over scales: steadier under the noise left).
# Mapper: a night pair verifies 30-50 inliers (castlep30-dark at 1000 e-: 47 at most), under COLMAP's 100 for the
# initial pair and 30 for the next views, so neither was met; only neighbouring photos match at night, so the initial
# pair's least triangulation angle is halved (16 -> 8 degrees: wider pairs share no matches). A photo is posed from
# 10 inliers (COLMAP: 30) but only within 4 px, the tolerance COLMAP itself puts on the initial pair and on every
# point (its 12 px let 10 loose matches pose fox-dark's views 0072-0085 a third of the scene away). Triangulation keeps
# two-view tracks: with few matches a pair, points seen by two photos only are most of the model, and the next photo
# is posed on them. Poses measured against the scenes' own (the note): median centre error 1-7 % of their extent.
NIGHT_SIFT = {"first_octave": 0, "domain_size_pooling": True}
NIGHT_MAPPER = {"init_min_num_inliers": 30, "init_min_tri_angle": 8.0, "abs_pose_min_num_inliers": 10,
                "abs_pose_max_error": 4.0}
NIGHT_TRIANGULATION = {"ignore_two_view_tracks": False}
# Loose-view guard, part of the night settings (the note's section 4): a photo posed from 10 loose inliers can land far
# from where it was taken, and a misplaced view is worse than a missing one (training would fit it). castlep30-dark's
# JPEGs at 1000 e-: views 0023 and 0024 posed 62 % and 79 % of the scene's extent away shared 13 and 8 points with
# their best neighbour; every other view of the six night folders measured shared 17 or more with one. A registered
# photo sharing fewer than ``min_shared_points`` 3D points with every other registered photo is dropped from the model.
NIGHT_GUARD = {"min_shared_points": 15}
# Agreeing models, part of the night settings (the note's section 5): SIFT's match ratio 0.9 (COLMAP's 0.8) keeps the
# matches that register the photos the strict matcher leaves out (fountain-dark 10-11/11, fox-dark JPEG 50/50), but at
# night it also built models wrong as a whole (castlep30-dark JPEG, median centre error 62-68 % of the extent), which
# NIGHT_GUARD, a per-view test, cannot see. So where the strict model leaves photos out, a second model is built from
# the looser matches and used only where it reproduces the strict model's camera layout on the photos both posed: the
# best similarity (rotation, translation, scale; no mirror) maps its centres to the strict model's within
# ``max_median_error`` (median) and ``max_error`` (largest) of the strict model's extent there (the RMS distance of
# those centres from their mean), and it poses more photos. The bounds: a model judged right in the note is up to
# about 10 % (median) off the scene's own poses (1-11 %), and the strict model is no better than the loose one, so two
# right models can differ by twice that (20 %; the wrong ones were 62-68 % off); a view 30 % off is misplaced in any
# model. Fewer than ``min_shared_photos`` shared photos cannot be checked (two centres fix no rotation about their
# axis): the strict model stays. The photos the loose model adds have no strict pose to compare with (fox-dark JPEG:
# a loose model agreeing with the strict one to 0.9 % on its 38 photos posed the 12 it added 36-42 % off, as one arc
# on weak links), so they are checked by a second mapping of the same loose matches from another seed: it must pose
# every added photo again and agree with the first within the same bounds (an arc attached by chance is attached
# elsewhere by another run), else the strict model stays.
# Two mappings, either one the reference (the note's section 6): the mapper is not repeatable at night inlier counts,
# and a right loose model of fountain-dark RAW was kept out when the FIRST mapping missed the strict model's bounds by
# a hair (30.2 % against 30 %) though the second might have met them. So ``loose_mappings`` mappings of the same loose
# matches are made (seeds s, s+1) and a mapping is used where it agrees with the strict model (as above) and every
# other mapping poses the photos it adds and agrees with it: either mapping may be the one that meets the strict
# model. No vote: mappings of the same loose matches are not independent evidence (section 6: two of three mappings of
# castlep30-dark JPEG's were wrong alike, 24-29 % (median) and 104-114 % (largest) off the scene's poses and within
# 6 % / 17 % of each other; two of three of fountain-dark RAW's put view 0000 40-45 % off alike), so one dissenting
# mapping keeps the strict model, and the strict model is never outvoted.
NIGHT_AGREE = {"loose_max_ratio": 0.9, "min_shared_photos": 3, "max_median_error": 0.20, "max_error": 0.30,
               "loose_mappings": 2}
NIGHT_CHOICES = ("auto", "on", "off")


@dataclass(frozen=True)
class PreviewDenoise:
    """How SfM's previews of dark photos are denoised before they are brightened (module docstring).

    ``recipe``: names the method, its settings and the photos' noise model (the copies' cache key); ``apply``:
    (linear RGB float32 [H,W,3], per-channel a, per-channel b of ``var = a·y + b``) -> the denoised linear RGB;
    ``photo_noise``: the (a, b) of the photos' linear light (None: photos other than raw files are not denoised)."""
    recipe: str
    apply: Callable[[np.ndarray, Sequence[float], Sequence[float]], np.ndarray]
    photo_noise: Optional[Tuple[Sequence[float], Sequence[float]]] = None


@dataclass
class SfmResult:
    """What :func:`run_sfm` produced."""

    model_dir: Path
    image_dir: Path
    num_images: int
    registered: List[str]
    num_points: int
    seconds: float
    enhanced: bool
    cached: bool = False
    matching: str = ""
    stage_seconds: dict = field(default_factory=dict)

    @property
    def num_registered(self) -> int:
        """Number of registered photos."""
        return len(self.registered)


# Recorded with cached SfM runs (as the enhancement method is) so a change of the raw preview invalidates them.
RAW_PREVIEW_METHOD = "raw-preview-full-p99-to-0.9+bilateral"


def raw_jpeg_pairs(paths: List[Path]) -> Optional[dict]:
    """For a folder's photos: None when none is a raw file; {raw file: its JPEG (or other photo) of the same
    stem} when every raw file has exactly one such photo and every other photo is such a partner (a camera's
    RAW + JPEG capture); UserError when raw and other photos are mixed without pairing up."""
    raws = [p for p in paths if is_raw_file(p)]
    if not raws:
        return None
    others = [p for p in paths if not is_raw_file(p)]
    if not others:
        return {}
    by_stem: dict = {}
    for p in others:
        by_stem.setdefault(p.stem, []).append(p)
    raw_stems = {p.stem for p in raws}
    unpaired = [p.name for p in raws if len(by_stem.get(p.stem, [])) != 1]
    unpaired += [p.name for p in others if p.stem not in raw_stems]
    if unpaired or len(raw_stems) != len(raws):
        shown = ", ".join(sorted(unpaired)[:4]) + (" ..." if len(unpaired) > 4 else "")
        raise UserError(f"{raws[0].parent} mixes camera raw files ({len(raws)}) and other photos ({len(others)}) "
                        f"that do not pair up by name (e.g. {shown or raws[0].name}); one scene's photos are all raw "
                        f"or all not (a RAW + JPEG capture, NAME.dng beside NAME.jpg, is also accepted): move "
                        f"the others to another folder")
    return {p: by_stem[p.stem][0] for p in raws}


def check_min_registered(min_registered: float) -> float:
    """``min_registered`` as a float when it is a share in [0, 1], else UserError."""
    try:
        share = float(min_registered)
    except (TypeError, ValueError):
        share = float("nan")
    if isinstance(min_registered, bool) or not 0.0 <= share <= 1.0:
        raise UserError(f"--min-registered must be the least share of the photos SfM must register, between 0 and 1 "
                        f"(default {MIN_REGISTERED_SHARE:g}; 0 accepts any model), got {min_registered!r}")
    return share


def _listed(names: List[str]) -> str:
    """``names`` joined by commas, the first SHOWN_NAMES of them and a count of the rest."""
    shown = ", ".join(names[:SHOWN_NAMES])
    return shown + (f" ... ({len(names) - SHOWN_NAMES} more)" if len(names) > SHOWN_NAMES else "")


def check_registration(image_dir: Path, names: List[str], registered: List[str], min_registered: float,
                       model_dir: Path) -> None:
    """Name the photos SfM left out (one ``warning:`` line); UserError when the registered share is below
    ``min_registered`` (see the module docstring)."""
    from retinexgs.data.scene import warn  # lazy: scene imports the image tensors' code

    reg = set(registered)
    dropped = [n for n in sorted(names) if n not in reg]
    if not dropped:
        return
    k, n = len(names) - len(dropped), len(names)
    if k / n < min_registered:
        floor = int(k / n * 100) / 100  # the share this model passes, rounded down
        raise UserError(f"SfM registered only {k} of {n} photos in {image_dir} ({k / n:.0%}, below "
                        f"--min-registered {min_registered:g}), so the scene would leave out the rest of the capture; "
                        f"not registered: {_listed(dropped)}. Photos too dark, blurred or overlapping too little with "
                        f"the others are dropped: add overlapping photos or remove those, or pass --min-registered "
                        f"{floor:g} (0 accepts any model) to use the {k} registered (the model is kept in {model_dir})")
    warn(f"SfM registered {k} of {n} photos in {image_dir}; not registered, left out of the scene: "
         f"{_listed(dropped)}")


def check_raw_sizes(raws: List[Path], where: Path) -> None:
    """UserError when the raw files ``raws`` are not all of one size (read from their headers)."""
    sizes: dict = {}
    for p in raws:
        sizes.setdefault(image_size(p), p)
    if len(sizes) > 1:
        (a, pa), (b, pb) = list(sizes.items())[:2]
        raise UserError(f"{where} holds raw photos of different sizes: {pa.name} is {a[0]}x{a[1]}, {pb.name} "
                        f"{b[0]}x{b[1]}; one scene is one sensor format (SfM would pose only one size's photos): "
                        f"shoot one format (no crop modes) or train them as separate scenes")


def check_night(night: Union[str, bool]) -> str:
    """``night`` ("auto", "on", "off", or a bool) as one of :data:`NIGHT_CHOICES`, else UserError (one line)."""
    value = {True: "on", False: "off"}.get(night, night) if isinstance(night, bool) else night
    if value not in NIGHT_CHOICES:
        raise UserError(f"--night must be one of {', '.join(NIGHT_CHOICES)} (default auto: on where SfM's previews "
                        f"are denoised), got {night!r}")
    return value


def night_settings(night: Union[str, bool], denoise: Optional[PreviewDenoise]) -> Optional[dict]:
    """The night settings SfM applies ({"sift": ..., "mapper": ..., "triangulation": ..., "guard": ..., "agree": ...}),
    or None for COLMAP's own (no guard, one model):
    ``night`` "on", or "auto" with previews denoised (``denoise`` given: they are night-noisy)."""
    value = check_night(night)
    if value == "on" or (value == "auto" and denoise is not None):
        return {"sift": dict(NIGHT_SIFT), "mapper": dict(NIGHT_MAPPER), "triangulation": dict(NIGHT_TRIANGULATION),
                "guard": dict(NIGHT_GUARD), "agree": dict(NIGHT_AGREE)}
    return None


def similarity_fit(src: "np.ndarray", dst: "np.ndarray") -> Tuple[float, "np.ndarray", "np.ndarray"]:
    """The similarity (scale s, rotation R, translation t; no reflection) that best maps points ``src`` [N,3] onto
    ``dst`` [N,3] in least squares (Umeyama 1991): ``dst ~ s * R @ src + t``. Degenerate input gives s = 0."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    u, sv, vt = np.linalg.svd(xd.T @ xs / len(src))
    d = np.eye(3)
    d[2, 2] = 1.0 if np.linalg.det(u @ vt) >= 0 else -1.0  # a mirror image is not the same layout
    rot = u @ d @ vt
    var = float((xs ** 2).sum(1).mean())
    scale = float(np.trace(np.diag(sv) @ d) / var) if var > 0 else 0.0
    return scale, rot, mu_d - scale * rot @ mu_s


def centre_agreement(strict: dict, loose: dict, min_shared_photos: int) -> Optional[dict]:
    """How well camera centres ``loose`` ({photo name: centre [3]}) reproduce ``strict``'s on the photos both hold,
    after :func:`similarity_fit`: {"shared": n, "median": m, "max": x}, the distances relative to the strict
    centres' extent (RMS distance from their mean); None when fewer than ``min_shared_photos`` are shared or the
    strict centres (or the loose ones) coincide (no layout to compare)."""
    names = sorted(set(strict) & set(loose))
    if len(names) < max(3, min_shared_photos):
        return None
    a = np.array([loose[n] for n in names], float)
    b = np.array([strict[n] for n in names], float)
    extent = float(np.sqrt(((b - b.mean(0)) ** 2).sum(1).mean()))
    scale, rot, t = similarity_fit(a, b)
    if not extent > 1e-12 or not scale > 0:
        return None
    err = np.linalg.norm((scale * (rot @ a.T)).T + t - b, axis=1) / extent
    return {"shared": len(names), "median": float(np.median(err)), "max": float(err.max())}


def confirm_added(strict: dict, loose: dict, again: Optional[dict], num_photos: int, agree: dict) -> Tuple[bool, str]:
    """Whether a second mapping ``again`` ({name: centre}; None: no model) of the looser matches confirms the photos
    the loose model adds to the strict one (:data:`NIGHT_AGREE`): it poses each of them and its centres agree with
    ``loose``'s on the photos both posed; and the one line that says which model is used and why."""
    k, m = len(strict), len(loose)
    added = sorted(set(loose) - set(strict))
    keep = f"kept the strict model ({k}/{num_photos} photos; looser matcher {agree['loose_max_ratio']:g}: {m})"
    missing = [n for n in added if n not in (again or {})]
    if missing:
        return False, (f"{keep}: a second mapping of the looser matches did not pose {len(missing)} of the "
                       f"{len(added)} photos it adds ({_listed(missing)})")
    fit = centre_agreement(loose, again, agree["min_shared_photos"])
    if fit is None:
        return False, f"{keep}: a second mapping of the looser matches cannot be compared with the first"
    how = (f"a second mapping of the looser matches puts the {fit['shared']} photos both posed {fit['median']:.1%} "
           f"(median) and {fit['max']:.1%} (largest) of the extent from the first")
    if fit["median"] <= agree["max_median_error"] and fit["max"] <= agree["max_error"]:
        return True, (f"used the looser matcher's model ({m}/{num_photos} photos; strict: {k}): it agrees with the "
                      f"strict model on the photos both posed, and {how}")
    return False, f"{keep}, the looser matches' mappings disagree: {how}"


def model_centres(rec) -> dict:
    """{photo name: camera centre} of the registered images of ``rec`` (a pycolmap Reconstruction)."""
    return {rec.images[i].name: np.asarray(rec.images[i].projection_center(), float) for i in rec.reg_image_ids()}


def choose_agreeing(strict: Optional[dict], loose: Optional[dict], num_photos: int, agree: dict) -> Tuple[bool, str]:
    """Whether to use the looser matcher's model (:data:`NIGHT_AGREE`) given the camera centres of the strict and
    the loose model ({name: centre}; None: no model), and the one line that says which and why."""
    k = len(strict or {})
    ratio = agree["loose_max_ratio"]
    if not loose:
        return False, f"kept the strict model ({k}/{num_photos} photos): the looser matcher ({ratio:g}) built none"
    m = len(loose)
    if m <= k:
        return False, (f"kept the strict model ({k}/{num_photos} photos): the looser matcher's ({ratio:g}) posed no "
                       f"more ({m})")
    fit = centre_agreement(strict or {}, loose, agree["min_shared_photos"])
    if fit is None:
        return False, (f"kept the strict model ({k}/{num_photos} photos): the looser matcher's model ({ratio:g}, "
                       f"{m} photos) cannot be checked against it (fewer than "
                       f"{max(3, agree['min_shared_photos'])} distinct photos posed by both)")
    how = (f"on the {fit['shared']} photos both posed its camera centres are {fit['median']:.1%} (median) and "
           f"{fit['max']:.1%} (largest) of the extent from the strict model's")
    if fit["median"] <= agree["max_median_error"] and fit["max"] <= agree["max_error"]:
        return True, f"the looser matcher's model ({ratio:g}, {m}/{num_photos} photos; strict: {k}) agrees: {how}"
    return False, (f"kept the strict model ({k}/{num_photos} photos; looser matcher {ratio:g}: {m}), the models "
                   f"disagree: {how} (bounds {agree['max_median_error']:.0%} / {agree['max_error']:.0%})")


def choose_consensus(strict: dict, mappings: Sequence[Optional[dict]], num_photos: int,
                     agree: dict) -> Tuple[Optional[int], str, List[dict]]:
    """Which of the mappings of the looser matches to use (:data:`NIGHT_AGREE`), given the strict model's camera
    centres and each mapping's ({name: centre}; None: no model): the index of the one used (None: the strict model
    stays), the one line that says which and why, and per mapping {"photos", "strict" (its agreement with the strict
    model, :func:`centre_agreement`, or None), "candidate" (it poses more photos and agrees with the strict model,
    :func:`choose_agreeing`), "supporters" (for a mapping posing more photos than the strict model: the other mappings
    that pose every photo it adds and agree with it, :func:`confirm_added`)}. A candidate supported by every other
    mapping is used (no vote: one dissent keeps the strict model); of two, the one with the most photos, then the
    least median distance from the strict model."""
    k, ratio = len(strict), agree["loose_max_ratio"]
    info: List[dict] = []
    for centres in mappings:
        use, _why = choose_agreeing(strict, centres, num_photos, agree)
        fit = centre_agreement(strict, centres, agree["min_shared_photos"]) if centres else None
        info.append({"photos": len(centres or {}), "strict": fit, "candidate": use, "supporters": []})
    for i, centres in enumerate(mappings):
        if info[i]["photos"] > k:
            info[i]["supporters"] = [j for j, other in enumerate(mappings) if j != i and other is not None and
                                     confirm_added(strict, centres, other, num_photos, agree)[0]]
    others = len(mappings) - 1
    adopted = [i for i in range(len(mappings)) if info[i]["candidate"] and others > 0 and
               len(info[i]["supporters"]) == others]
    counts = ", ".join(str(x["photos"]) for x in info)
    if not adopted:
        reasons = []
        for i, x in enumerate(info):
            fit = x["strict"]
            reasons.append(f"{i + 1}: " + (
                "no model" if mappings[i] is None else "no more photos" if x["photos"] <= k else
                "not comparable with the strict model" if fit is None else
                f"{fit['median']:.1%} / {fit['max']:.1%} from the strict model")
                + ("" if x["photos"] <= k else ", the other mapping poses the photos it adds alike"
                   if x["supporters"] else ", the other mapping does not pose the photos it adds alike"))
        return None, (f"kept the strict model ({k}/{num_photos} photos; looser matcher {ratio:g}: {counts} in "
                      f"{len(mappings)} mappings): none agrees with the strict model and with the other mapping "
                      f"(bounds {agree['max_median_error']:.0%} / {agree['max_error']:.0%}; "
                      f"{'; '.join(reasons)})"), info
    best = min(adopted, key=lambda i: (-info[i]["photos"], info[i]["strict"]["median"]))
    fit = info[best]["strict"]
    return best, (f"used mapping {best + 1} of {len(mappings)} of the looser matcher ({ratio:g}; {counts} photos; "
                  f"{info[best]['photos']}/{num_photos}, strict: {k}): its camera centres are {fit['median']:.1%} "
                  f"(median) and {fit['max']:.1%} (largest) of the extent from the strict model's on the "
                  f"{fit['shared']} photos both posed, and the other mapping poses the photos it adds alike"), info


def loose_views(rec, min_shared_points: int) -> List[int]:
    """The registered image ids of ``rec`` (a pycolmap Reconstruction) that share fewer than ``min_shared_points`` 3D
    points with every other registered image (posed on loose matches; :data:`NIGHT_GUARD`)."""
    reg = set(rec.reg_image_ids())
    shared: dict = {i: {} for i in reg}
    for point in rec.points3D.values():
        seen = sorted({el.image_id for el in point.track.elements} & reg)
        for a in seen:
            for b in seen:
                if a != b:
                    shared[a][b] = shared[a].get(b, 0) + 1
    return sorted(i for i in reg if max(shared[i].values(), default=0) < min_shared_points)


def drop_loose_views(rec, min_shared_points: int) -> List[str]:
    """Deregister the :func:`loose_views` of ``rec`` (their observations go, and the points left on fewer than two
    photos) and remove them from it; returns their names, sorted. Dropping one leaves the counts between the others
    unchanged (their shared points keep two photos or more), so one pass finds them all."""
    loose = loose_views(rec, min_shared_points)
    names = sorted(rec.images[i].name for i in loose)
    for frame_id in sorted({rec.images[i].frame_id for i in loose}):
        rec.deregister_frame(frame_id)
    if loose:
        rec.tear_down()  # the deregistered images leave the model files too
    return names


def _apply(target, settings: dict) -> None:
    """Set each of ``settings`` on a pycolmap options object ``target``."""
    for key, value in settings.items():
        setattr(target, key, value)


def _raw_preview(src: Path, denoise: Optional[PreviewDenoise] = None) -> "np.ndarray":
    """uint8 [H, W, 3]: the full-size bright, denoised preview of a raw file that COLMAP reads instead of it;
    with ``denoise``, its linear light goes through it under the file's own noise model first (the light
    bilateral filter of the plain preview is then left out), unless that noise cannot be measured."""
    from retinexgs.data.camera_raw import _demosaiced_srgb_linear, preview_srgb, read_raw
    from retinexgs.data.raw_noise import view_noise

    photo = read_raw(src)
    if denoise is not None:
        a, b, _source, _note = view_noise(photo)  # the light of _demosaiced_srgb_linear (exposure factor 1)
        if a is not None and b is not None and np.any(a > 0):
            return _bright_preview(denoise.apply(_demosaiced_srgb_linear(photo), a, b), percentile=99.0,
                                   target=0.9)
    return preview_srgb(photo, full_size=True)


def _bright_preview(lin: "np.ndarray", percentile: Optional[float] = None, target: float = 0.9) -> "np.ndarray":
    """uint8 sRGB of denoised linear light ``lin`` [H,W,3] brightened as the plain previews are: the luminance's
    ``percentile`` to ``target`` (the raw preview's rule), or (None) the median to the enhancement's mid-grey with
    its gain bounds (:mod:`retinexgs.data.enhance`)."""
    from retinexgs.data.enhance import MAX_GAIN, TARGET_MEDIAN_LINEAR
    from retinexgs.data.srgb import linear_to_srgb

    lin = np.asarray(lin, np.float32)
    lum = lin @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
    if percentile is not None:
        level = float(np.percentile(lum, percentile))
        gain = target / level if level > 1e-6 else 1.0
    else:
        gain = float(np.clip(TARGET_MEDIAN_LINEAR / max(float(np.median(lum)), 1e-6), 1.0, MAX_GAIN))
    out = np.asarray(linear_to_srgb(np.clip(lin * np.float32(gain), 0.0, 1.0)), np.float32)
    return np.clip(np.round(out * 255.0), 0, 255).astype(np.uint8)


def _photo_preview(src: Path, denoise: Optional[PreviewDenoise]) -> "np.ndarray":
    """uint8 [H,W,3]: the enhanced copy of a dark photo; with ``denoise`` and the photos' noise model, its linear
    light is denoised and then brightened (no blur: the denoiser took the noise the blur was for)."""
    rgb = read_image(src)
    if denoise is None or denoise.photo_noise is None:
        return enhance_for_features(rgb)
    from retinexgs.data.srgb import srgb_to_linear

    lin = np.asarray(srgb_to_linear(rgb.astype(np.float32) / 255.0), np.float32)
    a, b = denoise.photo_noise
    return _bright_preview(denoise.apply(lin, a, b))


def _pycolmap():
    try:
        import pycolmap
    except ImportError:
        raise UserError("structure-from-motion needs pycolmap: pip install pycolmap") from None
    keep_python_sigterm()
    return pycolmap


def check_sfm_numbers(max_num_features: int, max_image_size: int, num_threads: int) -> None:
    """UserError for a feature count or image size below 1, or a thread count other than -1 or >= 1 (pycolmap
    would fail on them with a C++ check, some only after extracting features)."""
    def whole(x) -> bool:
        return isinstance(x, int) and not isinstance(x, bool)

    if not whole(max_num_features) or max_num_features < 1:
        raise UserError(f"--max-features must be a positive number of SIFT features per photo (default 8192), "
                        f"got {max_num_features!r}")
    if not whole(max_image_size) or max_image_size < 1:
        raise UserError(f"max_image_size must be a positive number of pixels, got {max_image_size!r}")
    if not whole(num_threads) or not (num_threads == -1 or num_threads >= 1):
        raise UserError(f"--threads must be -1 (all CPU threads, the default) or a positive count, got {num_threads!r}")


def _topmost_missing(path: Path) -> Optional[Path]:
    """The outermost folder of ``path`` that does not exist yet (the first one mkdir(parents=True) makes)."""
    path, top = Path(path).absolute(), None
    while not path.exists() and path.parent != path:
        top, path = path, path.parent
    return top


def _stderr_progress(msg: str) -> None:
    print(f"[sfm] {msg}", file=sys.stderr, flush=True)


def sfm_camera_models() -> List[str]:
    """Camera models SfM may fit: those pycolmap knows that RetinexGS can read back (pinhole + OpenCV
    distortion; fisheye and other models would be refused when the scene is loaded)."""
    pycolmap = _pycolmap()
    known = {m for m in dir(pycolmap.CameraModelId) if m.isupper()}
    return [m for m in COLMAP_MODELS if m in known]


def check_camera_model(name: str) -> str:
    """``name`` upper-cased when it is one of :func:`sfm_camera_models`, else UserError listing them."""
    accepted = sfm_camera_models()
    model = str(name).strip().upper()
    if model not in accepted:
        raise UserError(f"--camera-model {name!r} is not supported; choose one of {', '.join(accepted)}")
    return model


def _made_by_sfm(meta_path: Path) -> bool:
    """True when ``meta_path`` is this command's record (a JSON object with a ``signature``): the COLMAP files
    next to it are then this command's own output, replaced freely."""
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and "signature" in meta


def foreign_colmap_files(out_dir: Path) -> List[str]:
    """COLMAP files in ``out_dir`` that ``retinexgs sfm`` did not make (database.db, sparse/): the user's, kept
    unless ``force``."""
    out_dir = Path(out_dir)
    found = [n for n in ("database.db", "sparse") if (out_dir / n).exists() or (out_dir / n).is_symlink()]
    if found and _made_by_sfm(out_dir / META_NAME):
        return []
    return found


def _host_tag() -> str:
    return hashlib.sha1(socket.gethostname().encode("utf-8", "replace")).hexdigest()[:8]


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):  # another user's process, or cannot ask: take it as running
        return True
    return True


def clear_leftovers(out_dir: Path, say: Progress = lambda _m: None) -> List[Path]:
    """Remove the ``.tmp-sfm-*`` folders in ``out_dir`` left by killed runs (their process, on this host, is
    gone; another host's or an unnamed one only when untouched for a day); returns those removed. Nothing else
    is touched, and a running call's folder is kept."""
    removed: List[Path] = []
    try:
        entries = list(Path(out_dir).iterdir())
    except OSError:
        return removed
    host, now = _host_tag(), time.time()
    for d in entries:
        if not d.name.startswith(TMP_PREFIX) or d.is_symlink() or not d.is_dir():
            continue
        parts = d.name[len(TMP_PREFIX):].split("-")
        try:
            age = now - d.stat().st_mtime
        except OSError:
            continue
        if len(parts) >= 3 and parts[0].isdigit() and parts[1] == host:
            pid = int(parts[0])
            stale = pid != os.getpid() and not _pid_alive(pid)
        else:
            stale = age > STALE_TMP_SECONDS
        if stale:
            shutil.rmtree(d, ignore_errors=True)
            removed.append(d)
    if removed:
        say(f"removed {len(removed)} temporary folder{'s' if len(removed) > 1 else ''} of an interrupted run")
    return removed


def sequential_pair_count(n: int, overlap: int, quadratic: bool) -> int:
    """Photo pairs sequential matching compares (each photo with the next ``overlap``, and with those
    2^k ahead for k < overlap when ``quadratic``), as COLMAP's sequential pairing does."""
    pairs = set()
    for i in range(n):
        for k in range(overlap):
            if i + k + 1 < n:
                pairs.add((i, i + k + 1))
            if quadratic and i + (1 << k) < n:
                pairs.add((i, i + (1 << k)))
    return len(pairs)


def default_sfm_dir(image_dir: Path) -> Path:
    """``<scene>/retinexgs_sfm`` where the scene is the photo folder, or its parent if it is named images/."""
    image_dir = Path(image_dir)
    root = image_dir.parent if image_dir.name == "images" else image_dir
    return root / "retinexgs_sfm"


def _without_denoise(signature: object) -> object:
    """A cached model's signature without its preview denoiser's recipe and the night settings that go with it (for
    ``run_sfm(denoise_cached=True)``)."""
    if not isinstance(signature, dict) or not isinstance(signature.get("options"), dict):
        return signature
    return {**signature, "options": {k: v for k, v in signature["options"].items() if k not in ("denoise", "night")}}


def run_sfm(images: Union[str, Path], out: Optional[Union[str, Path]] = None, *, matching: str = "auto",
            enhance: Union[str, bool] = "auto", camera_model: str = "SIMPLE_RADIAL", single_camera: bool = True,
            max_num_features: int = 8192, max_image_size: int = 3200, num_threads: int = -1, seed: int = 0,
            force: bool = False, progress: Optional[Progress] = _stderr_progress,
            min_registered: float = MIN_REGISTERED_SHARE, denoise: Optional[PreviewDenoise] = None,
            denoise_cached: bool = False, night: Union[str, bool] = "auto") -> SfmResult:
    """Run SfM on the photos directly inside ``images``; the model goes to ``<out>/sparse/0``.

    ``matching`` is "auto", "exhaustive" or "sequential"; ``enhance`` is "auto" (dark folders only), True
    or False. Returns a :class:`SfmResult`; reuses a cached model unless ``force``. Raises UserError for
    an empty folder, unreadable photos, raw files of different sizes, or when no model can be built, when
    ``out`` holds COLMAP files (database.db, sparse/) this function did not make, unless ``force`` (which also
    recomputes a cached model), and when fewer than ``min_registered`` (a share) of the photos are registered
    (the model is kept; the photos left out are named in a warning otherwise). ``denoise``: the previews of dark
    photos and raw files are denoised before they are brightened (:class:`PreviewDenoise`); ``denoise_cached``:
    a cached model matches whichever preview denoiser made it (a finished run reading its poses back). ``night``:
    "auto" (the night settings, :data:`NIGHT_SIFT`, :data:`NIGHT_MAPPER`, :data:`NIGHT_TRIANGULATION`,
    :data:`NIGHT_GUARD`, :data:`NIGHT_AGREE`, where ``denoise`` is given), "on" or "off" (:func:`night_settings`).
    """
    say = progress or (lambda _msg: None)
    check_sfm_numbers(max_num_features, max_image_size, num_threads)
    min_registered = check_min_registered(min_registered)
    night_opts = night_settings(night, denoise)
    image_dir = Path(images)
    if image_dir.exists() and not image_dir.is_dir():
        raise UserError(f"image folder {image_dir} is a file, not a folder: pass the folder that holds the photos")
    if not image_dir.is_dir():
        raise UserError(f"image folder {image_dir} does not exist")
    paths = list_images(image_dir)
    if not paths:
        raise UserError(f"image folder {image_dir} is empty (no .jpg/.png/... files)")
    pairs = raw_jpeg_pairs(paths)
    if pairs:  # RAW + JPEG: the camera's JPEGs give the poses (the loader trains on the raw files)
        paths = sorted(pairs.values(), key=lambda p: p.name)
        say(f"{len(pairs)} RAW + JPEG pairs in {image_dir}: SfM runs on the JPEGs, training reads the raw files")
    raw_input = pairs == {}  # raw files only: COLMAP reads their previews
    if pairs is not None:  # before SfM: it would register one size's photos and training would never see the rest
        check_raw_sizes(sorted(pairs) if pairs else paths, image_dir)
    if len(paths) < 2:
        raise UserError(f"image folder {image_dir} holds only one photo; SfM needs at least two")
    if matching not in ("auto", "exhaustive", "sequential"):
        raise UserError(f"matching must be auto, exhaustive or sequential, not {matching!r}")
    camera_model = check_camera_model(camera_model)
    if matching == "auto":
        matching = "exhaustive" if len(paths) <= EXHAUSTIVE_MAX else "sequential"
    out_dir = Path(out) if out is not None else default_sfm_dir(image_dir)
    sizes = {p.name: image_size(p) for p in paths}  # also rejects unreadable files early
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"SfM output folder {out_dir} is a file, not a folder: choose another --out")
    foreign = foreign_colmap_files(out_dir)
    if foreign and not force:
        raise UserError(f"SfM output folder {out_dir} already holds COLMAP files that retinexgs sfm did not make "
                        f"({', '.join(foreign)}); they would be replaced: choose another --out, or pass --force "
                        f"to replace them")
    # keyed by content: a photo replaced by one with an older mtime (cp -p) is noticed
    digests = {p.name: content_digest(p) for p in paths}
    if out_dir.is_dir():
        clear_leftovers(out_dir, say)  # a killed run's temporary folder (a cached call clears it too)
    options = dict(matching=matching, enhance=str(enhance),
                   enhance_method=RAW_PREVIEW_METHOD if raw_input else enhance_method, camera_model=camera_model,
                   single_camera=single_camera, max_num_features=max_num_features,
                   max_image_size=max_image_size, seed=seed)
    if denoise is not None:  # only then: a model cached without a denoiser keeps its signature
        options["denoise"] = denoise.recipe
    if night_opts is not None:  # likewise: models cached with COLMAP's own settings keep their signature
        options["night"] = night_opts
    signature = dict(options=options, images=[[p.name, list(sizes[p.name]), digests[p.name]] for p in paths])
    meta_path = out_dir / META_NAME
    model_dir = out_dir / "sparse" / "0"
    if not force and model_dir.is_dir() and meta_path.is_file():
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, json.JSONDecodeError):
            meta = None
        if meta and (meta.get("signature") == signature or
                     (denoise_cached and _without_denoise(meta.get("signature")) == _without_denoise(signature))):
            say(f"using cached model {model_dir}")
            r = meta["result"]
            check_registration(image_dir, [p.name for p in paths], r["registered"], min_registered, model_dir)
            return SfmResult(model_dir, image_dir, len(paths), r["registered"], r["num_points"],
                             r["seconds"], r["enhanced"], True, matching, r.get("stage_seconds", {}))

    pycolmap = _pycolmap()
    t0 = time.perf_counter()
    stages = {}
    made_out = _topmost_missing(out_dir)  # on failure this call removes what it made, never what was there
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        if is_out_of_space(exc, out_dir):
            raise out_of_space_error(out_dir / "database.db") from None
        raise UserError(f"cannot create SfM output folder {out_dir}: {exc}") from None
    made_enhanced = None

    def discard() -> None:
        for made in (made_out, made_enhanced):
            if made is not None:
                shutil.rmtree(made, ignore_errors=True)
        if made_enhanced is not None:  # the record of copies that are gone
            try:
                (out_dir / ENHANCED_MANIFEST).unlink()
            except OSError:
                pass

    def full_disk(exc: BaseException) -> Optional[UserError]:
        """The one-line error when ``exc`` means the output disk is full (COLMAP says only "No registered
        database factory succeeded" when it cannot create the database)."""
        if isinstance(exc, Exception) and not isinstance(exc, UserError) and is_out_of_space(exc, out_dir):
            return out_of_space_error(out_dir / "database.db")
        return None

    try:
        # 1. brightened + denoised copies for feature extraction
        # raw files always: COLMAP cannot read them (their previews are bright and denoised already)
        do_enhance = True if raw_input else folder_is_dark(paths) if enhance == "auto" else bool(enhance)
        # COLMAP cannot decode raw files nor HEIC/HEIF: it reads copies of them (PNG bytes under the same names)
        unreadable = raw_input or any(p.suffix.lower() in HEIF_EXTENSIONS for p in paths)
        method = RAW_PREVIEW_METHOD if raw_input else enhance_method if do_enhance else "decoded"
        if denoise is not None and (raw_input or do_enhance):  # the copies' cache key names the recipe
            method += f"+denoise-{denoise.recipe}"
        feature_dir = image_dir
        if do_enhance or unreadable:
            feature_dir = out_dir / "enhanced"
            made_enhanced = None if feature_dir.exists() else feature_dir
            say(f"writing bright, denoised previews of {len(paths)} raw photos into {feature_dir} (COLMAP cannot "
                f"read raw files)" if raw_input else
                f"brightening and denoising {len(paths)} dark photos into {feature_dir}" if do_enhance else
                f"decoding {len(paths)} photos into {feature_dir} (COLMAP cannot read HEIC/HEIF)")
            manifest_path = out_dir / ENHANCED_MANIFEST  # beside, not among, the copies
            try:  # which source content each copy was made from: the copies' cache key
                manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
                made_from = manifest["sources"] if manifest.get("method") == method else {}
                made_from = made_from if isinstance(made_from, dict) else {}
            except (OSError, ValueError, KeyError, TypeError, AttributeError):
                made_from = {}

            def work(p: Path) -> None:
                dst = feature_dir / p.name
                if made_from.get(p.name) != digests[p.name] or not dst.is_file():
                    # PNG bytes under the photo's own name (write_image_atomic writes PNG for a raw suffix)
                    copy = (_raw_preview(p, denoise) if raw_input else _photo_preview(p, denoise) if do_enhance
                            else read_image(p))
                    write_image_atomic(dst, copy, quality=97)

            with ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1)) as pool:
                list(pool.map(work, paths))
            made_from.update(digests)
            atomic_write_text(manifest_path, json.dumps(dict(method=method, sources=made_from), indent=1))
            stages["enhance"] = time.perf_counter() - t0

        same_size = len(set(sizes.values())) == 1
        names = [p.name for p in paths]
        # pid and host in the name: a later call knows when the run that made it is gone (clear_leftovers)
        tmp = Path(tempfile.mkdtemp(prefix=f"{TMP_PREFIX}{os.getpid()}-{_host_tag()}-", dir=out_dir))
    except BaseException as exc:
        discard()
        full = full_disk(exc)
        if full is not None:
            raise full from None
        raise
    old_level = pycolmap.logging.minloglevel
    # COLMAP's INFO/WARNING lines would drown the progress display, and its ERROR lines (a glog "E2026..."
    # before our own message when no model is found) say less than the UserError: FATAL only.
    pycolmap.logging.minloglevel = 3
    try:
        db = tmp / "database.db"
        t = time.perf_counter()
        say(f"extracting features from {len(paths)} photos")
        ext = pycolmap.FeatureExtractionOptions()
        ext.num_threads = num_threads
        ext.max_image_size = max_image_size
        ext.sift.max_num_features = max_num_features
        if night_opts is not None:
            _apply(ext.sift, night_opts["sift"])
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = camera_model
        mode = pycolmap.CameraMode.SINGLE if (single_camera and same_size) else pycolmap.CameraMode.AUTO
        pycolmap.extract_features(db, feature_dir, image_names=names, camera_mode=mode, reader_options=reader,
                                  extraction_options=ext, device=pycolmap.Device.cpu)
        stages["extract"] = time.perf_counter() - t
        say(f"extracted features in {stages['extract']:.1f} s")
        agree = night_opts.get("agree") if night_opts is not None else None
        db_loose = tmp / "database-loose.db"
        if agree is not None:  # the same features for a second model from looser matches (NIGHT_AGREE), if needed
            shutil.copyfile(db, db_loose)

        def match(database: Path, max_ratio: Optional[float] = None) -> None:
            mopt = pycolmap.FeatureMatchingOptions()
            mopt.num_threads = num_threads
            if max_ratio is not None:
                mopt.sift.max_ratio = max_ratio
            # pycolmap reports nothing while it matches (tens of seconds at 50 photos): say how much work it is
            if matching == "exhaustive":
                say(f"matching {len(paths) * (len(paths) - 1) // 2} photo pairs (exhaustive)...")
                pycolmap.match_exhaustive(database, matching_options=mopt, device=pycolmap.Device.cpu)
            else:
                pair = pycolmap.SequentialPairingOptions()
                pair.overlap = SEQUENTIAL_OVERLAP
                n_pairs = sequential_pair_count(len(paths), pair.overlap, bool(pair.quadratic_overlap))
                say(f"matching {n_pairs} photo pairs (sequential)...")
                pycolmap.match_sequential(database, matching_options=mopt, pairing_options=pair,
                                          device=pycolmap.Device.cpu)

        t = time.perf_counter()
        match(db)
        stages["match"] = time.perf_counter() - t
        say(f"matched in {stages['match']:.1f} s")

        t = time.perf_counter()
        popt = pycolmap.IncrementalPipelineOptions()
        popt.num_threads = num_threads
        popt.random_seed = seed
        popt.min_model_size = min(popt.min_model_size, max(2, len(paths) // 2))
        if night_opts is not None:
            _apply(popt.mapper, night_opts["mapper"])
            _apply(popt.triangulation, night_opts["triangulation"])
        count, model_no = [0], [0]

        # COLMAP calls these for every model it builds: a second model starts a new count (counting across
        # models showed "13/10 photos")
        def initial_pair() -> None:
            model_no[0] += 1
            count[0] = 2
            label = f" model {model_no[0]}," if model_no[0] > 1 else ""
            say(f"mapping:{label} initial pair, {min(count[0], len(paths))}/{len(paths)} photos")

        def next_image() -> None:
            count[0] += 1
            label = f" model {model_no[0]}," if model_no[0] > 1 else ""
            say(f"mapping:{label} {min(count[0], len(paths))}/{len(paths)} photos")

        def mapped(database: Path, models_dir: Path, map_seed: int = seed):
            """The largest model the mapper builds from ``database`` (after the night guard), or None."""
            count[0], model_no[0] = 0, 0
            popt.random_seed = map_seed
            say("incremental mapping")
            # point colours from the originals, or from the copies where COLMAP cannot read the originals (raw, HEIC)
            models = pycolmap.incremental_mapping(database, feature_dir if unreadable else image_dir, models_dir,
                                                  options=popt,
                                                  initial_image_pair_callback=initial_pair,
                                                  next_image_callback=next_image)
            if not models:
                return None
            loose: dict = {}
            if night_opts is not None and "guard" in night_opts:  # before choosing: the largest model once guarded
                loose = {k: drop_loose_views(r, night_opts["guard"]["min_shared_points"]) for k, r in models.items()}
            best_key = max(models, key=lambda k: models[k].num_reg_images())
            if loose.get(best_key):
                n_loose = len(loose[best_key])
                say(f"dropped {n_loose} photo{'s' if n_loose > 1 else ''} posed on loose matches (sharing fewer "
                    f"than {night_opts['guard']['min_shared_points']} points with any other photo): "
                    f"{_listed(loose[best_key])}")
            return models[best_key]

        best = mapped(db, tmp / "models")
        stages["map"] = time.perf_counter() - t
        if best is None:
            raise UserError(f"SfM could not build a model from the {len(paths)} photos in {image_dir} "
                            f"(too few matching features); try brighter or more overlapping photos")
        db_used = db
        if agree is not None and best.num_reg_images() < len(paths):
            k = best.num_reg_images()
            if k < max(3, agree["min_shared_photos"]):
                say(f"night check: kept the strict model ({k}/{len(paths)} photos): too few photos to check a "
                    f"model from looser matches against (fewer than {max(3, agree['min_shared_photos'])})")
            else:
                say(f"the strict model posed {k}/{len(paths)} photos: matching again with SIFT's match ratio "
                    f"{agree['loose_max_ratio']:g} for {agree['loose_mappings']} more mappings, one used only if "
                    f"it agrees with the strict model and the others")
                t = time.perf_counter()
                match(db_loose, agree["loose_max_ratio"])
                strict_c = model_centres(best)
                models, centres = [], []
                for j in range(agree["loose_mappings"]):  # seeds s, s+1: the mapper is not repeatable here
                    if j:
                        say(f"mapping the looser matches again (seed {seed + j}) to check the photos they add")
                    models.append(mapped(db_loose, tmp / f"models-loose-{j}", seed + j))
                    centres.append(model_centres(models[-1]) if models[-1] is not None else None)
                chosen, why, _info = choose_consensus(strict_c, centres, len(paths), agree)
                stages["loose"] = time.perf_counter() - t
                say(f"night check: {why}")
                if chosen is not None:
                    best, db_used = models[chosen], db_loose
        if best.num_reg_images() < 2:
            raise UserError(f"SfM could not build a model from the {len(paths)} photos in {image_dir}: the photos "
                            f"it posed share too few points with one another to be trusted; try brighter or more "
                            f"overlapping photos")
        (tmp / "sparse" / "0").mkdir(parents=True)
        best.write_binary(str(tmp / "sparse" / "0"))
        registered = sorted(best.images[i].name for i in best.reg_image_ids())
        num_points = best.num_points3D()
        seconds = time.perf_counter() - t0

        # mark the folder as this command's before its COLMAP files change (no signature match: no cache hit
        # until the final record), so a run killed between the moves is not taken for the user's files
        atomic_write_text(meta_path, json.dumps(dict(signature=None, result=None)))
        # move into place: old model aside, new one in, then drop the old one
        (out_dir / "sparse").mkdir(exist_ok=True)
        if model_dir.exists():
            trash = tmp / "old_model"
            os.replace(model_dir, trash)
        os.replace(tmp / "sparse" / "0", model_dir)
        os.replace(db_used, out_dir / "database.db")
        result = dict(registered=registered, num_points=num_points, seconds=seconds, enhanced=do_enhance,
                      stage_seconds=stages)
        meta_tmp = tmp / "meta.json"
        meta_tmp.write_text(json.dumps(dict(signature=signature, result=result), indent=1))
        os.replace(meta_tmp, meta_path)
    except BaseException as exc:
        discard()
        full = full_disk(exc)
        if full is not None:
            raise full from None
        raise
    finally:
        pycolmap.logging.minloglevel = old_level
        shutil.rmtree(tmp, ignore_errors=True)
    say(f"registered {len(registered)}/{len(paths)} photos, {num_points} points, {seconds:.1f} s -> {model_dir}")
    check_registration(image_dir, names, registered, min_registered, model_dir)
    return SfmResult(model_dir, image_dir, len(paths), registered, num_points, seconds, do_enhance, False,
                     matching, stages)
