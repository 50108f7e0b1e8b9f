"""Photos from a video: decode a (phone) video, split it into equal time intervals and keep the sharpest frame
of each as a lossless 8-bit PNG named by its time in the video (``retinexgs frames``).

Two passes over the video through imageio-ffmpeg's static ffmpeg:

1. *Score.* ffmpeg hands over each frame as its luma (``gray``), downscaled to at most
   :data:`MEASURE_LONG_SIDE` pixels a side; :func:`sharpness` is the variance of the Laplacian of that frame
   after a light Gaussian blur. A dark, noisy night video is mostly sensor noise at the pixel scale, and noise
   inflates the Laplacian (a noisy blurred frame can outscore a clean sharp one): the downscale (area
   average) and the blur take the noise out and keep the edges that motion blur removes. Frames whose luma is
   flat (all black, a lens cap) are :func:`blank` and never picked.
2. *Write.* The video is decoded again at full size and the chosen frames are written (atomic writes).

The choice is made on the scores alone (:func:`pick_sharpest`, pure), before anything is written, so a video
that cannot give enough sharp frames ends with one line and leaves nothing behind. ffmpeg writes its raw
frames at a constant rate (a variable-rate phone video gets frames repeated or dropped to its nominal rate),
so frame ``k`` is at ``k / fps`` seconds, and both passes see the same frames.
"""
from __future__ import annotations

import importlib.util
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, Iterator, List, Optional, Sequence, Tuple, Union

import numpy as np

from retinexgs.errors import UserError
from retinexgs.fileio import atomic_write, atomic_write_text, check_writable_folder

# Fewer photos than this cannot make a scene worth training (SfM itself needs two views and an initial pair
# plus one more to check it); a video that cannot give them is refused.
MIN_FRAMES = 3
# Intervals (frames) when neither --max nor --every is given: enough views for SfM to register a walk-around,
# few enough that SfM's exhaustive matching (up to 100 photos) stays quick.
DEFAULT_MAX_FRAMES = 60
# An interval whose sharpest frame scores below this share of the video's median frame is left out: the whole
# interval is motion blur (a fast turn), and a blurred view costs SfM matches and training detail.
DEFAULT_SHARPNESS_FLOOR = 0.5
# Sharpness is measured on the luma downscaled to this long side: sharpness is only ever compared within one
# video, and an area average over 4x4 pixels of a 1080p frame (8x8 of 4K) halves to quarters the sensor noise
# while a blur of several pixels at full size still shows.
MEASURE_LONG_SIDE = 480
# The light Gaussian blur (pixels of the downscaled luma) before the Laplacian: takes out the pixel-scale noise
# left after the downscale, which would otherwise inflate a noisy (dark) frame's score. 1.5: on the test's night
# frames a motion-blurred frame with 1.7x the noise of a sharp one outscores it without the blur and at sigma 0.7,
# scores level at 1, and half of it at 1.5; a blur of 3 px at 1080p (1.5 px after the downscale) still counts.
PRE_BLUR_SIGMA = 1.5
# A frame whose luma spans fewer than this many 8-bit codes between its 1st and 99th percentiles is blank
# (black, or one flat colour): nothing to match or train on.
BLANK_RANGE = 2.0
# A video whose frames stop before this share of the frames its header declares is truncated (a copy cut
# short); a small shortfall is ordinary (rounded durations, a last frame's length).
TRUNCATED_SHARE = 0.9
# PNG compression: SfM and training read the frames many times, and zlib level 3 writes a 4K frame several
# times faster than the default 6 for a few per cent more bytes.
PNG_COMPRESS_LEVEL = 3
# What ``frames`` writes beside its frames: the list of them, so that --overwrite replaces only its own files.
MANIFEST_NAME = ".retinexgs_frames.json"
FRAME_PREFIX = "frame_"

Progress = Callable[[str], None]


@dataclass
class VideoScores:
    """Pass 1 over a video: per frame (in decoding order) its sharpness and whether it is blank."""

    fps: float
    declared_duration: float  # the header's duration in seconds (0 when it has none)
    width: int  # the decoded frames' size (after the rotation the file asks for)
    height: int
    codec: str
    scores: np.ndarray  # [n] float64
    blank: np.ndarray  # [n] bool

    @property
    def num_frames(self) -> int:
        return int(len(self.scores))

    @property
    def duration(self) -> float:
        """Seconds covered by the decoded frames."""
        return self.num_frames / self.fps


