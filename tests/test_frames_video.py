"""Issue 62, "Video in": ``retinexgs frames`` turns a night video into a folder of photos (the sharpest frame of
each equal time interval, PNG, named by time) that ``sfm`` and ``train`` take as any folder of photos; a bad
video is one line (exit 2) and leaves nothing behind.

The video is made here: the demo's synthetic scene (retinexgs/demo/synthetic.py) seen from a camera moving on an
arc, darkened with shot and read noise as a night capture, where all frames of each interval but one are motion
blurred (before the noise, as in a camera), encoded as a small H.264 MP4 with imageio-ffmpeg."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from retinexgs.data import video as V
from scenes import TINY_RUN, run_cli

iio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
cv2 = pytest.importorskip("cv2")

W, H, FPS = 192, 144, 10
PER = 5  # frames per interval
N_INT = 8  # intervals: the frames command is run with --max N_INT
SHARP_AT = [(3 * k + 1) % PER for k in range(N_INT)]  # the one sharp frame's place in each interval
SHARP = [k * PER + j for k, j in enumerate(SHARP_AT)]


def _camera(angle_deg: float):
    """A DemoCamera on the demo's circle (radius 3.2, height 1.6) looking at the scene centre, OpenGL axes."""
    from retinexgs.demo.synthetic import SCENE_CENTER, DemoCamera

    a = math.radians(angle_deg)
    eye = np.array([3.2 * math.sin(a), 1.6, 3.2 * math.cos(a)])
    fwd = (SCENE_CENTER - eye) / np.linalg.norm(SCENE_CENTER - eye)
    right = np.cross(fwd, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(right, fwd), -fwd, eye
    f = 0.5 * W / math.tan(math.radians(30.0))
    return DemoCamera("v", "train", W, H, f, f, W / 2, H / 2, c2w)


_LATTICE = np.random.default_rng(7).uniform(0.25, 1.0, (96, 96, 96))  # value noise over [-3.6, 3.6]^3
_CELL = 0.075  # world units: 3-4 pixels at the test's size and distance, blobs SIFT finds


def _texture(p: np.ndarray) -> np.ndarray:
    """3D value noise (trilinear in a random lattice) at world points ``p`` [...,3]: a fixed speckle on every
    surface, so the demo scene's smooth shading gets the detail SfM matches on."""
    q = np.clip((p + 3.6) / _CELL, 0, _LATTICE.shape[0] - 1.001)
    i = np.floor(q).astype(int)
    f = q - i
    out = 0.0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = (np.where(dx, f[..., 0], 1 - f[..., 0]) * np.where(dy, f[..., 1], 1 - f[..., 1])
                     * np.where(dz, f[..., 2], 1 - f[..., 2]))
                out = out + w * _LATTICE[i[..., 0] + dx, i[..., 1] + dy, i[..., 2] + dz]
    return out


def render(cam) -> np.ndarray:
    """Linear radiance [H,W,3] of the demo scene from ``cam``, its surfaces speckled by :func:`_texture`."""
    from retinexgs.demo.synthetic import cast_rays, render_linear

    lin = render_linear(cam, supersample=1) * 1.6
    o, d = cam.pixel_rays()
    hit = cast_rays(o[0], d[0])
    tex = np.where(np.isfinite(hit["t"]), _texture(np.nan_to_num(hit["point"])), 1.0)
    return lin * tex[..., None]


def _night(lin: np.ndarray, rng: np.random.Generator, k: float = 0.2, full_well: float = 1500.0,
           read_noise: float = 3.0) -> np.ndarray:
    """A dark, noisy 8-bit sRGB frame of linear radiance ``lin`` (shot + read noise, as the demo darkens)."""
    from retinexgs.data.srgb import linear_to_srgb

    e = np.clip(lin, 0, 1) * k * full_well
    noisy = rng.poisson(e).astype(np.float64) + rng.normal(0.0, read_noise, lin.shape)
    return np.clip(np.round(linear_to_srgb(np.clip(noisy / full_well, 0, 1)) * 255), 0, 255).astype(np.uint8)


def write_video(path: Path, frames) -> Path:
    """``frames`` (uint8 [H,W,3]) as an H.264 MP4 at FPS."""
    frames = list(frames)
    h, w = frames[0].shape[:2]
    g = iio_ffmpeg.write_frames(str(path), (w, h), fps=FPS, codec="libx264", quality=9, macro_block_size=1)
    g.send(None)
    for f in frames:
        g.send(np.ascontiguousarray(f).tobytes())
    g.close()
    return path


def _motion_blur(lin: np.ndarray, length: int = 13) -> np.ndarray:
    return cv2.blur(lin.astype(np.float32), (length, 1)).astype(np.float64)


@pytest.fixture(scope="module")
def night_video(tmp_path_factory):
    """(path, linear renders) of the test video: 40 frames on a 60-degree arc, 8 intervals of 5 frames, one sharp
    frame per interval (SHARP), the others motion blurred."""
    base = tmp_path_factory.mktemp("video")
    rng = np.random.default_rng(0)
    n = PER * N_INT
    frames, renders = [], []
    for i in range(n):
        lin = render(_camera(-30.0 + 60.0 * i / (n - 1)))
        renders.append(lin)
        frames.append(_night(lin if i in SHARP else _motion_blur(lin), rng))
    return write_video(base / "night.mp4", frames), renders


def _one_line_error(code: int, err: str, *says: str) -> None:
    assert code == 2, err
    assert "Traceback" not in err, err
    lines = [ln for ln in err.strip().splitlines() if "error:" in ln]  # progress lines may come before it
    assert len(lines) == 1 and err.strip().splitlines()[-1].startswith("retinexgs frames: error:"), err
    for s in says:
        assert s in lines[0], (s, lines[0])


# ---- the measure and the choice (pure) ---------------------------------------------------------------------

def test_sharpness_ranks_a_sharp_frame_over_a_blurred_noisier_one_only_with_the_pre_blur():
    """A night video's gain changes from frame to frame: a blurred frame with more noise must not outscore a
    sharp one. The raw Laplacian variance (no pre-blur) is fooled by the noise; the measure is not."""
    lin = render(_camera(0.0))
    rng = np.random.default_rng(1)
    luma = lambda rgb: cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)  # noqa: E731
    sharp = luma(_night(lin, rng, full_well=1500.0, read_noise=3.0))
    blurred_noisy = luma(_night(_motion_blur(lin), rng, full_well=500.0, read_noise=4.0))  # 1.7x the noise
    assert V.sharpness(sharp) > 1.5 * V.sharpness(blurred_noisy)
    assert V.sharpness(sharp, sigma=0.0) < V.sharpness(blurred_noisy, sigma=0.0)  # why the pre-blur is there


