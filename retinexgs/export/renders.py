"""``retinexgs render``: a trained run's maps for its test/train views (PNG) or along a camera path (MP4/PNG).

Maps (``--maps``, comma-separated): ``enhanced`` (the model's output, S_enh; the default), ``R`` (R̂), ``L``
(the illumination normalised for viewing: L̂ / L_ref clipped to [0, 1], L_ref the scene's full light, one
constant for every view and frame; the same rule as ``eval``'s side-by-side panel and the viewer, and the light
the enhancement acts on), ``L_raw`` (L̂ as rendered, unscaled: nearly black for a dark capture), ``low`` (the
low-light reconstruction R̂·L̂, the model's ``S_rec``) and ``depth`` (inverse depth, white = near, black = far or
empty, on one range for all frames of a call so videos do not flicker). ``R``, ``L``, ``L_raw`` and ``low`` exist
only for RetinexGS runs.

Files: views go to ``OUT/<map>/<view name>.png`` (default OUT = ``RUN/renders/<test|train|val>``); OUT is a
folder, and one ending in ``.mp4`` is refused (views are PNG files; a video is a ``--path``). A path video goes
to OUT when OUT ends in ``.mp4``, else into the folder OUT (made when missing) as ``OUT/path_<kind>.mp4``
(default ``RUN/renders/path_<kind>.mp4``), for the first map, and with ``_<map>`` before the suffix for the
others; with ``--format png`` to ``OUT/<map>/<frame>.png`` (default OUT = ``RUN/renders/path_<kind>``). An OUT
named like one image file (``o.exr``, ``o.png``: :data:`_IMAGE_SUFFIXES`) is refused for both, unless it is an
existing folder. Existing files are kept unless ``force``; every file is written atomically.

``--format exr`` (views and paths; ``png,exr`` for both side by side) writes scene-linear float32 OpenEXR
(Rec.709 primaries, :mod:`retinexgs.export.exr`) to ``OUT/<map>/<name>.exr`` instead of the PNG: ``enhanced`` is
the linear light the PNG encodes before the highlight shoulder and the sRGB curve (tone ``exposure``:
k·lin(R̂∘L̂) after the white balance; 1.0 = the PNG's white with the shoulder off, brighter light above 1 kept);
``R`` is lin(R̂), ``L`` lin(L̂)/lin(L_ref) (1.0 = the scene's full light, not clipped), ``L_raw`` lin(L̂),
``low`` lin(R̂·L̂); lin is the sRGB decoding. ``depth`` has no EXR form.

``--white-balance`` (:mod:`retinexgs.model.white_balance`) edits the enhanced image's linear light before the
shoulder and the curve (PNG, EXR and MP4 alike); the other maps are the decomposition and keep as trained. The
edits used (exposure or gamma, and the white balance's numbers) are recorded in each PNG's text chunk
``retinexgs`` and each EXR's header attribute ``retinexgs``, and printed.
"""
from __future__ import annotations

import importlib.util
import shutil
import tempfile
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch
from torch import Tensor

from retinexgs.data.scene import View
from retinexgs.errors import UserError
from retinexgs.evaluate.evaluate import to_uint8
from retinexgs.export.common import check_enhancement_flags, read_run_config, refuse_existing
from retinexgs.fileio import check_writable_file
from retinexgs.export import PATH_KINDS
from retinexgs.export.exr import need_openexr, write_exr
from retinexgs.export.paths import camera_path
from retinexgs.fileio import (TMP_PREFIX, atomic_write, is_out_of_space, make_folders, out_of_space_error,
                              remove_empty_folders)
from retinexgs.render import Camera, rasterize_gaussians
from retinexgs.run.folder import load_run
from retinexgs.model.tone import srgb_to_linear
from retinexgs.model.white_balance import describe_balance, parse_white_balance
from retinexgs.run.render import render_function, white_balance_of
from retinexgs.run.render import active_sh_degree, view_camera