@dataclass
class FramesResult:
    """What :func:`extract_frames` did."""

    out_dir: Path
    written: List[Path]
    times: List[float]  # seconds into the video, one per written frame
    num_intervals: int
    num_decoded: int
    fps: float
    left_out: List[Tuple[float, float]] = field(default_factory=list)  # (start, end) s of intervals without a pick
    removed: List[str] = field(default_factory=list)  # earlier frames of ours replaced (--overwrite)
    kept: List[str] = field(default_factory=list)  # other entries of --out, kept (--overwrite)


# ---------------------------------------------------------------------------------------------------------
# Pure parts: measures, intervals, choice, names


def sharpness(grey: np.ndarray, sigma: float = PRE_BLUR_SIGMA) -> float:
    """Variance of the Laplacian of ``grey`` (a 2D luma image, 8-bit scale) after a Gaussian blur of
    ``sigma`` pixels: high for crisp edges, low for motion or focus blur. The blur first: on a dark, noisy
    frame the pixel-scale noise would dominate the Laplacian (see the module docstring)."""
    import cv2  # a requirement (opencv-contrib-python-headless); lazy: --help stays fast

    g = np.asarray(grey, dtype=np.float32)
    if sigma > 0:
        g = cv2.GaussianBlur(g, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT)
    lap = cv2.Laplacian(g, cv2.CV_32F, ksize=1, borderType=cv2.BORDER_REFLECT)
    return float(lap.astype(np.float64).var())


def blank(grey: np.ndarray, min_range: float = BLANK_RANGE) -> bool:
    """True when ``grey`` (luma, 8-bit scale) spans fewer than ``min_range`` codes between its 1st and 99th
    percentiles: a black or flat frame."""
    lo, hi = np.percentile(np.asarray(grey, dtype=np.float32), [1.0, 99.0])
    return bool(hi - lo < min_range)


def interval_count(num_frames: int, fps: float, max_frames: Optional[int], every: Optional[float]) -> int:
    """How many equal time intervals to split ``num_frames`` frames at ``fps`` into: one per ``every`` seconds
    (rounded up) when given, else ``max_frames`` (default :data:`DEFAULT_MAX_FRAMES`); never more than
    ``max_frames`` when that is given, nor more than there are frames."""
    if every is not None:
        n = math.ceil(num_frames / fps / every - 1e-9)
        if max_frames is not None:
            n = min(n, max_frames)
    else:
        n = DEFAULT_MAX_FRAMES if max_frames is None else max_frames
    return max(1, min(n, num_frames))


def interval_of(index: int, num_frames: int, num_intervals: int) -> int:
    """The interval frame ``index`` falls in when ``num_frames`` frames (a constant rate) are split into
    ``num_intervals`` equal time intervals. Integer arithmetic: no frame lands in two intervals by rounding."""
    return index * num_intervals // num_frames


def pick_sharpest(scores: Sequence[float], blanks: Sequence[bool], num_intervals: int,
                  floor: float = DEFAULT_SHARPNESS_FLOOR) -> List[Optional[int]]:
    """Per interval, the index of its sharpest frame, or None when the interval has none sharp enough.

    ``scores`` and ``blanks`` are per frame in time order (a constant frame rate). A blank frame is never
    picked; an interval's best frame is left out when its score is below ``floor`` times the median score of
    the video's non-blank frames. Ties go to the earlier frame.
    """
    s = np.asarray(scores, dtype=np.float64)
    b = np.asarray(blanks, dtype=bool)
    n = len(s)
    if len(b) != n:
        raise ValueError("scores and blanks differ in length")
    if n == 0:
        return [None] * num_intervals
    usable = ~b
    median = float(np.median(s[usable])) if usable.any() else 0.0
    picks: List[Optional[int]] = [None] * num_intervals
    for i in range(n):
        if not usable[i]:
            continue
        k = interval_of(i, n, num_intervals)
        if picks[k] is None or s[i] > s[picks[k]]:
            picks[k] = i
    return [p if p is not None and s[p] >= floor * median and s[p] > 0 else None for p in picks]


def frame_name(seconds: float) -> str:
    """The file name of the frame at ``seconds`` into the video: ``frame_000012.345s.png``. Zero-padded to
    six digits of seconds (277 hours), so the names sort by time."""
    return f"{FRAME_PREFIX}{seconds:010.3f}s.png"