def test_blank_frames_are_black_or_flat():
    assert V.blank(np.zeros((20, 30))) and V.blank(np.full((20, 30), 200.0))
    assert V.blank(np.random.default_rng(0).integers(0, 2, (20, 30)))  # black with a code of noise
    assert not V.blank(np.tile(np.arange(30.0), (20, 1)))


def test_pick_sharpest_takes_each_intervals_best_and_leaves_out_blurred_or_blank_intervals():
    scores = [1, 5, 2, 9, 3, 3, 0.2, 0.3, 0.1, 4, 8, 4]
    blanks = [False] * 12
    assert V.pick_sharpest(scores, blanks, 4, floor=0.0) == [1, 3, 7, 10]
    # median 3: interval 2's best (0.3) is below 0.5 x 3
    assert V.pick_sharpest(scores, blanks, 4, floor=0.5) == [1, 3, None, 10]
    blanks[10] = blanks[9] = blanks[11] = True  # a black stretch: no pick there
    assert V.pick_sharpest(scores, blanks, 4, floor=0.0) == [1, 3, 7, None]
    assert V.pick_sharpest([2.0, 2.0, 1.0], [False] * 3, 1, floor=0.0) == [0]  # ties: the earlier frame


def test_intervals_are_equal_in_time_and_counted_from_max_or_every():
    assert [V.interval_of(i, 10, 3) for i in range(10)] == [0, 0, 0, 0, 1, 1, 1, 2, 2, 2]
    assert V.interval_count(300, 30.0, None, None) == V.DEFAULT_MAX_FRAMES
    assert V.interval_count(300, 30.0, 8, None) == 8
    assert V.interval_count(300, 30.0, None, 2.0) == 5  # 10 s, one per 2 s
    assert V.interval_count(300, 30.0, None, 3.0) == 4  # 10 s: the last interval shorter
    assert V.interval_count(300, 30.0, 3, 1.0) == 3  # --max caps --every
    assert V.interval_count(5, 30.0, 60, None) == 5  # never more than the frames