MAPS = ("enhanced", "R", "L", "L_raw", "depth", "low")
DECOMPOSED_MAPS = ("R", "L", "L_raw", "low")
# map name -> key of run.render.render_function's maps ("L_view": L̂ / L_ref, see the module docstring)
_KEYS = {"enhanced": "rgb", "R": "R", "L": "L_view", "L_raw": "L", "low": "S_rec"}
# What players and editors take for a video file: a path video must be .mp4; any of these is refused, not a folder.
_VIDEO_SUFFIXES = (".mp4", ".m4v", ".mov", ".mkv", ".avi", ".webm", ".gif")
# What names one image file: an --out ending in one of these is refused where the output is a folder (views, a path's
# frames) or an MP4 (a path video), unless that folder exists. Refused, not written to the name without the suffix:
# `--out o.exr` made a folder o.exr of frames, which tools then took for one EXR file; writing to o/ instead would
# put the output where the user did not say. Checked before the run loads.
_IMAGE_SUFFIXES = (".png", ".exr", ".jpg", ".jpeg", ".tif", ".tiff", ".webp", ".bmp", ".hdr", ".ply")
VIEW_SETS = ("test", "train", "val", "path")
FORMATS = ("mp4", "png", "exr")
# What --format exr writes per map: a note for the file's header (the scale is in the module docstring).
_EXR_MEANING = {
    "enhanced": "scene-linear Rec.709 light of the enhanced image before the highlight shoulder and the sRGB "
                "curve; 1.0 = the PNG's white (shoulder off)",
    "R": "lin(R): the reflectance decoded from sRGB to linear",
    "L": "lin(L)/lin(L_ref): the illumination in linear light, 1.0 = the scene's full light L_ref, not clipped",
    "L_raw": "lin(L): the illumination as rendered, decoded to linear",
    "low": "lin(R*L): the low-light reconstruction decoded to linear",
}


def parse_formats(text: str) -> List[str]:
    """``--format`` -> the formats: ``mp4``, ``png``, ``exr`` or ``png,exr`` (PNG and EXR side by side); a
    UserError for anything else."""
    names: List[str] = []
    for name in (t.strip().lower() for t in str(text).split(",")):
        if name not in FORMATS:
            raise UserError(f"unknown --format {name!r}; choose from {', '.join(FORMATS)} (or png,exr for both)")
        if name not in names:
            names.append(name)
    if "mp4" in names and len(names) > 1:
        raise UserError(f"--format {text}: mp4 is a video of the path and cannot be combined; give mp4, png, exr "
                        "or png,exr")
    return names


def _save_png(img: Tensor, path: Path, note: Optional[str]) -> None:
    """An [H,W,C] image in [0,1] as PNG, atomically, with ``note`` in its text chunk ``retinexgs``."""
    from PIL import Image, PngImagePlugin

    info = None
    if note:
        info = PngImagePlugin.PngInfo()
        info.add_itxt("retinexgs", note)
    arr = to_uint8(img)
    atomic_write(path, lambda f: Image.fromarray(arr).save(f, format="PNG", pnginfo=info))


def _exr_map(name: str, res: Dict, model) -> Tensor:
    """The linear light of map ``name`` for --format exr (module docstring)."""
    if name == "enhanced":
        return res["rgb_linear"].float().cpu()
    if name == "R":
        return srgb_to_linear(res["R"]).float().cpu()
    if name == "L":
        ref = srgb_to_linear(model.illum_ref.to(res["L"])).clamp_min(1e-12)
        return (srgb_to_linear(res["L"]) / ref).float().cpu()
    if name == "L_raw":
        return srgb_to_linear(res["L"]).float().cpu()
    if name == "low":
        return srgb_to_linear(res["R"] * res["L"]).float().cpu()
    raise ValueError(f"map {name!r} has no EXR form")


def parse_maps(text: str) -> List[str]:
    """``enhanced,R`` -> ["enhanced", "R"]; unknown names raise a UserError listing the known ones."""
    names: List[str] = []
    for name in (t.strip() for t in text.split(",")):
        if name not in MAPS:
            raise UserError(f"unknown map {name!r} in --maps; choose from {', '.join(MAPS)}")
        if name not in names:
            names.append(name)
    return names


def _need_ffmpeg() -> None:
    if importlib.util.find_spec("imageio") is None or importlib.util.find_spec("imageio_ffmpeg") is None:
        raise UserError("writing MP4 needs imageio with its ffmpeg plugin: pip install imageio[ffmpeg] "
                        "(or pass --format png to write the frames as PNG files)")