# ---------------------------------------------------------------------------------------------------------
# Checks and decoding


def _still_image_type(head: bytes) -> Optional[str]:
    """The photo type whose signature starts ``head``, or None: a photo given as a video."""
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return "PNG"
    if head.startswith(b"\xff\xd8\xff"):
        return "JPEG"
    if head.startswith(b"II\x1a\x00\x00\x00HEAPCCDR"):
        return "Canon CRW raw"
    if head[:4] in (b"II*\x00", b"MM\x00*"):
        return "TIFF or camera raw"
    if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
        return "WebP"
    if head[4:8] == b"ftyp":
        brand = head[8:12]
        if brand in (b"heic", b"heix", b"heim", b"heis", b"mif1", b"avif"):
            return "HEIC/HEIF"
        if brand == b"crx ":
            return "Canon CR3 raw"
    return None


def check_video_file(path: Union[str, Path]) -> Path:
    """Refuse, with one line, a --video that is missing, a folder, empty, or a photo; returns it as a Path."""
    p = Path(path)
    if not p.exists():
        raise UserError(f"--video {p} does not exist")
    if p.is_dir():
        raise UserError(f"--video {p} is a folder, not a video file")
    if not p.is_file():  # a pipe or a device: ffmpeg could wait on it for ever
        raise UserError(f"--video {p} is not a regular file (a pipe or a device): save the video to a file first")
    try:
        with open(p, "rb") as f:
            head = f.read(16)
    except OSError as exc:
        raise UserError(f"--video {p} cannot be read ({exc.strerror or exc})") from None
    if not head:
        raise UserError(f"--video {p} is empty (0 bytes): copy it again")
    kind = _still_image_type(head)
    if kind:
        raise UserError(f"--video {p} is a still photo ({kind}), not a video: put photos in a folder and pass "
                        f"it to retinexgs sfm --images or retinexgs train --data")
    return p


def _ffmpeg():
    """imageio-ffmpeg (an install requirement, with its own static ffmpeg)."""
    if importlib.util.find_spec("imageio_ffmpeg") is None:
        raise UserError("reading a video needs imageio-ffmpeg, an install requirement missing here: "
                        "pip install imageio-ffmpeg")
    import imageio_ffmpeg

    return imageio_ffmpeg


def _open_error(path: Path, text: str) -> UserError:
    """The one line for a file ffmpeg could not open, from ffmpeg's log ``text``."""
    lines = [ln.strip() for ln in str(text).splitlines() if ln.strip()]
    try:
        with open(path, "rb") as f:
            head = f.read(12)
    except OSError:
        head = b""
    # ffmpeg picks the MP4 reader by the name: only a file that starts as an MP4/MOV does is a cut-short one
    mp4_start = head[4:8] in (b"ftyp", b"mdat", b"moov", b"free", b"wide", b"skip")
    if mp4_start and any("moov atom not found" in ln for ln in lines):
        return UserError(f"--video {path} is truncated or not a finished video (ffmpeg: moov atom not found, "
                         f"the index a phone writes when it stops recording): copy it again")
    if any(" Audio: " in ln for ln in lines) and not any(" Video: " in ln for ln in lines):
        return UserError(f"--video {path} holds no video stream (sound only)")
    why = next((ln for ln in reversed(lines) if "Invalid data" in ln), "")
    why = why.split(": ", 1)[-1].lower() if why else "no video stream found"
    return UserError(f"--video {path} is not a video ffmpeg can read ({why})")


# The output size of pass 1: the long side at most MEASURE_LONG_SIDE, the aspect kept (-2: an even size).
_SCALE = (f"scale=w='if(gte(iw,ih),min(iw,{MEASURE_LONG_SIDE}),-2)':"
          f"h='if(gte(iw,ih),-2,min(ih,{MEASURE_LONG_SIDE}))':flags=area")