def test_frame_names_sort_by_time():
    times = [0.0, 0.1, 9.95, 10.0, 99.5, 100.25, 3599.999, 36000.0]
    names = [V.frame_name(t) for t in times]
    assert names[1] == "frame_000000.100s.png" and names[5] == "frame_000100.250s.png"
    assert sorted(names) == names and len(set(names)) == len(names)
    assert sorted(reversed(names)) == names


def test_the_commands_defaults_are_the_modules():
    from retinexgs.commands import frames

    assert (frames._DEFAULT_MAX, frames._DEFAULT_FLOOR) == (V.DEFAULT_MAX_FRAMES, V.DEFAULT_SHARPNESS_FLOOR)


# ---- the command on a night video, then sfm and train ----------------------------------------------------

def test_frames_picks_the_sharp_frames_and_sfm_and_train_take_the_folder(night_video, tmp_path, capsys, one_thread):
    video, _ = night_video
    photos = tmp_path / "photos"
    code, out, err = run_cli(["frames", "--video", video, "--out", photos, "--max", N_INT], capsys)
    assert code == 0, err
    names = sorted(p.name for p in photos.glob("*.png"))
    assert names == [V.frame_name(i / FPS) for i in SHARP], (names, SHARP)  # the sharp ones, none blurred
    assert names[0] == "frame_000000.100s.png"
    assert f"frames: {N_INT} of {N_INT} intervals (40 frames decoded at 10 fps)" in out
    assert f"retinexgs sfm --images {photos}" in out
    with Image.open(photos / names[0]) as im:  # lossless 8-bit RGB, at the video's size
        assert (im.format, im.mode, im.size) == ("PNG", "RGB", (W, H))
        assert "night.mp4 at 0.100 s" in im.text["Source"]
    assert json.loads((photos / V.MANIFEST_NAME).read_text())["frames"] == names
    assert not [p for p in photos.iterdir() if p.name.startswith(".tmp")]

    code, out, err = run_cli(["sfm", "--images", photos, "--quiet"], capsys)
    assert code == 0, err
    assert f"registered views: {N_INT}/{N_INT}" in out, out

    sets = [a for s in TINY_RUN for a in ("--set", s)]
    code, out, err = run_cli(["train", "--data", photos, "--out", tmp_path / "run", "--config", "demo", *sets,
                              "--device", "cpu", "--quiet"], capsys)
    assert code == 0, err
    assert any((tmp_path / "run" / "checkpoints").iterdir())
    cfg = (tmp_path / "run" / "config.yaml").read_text()
    assert str(photos) in cfg


def test_every_gives_one_frame_per_interval_of_that_length(night_video, tmp_path, capsys):
    video, _ = night_video
    code, out, err = run_cli(["frames", "--video", video, "--out", tmp_path / "p", "--every", "1", "--quiet"],
                             capsys)
    assert code == 0, err
    names = sorted(p.name for p in (tmp_path / "p").glob("*.png"))
    assert len(names) == 4  # 4 s of video
    for k, name in enumerate(names):  # each in its own second
        assert k <= float(name[len("frame_"):-len("s.png")]) < k + 1, names


