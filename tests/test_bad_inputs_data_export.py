"""Issue 15, scene data, decomposition cache and export: inputs that used to be read silently wrong or end
in a traceback now read right or fail with one clear paragraph naming the file, frame and field; nothing
is written before the inputs are validated and nothing partial is left in the user's scene folder.

Every fixture is built here (a tiny synthetic demo scene); no dev data is used.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import List

import numpy as np
import pytest
import torch
from PIL import Image

from retinexgs.data import load_scene
from retinexgs.data.images import load_image_tensor, read_image
from retinexgs.demo.synthetic import make_demo_scene
from retinexgs.errors import UserError
from scenes import run_cli

TINY = ["steps=3", "checkpoint.every=3", "log.every=1", "log.tensorboard=false", "model.sh_degree=1",
        "model.max_init_points=300", "decomposer.method=lime", "eval.lpips=false"]


_cli = run_cli


def _tree(root: Path):
    """Names, sizes and modification times of everything under ``root``."""
    out = {}
    for p in sorted(Path(root).rglob("*")):
        st = p.lstat()
        out[str(p.relative_to(root))] = (p.is_dir(), 0 if p.is_dir() else st.st_size,
                                         0 if p.is_dir() else st.st_mtime_ns)
    return out


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """A tiny demo scene (3 train, 1 test view, 24x18) kept pristine: tests copy it."""
    return make_demo_scene(tmp_path_factory.mktemp("demo") / "scene", n_train=3, n_test=1, width=24, height=18,
                           n_points=200)


@pytest.fixture
def scene(demo, tmp_path):
    """A private copy of the demo scene."""
    dst = tmp_path / "scene"
    shutil.copytree(demo, dst)
    return dst


def _edit_json(path: Path, edit) -> None:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


# ---- 1. images of every bit depth and channel layout read scaled to [0,1] ---------------------------------

def _levels(h=6, w=8):
    """16-bit levels covering the range, and the same as 8-bit."""
    v16 = np.linspace(0, 65535, h * w).reshape(h, w).astype(np.uint16)
    return v16, np.rint(v16 / 257.0).astype(np.uint8)


def test_16bit_grey_png_is_scaled_not_saturated(tmp_path):
    v16, _ = _levels()
    path = tmp_path / "g16.png"
    Image.fromarray(v16).save(path)  # Pillow writes mode I;16 as a 16-bit greyscale PNG
    with Image.open(path) as im:
        assert im.mode.startswith("I")  # the case that convert("RGB") saturated to white
    img = load_image_tensor(path).numpy()
    assert img.shape == (6, 8, 3) and img.dtype == np.float32
    assert np.allclose(img, (v16 / 65535.0)[:, :, None], atol=1e-6)
    assert np.array_equal(read_image(path)[:, :, 1], np.rint(v16 / 257.0).astype(np.uint8))


@pytest.mark.parametrize("layout", ["L", "LA", "RGB", "RGBA"])
def test_8bit_layouts_are_scaled(tmp_path, layout):
    _, v8 = _levels()
    rgb = np.stack([v8, v8[::-1], 255 - v8], -1)
    arrays = {"L": v8, "LA": np.stack([v8, np.full_like(v8, 7)], -1), "RGB": rgb,
              "RGBA": np.concatenate([rgb, np.full_like(v8, 9)[:, :, None]], -1)}
    path = tmp_path / f"{layout}.png"
    Image.fromarray(arrays[layout], layout).save(path)
    want = (np.repeat(v8[:, :, None], 3, 2) if layout in ("L", "LA") else rgb) / 255.0
    assert np.allclose(load_image_tensor(path).numpy(), want, atol=1e-6)


@pytest.mark.parametrize("alpha", [False, True])
def test_16bit_colour_png_keeps_its_depth(tmp_path, alpha):
    cv2 = pytest.importorskip("cv2")
    v16, _ = _levels()
    rgb = np.stack([v16, v16[::-1], 65535 - v16], -1)
    bgr = rgb[:, :, ::-1]
    if alpha:
        bgr = np.concatenate([bgr, np.full_like(v16, 1234)[:, :, None]], -1)
    path = tmp_path / "c16.png"
    cv2.imwrite(str(path), np.ascontiguousarray(bgr))
    img = load_image_tensor(path).numpy()
    assert np.allclose(img, rgb / 65535.0, atol=1e-6)  # 8-bit would be off by up to 1/510


# ---- 1. degenerate poses and intrinsics, non-numeric fields ------------------------------------------------

@pytest.mark.parametrize("rotation, says", [
    (np.zeros((3, 3)), "all zero"),
    (np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 0]]), "rank-deficient (rank 2)"),
    (np.diag([2.0, 2.0, 2.0]), "not a rotation"),
    (np.diag([1.0, 1.0, -1.0]), "not a rotation"),
])
def test_degenerate_rotation_is_refused(scene, rotation, says):
    def edit(data):
        m = np.asarray(data["frames"][1]["transform_matrix"], dtype=np.float64)
        m[:3, :3] = rotation
        data["frames"][1]["transform_matrix"] = m.tolist()

    _edit_json(scene / "transforms_train.json", edit)
    with pytest.raises(UserError) as err:
        load_scene(scene)
    msg = str(err.value)
    assert "transforms_train.json frame 1" in msg and "transform_matrix" in msg and says in msg, msg
    assert not (scene / "retinexgs_cache").exists()


@pytest.mark.parametrize("field, value, says", [
    ("fl_x", 0, "fl_x"), ("fl_x", -10.0, "fl_x"), ("fl_y", 0, "fl_y"), ("fl_x", "NaN", "fl_x"),
    ("cx", "inf", "cx"),
])
def test_bad_intrinsics_are_refused(scene, field, value, says):
    def edit(data):
        data.update({field: value})
        for f in data["frames"]:
            f.pop(field, None)
        if field == "fl_x":
            data["fl_y"] = data.get("fl_y", 20.0)

    _edit_json(scene / "transforms_train.json", edit)
    with pytest.raises(UserError) as err:
        load_scene(scene)
    msg = str(err.value)
    assert "transforms_train.json frame 0" in msg and says in msg, msg


def test_zero_focal_lengths_per_frame_are_refused(scene):
    def edit(data):
        data["frames"][2].update(fl_x=0, fl_y=0)

    _edit_json(scene / "transforms_train.json", edit)
    with pytest.raises(UserError, match=r"transforms_train\.json frame 2 .*focal length fx \(fl_x\)"):
        load_scene(scene)


def test_non_numeric_width_names_key_and_value(scene, capsys):
    _edit_json(scene / "transforms_train.json", lambda d: d.update(w="wide"))
    code, out, err = _cli(["train", "--data", scene, "--out", scene.parent / "run", "--device", "cpu"], capsys)
    assert code == 2 and "Traceback" not in err, err
    assert "transforms_train.json frame 0" in err and "'w' must be a" in err and "'wide'" in err, err


# ---- 2 and 4. render --views val; export into an unwritable folder or from a non-ASCII run folder ---------

@pytest.fixture(scope="module")
def run_with_val(tmp_path_factory, demo):
    """A 3-step run of a copy of the demo scene given a val split (the test frames listed again)."""
    base = tmp_path_factory.mktemp("valrun")
    scene = base / "scene"
    shutil.copytree(demo, scene)
    shutil.copy(scene / "transforms_test.json", scene / "transforms_val.json")
    from retinexgs.train.runner import train_run

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        train_run(scene, base / "rün ✓", ["demo"], TINY, "cpu", progress=False, log=lambda s: None)
    finally:
        torch.set_num_threads(n)
    return base / "rün ✓"


def test_render_val_views(run_with_val, tmp_path, capsys):
    out = tmp_path / "val"
    code, _, err = _cli(["render", "--run", run_with_val, "--views", "val", "--out", out, "--device", "cpu",
                         "--quiet"], capsys)
    assert code == 0, err
    scene = run_with_val.parent / "scene"
    val = [Path(f["file_path"]).stem + ".png" for f in json.loads((scene / "transforms_val.json").read_text())["frames"]]
    assert sorted(p.name for p in (out / "enhanced").iterdir()) == sorted(val)


def test_render_val_without_a_val_split_names_the_splits_there_are(tmp_path, monkeypatch):
    import retinexgs.export.renders as renders

    class _Scene:  # what load_run returns, reduced to the splits
        test, train, val = [object()], [object()], []

    run = tmp_path / "run"
    run.mkdir()
    import yaml

    from retinexgs.config import plain
    from retinexgs.run.config import load_config

    # a whole recorded config: render validates it before loading the run
    (run / "config.yaml").write_text(yaml.safe_dump(dict(plain(load_config()), scene=str(tmp_path))))
    monkeypatch.setattr(renders, "load_run", lambda run_dir, device: ({}, _Scene, None, 0))
    with pytest.raises(UserError, match=r"no val views; try --views test or --views train or --views path"):
        renders.render_run(run, "val", tmp_path / "out")


def test_export_from_a_non_ascii_run_folder_writes_an_ascii_header(run_with_val, tmp_path, capsys):
    from retinexgs.export.ply import read_ply

    out = tmp_path / "out.ply"
    code, _, err = _cli(["export", "--run", run_with_val, "--out", out, "--device", "cpu", "--quiet"], capsys)
    assert code == 0 and "Traceback" not in err, err
    data = out.read_bytes()
    header = data[: data.index(b"end_header\n")]
    header.decode("ascii")  # the PLY header must be ASCII
    assert b"r\\xfcn \\u2713" in header  # the folder name, escaped
    assert read_ply(out)["means"].shape[1] == 3


@pytest.fixture
def no_model_load(monkeypatch):
    """Fail the test if export gets as far as loading the model (the slow part comes after)."""
    import retinexgs.export.export as export_mod

    def refuse(*a, **k):
        raise AssertionError("export loaded the run before checking its --out")

    monkeypatch.setattr(export_mod, "load_run", refuse)


def test_export_under_a_file_fails_before_loading(run_with_val, tmp_path, capsys, no_model_load):
    (tmp_path / "afile").write_text("x")
    code, _, err = _cli(["export", "--run", run_with_val, "--out", tmp_path / "afile" / "sub" / "o.ply",
                         "--device", "cpu"], capsys)
    assert code == 2 and "Traceback" not in err, err
    assert "is a file, not a folder" in err and "afile" in err, err


def test_export_into_an_unwritable_folder_fails_before_loading(run_with_val, tmp_path, capsys, no_model_load,
                                                                monkeypatch):
    import tempfile

    locked = tmp_path / "locked"
    locked.mkdir()

    def denied(*a, dir=None, **k):
        if Path(dir) == locked:
            raise PermissionError(13, "Permission denied")
        return real(*a, dir=dir, **k)

    real = tempfile.mkstemp
    # tests run as root here, where chmod cannot make a folder unwritable: the write probe is refused instead
    monkeypatch.setattr(tempfile, "mkstemp", denied)
    code, _, err = _cli(["export", "--run", run_with_val, "--out", locked / "o.ply", "--device", "cpu"], capsys)
    assert code == 2 and "Traceback" not in err, err
    assert f"cannot write in {locked} (Permission denied)" in err, err
    assert not list(locked.iterdir())


# ---- 5. sfm --camera-model ---------------------------------------------------------------------------------

def test_sfm_unknown_camera_model_lists_the_accepted_ones(demo, tmp_path, capsys):
    photos = tmp_path / "photos"
    shutil.copytree(demo / "low", photos)
    code, _, err = _cli(["sfm", "--images", photos, "--camera-model", "FISHEYE_XYZ", "--quiet"], capsys)
    assert code == 2 and "Traceback" not in err, err
    assert "--camera-model 'FISHEYE_XYZ' is not supported" in err, err
    assert "SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV" in err, err
    # a model pycolmap knows but the scene loader cannot read back is refused as well, before any work
    code, _, err = _cli(["sfm", "--images", photos, "--camera-model", "OPENCV_FISHEYE", "--quiet"], capsys)
    assert code == 2 and "'OPENCV_FISHEYE' is not supported" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos"]


# ---- 3. decomposition cache shared by decompose and train; scene cache validated, never left partial -------

@pytest.fixture
def no_decomposition(monkeypatch):
    """Fail the test if anything is decomposed (train must find every entry in the cache)."""
    from retinexgs.retinex.base import Decomposer

    def refuse(self, image):
        raise AssertionError("train decomposed a view that decompose had cached")

    return lambda: monkeypatch.setattr(Decomposer, "decompose", refuse)


def _train(scene: Path, out: Path, extra=()) -> None:
    from retinexgs.train.runner import train_run

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        train_run(scene, out, ["demo"], TINY + list(extra), "cpu", progress=False, log=lambda s: None)
    finally:
        torch.set_num_threads(n)


@pytest.mark.parametrize("cache", [False, True])
def test_train_finds_what_decompose_cached_for_a_downscaled_scene(scene, tmp_path, capsys, no_decomposition,
                                                                   cache):
    flags = ["--set", "data.downscale=1.5"] + (["--cache", tmp_path / "caches"] if cache else [])
    code, out, err = _cli(["decompose", "--data", scene, "--method", "lime", "--quiet", *flags], capsys)
    assert code == 0, err
    assert "3 view(s) decomposed with lime: 3 computed" in out, out
    no_decomposition()
    extra = ["data.downscale=1.5"] + ([f"data.cache_dir={tmp_path / 'caches'}"] if cache else [])
    _train(scene, tmp_path / "run", extra)
    assert (tmp_path / "run" / "config.yaml").is_file()


def test_huge_downscale_is_refused_before_anything_is_written(scene, tmp_path, capsys):
    before = _tree(scene)
    code, _, err = _cli(["train", "--data", scene, "--out", tmp_path / "run", "--device", "cpu", "--set",
                         "data.downscale=1000"], capsys)
    assert code == 2 and "Traceback" not in err, err
    assert "downscale 1000 shrinks" in err and "to 1x1 pixels" in err and "at most 1.7" in err, err
    assert _tree(scene) == before and not (tmp_path / "run").exists()
    code, _, err = _cli(["decompose", "--data", scene, "--set", "data.downscale=1000", "--quiet"], capsys)
    assert code == 2 and "downscale 1000 shrinks" in err, err
    assert _tree(scene) == before


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def test_failed_load_leaves_no_partial_cache(scene):
    _truncate(scene / "low" / sorted(p.name for p in (scene / "low").iterdir())[1])
    with pytest.raises(UserError, match="cannot read image"):
        load_scene(scene, downscale=1.5)
    assert not (scene / "retinexgs_cache").exists()


def test_failed_load_adds_nothing_to_an_existing_cache(scene):
    load_scene(scene, downscale=1.5)
    before = _tree(scene / "retinexgs_cache")
    _truncate(scene / "low" / sorted(p.name for p in (scene / "low").iterdir())[1])
    with pytest.raises(UserError, match="cannot read image"):
        load_scene(scene, downscale=1.2)
    assert _tree(scene / "retinexgs_cache") == before


@pytest.mark.parametrize("command, blocked, hint", [
    (["train", "--out", "{tmp}/run", "--device", "cpu", "--set", "data.downscale=1.5"], "retinexgs_cache",
     "with --set data.cache_dir=DIR"),
    (["decompose", "--method", "lime", "--quiet", "--set", "data.downscale=1.5"], "retinexgs_cache", "with --cache DIR"),
    (["decompose", "--method", "lime", "--quiet"], "retinex_cache", "with --cache DIR"),
])
def test_unwritable_scene_names_the_cache_option_of_the_command(scene, tmp_path, capsys, command, blocked, hint):
    # Running as root, chmod cannot make the scene read-only: a file where the cache folder goes blocks it.
    (scene / blocked).write_text("in the way\n")
    argv = [a.format(tmp=tmp_path) for a in command]
    code, _, err = _cli([argv[0], "--data", scene, *argv[1:]], capsys)
    assert code == 2 and "Traceback" not in err, err
    assert str(scene / blocked) in err and hint in err and "pass cache_dir=" not in err, err


class _ReadOnly:
    """Makes every write, rename, delete and mkdir under ``root`` fail with EROFS while ``on``: tests run as
    root here, where chmod cannot make a folder read-only (a read-only copy or mount of a scene)."""

    def __init__(self, monkeypatch, root: Path):
        import errno
        import os
        import tempfile

        self.root, self.on = Path(root).resolve(), False

        def guard(real, arg_of):
            def wrapped(*a, **k):
                target = arg_of(a, k)
                if self.on and target is not None and (Path(target).resolve() == self.root
                                                       or self.root in Path(target).resolve().parents):
                    raise OSError(errno.EROFS, "Read-only file system", str(target))
                return real(*a, **k)
            return wrapped

        first = lambda a, k: a[0] if a else None  # noqa: E731
        for name in ("unlink", "mkdir", "rmdir", "replace", "rename"):
            monkeypatch.setattr(os, name, guard(getattr(os, name), first))
        for name in ("mkstemp", "mkdtemp", "TemporaryFile", "NamedTemporaryFile"):
            monkeypatch.setattr(tempfile, name, guard(getattr(tempfile, name), lambda a, k: k.get("dir")))


def test_read_only_scene_with_a_cache_is_read_and_a_needed_write_names_the_option(scene, tmp_path, capsys,
                                                                                  monkeypatch):
    from retinexgs.retinex.base import Decomposer

    code, _, err = _cli(["decompose", "--data", scene, "--method", "lime", "--quiet"], capsys)
    assert code == 0, err
    ro = _ReadOnly(monkeypatch, scene)
    ro.on = True
    before = _tree(scene)
    calls = []
    real = Decomposer.decompose
    monkeypatch.setattr(Decomposer, "decompose", lambda self, image: calls.append(1) or real(self, image))
    # every entry is there: decompose and train read them from the read-only scene and write nothing into it
    code, out, err = _cli(["decompose", "--data", scene, "--method", "lime", "--quiet"], capsys)
    assert code == 0 and "3 reused" in out, err
    _train(scene, tmp_path / "run")
    assert calls == [] and _tree(scene) == before
    # one entry missing: the write it needs fails with the command's option, no traceback
    ro.on = False
    sorted((scene / "retinex_cache").rglob("*.npz"))[0].unlink()
    ro.on = True
    before = _tree(scene)
    code, _, err = _cli(["decompose", "--data", scene, "--method", "lime", "--quiet"], capsys)
    assert code == 2 and "Traceback" not in err, err
    assert "cannot write the cache folder" in err and str(scene / "retinex_cache") in err, err
    assert "Read-only file system; put the caches elsewhere with --cache DIR" in err, err
    code, _, err = _cli(["train", "--data", scene, "--out", tmp_path / "run2", "--device", "cpu", "--config", "demo",
                         *[a for t in TINY for a in ("--set", t)]], capsys)
    assert code == 2 and "Traceback" not in err, err
    assert "Read-only file system; put the caches elsewhere with --set data.cache_dir=DIR" in err, err
    assert _tree(scene) == before and not (tmp_path / "run2").exists()


# ---- 1 and 6. COLMAP models through pycolmap: bad intrinsics named -----------------------------------------

def test_colmap_camera_with_zero_focal_length_is_refused(scene):
    from retinexgs.data.colmap import read_model

    model = scene / "colmap_sparse" / "0"
    lines = (model / "cameras.txt").read_text().splitlines()
    cam = [i for i, line in enumerate(lines) if line and not line.startswith("#")][0]
    fields = lines[cam].split()
    fields[4] = "0"  # fx of a PINHOLE camera: CAMERA_ID MODEL WIDTH HEIGHT fx fy cx cy
    lines[cam] = " ".join(fields)
    (model / "cameras.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(UserError, match=r"colmap_sparse/0 camera 1: focal length fx .* got 0\.0"):
        read_model(model)
    with pytest.raises(UserError, match=r"camera 1: focal length fx"):
        load_scene(scene)  # the transforms reader reads the model for its points, with the same check


def test_decompose_with_no_decomposer_configured_writes_nothing(scene, capsys):
    before = _tree(scene)
    code, _, err = _cli(["decompose", "--data", scene, "--set", "decomposer.method=none", "--set",
                         "data.downscale=1.5", "--quiet"], capsys)
    assert code == 2 and "decomposer.method is none: there is nothing to decompose" in err, err
    assert _tree(scene) == before


# ---- issue 36: render --frames/--fps, sfm's numeric options and a failed SfM --------------------------------

@pytest.mark.parametrize("args, says", [
    (["--frames", "100000000"], "--frames 100000000 is too many: at most 100000"),
    (["--frames", "0"], "--frames must be at least 1, got 0"),
    (["--fps", "inf"], "--fps must be a positive finite number of frames per second, got inf"),
    (["--fps", "nan"], "--fps must be a positive finite number of frames per second, got nan"),
    (["--fps", "0"], "--fps must be a positive finite number of frames per second, got 0"),
])
def test_render_frames_and_fps_are_refused_before_the_run_loads(tmp_path, capsys, monkeypatch, args, says):
    import retinexgs.export.renders as renders

    def refuse(*a, **k):  # 10^8 frames used to build a camera path silently for minutes after this
        raise AssertionError("render loaded the run before checking --frames/--fps")

    monkeypatch.setattr(renders, "load_run", refuse)
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("method: retinexgs\n")
    code, _, err = _cli(["render", "--run", run, "--path", "orbit", "--format", "png", "--device", "cpu", *args],
                        capsys)
    assert code == 2 and says in err and "Traceback" not in err, err
    assert sorted(p.name for p in run.iterdir()) == ["config.yaml"]


@pytest.mark.parametrize("args, says", [
    (["--max-features", "0"], "--max-features must be a positive number of SIFT features per photo"),
    (["--threads", "-5"], "--threads must be -1 (all CPU threads, the default) or a positive count, got -5"),
    (["--threads", "0"], "--threads must be -1"),
])
def test_sfm_numeric_options_are_refused_before_any_work(demo, tmp_path, capfd, args, says):
    photos = tmp_path / "photos"
    shutil.copytree(demo / "low", photos)
    before = _tree(tmp_path)
    code, _, err = _cli(["sfm", "--images", photos, "--enhance", "on", "--quiet", *args], capfd)
    assert code == 2 and says in err and "Traceback" not in err and "Check failed" not in err, err
    assert _tree(tmp_path) == before  # --threads -5 used to extract features first, leaving OUT/enhanced/


def _noise_photos(folder: Path, n: int = 3) -> None:
    """Dark photos of noise: nothing SfM can match."""
    folder.mkdir(parents=True)
    for i in range(n):
        pixels = (np.random.RandomState(i).rand(120, 160, 3) * 40).astype(np.uint8)
        Image.fromarray(pixels).save(folder / f"p{i}.jpg", quality=95)


@pytest.mark.parametrize("user_folder", [False, True])
def test_a_failed_sfm_removes_what_it_made_and_says_one_line(tmp_path, capfd, user_folder):
    """The brightened copies (PHOTOS/retinexgs_sfm/enhanced/) go, a folder the user had there stays, and
    COLMAP's glog ``E2026...`` line does not leak before the error (fd 2, so ``capfd``)."""
    photos = tmp_path / "photos"
    _noise_photos(photos)
    if user_folder:
        (photos / "retinexgs_sfm").mkdir()
        (photos / "retinexgs_sfm" / "notes.txt").write_text("mine\n")
    before = _tree(tmp_path)
    code, out, err = _cli(["sfm", "--images", photos, "--enhance", "on", "--quiet"], capfd)
    assert code == 2 and "Traceback" not in err, err
    assert err.strip().splitlines() == [f"retinexgs sfm: error: SfM could not build a model from the 3 photos in "
                                        f"{photos} (too few matching features); try brighter or more overlapping "
                                        f"photos"], err
    assert _tree(tmp_path) == before