def _frames(path: Path, pix_fmt: str, bits: int, output_params: List[str]) -> Tuple[dict, Iterator[bytes]]:
    """(ffmpeg's header, an iterator over the raw frames) for ``path``; one line when ffmpeg cannot open it."""
    ff = _ffmpeg()
    # "file:" + an absolute path: a name such as "pipe:1" or "-x.mp4" is never read as a protocol or an option
    gen = ff.read_frames("file:" + str(path.absolute()), pix_fmt=pix_fmt, bits_per_pixel=bits,
                         output_params=output_params)
    try:
        meta = next(gen)
    except OSError as exc:
        gen.close()
        raise _open_error(path, str(exc)) from None
    except (IndexError, AttributeError, ValueError):  # no "Video:" stream line (a sound file) or no size
        gen.close()
        raise UserError(f"--video {path} holds no video stream") from None
    except StopIteration:
        raise UserError(f"--video {path} is not a video ffmpeg can read") from None
    return meta, gen


def _decode_error(path: Path, index: int) -> UserError:
    return UserError(f"--video {path}: decoding stopped at frame {index} (the file is truncated or corrupt): "
                     f"copy it again")


def score_video(path: Union[str, Path], progress: Optional[Callable[[int, int], None]] = None) -> VideoScores:
    """Pass 1: decode ``path`` as downscaled luma and score every frame (:func:`sharpness`, :func:`blank`).

    ``progress(done, expected)`` is called every few frames. Raises UserError (one line) for a file ffmpeg
    cannot open, a video without frames, and a truncated one (frames stop before :data:`TRUNCATED_SHARE` of the
    declared duration, or mid-frame).
    """
    path = check_video_file(path)
    meta, gen = _frames(path, "gray", 8, ["-vf", _SCALE])
    try:
        w, h = (int(x) for x in meta["size"])
        fps = float(meta.get("fps") or 0.0)
        declared = float(meta.get("duration") or 0.0)
        codec = str(meta.get("codec", "")).rstrip(",")
        if w <= 0 or h <= 0:
            raise UserError(f"--video {path} holds no video stream with a size")
        expected = int(round(declared * fps)) if fps > 0 else 0
        scores: List[float] = []
        blanks: List[bool] = []
        i = 0
        try:
            for raw in gen:
                grey = np.frombuffer(raw, dtype=np.uint8).reshape(h, w)
                scores.append(sharpness(grey))
                blanks.append(blank(grey))
                i += 1
                if progress is not None and i % 16 == 0:
                    progress(i, expected)
        except RuntimeError:  # a frame cut short: imageio-ffmpeg's "Could not read frame"
            raise _decode_error(path, i) from None
    finally:
        gen.close()
    if progress is not None:
        progress(i, expected)
    n = len(scores)
    if n == 0:
        raise UserError(f"--video {path} holds no frames (ffmpeg decoded none): copy it again")
    if fps <= 0:
        raise UserError(f"--video {path} has no frame rate in its header: frames cannot be timed")
    if expected and n < TRUNCATED_SHARE * expected:
        raise UserError(f"--video {path} is truncated: its frames stop at {n / fps:.2f} s of the {declared:.2f} s "
                        f"its header declares ({n} of {expected} frames): copy it again")
    return VideoScores(fps, declared, w, h, codec, np.asarray(scores, np.float64), np.asarray(blanks, bool))


def read_frames_at(path: Union[str, Path], indices: Sequence[int]) -> Iterator[Tuple[int, np.ndarray]]:
    """Pass 2: (index, uint8 [H,W,3] RGB) for each of ``indices`` (frame numbers in decoding order), in order,
    decoding the video at full size and stopping after the last one."""
    path = Path(path)
    wanted = set(int(k) for k in indices)
    if not wanted:
        return
    last = max(wanted)
    meta, gen = _frames(path, "rgb24", 24, [])
    w, h = (int(x) for x in meta["size"])
    i = 0
    try:
        for raw in gen:
            if i in wanted:
                yield i, np.frombuffer(raw, dtype=np.uint8).reshape(h, w, 3)
            if i >= last:
                return
            i += 1
    except RuntimeError:
        raise _decode_error(path, i) from None
    finally:
        gen.close()
    raise UserError(f"--video {path} changed while it was read: frame {last} is gone; run frames again")


# ---------------------------------------------------------------------------------------------------------
# The folder


def _own_frames(out: Path) -> List[str]:
    """The frame names an earlier ``frames`` recorded in ``out``'s manifest (empty when there is none)."""
    try:
        data = json.loads((out / MANIFEST_NAME).read_text())
        names = data.get("frames", [])
    except (OSError, ValueError, AttributeError):
        return []
    return [n for n in names if isinstance(n, str) and "/" not in n and n.startswith(FRAME_PREFIX)]


