"""A documented low-light sensor model, and the noise of a photo estimated from its own pixels.

Darkening (``retinexgs darken``, the noise ladder of ``bench quality``): a normal-light photo ``x`` (sRGB, 8 or 16
bit) becomes what a camera at a short exposure records, in linear light:

    e_c  = Poisson(lin(x_c) · g_c · k_v · W) + Normal(0, r²)      electrons of channel c
    y_c  = clip(e_c / W, 0, 1)                                  the raw value, full well = 1
    out  = JPEG_q(round(255 · srgb(y)))                         the 8-bit photo the user gets

with ``k_v = k · (1 + U(-j, j))`` the view's exposure (``k`` the exposure ratio, ``j`` its jitter between views),
``g_c`` the channel gains of a colour cast (white balance the camera got wrong), ``W`` the full well in
electrons (the sensor's saturation: fewer electrons = more shot noise), ``r`` the read noise in electrons and ``q``
the JPEG quality. A mid-grey pixel (lin 0.18) at k = 0.03 and W = 1500 holds about 8 electrons: SNR ≈ 3, a phone's
night photo. ``full_well=None`` is noise-free (the ladder's clean level).

Estimation (:func:`estimate_noise`): the same model seen from the photo. In linear light the variance of a raw
value is ``a · y + b`` with ``a = 1/W`` (shot noise) and ``b = (r/W)²`` (read noise), per channel. The residual of
a 3×3 second-difference filter (Immerkær 1996; its taps' squares sum to 36) carries the noise and little of a
smooth image; its robust spread (MAD) in bins of local brightness, fitted by ``a · y + b`` as seen through the
clip at black (near black the recorded noise is clipped: smaller, and its mean above the light), gives both numbers.
JPEG removes part of the noise, so estimates from JPEG photos are lower than the sensor's truth, most near black
(``experiments/notes/2026-11-26-noise-estimate.md``). :func:`estimate_noise_through_codec` models that loss with the
file's own JPEG tables (:class:`JpegCodec`) and reads the floor within about 25 %
(``experiments/notes/2026-11-27-black-level.md``).
"""
from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import math
import os
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Dict, Iterator, List, Optional, Sequence, Tuple, TypeVar

import numpy as np

from retinexgs.data.srgb import linear_to_srgb, srgb_to_linear  # noqa: F401 (re-exported for the demo)
from retinexgs.data.images import list_images, no_images_reason, read_image_float, write_image_atomic
from retinexgs.errors import UserError
from retinexgs.fileio import atomic_write_text, check_writable_folder, is_out_of_space, out_of_space_error
from retinexgs.formats import PLAIN_EXTENSIONS

if TYPE_CHECKING:  # a type hint only: raw_sim is imported lazily where --raw uses it
    from retinexgs.data.raw_sim import RawCamera

T, R = TypeVar("T"), TypeVar("R")


@dataclass(frozen=True)
class SensorModel:
    """The low-light capture of the module docstring; every field is one of its symbols."""

    exposure: float = 0.05                    # k: the share of the normal-light signal that is recorded
    exposure_jitter: float = 0.1              # j: each view's exposure is k · (1 ± j), uniform
    full_well: Optional[float] = 1500.0       # W, electrons at raw 1 (None: noise-free)
    read_noise: float = 4.0                   # r, electrons (standard deviation)
    cast: Tuple[float, float, float] = (1.0, 1.0, 1.0)  # g_c, the colour cast's channel gains
    jpeg_quality: int = 90                    # q (0: PNG, lossless)

    def check(self) -> None:
        """UserError naming the first field out of range."""
        if not (0 < self.exposure <= 1):
            raise UserError(f"--exposure must be in (0, 1] (the share of the light recorded), got {self.exposure}")
        if not (0 <= self.exposure_jitter < 1):
            raise UserError(f"--exposure-jitter must be in [0, 1), got {self.exposure_jitter}")
        if self.full_well is not None and not (self.full_well > 0 and math.isfinite(self.full_well)):
            raise UserError(f"--full-well must be a positive number of electrons, got {self.full_well}")
        if not (self.read_noise >= 0 and math.isfinite(self.read_noise)):
            raise UserError(f"--read-noise must be >= 0 electrons, got {self.read_noise}")
        if len(self.cast) != 3 or not all(g > 0 and math.isfinite(g) for g in self.cast):
            raise UserError(f"--cast must be three positive channel gains R,G,B, got {self.cast}")
        if not (0 <= self.jpeg_quality <= 100):
            raise UserError(f"--jpeg-quality must be 0 (PNG) to 100, got {self.jpeg_quality}")

    def view_exposure(self, rng: np.random.Generator) -> float:
        """k_v, one view's exposure."""
        return self.exposure * (1.0 + rng.uniform(-self.exposure_jitter, self.exposure_jitter))

    def capture(self, srgb: np.ndarray, k_view: float, rng: np.random.Generator) -> np.ndarray:
        """The raw linear values y [H,W,3] in [0,1] of a normal-light sRGB photo [H,W,3] in [0,1]."""
        signal = srgb_to_linear(srgb.astype(np.float64)) * np.asarray(self.cast) * k_view
        if self.full_well is None:
            return np.clip(signal, 0.0, 1.0)
        electrons = rng.poisson(np.clip(signal, 0.0, None) * self.full_well).astype(np.float64)
        electrons += rng.normal(0.0, self.read_noise, size=electrons.shape)
        return np.clip(electrons / self.full_well, 0.0, 1.0)

    def darken(self, srgb: np.ndarray, k_view: float, rng: np.random.Generator) -> np.ndarray:
        """The 8-bit sRGB photo [H,W,3] uint8 (before JPEG) of a normal-light sRGB photo in [0,1]."""
        return np.round(linear_to_srgb(self.capture(srgb, k_view, rng)) * 255.0).astype(np.uint8)