# ---- issue 36, part C: scenes accepted silently, misleading messages -----------------------------------------

def _warnings(err: str) -> List[str]:
    return [line for line in err.splitlines() if line.startswith("warning: ")]


def test_one_training_view_is_refused_two_load(scene, capsys):
    _edit_json(scene / "transforms_train.json", lambda d: d.update(frames=d["frames"][:2]))
    assert len(load_scene(scene).train) == 2
    _edit_json(scene / "transforms_train.json", lambda d: d.update(frames=d["frames"][:1]))
    shutil.rmtree(scene / "retinexgs_cache", ignore_errors=True)
    with pytest.raises(UserError, match=r"has only 1 training view \(low/0000\.png\); a 3D reconstruction needs at "
                                        r"least 2 views"):
        load_scene(scene)
    assert not (scene / "retinexgs_cache").exists()


def test_duplicate_frame_warns_with_the_same_pose_and_is_refused_with_another(scene, capsys):
    _edit_json(scene / "transforms_train.json", lambda d: d["frames"].append(dict(d["frames"][0])))
    capsys.readouterr()
    assert len(load_scene(scene).train) == 4
    assert _warnings(capsys.readouterr().err) == [
        "warning: transforms_train.json frames 0 and 3 both list low/0000.png (same pose): the view counts twice in "
        "training; remove the duplicate frame"]

    def moved(d):
        d["frames"][3]["transform_matrix"] = d["frames"][1]["transform_matrix"]

    _edit_json(scene / "transforms_train.json", moved)
    with pytest.raises(UserError, match=r"transforms_train\.json frames 0 and 3 both list low/0000\.png with "
                                        r"different camera poses"):
        load_scene(scene)