def _check_out(out: Path, names: List[str], overwrite: bool) -> Tuple[List[str], List[str]]:
    """Refuse an --out that holds anything unless ``overwrite``; with it, refuse to replace a file of the new
    frames' names that ``frames`` did not write. Returns (our earlier frames to remove, other entries kept)."""
    check_writable_folder(out, "--out")
    if not out.is_dir():
        return [], []
    entries = sorted(p.name for p in out.iterdir())
    if not entries:
        return [], []
    if not overwrite:
        shown = ", ".join(entries[:3]) + (f" and {len(entries) - 3} more" if len(entries) > 3 else "")
        raise UserError(f"--out {out} is not empty ({shown}): choose a new or empty folder, or pass --overwrite "
                        f"to replace the frames an earlier retinexgs frames wrote there (nothing else is touched)")
    own = set(_own_frames(out))
    clash = [n for n in names if (out / n).exists() and n not in own]
    if clash:
        raise UserError(f"--out {out} holds {clash[0]}, which retinexgs frames did not write there: --overwrite "
                        f"replaces only its own frames; choose another --out or move that file")
    stale = sorted(n for n in own if n not in names and (out / n).is_file())
    kept = [e for e in entries if e not in own and e != MANIFEST_NAME]
    return stale, kept


def _png_bytes(rgb: np.ndarray, video: Path, seconds: float) -> bytes:
    from PIL import Image, PngImagePlugin

    info = PngImagePlugin.PngInfo()
    info.add_text("Source", f"{video.name} at {seconds:.3f} s (retinexgs frames)")
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb), "RGB").save(buf, format="PNG", pnginfo=info,
                                                           compress_level=PNG_COMPRESS_LEVEL)
    return buf.getvalue()