def test_a_busy_out_is_refused_and_overwrite_replaces_only_its_own_frames(night_video, tmp_path, capsys):
    video, _ = night_video
    out = tmp_path / "photos"
    assert run_cli(["frames", "--video", video, "--out", out, "--max", N_INT, "--quiet"], capsys)[0] == 0
    first = sorted(p.name for p in out.glob("frame_*.png"))
    (out / "notes.txt").write_text("mine\n")
    (out / "retinexgs_sfm").mkdir()  # as sfm leaves it
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}

    code, _, err = run_cli(["frames", "--video", video, "--out", out, "--max", "4", "--quiet"], capsys)
    _one_line_error(code, err, f"--out {out} is not empty", "--overwrite")
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before

    code, _, err = run_cli(["frames", "--video", video, "--out", out, "--max", "4", "--overwrite"], capsys)
    assert code == 0, err
    now = sorted(p.name for p in out.glob("frame_*.png"))
    assert len(now) == 4 and set(now) <= set(first)  # the sharpest of 10-frame intervals are sharp frames too
    assert (out / "notes.txt").read_text() == "mine\n" and (out / "retinexgs_sfm").is_dir()
    assert "removed 4 earlier frames" in err and "notes.txt" in err, err

    # a file of a frame's name that frames did not write is not replaced, even with --overwrite
    (out / V.MANIFEST_NAME).unlink()
    code, _, err = run_cli(["frames", "--video", video, "--out", out, "--max", "4", "--overwrite", "--quiet"],
                           capsys)
    _one_line_error(code, err, "which retinexgs frames did not write")


def test_sfm_video_writes_the_frames_into_scene_images_and_poses_them(night_video, tmp_path, capsys):
    """The shortcut: `sfm --video clips/walk.mp4` = `frames` into clips/walk/images, then `sfm` on them."""
    rng = np.random.default_rng(5)
    (tmp_path / "clips").mkdir()
    clip = write_video(tmp_path / "clips" / "walk.mp4", [_night(r, rng) for r in night_video[1][::5]])
    scene = tmp_path / "clips" / "walk"
    code, out, err = run_cli(["sfm", "--video", clip, "--quiet"], capsys)
    assert code == 0, err
    assert sorted(p.name for p in (scene / "images").glob("*.png")) == [V.frame_name(i / FPS) for i in range(8)]
    assert "registered views: 8/8" in out and str(scene / "retinexgs_sfm") in out, out
    code, out, err = run_cli(["sfm", "--video", clip], capsys)  # again: the frames and the model are reused
    assert code == 0 and "using the frames of walk.mp4 already in" in err and "(cached)" in out, err
    (scene / "images" / "mine.jpg").write_bytes(b"not made by frames")
    code, _, err = run_cli(["sfm", "--video", clip, "--quiet"], capsys)
    assert code == 2 and "already holds other files" in err and "Traceback" not in err, err
    code, _, err = run_cli(["sfm", "--quiet"], capsys)
    assert code == 2 and "one of the arguments --images --video is required" in err


# ---- bad videos: one line, exit 2, nothing written ---------------------------------------------------------

def _bad(tmp_path, capsys, video, *says, extra=()):
    out = tmp_path / "photos"
    code, _, err = run_cli(["frames", "--video", video, "--out", out, *extra], capsys)
    _one_line_error(code, err, *says)
    assert not out.exists(), "a failed frames wrote its --out"


def test_missing_video(tmp_path, capsys):
    _bad(tmp_path, capsys, tmp_path / "nothere.mp4", "nothere.mp4 does not exist")


def test_a_folder_as_video(tmp_path, capsys):
    (tmp_path / "clips").mkdir()
    _bad(tmp_path, capsys, tmp_path / "clips", "is a folder, not a video file")


def test_an_empty_file(tmp_path, capsys):
    (tmp_path / "night.mp4").write_bytes(b"")
    _bad(tmp_path, capsys, tmp_path / "night.mp4", "is empty (0 bytes)")


def test_a_text_file(tmp_path, capsys):
    (tmp_path / "night.mp4").write_text("not a video at all\n" * 20)
    _bad(tmp_path, capsys, tmp_path / "night.mp4", "is not a video ffmpeg can read")


@pytest.mark.parametrize("fmt,kind", [("PNG", "PNG"), ("JPEG", "JPEG")])
def test_a_still_photo(tmp_path, capsys, fmt, kind):
    path = tmp_path / f"photo.{fmt.lower()}"
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)).save(path, fmt)
    _bad(tmp_path, capsys, path, f"is a still photo ({kind}), not a video", "sfm --images")