def test_duplicate_file_by_another_spelling_is_found(scene, capsys):
    def again(d):  # the same file without its extension
        d["frames"].append(dict(d["frames"][1], file_path=d["frames"][1]["file_path"][:-4]))

    _edit_json(scene / "transforms_train.json", again)
    capsys.readouterr()
    load_scene(scene)
    assert "frames 1 and 3 both list low/0001.png" in capsys.readouterr().err


def test_test_views_that_are_training_views_warn_and_are_recorded(scene, tmp_path, capsys):
    train = json.loads((scene / "transforms_train.json").read_text())["frames"]

    def add(d):
        d["frames"].append(dict(train[1], file_path="high/" + Path(train[1]["file_path"]).name))

    _edit_json(scene / "transforms_test.json", add)
    capsys.readouterr()
    load_scene(scene)
    assert _warnings(capsys.readouterr().err) == [
        "warning: 1 of 2 test views are also training views (low/0001.png): the test metrics are not held-out "
        "(recorded as test_in_train in metrics.json); list them in one split only"]
    _train(scene, tmp_path / "run")
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["test_in_train"] == 1 and len(metrics["views"]) == 2


def test_held_out_metrics_record_no_test_in_train(run_with_val):
    assert "test_in_train" not in json.loads((run_with_val / "metrics.json").read_text())