# The noise ladder of issue 32: (label, full well, read noise), from clean to a phone's worst night photo; 800e
# (issue 64) is the harsher rung where a mid-grey pixel at k = 0.05 holds about 7 electrons against 6 of read noise.
NOISE_LADDER: List[Tuple[str, Optional[float], float]] = [
    ("clean", None, 0.0), ("8000e", 8000.0, 2.0), ("3000e", 3000.0, 3.0), ("1500e", 1500.0, 4.0),
    ("1000e", 1000.0, 6.0), ("800e", 800.0, 6.0)]
# The raw bit depth of a rung in ``bench quality --raw-ladder`` where it is not RawCamera's default (14 bit): 800e is a
# small-sensor camera, 12 bit like most phones and compacts, so its DNGs also carry the coarser quantisation.
LADDER_RAW_BITS: Dict[str, int] = {"800e": 12}


@dataclass
class DarkenReport:
    """What :func:`darken_scene` wrote."""

    out: Path
    photos: int
    exposures: Dict[str, float] = field(default_factory=dict)


def _dark_name(name: str, quality: int) -> str:
    """The dark photo's file name: the source's, unless darken cannot write its type (HEIC/HEIF, camera raw; the
    writer knows :data:`retinexgs.formats.PLAIN_EXTENSIONS`): then the stem with .jpg (.png at quality 0), so that
    the extension says what the file holds and every command reads it (``IMG_1.HEIC`` -> ``IMG_1.jpg``)."""
    p = Path(name)
    return name if p.suffix.lower() in PLAIN_EXTENSIONS else p.stem + (".jpg" if quality else ".png")


def _scene_photos(src: Path, quality: int, raw: bool) -> Tuple[Path, List[Tuple[Path, str]]]:
    """(the folder of normal-light photos, [(photo, the darkened file's path relative to the output)]); UserError
    when two photos would get one name, or for a LOM scene whose high/ photos darken cannot write by name."""
    high = src / "high"
    if high.is_dir():  # a LOM-style scene: high/NAME -> low/NAME (LOM pairs the two folders by file name)
        photos = list_images(high)
        odd = [p.name for p in photos if _dark_name(p.name, quality) != p.name]
        if odd and not raw:  # renaming low/ alone would break the pairing; --raw's low/NAME.dng pairs by stem
            more = f" (and {len(odd) - 1} more)" if len(odd) > 1 else ""
            raise UserError(f"{high / odd[0]}{more}: darken cannot write a {Path(odd[0]).suffix} photo, and a scene's "
                            "low/ and high/ pair by file name: convert high/ to PNG or JPEG (and the names in its "
                            f"transforms JSON), darken {high} as a plain folder of photos, or use --raw")
        return high, [(p, f"low/{p.name}") for p in photos]
    jobs = [(p, _dark_name(p.name, quality)) for p in list_images(src)]
    seen: Dict[str, Path] = {}
    for photo, rel in jobs:
        other = seen.setdefault(rel, photo)
        if other != photo:
            raise UserError(f"{other.name} and {photo.name} in {src} would both be written as {rel} (darken "
                            "writes HEIC and raw photos as .jpg, .png at --jpeg-quality 0); rename one of them")
    return src, jobs