def extract_frames(video: Union[str, Path], out: Union[str, Path], *, max_frames: Optional[int] = None,
                   every: Optional[float] = None, floor: float = DEFAULT_SHARPNESS_FLOOR,
                   overwrite: bool = False, progress: Optional[Progress] = None,
                   bar: Optional[Callable[[int, int], None]] = None) -> FramesResult:
    """Write the sharpest frame of each equal time interval of ``video`` into ``out`` as 8-bit PNG.

    The number of intervals is ``max_frames`` (default :data:`DEFAULT_MAX_FRAMES`), or one per ``every``
    seconds (at most ``max_frames`` when both are given). ``floor``: an interval whose best frame scores below
    ``floor`` × the median frame is left out. ``out`` must be new or empty unless ``overwrite``, which replaces
    (and removes) only frames an earlier call wrote there. Raises UserError (one line, nothing written) for a
    bad video or folder, and when fewer than :data:`MIN_FRAMES` frames are sharp enough.
    ``progress`` gets status lines, ``bar(done, expected)`` the scoring pass's frame count.
    """
    say = progress or (lambda _m: None)
    video = Path(video)
    out = Path(out)
    if max_frames is not None and max_frames < MIN_FRAMES:
        raise UserError(f"--max must be at least {MIN_FRAMES} (SfM needs that many photos), got {max_frames}")
    if every is not None and not (math.isfinite(every) and every > 0):
        raise UserError(f"--every must be a positive number of seconds, got {every}")
    if not (math.isfinite(floor) and floor >= 0):
        raise UserError(f"--sharpness-floor must be a number >= 0, got {floor}")
    check_video_file(video)
    check_writable_folder(out, "--out")  # before the decoding, which may take a while
    if not overwrite and out.is_dir() and any(out.iterdir()):
        _check_out(out, [], overwrite)  # raises: names the entries
    vs = score_video(video, bar)
    n_int = interval_count(vs.num_frames, vs.fps, max_frames, every)
    say(f"{video.name}: {vs.num_frames} frames, {vs.duration:.2f} s at {vs.fps:g} fps, {vs.width}x{vs.height} "
        f"scored; the sharpest of each of {n_int} intervals of {vs.duration / n_int:.2f} s")
    if vs.blank.all():
        raise UserError(f"--video {video}: all {vs.num_frames} frames are blank (black or one flat colour): "
                        f"nothing to reconstruct")
    picks = pick_sharpest(vs.scores, vs.blank, n_int, floor)
    chosen = [p for p in picks if p is not None]
    span = vs.duration / n_int
    left_out = [(k * span, (k + 1) * span) for k, p in enumerate(picks) if p is None]
    if len(chosen) < MIN_FRAMES:
        n_blank = int(vs.blank.sum())
        raise UserError(f"--video {video}: only {len(chosen)} of {n_int} intervals have a sharp frame (sharpness "
                        f"at least {floor:g} x the video's median, not blank; {n_blank} of {vs.num_frames} frames "
                        f"are blank); at least {MIN_FRAMES} are needed: film slower or longer, or lower "
                        f"--sharpness-floor")
    times = [i / vs.fps for i in chosen]
    names = [frame_name(t) for t in times]
    if len(set(names)) != len(names):  # only above 1000 fps: the names keep milliseconds
        raise UserError(f"--video {video}: {vs.fps:g} fps is too fast for millisecond frame names; use --max "
                        f"or --every for fewer frames")
    stale, kept = _check_out(out, names, overwrite)
    made_out = not out.exists()
    st = video.stat()
    manifest = {"tool": "retinexgs frames", "video": str(video.resolve()), "video_size": st.st_size,
                "video_mtime_ns": st.st_mtime_ns, "fps": vs.fps,
                "num_frames": vs.num_frames, "intervals": n_int, "sharpness_floor": floor,
                "frames": sorted(set(names) | set(stale)),
                "scores": {}}
    written: List[Path] = []
    try:
        out.mkdir(parents=True, exist_ok=True)
        # The manifest first: a frame written by a run killed half-way is still known as ours.
        atomic_write_text(out / MANIFEST_NAME, json.dumps(manifest, indent=1))
        by_index: Dict[int, str] = dict(zip(chosen, names))
        for i, rgb in read_frames_at(video, chosen):
            data = _png_bytes(rgb, video, i / vs.fps)
            written.append(atomic_write(out / by_index[i], lambda f, d=data: f.write(d)))
            say(f"wrote {by_index[i]} ({len(written)}/{len(chosen)})")
        for n in stale:
            (out / n).unlink(missing_ok=True)
        manifest["frames"] = names
        manifest["scores"] = {n: round(float(vs.scores[i]), 3) for i, n in zip(chosen, names)}
        atomic_write_text(out / MANIFEST_NAME, json.dumps(manifest, indent=1))
    except BaseException:
        if made_out:  # a folder this call made holds only what it wrote: leave nothing behind
            for p in written + [out / MANIFEST_NAME]:
                try:
                    p.unlink()
                except OSError:
                    pass
            try:
                out.rmdir()
            except OSError:
                pass
        raise
    return FramesResult(out, written, times, n_int, vs.num_frames, vs.fps, left_out, stale, kept)


def list_frame_files(out: Union[str, Path]) -> List[str]:
    """The frames ``frames`` last wrote into ``out`` (from its manifest), in time order."""
    return sorted(_own_frames(Path(out)))


def frames_made_from(out: Union[str, Path], video: Union[str, Path]) -> bool:
    """True when ``out`` holds, complete, the frames an earlier :func:`extract_frames` made from this very
    ``video`` (same path, size and modification time) and nothing else but its manifest and an SfM folder: they
    can be used again instead of decoding the video anew (``sfm --video`` run twice)."""
    out, video = Path(out), Path(video)
    try:
        data = json.loads((out / MANIFEST_NAME).read_text())
        st = video.stat()
    except (OSError, ValueError):
        return False
    if not isinstance(data, dict) or data.get("video") != str(video.resolve()):
        return False
    if data.get("video_size") != st.st_size or data.get("video_mtime_ns") != st.st_mtime_ns:
        return False
    names = _own_frames(out)
    if len(names) < MIN_FRAMES or not all((out / n).is_file() for n in names):
        return False
    return {p.name for p in out.iterdir()} <= set(names) | {MANIFEST_NAME, "retinexgs_sfm"}


__all__ = ["MIN_FRAMES", "DEFAULT_MAX_FRAMES", "DEFAULT_SHARPNESS_FLOOR", "FramesResult", "VideoScores",
           "blank", "check_video_file", "extract_frames", "frame_name", "interval_count", "interval_of",
           "frames_made_from", "list_frame_files", "pick_sharpest", "read_frames_at", "score_video", "sharpness"]