def test_json_size_that_disagrees_with_the_images_warns_once(scene, capsys):
    before = load_scene(scene).train[0].fx
    _edit_json(scene / "transforms_train.json", lambda d: d.update(w=48, h=36))
    capsys.readouterr()
    s = load_scene(scene)
    assert _warnings(capsys.readouterr().err) == [
        "warning: the transforms JSON gives w x h = 48x36 but the images are 24x18 (3 views, e.g. low/0000.png): the "
        "intrinsics (focal length, principal point) are rescaled by 0.5 to fit the images"]
    assert s.train[0].fx == pytest.approx(before / 2)  # fl_x was given for 48 pixels: rescaled, as before


def test_a_consistent_scene_loads_without_warnings(scene, capsys):
    capsys.readouterr()
    load_scene(scene)
    assert _warnings(capsys.readouterr().err) == []


def test_demo_scene_without_test_views(tmp_path):
    out = make_demo_scene(tmp_path / "s", n_train=3, n_test=0, width=24, height=18, n_points=50)
    assert not (out / "transforms_test.json").exists()
    s = load_scene(out)
    assert len(s.train) == 3 and s.test == []


def test_side_by_side_pngs_name_their_panels(run_with_val):
    from retinexgs.evaluate.evaluate import LABEL_ROWS, to_uint8
    from retinexgs.run.folder import load_run

    metrics = json.loads((run_with_val / "metrics.json").read_text())
    n = metrics["panels"].count("|") + 1
    assert metrics["label_rows"] == LABEL_ROWS and n == 5
    (path,) = (run_with_val / "renders" / "test").glob("*.png")
    png = np.asarray(Image.open(path).convert("RGB"))
    w = png.shape[1] // n
    assert png.shape[0] == LABEL_ROWS + 18 and w == 24
    cells = [png[:LABEL_ROWS, i * w:(i + 1) * w] for i in range(n)]
    assert all(int(c.max()) > 128 for c in cells)  # white text over black in every panel
    assert len({c.tobytes() for c in cells}) == n  # five different names
    # the panels themselves are below the strip, untouched: the first is the dark input
    _, scene, _, _ = load_run(run_with_val, "cpu")
    assert np.array_equal(png[LABEL_ROWS:, :w], to_uint8(scene.test[0].image))


def test_duplicate_image_in_a_colmap_model_warns(scene, capsys):
    images = scene / "colmap_sparse" / "0" / "images.txt"
    first = next(line for line in images.read_text().splitlines() if line and not line.startswith("#"))
    images.write_text(images.read_text() + " ".join(["99"] + first.split()[1:]) + "\n\n")  # another id, same file
    capsys.readouterr()
    assert len(load_scene(scene, reader="colmap").train) == 4
    assert _warnings(capsys.readouterr().err) == [
        "warning: the train split lists low/0000.png twice (same pose): the view counts twice in training; remove "
        "the duplicate frame"]