def darken_scene(src: Path, out: Path, model: SensorModel, seed: int = 0, progress: bool = True,
                 raw: Optional["RawCamera"] = None, jobs: Optional[int] = None) -> DarkenReport:
    """Darken the normal-light photos of ``src`` into the new folder ``out``.

    ``src`` is a scene in LOM's layout (``high/`` photos with ``transforms_*.json``, ``split.json``,
    ``colmap_sparse/``; the poses are copied, ``high/`` too, and ``low/`` is written from ``high/``, so the result
    trains and scores like LOM's own scenes) or a plain folder of photos (darkened beside nothing else).
    ``out/sensor.json`` records the model, the seed and every view's exposure. A dark photo keeps its source's
    name, but for a type darken cannot write (HEIC, camera raw: :func:`_dark_name`, ``.jpg`` or ``.png``).

    ``raw`` (a :class:`retinexgs.data.raw_sim.RawCamera`): simulate the camera's raw files instead, see
    :func:`_darken_raw`: ``out/raw/`` (DNGs) and ``out/jpeg/`` (the camera's JPEGs of the same photons), the
    views spread over ``jobs`` worker processes (None: one per CPU core; the files do not depend on it)."""
    model.check()
    if raw is not None:
        return _darken_raw(Path(src), Path(out), model, raw, seed, progress, jobs)
    src, out = Path(src), Path(out)
    folder, jobs = _darken_inputs(src, out, model.jpeg_quality, raw=False)
    rng = np.random.default_rng(seed)
    report = DarkenReport(out, len(jobs))
    check_writable_folder(out)  # a read-only or misplaced --out: one line before any work
    made = not out.exists()
    with _dark_scene_writes(out, made):  # nothing half-made is left behind
        out.mkdir(parents=True, exist_ok=True)
        if folder != src:
            _copy_scene(src, out)
        from tqdm import tqdm
        for photo, rel in tqdm(jobs, desc="darken", disable=not progress, dynamic_ncols=True):
            k = model.view_exposure(rng)
            dark = model.darken(read_image_float(photo), k, rng)
            _write_dark_photo(out / rel, dark, model.jpeg_quality)
            report.exposures[rel] = round(k, 6)
        atomic_write_text(out / "sensor.json", json.dumps(
            {"model": asdict(model), "seed": seed, "source": str(src.resolve()),
             "view_exposures": report.exposures}, indent=1))
    return report


def _darken_inputs(src: Path, out: Path, quality: int, raw: bool) -> Tuple[Path, List[Tuple[Path, str]]]:
    """The photo folder and the (photo, relative name) jobs of ``src`` (see :func:`_scene_photos`); UserError for
    a missing source, an ``out`` that holds files, or a source without photos (checked before anything is
    written)."""
    if not src.is_dir():
        raise UserError(f"{src} is not a folder of photos or a scene folder")
    if out.exists() and any(out.iterdir()):
        raise UserError(f"{out} already exists and is not empty; choose another --out")
    folder, jobs = _scene_photos(src, quality, raw)
    if not jobs:
        raise UserError(f"no photos in {folder}: {no_images_reason(folder)}")
    return folder, jobs


def _copy_scene(src: Path, dst: Path) -> None:
    """Copy a LOM-layout scene's poses, splits and ``high/`` into ``dst`` (not ``low/`` nor caches)."""
    for item in sorted(src.iterdir()):
        if item.name in ("low", "retinex_cache", "retinexgs_cache", "retinexgs_sfm") or item.name.startswith("."):
            continue
        if item.is_dir():
            shutil.copytree(item, dst / item.name)
        else:
            shutil.copy2(item, dst / item.name)


def _write_dark_photo(target: Path, dark: np.ndarray, quality: int) -> None:
    """Write a dark uint8 photo under the source's name and format: a .png keeps the JPEG's loss, losslessly."""
    if quality and target.suffix.lower() not in (".jpg", ".jpeg"):
        dark = jpeg_roundtrip(dark, quality)
    write_image_atomic(target, dark, quality=quality or 95)


def _dng_name(name: str) -> str:
    """``0001.png`` -> ``0001.dng``; a name without an image extension (allowed in transforms) gets ``.dng``."""
    from retinexgs.data.images import IMAGE_EXTENSIONS

    p = Path(name)
    return (p.stem if p.suffix.lower() in IMAGE_EXTENSIONS else p.name) + ".dng"


def _rename_to_dng(scene: Path) -> None:
    """Make a copied LOM scene name its raw files: every transforms frame in ``low/`` or ``high/`` becomes
    ``low/NAME.dng`` (the input of a view is its low/ file; the DNG is it), and split.json's names NAME.dng."""
    for js in sorted(scene.glob("transforms*.json")):
        try:
            data = json.loads(js.read_text())
        except (OSError, ValueError) as exc:
            raise UserError(f"{js}: not a readable transforms JSON ({exc}); fix or remove it") from None
        for frame in data.get("frames", []) if isinstance(data, dict) else []:
            fp = frame.get("file_path") if isinstance(frame, dict) else None
            if isinstance(fp, str) and Path(fp.replace("\\", "/")).parent.name in ("low", "high"):
                frame["file_path"] = "low/" + _dng_name(Path(fp.replace("\\", "/")).name)
        atomic_write_text(js, json.dumps(data, indent=2))
    split = scene / "split.json"
    if split.is_file():
        try:
            data = json.loads(split.read_text())
        except (OSError, ValueError) as exc:
            raise UserError(f"{split}: not readable JSON ({exc}); fix or remove it") from None
        if isinstance(data, dict):
            data = {k: [_dng_name(v) if isinstance(v, str) else v for v in vals] if isinstance(vals, list) else vals
                    for k, vals in data.items()}
            atomic_write_text(split, json.dumps(data, indent=2))