def depth_range(model, views: Sequence[View]) -> Tuple[float, float]:
    """(near, far): the 2nd and 98th percentiles of the visible Gaussian centres' depths over the views (at most
    ~256 of them, spread over a long camera path: silent work before the progress bar)."""
    g = model.gaussians
    keep = g.opacities.detach() > 0.05
    means = (g.means.detach()[keep] if bool(keep.any()) else g.means.detach()).double().cpu()
    lo, hi = [], []
    for v in views[:: max(1, len(views) // 256)]:
        w2c = v.world_to_camera()
        z = means @ w2c[2, :3] + w2c[2, 3]
        z = z[z > 0.01]
        if len(z):
            lo.append(float(torch.quantile(z, 0.02)))
            hi.append(float(torch.quantile(z, 0.98)))
    if not lo:
        return 0.1, 10.0
    near, far = max(min(lo), 1e-3), max(hi)
    return near, max(far, near * 1.01)


def render_depth(model, view: Union[View, Camera], near: float, far: float) -> Tensor:
    """[H,W,1] inverse depth mapped to [0,1] between 1/far (0) and 1/near (1); empty pixels 0. ``view`` is a
    data-layer view or a renderer camera (the viewer's)."""
    g = model.gaussians
    camera = model.camera_for(view if isinstance(view, Camera) else view_camera(view))  # the near plane of its frames
    with torch.no_grad():
        ones = torch.ones(len(g), 1, dtype=g.means.dtype, device=g.means.device)
        out = rasterize_gaussians(g.means, g.quats, g.scales, g.opacities, ones, camera, render_depth=True)
    alpha = out.alpha.float().cpu()
    z = out.depth.float().cpu() / alpha.clamp_min(1e-6)
    disp = (1.0 / z.clamp_min(1e-6) - 1.0 / far) / (1.0 / near - 1.0 / far)
    return torch.where(alpha > 1e-3, disp.clamp(0, 1), torch.zeros_like(disp))


def _frame_maps(fn: Callable, model, view: View, maps: Sequence[str], zrange: Tuple[float, float],
                exr: bool = False) -> Tuple[Dict, Dict]:
    """(the maps for PNG/MP4, the maps' linear light for EXR when ``exr``) of one view."""
    res = fn(view)
    out = {}
    for name in maps:
        out[name] = render_depth(model, view, *zrange) if name == "depth" else res[_KEYS[name]].float().cpu()
    linear = {name: _exr_map(name, res, model) for name in maps} if exr else {}
    return out, linear


def _suffixed(path: Path, name: str, first: bool) -> Path:
    return path if first else path.with_name(f"{path.stem}_{name}{path.suffix}")


def _video_target(out: Optional[Path], default_dir: Path, path: str) -> Path:
    """The MP4 file of a path video: ``out`` itself when it ends in .mp4, else ``out/path_<kind>.mp4`` (a folder,
    existing or new); UserError for another video suffix or a file that is not a folder."""
    name = f"path_{path}.mp4"
    if out is None:
        return default_dir / name
    suffix = out.suffix.lower()
    if suffix == ".mp4":
        if out.is_dir():
            raise UserError(f"--out {out} is a folder; name the video file, e.g. --out {out / name}, "
                            f"or pass the folder without .mp4")
        return out
    if suffix in _VIDEO_SUFFIXES:
        raise UserError(f"--out {out}: path videos are written as MP4; name a .mp4 file (e.g. "
                        f"--out {out.with_suffix('.mp4')}) or a folder to write {name} into")
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} is a file; name a .mp4 file or a folder to write {name} into")
    return out / name


def _even(frame: np.ndarray) -> np.ndarray:
    # yuv420p (what players expect from H.264) needs even sides: repeat the last row/column when odd.
    h, w = frame.shape[:2]
    return np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


def render_run(run_dir: Path, views: Optional[str] = None, out: Optional[Path] = None,
               maps: Sequence[str] = ("enhanced",), exposure: Optional[float] = None, gamma: Optional[float] = None,
               path: Optional[str] = None, frames: int = 120, fps: float = 30.0, fmt: str = "mp4",
               device: Optional[str] = None, force: bool = False, progress: bool = True,
               log: Callable[[str], None] = print, white_balance: Optional[str] = None) -> List[Path]:
    """Render ``maps`` of a run for its ``views`` (``test``, ``train``, ``val``) or a camera ``path`` (``orbit``,
    ``orbit-360``, ``interpolate``; ``views="path"`` alone means an orbit); see the module docstring for the maps
    and the files.

    ``exposure`` adjusts the predicted gamma (< 1 brighter), ``gamma`` replaces it (RetinexGS runs only).
    ``fmt``: mp4, png, exr or png,exr (:func:`parse_formats`); ``white_balance``: the ``--white-balance`` text
    (default as-trained). Everything is checked before anything is written. Returns the files written.
    """
    run_dir = Path(run_dir)
    views = views if views is not None else ("path" if path else "test")
    if views not in VIEW_SETS:
        raise UserError(f"unknown --views {views!r}; choose from {', '.join(VIEW_SETS)}")
    if path is not None and views != "path":
        raise UserError(f"--path renders a camera path; it cannot be combined with --views {views}")
    path = path or ("orbit" if views == "path" else None)
    if path is not None and path not in PATH_KINDS:
        raise UserError(f"unknown --path {path!r}; choose from {', '.join(PATH_KINDS)}")
    formats = parse_formats(fmt)
    if "exr" in formats:
        need_openexr()  # before anything is read: one line with the install command
    wb = parse_white_balance(white_balance)
    if path is not None and (frames < 1 or not fps > 0):
        raise UserError(f"--frames must be at least 1 and --fps positive, got {frames} and {fps}")
    maps = list(maps)
    if not maps:
        raise UserError("--maps is empty; choose from " + ", ".join(MAPS))
    cfg = read_run_config(run_dir)
    check_enhancement_flags(cfg, run_dir, exposure, gamma)
    if cfg.method != "retinexgs" and set(maps) & set(DECOMPOSED_MAPS):
        bad = ", ".join(m for m in maps if m in DECOMPOSED_MAPS)
        raise UserError(f"--maps {bad}: {run_dir} is a method={cfg.method} baseline with no R̂/L̂ "
                        "decomposition; it has only enhanced and depth")
    exr = "exr" in formats
    if exr and "depth" in maps:
        raise UserError("--maps depth has no EXR form (EXR holds linear light); render depth with --format png, "
                        "or drop it from --maps")
    video = path is not None and formats == ["mp4"]
    if not video and out is not None and Path(out).suffix.lower() in _VIDEO_SUFFIXES and not Path(out).is_dir():
        what = (f"the {views} views render to PNG files in a folder" if path is None
                else "--format png writes the path's frames as PNG files in a folder")
        hint = ("; for a video along a camera path use --path orbit (or interpolate) --out " + str(out)
                if path is None else "; drop --format png for an MP4")
        raise UserError(f"--out {out} names a video file, but {what}: pass a folder (e.g. --out "
                        f"{Path(out).with_suffix('')}){hint}")
    if out is not None and Path(out).suffix.lower() in _IMAGE_SUFFIXES and not Path(out).is_dir():
        kind = Path(out).suffix.upper().lstrip(".")
        kind = ("an " if kind[0] in "AEFHILMNORSX" else "a ") + kind  # as spelled out: an EXR, an HDR, a PNG
        if video:
            raise UserError(f"--out {out} names {kind} file, but a path video is one MP4: name a .mp4 file, or a "
                            f"folder to write path_{path}.mp4 into (e.g. --out {Path(out).with_suffix('')})")
        ext = "|".join(f for f in formats if f != "mp4") or "png"
        what = "the path's frames render" if path else f"the {views} views render"
        raise UserError(f"--out {out} names {kind} file, but {what} to one file each in a folder "
                        f"(OUT/<map>/<name>.{ext}): pass a folder name without a file extension (e.g. --out "
                        f"{Path(out).with_suffix('')})")
    if video:
        _need_ffmpeg()

    cfg, scene, model, step = load_run(run_dir, device)
    if path is None:
        splits = {"test": scene.test, "train": scene.train, "val": scene.val}
        frames_views = list(splits[views])
        if not frames_views:
            others = [name for name, vs in splits.items() if vs and name != views]
            raise UserError(f"the scene of {run_dir} has no {views} views; try "
                            + "".join(f"--views {name} or " for name in others) + "--views path")
        out = Path(out) if out is not None else run_dir / "renders" / views
    else:
        if not scene.train:
            raise UserError(f"the scene of {run_dir} has no train views to build a camera path from")
        frames_views = camera_path(path, scene.train, frames, model.gaussians.means.detach())
        out = _video_target(out, run_dir / "renders", path) if video else (
            Path(out) if out is not None else run_dir / "renders" / f"path_{path}")
    if video:
        targets = [_suffixed(out, name, i == 0) for i, name in enumerate(maps)]
    else:
        if out.exists() and not out.is_dir():
            raise UserError(f"--out {out} is a file; PNG renders need a folder")
        suffixes = [f".{f}" for f in formats if f != "mp4"] or [".png"]  # views with the default mp4: PNG
        targets = [out / name / f"{Path(v.name).stem}{suffix}" for suffix in suffixes for name in maps
                   for v in frames_views]
    refuse_existing(targets, force)
    check_writable_file(targets[0])

    degree = active_sh_degree(cfg, step)
    balance = white_balance_of(wb, model, cfg, scene, degree, exposure, gamma)
    edit = ("exposure " + (f"{exposure:g}" if exposure is not None else "as predicted") if gamma is None
            else f"gamma {gamma:g} (fixed)")
    note = f"retinexgs render of {run_dir.name}: {edit}; {describe_balance(wb, balance)}"
    if balance is not None:
        log(describe_balance(wb, balance))
    fn = render_function(model, cfg, degree, exposure=exposure, gamma=gamma, balance=balance, linear=exr)
    zrange = depth_range(model, frames_views) if "depth" in maps else (0.1, 10.0)
    from tqdm import tqdm
    bar = tqdm(frames_views, desc=f"render {path or views}", unit="frame", disable=not progress, dynamic_ncols=True)
    if not video:
        png = ".png" in suffixes
        for view in bar:
            images, linear = _frame_maps(fn, model, view, maps, zrange, exr)
            stem = Path(view.name).stem
            if png:
                for name, img in images.items():
                    _save_png(img, out / name / f"{stem}.png", note if name == "enhanced" else None)
            for name, img in linear.items():
                write_exr(out / name / f"{stem}.exr", img,
                          {"retinexgs": note, "retinexgs_values": _EXR_MEANING[name]})
        kinds = " and ".join(s[1:].upper() for s in suffixes)
        log(f"wrote {len(targets)} {kinds} files to {out}/<{'|'.join(maps)}>/")
        return targets

    made = make_folders(out.parent)
    try:
        _write_videos(fn, model, frames_views, maps, zrange, fps, bar, out, targets)
    except BaseException:
        remove_empty_folders(made)  # a failed video leaves no empty folder of its own behind
        raise
    log(f"wrote {len(frames_views)} frames at {fps:g} fps to " + ", ".join(str(t) for t in targets))
    return targets


def _write_videos(fn: Callable, model, frames_views: Sequence, maps: Sequence[str], zrange: Tuple[float, float],
                  fps: float, bar, out: Path, targets: Sequence[Path]) -> None:
    """Encode one MP4 per map of ``frames_views`` to ``targets`` (``out``'s folder exists)."""
    import imageio
    # ffmpeg writes to a file name: encode into a temporary folder next to the output, then copy each video
    # through atomic_write, so an interrupted render never leaves a truncated MP4 under the final name.
    with tempfile.TemporaryDirectory(prefix=TMP_PREFIX, dir=out.parent) as tmp:
        tmp_files = [Path(tmp) / f"{i}.mp4" for i in range(len(maps))]
        writers = [imageio.get_writer(str(f), format="FFMPEG", mode="I", fps=fps, codec="libx264", quality=8,
                                      macro_block_size=1, ffmpeg_log_level="error") for f in tmp_files]
        try:
            try:
                for view in bar:
                    for writer, img in zip(writers, _frame_maps(fn, model, view, maps, zrange)[0].values()):
                        writer.append_data(_even(to_uint8(img)))
            finally:
                for writer in writers:
                    writer.close()
        except (OSError, RuntimeError) as exc:  # ffmpeg writes the file itself: a full disk shows as a broken pipe
            if is_out_of_space(exc, out.parent):
                raise out_of_space_error(targets[0]) from None
            raise
        for src, dst in zip(tmp_files, targets):
            with open(src, "rb") as f_in:
                atomic_write(dst, lambda f_out: shutil.copyfileobj(f_in, f_out))