def test_a_truncated_video_without_its_index(night_video, tmp_path, capsys):
    data = night_video[0].read_bytes()  # ffmpeg writes the index (moov) at the end, as a phone does
    (tmp_path / "cut.mp4").write_bytes(data[: len(data) // 2])
    _bad(tmp_path, capsys, tmp_path / "cut.mp4", "cut.mp4 is truncated", "moov atom not found")


def test_a_truncated_video_with_its_index_first(tmp_path, capsys):
    frames = [np.full((64, 80, 3), 10 * i, np.uint8) + np.random.default_rng(i).integers(0, 60, (64, 80, 3),
                                                                                         dtype=np.uint8)
              for i in range(20)]
    src = tmp_path / "src.mp4"
    g = iio_ffmpeg.write_frames(str(src), (80, 64), fps=FPS, codec="libx264", macro_block_size=1,
                                output_params=["-movflags", "+faststart"])  # streamable: the index first
    g.send(None)
    for f in frames:
        g.send(f.tobytes())
    g.close()
    data = src.read_bytes()
    (tmp_path / "cut.mp4").write_bytes(data[: len(data) // 2])
    _bad(tmp_path, capsys, tmp_path / "cut.mp4", "cut.mp4 is truncated: its frames stop at", "of the 2.00 s")


def test_a_sound_file_has_no_video_stream(tmp_path, capsys):
    ff = iio_ffmpeg.get_ffmpeg_exe()
    path = tmp_path / "voice.m4a"
    import subprocess
    subprocess.run([ff, "-v", "error", "-f", "lavfi", "-i", "sine=frequency=440:duration=1", str(path)], check=True)
    _bad(tmp_path, capsys, path, "holds no video stream")


def test_a_video_of_black_frames(tmp_path, capsys):
    video = write_video(tmp_path / "black.mp4", [np.zeros((48, 64, 3), np.uint8)] * 20)
    _bad(tmp_path, capsys, video, "all 20 frames are blank")


def test_too_few_sharp_frames_mostly_black(night_video, tmp_path, capsys):
    """Two seconds of scene in ten of a lens cap: two of the ten intervals have a frame worth keeping."""
    rng = np.random.default_rng(3)
    _, renders = night_video
    frames = [_night(renders[i], rng) for i in range(20)] + [np.zeros((H, W, 3), np.uint8)] * 80
    video = write_video(tmp_path / "cap.mp4", frames)
    _bad(tmp_path, capsys, video, "only 2 of 10 intervals have a sharp frame", "80 of 100 frames are blank",
         "at least 3 are needed", extra=["--max", "10"])


def test_too_few_sharp_frames_mostly_blurred(night_video, tmp_path, capsys):
    """Three intervals, the last all motion blur: its best frame is far below the video's median, so it is left
    out, and two frames are too few."""
    rng = np.random.default_rng(4)
    _, renders = night_video
    frames = [_night(r, rng) for r in renders[:20]] + [_night(_motion_blur(r, 25), rng) for r in renders[20:30]]
    video = write_video(tmp_path / "whip.mp4", frames)
    _bad(tmp_path, capsys, video, "only 2 of 3 intervals have a sharp frame", extra=["--max", "3"])
    out = tmp_path / "kept"  # with no floor, the blurred interval is kept
    code, _, err = run_cli(["frames", "--video", video, "--out", out, "--max", "3", "--sharpness-floor", "0",
                            "--quiet"], capsys)
    assert code == 0 and len(list(out.glob("*.png"))) == 3, err


@pytest.mark.parametrize("extra,says", [(["--max", "2"], "--max must be at least 3"),
                                        (["--every", "0"], "--every must be a positive number"),
                                        (["--sharpness-floor", "nan"], "--sharpness-floor must be")])
def test_bad_numbers(night_video, tmp_path, capsys, extra, says):
    _bad(tmp_path, capsys, night_video[0], says, extra=extra)


def test_out_that_is_a_file(night_video, tmp_path, capsys):
    (tmp_path / "photos").write_text("x")
    code, _, err = run_cli(["frames", "--video", night_video[0], "--out", tmp_path / "photos"], capsys)
    _one_line_error(code, err, "is a file")
    assert (tmp_path / "photos").read_text() == "x"


def test_scoring_reads_the_video_at_most_480_pixels_a_side(tmp_path):
    rng = np.random.default_rng(0)
    video = write_video(tmp_path / "big.mp4", [rng.integers(0, 255, (300, 960, 3), dtype=np.uint8)] * 4)
    vs = V.score_video(video)
    assert (vs.width, vs.height, vs.num_frames, vs.fps) == (480, 150, 4, FPS)