def _darken_raw(src: Path, out: Path, model: SensorModel, camera: "RawCamera", seed: int,
                progress: bool, n_jobs: Optional[int] = None) -> DarkenReport:
    """``darken --raw``: each normal-light photo becomes the raw file a camera writes at night and that
    camera's own JPEG of the same noisy mosaic (retinexgs/data/raw_sim.py has the pipeline):

    - ``out/raw/``: the scene with ``low/NAME.dng`` (its transforms JSON and split.json renamed to the DNGs;
      ``high/`` and ``colmap_sparse/`` copied as they are);
    - ``out/jpeg/``: the same scene with ``low/NAME`` the camera JPEG (the source's name and format, as the
      JPEG ``darken`` writes), a complete scene that trains today;
    - ``sensor.json`` in ``out/`` and in each: the model, the camera (matrix, white balance, CFA, bits, black,
      white, NoiseProfile) and every view's exposure.

    A plain folder of photos gives ``out/raw/NAME.dng`` and ``out/jpeg/NAME``.

    Each view draws its exposure and noise from its own random stream (:func:`view_rng`, from ``seed`` and the
    view's name), so the views run in ``n_jobs`` worker processes (None: one per CPU core) and the files are the
    same for any number of them; a worker holds one view at a time (memory is bounded by the workers, not by
    the views)."""
    from retinexgs.data import raw_sim

    camera.check()
    camera.black_level(model.full_well, model.read_noise)  # a read noise no raw range holds: one line, now
    folder, jobs = _darken_inputs(src, out, model.jpeg_quality, raw=True)
    names: Dict[str, Path] = {}
    for photo, _ in jobs:
        other = names.setdefault(_dng_name(photo.name), photo)
        if other != photo:
            raise UserError(f"{other.name} and {photo.name} in {folder} would both become {_dng_name(photo.name)}; "
                            f"rename one of them")
    workers = _worker_count(n_jobs, len(jobs))
    report = DarkenReport(out, len(jobs))
    check_writable_folder(out)
    made = not out.exists()
    raw_dir, jpeg_dir = out / "raw", out / "jpeg"
    times: Dict[str, float] = {}
    with _dark_scene_writes(out, made):  # nothing half-made is left behind
        for d in (raw_dir, jpeg_dir):
            d.mkdir(parents=True, exist_ok=True)
            if folder != src:
                _copy_scene(src, d)
        if folder != src:
            _rename_to_dng(raw_dir)
        views = []
        for photo, rel in jobs:
            rel_dng = Path(rel).with_name(_dng_name(photo.name)).as_posix()
            for target in (raw_dir / rel_dng, jpeg_dir / rel):
                target.parent.mkdir(parents=True, exist_ok=True)
            views.append(RawView(photo, rel, raw_dir / rel_dng, jpeg_dir / rel))
        work = functools.partial(darken_raw_view, model=model, camera=camera, seed=seed)
        for view, k in zip(views, map_views(work, views, workers, progress, "darken --raw")):
            report.exposures[view.name] = round(k, 6)
            times[Path(view.name).with_name(view.dng.name).as_posix()] = camera.normal_time * k  # the DNG's EXIF
        record = {"model": asdict(model), "camera": camera.record(model.full_well, model.read_noise),
                  "seed": seed, "rng": RNG_RECORD,
                  "source": str(src.resolve()), "layout": {"raw": "raw/", "jpeg": "jpeg/"},
                  "view_exposures": report.exposures, "raw_exposure_times": times}
        text = json.dumps(record, indent=1)
        atomic_write_text(raw_dir / "sensor.json", text)
        atomic_write_text(jpeg_dir / "sensor.json", text)
        atomic_write_text(out / "sensor.json", text)  # last: its presence says the whole capture is written
    return report


# ---- darken --raw's views, one random stream each, spread over worker processes --------------------------------

RNG_RECORD = ("numpy default_rng(SeedSequence(seed, spawn_key=(view key,))) per view; view key = the first 8 bytes "
              "of the SHA-256 of the view's relative name (low/NAME), big-endian; exposure first, then the noise")


def view_rng(seed: int, name: str) -> np.random.Generator:
    """The random stream of the view named ``name`` (its path in the dark scene, e.g. ``low/0001.jpg``): a child
    of ``seed`` keyed by the name (:data:`RNG_RECORD`), so a view's exposure and noise depend neither on the
    views before it nor on which worker draws them, and stay the same when views are added or removed."""
    key = int.from_bytes(hashlib.sha256(name.encode("utf-8")).digest()[:8], "big")
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(key,)))


@dataclass(frozen=True)
class RawView:
    """One view of ``darken --raw``: the normal-light photo, its name in the scene and the two files it becomes."""

    photo: Path
    name: str   # the dark photo's path relative to the scene (``low/NAME``): its random stream's key
    dng: Path
    jpeg: Path


def darken_raw_view(view: RawView, model: SensorModel, camera: "RawCamera", seed: int) -> float:
    """Write one view's DNG and camera JPEG (retinexgs/data/raw_sim.py's pipeline) with its own random stream
    (:func:`view_rng`); its exposure k_v. Runs in a worker process: everything it needs is in its arguments."""
    from retinexgs.data import raw_sim

    rng = view_rng(seed, view.name)
    k = model.view_exposure(rng)
    dn = raw_sim.capture_mosaic(read_image_float(view.photo), model, camera, k, rng)
    raw_sim.write_raw_view(view.dng, dn, camera, model, k)
    rgb = raw_sim.to_uint8(raw_sim.process(dn, camera, camera.black_level(model.full_well, model.read_noise)))
    del dn
    _write_dark_photo(view.jpeg, rgb, model.jpeg_quality)
    return k


def _worker_count(jobs: Optional[int], views: int) -> int:
    """``--jobs`` checked (UserError below 1); None: one worker per CPU core; never more workers than views."""
    if jobs is not None and jobs < 1:
        raise UserError(f"--jobs must be at least 1 (worker processes), got {jobs}")
    return max(1, min(jobs or os.cpu_count() or 1, views))


@contextlib.contextmanager
def _one_thread_per_worker() -> Iterator[None]:
    """While worker processes start: numeric libraries in each use one thread (N workers each starting a thread
    per core would oversubscribe the CPU). The parent's settings are restored after."""
    names = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    saved = {n: os.environ.get(n) for n in names}
    os.environ.update({n: "1" for n in names})
    try:
        yield
    finally:
        for n, v in saved.items():
            if v is None:
                os.environ.pop(n, None)
            else:
                os.environ[n] = v


def _worker_context():
    """The multiprocessing context of :func:`map_views`: a fork server that imported this module (and with it
    torch, which retinexgs.data loads) once, so that each worker starts in a fraction of a second instead of
    importing torch itself; not a plain fork of the caller, which may hold threads (torch's, a progress bar's)
    that a fork copies badly. Spawned workers where there is no fork server (Windows)."""
    import multiprocessing

    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["retinexgs.data.sensor", "retinexgs.data.raw_sim"])
    return ctx


def map_views(fn: Callable[[T], R], items: Sequence[T], workers: int, progress: bool, desc: str) -> List[R]:
    """``[fn(item) for item in items]``, in ``workers`` processes when more than one (:func:`_worker_context`).
    Only the items and results cross between processes, so each worker holds one view at a time. On the first
    failure the views not started are cancelled and the error is raised here (after the running ones end, so
    nothing writes into a folder being removed); a worker that dies becomes a UserError naming --jobs."""
    from tqdm import tqdm

    with tqdm(total=len(items), desc=desc, disable=not progress, dynamic_ncols=True) as bar:
        if workers <= 1 or len(items) <= 1:
            results = []
            for item in items:
                results.append(fn(item))
                bar.update()
            return results
        from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait
        from concurrent.futures.process import BrokenProcessPool

        with _one_thread_per_worker():
            pool = ProcessPoolExecutor(max_workers=workers, mp_context=_worker_context())
            try:
                futures = [pool.submit(fn, item) for item in items]  # in item order
                pending = set(futures)
                while pending:
                    done, pending = wait(pending, return_when=FIRST_EXCEPTION)
                    for f in done:
                        f.result()  # the first failure is raised here
                    bar.update(len(done))
                return [f.result() for f in futures]
            except BrokenProcessPool:
                raise UserError(f"{desc}: a worker process stopped abruptly (killed, perhaps for memory: each holds "
                                f"one view); run again with a smaller --jobs than {workers}") from None
            finally:
                pool.shutdown(wait=True, cancel_futures=True)


@contextlib.contextmanager
def _dark_scene_writes(out: Path, made: bool) -> Iterator[None]:
    """Around darken's writes into ``out``: on any failure, what was written is removed (:func:`_remove_made`), and
    a write error becomes one line (a full disk named as such)."""
    try:
        yield
    except BaseException as exc:
        _remove_made(out, made)
        if isinstance(exc, (OSError, shutil.Error)):  # shutil.Error: copytree's list of failed copies
            if is_out_of_space(exc, out.parent):
                raise out_of_space_error(out) from None
            raise UserError(f"--out {out}: cannot write the dark scene there ({_first_reason(exc)}); "
                            "choose another --out") from None
        raise


def _remove_made(out: Path, made: bool) -> None:
    """Remove what darken wrote into ``out``: the folder itself when darken made it, else its contents (the
    user's empty folder stays)."""
    if made:
        shutil.rmtree(out, ignore_errors=True)
    elif out.is_dir():
        for p in out.iterdir():
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() and not p.is_symlink() else p.unlink(missing_ok=True)


def _first_reason(exc: BaseException) -> str:
    """A one-line reason from an OSError or from the first entry of a shutil.Error's list."""
    if isinstance(exc, shutil.Error) and exc.args and isinstance(exc.args[0], list) and exc.args[0]:
        return str(exc.args[0][0][-1])
    return getattr(exc, "strerror", None) or str(exc)


def jpeg_roundtrip(rgb: np.ndarray, quality: int) -> np.ndarray:
    """uint8 [H,W,3] as a camera's JPEG at ``quality`` would decode it."""
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgb, "RGB").save(buf, format="JPEG", quality=quality)
    buf.seek(0)
    with Image.open(buf) as im:
        return np.asarray(im.convert("RGB"), dtype=np.uint8)


# ---- the noise of a photo ------------------------------------------------------------------------------------

# Immerkær's 3×3 mask: zero on planes and ramps; for white noise of variance s² the response has variance 36 s².
_MASK = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float64)


def _filter3(x: np.ndarray, k: np.ndarray) -> np.ndarray:
    """'valid' 3×3 correlation of [H,W]."""
    H, W = x.shape
    out = np.zeros((H - 2, W - 2))
    for i in range(3):
        for j in range(3):
            if k[i, j]:
                out += k[i, j] * x[i:i + H - 2, j:j + W - 2]
    return out


@dataclass(frozen=True)
class NoiseEstimate:
    """Per channel, the raw-variance model ``var = a · y + b`` in linear light, and what it implies."""

    a: Tuple[float, float, float]   # shot-noise slope (1 / full well, in raw units)
    b: Tuple[float, float, float]   # read-noise floor (variance)
    bins: int                       # brightness bins the fit used (summed over channels)

    def sigma_at(self, y: float) -> Tuple[float, float, float]:
        """The noise's standard deviation per channel at raw linear level ``y``."""
        return tuple(math.sqrt(max(a * y + b, 0.0)) for a, b in zip(self.a, self.b))  # type: ignore[return-value]

    @property
    def full_well(self) -> Tuple[float, float, float]:
        """1 / a: the electrons a raw value of 1 holds (inf where no shot noise was seen)."""
        return tuple(1.0 / a if a > 0 else math.inf for a in self.a)  # type: ignore[return-value]


def _phi(u: np.ndarray) -> np.ndarray:
    return np.exp(-0.5 * u * u) / math.sqrt(2.0 * math.pi)


def _Phi(u: np.ndarray) -> np.ndarray:
    """The standard normal CDF through Abramowitz & Stegun 7.1.26 (|error| < 1.5e-7): vectorised, no scipy."""
    x = np.abs(u) / math.sqrt(2.0)
    t = 1.0 / (1.0 + 0.3275911 * x)
    poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))))
    erf = 1.0 - poly * np.exp(-x * x)
    return 0.5 * (1.0 + np.sign(u) * erf)


def clipped_moments(mu: np.ndarray, sigma: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Mean and variance of max(0, μ + σz), z ~ N(0, 1): what a sensor records of light μ with noise σ, clipped at
    black (Foi et al. 2008, "Practical Poissonian-Gaussian noise modeling and fitting for single-image raw-data")."""
    sigma = np.maximum(sigma, 1e-12)
    u = mu / sigma
    cdf, pdf = _Phi(u), _phi(u)
    mean = mu * cdf + sigma * pdf
    var = (mu * mu + sigma * sigma) * cdf + mu * sigma * pdf - mean * mean
    return mean, np.maximum(var, 0.0)


def fit_clipped_noise(means: np.ndarray, variances: np.ndarray, weights: np.ndarray) -> Tuple[float, float]:
    """(a, b) ≥ 0 of ``var = a·μ + b`` fitted to binned (mean, variance) pairs of a photo whose values are clipped at
    black: each bin's observed mean and variance are the clipped ones (:func:`clipped_moments`) of the light μ it
    records, so near black the variance seen is smaller and the mean higher than the model's. A plain line through
    those bins reads the read noise b several times too low (b = 0 at 1000 e⁻, read noise 6 e⁻) and the shot noise
    too high. Least squares on log σ, weighted by ``weights``, over a log grid of (a, b), refined twice."""
    y, v, w = (np.asarray(x, dtype=np.float64) for x in (means, variances, weights))
    keep = v > 0
    if not keep.any():
        return 0.0, 0.0
    y, v, w = y[keep], v[keep], w[keep]
    log_s = 0.5 * np.log(v)

    def cost(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        # [A, B] candidates x bins: the light μ whose clipped mean is each bin's mean (bisection; it rises with μ)
        a_, b_ = a[:, None, None], b[None, :, None]
        lo, hi = np.zeros(a_.shape[:1] + b_.shape[1:2] + y.shape), np.broadcast_to(y, (a.size, b.size, y.size)) + 0.0
        for _ in range(30):
            mid = 0.5 * (lo + hi)
            m, _ = clipped_moments(mid, np.sqrt(a_ * mid + b_))
            below = m < y
            lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
        mu = 0.5 * (lo + hi)
        _, var = clipped_moments(mu, np.sqrt(a_ * mu + b_))
        return np.sum(w * (0.5 * np.log(np.maximum(var, 1e-30)) - log_s) ** 2, axis=-1)

    a_grid = np.concatenate([[0.0], np.logspace(-7, -1, 25)])
    b_grid = np.concatenate([[0.0], np.logspace(-12, -2, 21)])
    c = cost(a_grid, b_grid)
    i, j = np.unravel_index(np.argmin(c), c.shape)
    a0, b0 = a_grid[i], b_grid[j]
    for step in (0.25, 0.0625):  # refine twice around the best point, to 1/16 and 1/64 of a decade
        a_fine = a0 * 10 ** np.linspace(-step, step, 9) if a0 > 0 else a_grid[:2]
        b_fine = b0 * 10 ** np.linspace(-2 * step, 2 * step, 9) if b0 > 0 else b_grid[:2]
        c = cost(a_fine, b_fine)
        i, j = np.unravel_index(np.argmin(c), c.shape)
        a0, b0 = a_fine[i], b_fine[j]
    return float(a0), float(b0)


def _noise_bins(x: np.ndarray, bins: int, min_pixels: int) -> np.ndarray:
    """[K, 3] rows (mean level, noise variance, pixels) of one channel [H,W] in linear light: pixels binned by their
    3×3 mean into ``bins`` quantiles; in each bin the robust σ (MAD) of Immerkær's residual (edges and texture are the
    outliers it ignores). Bins of fewer than max(30, min_pixels / bins) pixels are left out; [0, 3] when the channel
    has fewer than ``min_pixels`` unclipped pixels."""
    resid = _filter3(x, _MASK) / 6.0  # σ of white noise, per pixel
    level = _filter3(x, np.ones((3, 3)) / 9.0)
    ok = (level > 0.0) & (level < 0.9)  # clipped pixels have no noise to see
    lv, rs = level[ok], resid[ok]
    if lv.size < min_pixels:
        return np.zeros((0, 3))
    edges = np.unique(np.quantile(lv, np.linspace(0, 1, bins + 1)))
    rows = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (lv >= lo) & (lv < hi) if hi < edges[-1] else (lv >= lo) & (lv <= hi)
        n = int(sel.sum())
        if n < max(30, min_pixels // bins):
            continue
        r = rs[sel]
        sigma = 1.4826 * np.median(np.abs(r - np.median(r)))
        rows.append((float(lv[sel].mean()), float(sigma ** 2), n))
    return np.array(rows, dtype=np.float64).reshape(-1, 3)


def _fit_bins(rows: np.ndarray) -> Tuple[float, float]:
    """(a, b) of one channel's :func:`_noise_bins`; one bin: its variance as the floor."""
    if len(rows) < 2:
        return 0.0, (float(rows[0, 1]) if len(rows) else 0.0)
    return fit_clipped_noise(rows[:, 0], rows[:, 1], np.sqrt(rows[:, 2]))


def _check_photo(srgb: np.ndarray) -> None:
    if srgb.ndim != 3 or srgb.shape[-1] != 3 or min(srgb.shape[:2]) < 8:
        raise ValueError(f"expected an [H,W,3] photo of at least 8x8 pixels, got shape {tuple(srgb.shape)}")


def estimate_noise(srgb: np.ndarray, bins: int = 16, min_pixels: int = 400) -> NoiseEstimate:
    """The Poisson-Gaussian noise of one photo [H,W,3] in sRGB [0,1], per channel (module docstring).

    Pixels are binned by the local mean (3×3, linear); in each bin the residual's MAD gives a robust σ (edges and
    texture are the outliers it ignores); ``var = a · y + b`` is fitted to the bins by least squares weighted by
    their pixel counts, with a, b ≥ 0, as the clipped model predicts them (:func:`fit_clipped_noise`)."""
    _check_photo(srgb)
    lin = srgb_to_linear(srgb.astype(np.float64))
    rows = [_noise_bins(lin[..., c], bins, min_pixels) for c in range(3)]
    fits = [_fit_bins(r) for r in rows]
    used = sum(len(r) for r in rows if len(r) >= 2)
    return NoiseEstimate(tuple(f[0] for f in fits), tuple(f[1] for f in fits), used)  # type: ignore[arg-type]


# ---- the noise of a photo seen through its JPEG ---------------------------------------------------------------

@dataclass(frozen=True)
class JpegCodec:
    """How a camera encoded a photo: its JPEG quantisation tables and chroma subsampling, as PIL reads them."""

    qtables: Tuple[Tuple[int, ...], ...]
    subsampling: int  # PIL's: 0 = 4:4:4, 1 = 4:2:2, 2 = 4:2:0

    @classmethod
    def of_file(cls, path: Path) -> Optional["JpegCodec"]:
        """The codec of the JPEG file ``path``; None for any other format (lossless: nothing to model)."""
        from PIL import Image, JpegImagePlugin

        with Image.open(path) as im:
            if im.format != "JPEG" or not getattr(im, "quantization", None):
                return None
            tables = tuple(tuple(int(v) for v in im.quantization[k]) for k in sorted(im.quantization))
            sampling = JpegImagePlugin.get_sampling(im)
        return cls(tables, sampling if sampling in (0, 1, 2) else 0)

    def roundtrip(self, rgb: np.ndarray) -> np.ndarray:
        """uint8 [H,W,3] encoded and decoded with this codec."""
        import io

        from PIL import Image

        buf = io.BytesIO()
        Image.fromarray(rgb, "RGB").save(buf, format="JPEG", qtables=[list(t) for t in self.qtables],
                                         subsampling=self.subsampling)
        buf.seek(0)
        with Image.open(buf) as im:
            return np.asarray(im.convert("RGB"), dtype=np.uint8)


def _blur(x: np.ndarray, sigma: float = 1.5) -> np.ndarray:
    """Separable Gaussian blur of [H,W] (reflected edges)."""
    r = int(math.ceil(3 * sigma))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    for axis in (0, 1):
        p = np.pad(x, [(r, r) if a == axis else (0, 0) for a in (0, 1)], mode="reflect")
        n = x.shape[axis]
        x = sum(w * (p[i:i + n] if axis == 0 else p[:, i:i + n]) for i, w in enumerate(k))
    return x


def estimate_noise_through_codec(srgb: np.ndarray, codec: JpegCodec, rounds: int = 8, damping: float = 0.5,
                                 seed: int = 0, bins: int = 16, min_pixels: int = 400,
                                 pool_channels: bool = True) -> NoiseEstimate:
    """:func:`estimate_noise` of a JPEG photo [H,W,3] (sRGB [0,1]) with the JPEG's own loss of noise modelled.

    JPEG's quantisation removes a dark photo's noise unevenly: on photos darkened by the sensor model at q 90 the
    plain estimate reads 0.15–0.6 of the true σ near black, while the clipped noise's positive mean, which lifts the
    blacks, passes through JPEG whole (its block means survive). So the noise is fitted by simulation: the candidate
    (a, b) is drawn on a smoothed copy of the photo, clipped, written to 8 bits, encoded with ``codec`` (the photo's
    own tables) and measured like the photo; each bin's variance is then moved towards the candidate's scaled by
    observed / simulated (``damping``: the exponent of that ratio, 0.5: JPEG's loss grows steeply as the noise
    shrinks, and a full step overshoots) and refitted, ``rounds`` times.

    ``pool_channels``: one (a, b) for the three channels, fitted to all their bins. Read noise and full well belong
    to the sensor, not to a colour; fitted per channel through JPEG, the read noise near black came out 0.08–1.55 of
    the truth on 512² crops (the chroma channels are quantised hardest), pooled 0.99–1.23
    (experiments/notes/2026-11-27-black-level.md). A camera's white balance, applied after the noise, makes the
    channels differ in truth; the pooled figure is then their compromise."""
    _check_photo(srgb)
    lin = srgb_to_linear(srgb.astype(np.float64))
    obs = [_noise_bins(lin[..., c], bins, min_pixels) for c in range(3)]
    groups = [[0, 1, 2]] if pool_channels else [[0], [1], [2]]
    fits = {}
    for g in groups:
        rows = np.concatenate([obs[c] for c in g])
        fits.update({c: _fit_bins(rows) for c in g})
    base = np.stack([_blur(lin[..., c]) for c in range(3)], axis=-1)
    for _ in range(rounds):
        a = np.array([fits[c][0] for c in range(3)])
        b = np.array([fits[c][1] for c in range(3)])
        rng = np.random.default_rng(seed)  # the same draw each round: the update sees the candidate, not the dice
        y = np.clip(base + np.sqrt(a * base + b) * rng.standard_normal(base.shape), 0.0, 1.0)
        sim = codec.roundtrip(np.round(linear_to_srgb(y) * 255.0).astype(np.uint8))
        sim_lin = srgb_to_linear(sim.astype(np.float64) / 255.0)
        for g in groups:
            means, targets, weights = [], [], []
            for c in g:
                rows = _noise_bins(sim_lin[..., c], bins, min_pixels)
                if len(obs[c]) < 2 or len(rows) < 2:
                    continue
                m = obs[c][:, 0]
                v_sim = np.interp(np.log(m), np.log(rows[:, 0]), rows[:, 1])
                _, v_cand = clipped_moments(m, np.sqrt(a[c] * m + b[c]))
                ratio = np.clip(obs[c][:, 1] / np.maximum(v_sim, 1e-30), 1e-3, 1e3)
                means.append(m)
                targets.append(v_cand * ratio ** damping)
                weights.append(np.sqrt(obs[c][:, 2]))
            if means:
                fit = fit_clipped_noise(np.concatenate(means), np.concatenate(targets), np.concatenate(weights))
                fits.update({c: fit for c in g})
    used = sum(len(r) for r in obs if len(r) >= 2)
    return NoiseEstimate(tuple(fits[c][0] for c in range(3)), tuple(fits[c][1] for c in range(3)), used)  # type: ignore[arg-type]
