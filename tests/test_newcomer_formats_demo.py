"""Issue 62, items 4-7 and 8a: one list of readable photo types for every command (decompose read only
.jpg/.jpeg/.png); darken names a HEIC or raw photo's dark copy by what it holds; `demo --overwrite` refuses,
naming them, files the demo did not write; `eval` on a read-only run is one line; an all-black photo's error names
the user's file, not the loader's downscaled copy of it."""
from __future__ import annotations

import errno
import json
import os
import re
import tempfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from retinexgs import formats
from retinexgs.data import camera_raw, images
from retinexgs.demo.synthetic import make_demo_scene
from scenes import run_cli, tiny_trained_run

W, H = 40, 30


def _photo(seed: int) -> np.ndarray:
    """A 40x30 uint8 photo: a smooth ramp with some texture (never black)."""
    rng = np.random.default_rng(seed)
    ramp = np.linspace(40, 200, W)[None, :, None] * np.ones((H, 1, 3))
    return np.clip(ramp + rng.normal(0, 12, (H, W, 3)), 1, 255).astype(np.uint8)


def _save_heic(rgb: np.ndarray, path: Path) -> None:
    import pillow_heif

    pillow_heif.register_heif_opener()
    Image.fromarray(rgb).save(path, format="HEIF")


def _save_dng(rgb: np.ndarray, path: Path) -> None:
    from retinexgs.data.raw_sim import RawCamera, capture_mosaic, write_raw_view
    from retinexgs.data.sensor import SensorModel

    cam, model = RawCamera(), SensorModel(full_well=None, read_noise=0.0)
    write_raw_view(path, capture_mosaic(rgb.astype(np.float32) / 255, model, cam, 0.5, None), cam, model, 0.5)


def _every_type_folder(folder: Path) -> Path:
    """A plain folder with one photo of each family: PNG, TIFF, WebP, HEIC, camera raw (and a note)."""
    folder.mkdir(parents=True)
    Image.fromarray(_photo(0)).save(folder / "a.png")
    Image.fromarray(_photo(1)).save(folder / "b.tif")
    Image.fromarray(_photo(2)).save(folder / "c.webp", quality=90)
    _save_heic(_photo(3), folder / "d.HEIC")
    _save_dng(_photo(4), folder / "e.dng")
    (folder / "notes.txt").write_text("not a photo")
    return folder


def _one_line(code: int, err: str, *words: str) -> str:
    assert code == 2, err
    assert "Traceback" not in err, err
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("retinexgs")]
    assert len(lines) == 1, err
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


# ---- 4: one list of readable types ----------------------------------------------------------------------------

def test_the_readers_and_the_raw_module_share_the_one_list():
    assert images.IMAGE_EXTENSIONS is formats.IMAGE_EXTENSIONS
    assert camera_raw.BAYER_RAW_EXTENSIONS is formats.BAYER_RAW_EXTENSIONS
    assert images.HEIF_EXTENSIONS is formats.HEIF_EXTENSIONS
    assert {".heic", ".tif", ".webp", ".dng", ".cr2"} <= set(formats.IMAGE_EXTENSIONS)


def test_decompose_reads_every_type_train_reads(tmp_path, capsys):
    """decompose read only .jpg/.jpeg/.png in a plain folder: TIFF, WebP, HEIC and raw gave "no images"."""
    from retinexgs.commands.decompose import list_scene_images

    folder = _every_type_folder(tmp_path / "photos")
    assert [p.name for p in list_scene_images(folder)] == ["a.png", "b.tif", "c.webp", "d.HEIC", "e.dng"]
    code, out, err = run_cli(["decompose", "--data", folder, "--method", "lime", "--device", "cpu", "--quiet"],
                             capsys)
    assert code == 0, err
    assert "5 view(s) decomposed with lime: 5 computed" in out, out


def test_a_folder_of_only_heic_is_decomposed_not_no_images(tmp_path, capsys):
    folder = tmp_path / "phone"
    folder.mkdir()
    for i in range(2):
        _save_heic(_photo(i), folder / f"IMG_{i}.HEIC")
    code, out, err = run_cli(["decompose", "--data", folder, "--method", "lime", "--device", "cpu", "--quiet"],
                             capsys)
    assert code == 0, err
    assert "2 view(s) decomposed" in out


def test_decompose_without_photos_names_the_one_list(tmp_path, capsys):
    folder = tmp_path / "empty"
    folder.mkdir()
    (folder / "x.txt").write_text("no photo")
    code, _, err = run_cli(["decompose", "--data", folder], capsys)
    _one_line(code, err, f"no photos in {folder}", formats.readable_formats(), ".txt")


@pytest.mark.parametrize("command", ["train", "decompose", "sfm", "darken"])
def test_the_help_texts_name_the_one_list(command, capsys):
    code, out, _ = run_cli([command, "--help"], capsys)
    assert code == 0
    flat = re.sub(r"\s+", " ", out)
    assert formats.readable_formats() in flat, flat
    assert ".jpg/.jpeg/.png" not in flat


# ---- 5: darken writes what the extension says -----------------------------------------------------------------

def _darken(src: Path, out: Path, capsys, *extra):
    return run_cli(["darken", "--data", src, "--out", out, "--full-well", "0", "--quiet", *extra], capsys)


def test_darken_names_a_heic_or_raw_photos_dark_copy_by_its_content(tmp_path, capsys):
    """PNG bytes under .HEIC / .dng names: no command read them back."""
    src = _every_type_folder(tmp_path / "src")
    out = tmp_path / "dark"
    code, _, err = _darken(src, out, capsys)
    assert code == 0, err
    written = sorted(p.name for p in out.iterdir() if p.name != "sensor.json")
    assert written == ["a.png", "b.tif", "c.webp", "d.jpg", "e.jpg"], written
    kinds = {".png": "PNG", ".tif": "TIFF", ".webp": "WEBP", ".jpg": "JPEG"}
    for name in written:
        with Image.open(out / name) as im:
            assert im.format == kinds[Path(name).suffix], name
        assert images.read_image_float(out / name).shape == (H, W, 3)
    exposures = json.loads((out / "sensor.json").read_text())["view_exposures"]
    assert sorted(exposures) == written
    code, out_text, err = run_cli(["decompose", "--data", out, "--method", "lime", "--device", "cpu", "--quiet"],
                                  capsys)
    assert code == 0 and "5 view(s) decomposed" in out_text, err


def test_darken_at_jpeg_quality_0_writes_png(tmp_path, capsys):
    src = tmp_path / "src"
    src.mkdir()
    _save_heic(_photo(0), src / "IMG_1.heic")
    code, _, err = _darken(src, tmp_path / "dark", capsys, "--jpeg-quality", "0")
    assert code == 0, err
    with Image.open(tmp_path / "dark" / "IMG_1.png") as im:
        assert im.format == "PNG"


def test_darken_refuses_two_photos_that_would_share_a_name(tmp_path, capsys):
    src = tmp_path / "src"
    src.mkdir()
    _save_heic(_photo(0), src / "a.HEIC")
    Image.fromarray(_photo(1)).save(src / "a.jpg")
    code, _, err = _darken(src, tmp_path / "dark", capsys)
    _one_line(code, err, "a.HEIC", "a.jpg", "would both be written as a.jpg")
    assert not (tmp_path / "dark").exists()


def test_darken_refuses_a_lom_scene_whose_high_photos_it_cannot_write(tmp_path, capsys):
    """low/ and high/ pair by file name: renaming low/x.HEIC to low/x.jpg would break the pairing."""
    src = tmp_path / "scene"
    (src / "high").mkdir(parents=True)
    _save_heic(_photo(0), src / "high" / "x.HEIC")
    code, _, err = _darken(src, tmp_path / "dark", capsys)
    _one_line(code, err, "x.HEIC", "pair by file name", "--raw")
    assert not (tmp_path / "dark").exists()


# ---- 6: demo --overwrite keeps the user's files ---------------------------------------------------------------

@pytest.fixture()
def fake_demo(monkeypatch):
    """The demo with its scene and training replaced by two small writers (what they wrote: scene/a.png,
    run/metrics.json, run/checkpoints/c.pt)."""
    import retinexgs.demo.synthetic as synthetic
    import retinexgs.train.runner as runner

    def fake_scene(folder):
        folder.mkdir(parents=True)
        (folder / "a.png").write_bytes(b"scene")
        return folder

    def fake_train(scene, run, *a, **k):
        (run / "checkpoints").mkdir(parents=True)
        (run / "metrics.json").write_text("{}")
        (run / "checkpoints" / "c.pt").write_bytes(b"ckpt")
        return None

    monkeypatch.setattr(synthetic, "make_demo_scene", fake_scene)
    monkeypatch.setattr(runner, "train_run", fake_train)


def _demo(out: Path, capsys, *extra):
    return run_cli(["demo", "--out", out, "--device", "cpu", "--quiet", *extra], capsys)


def test_demo_overwrite_refuses_naming_the_users_files_in_run_and_scene(tmp_path, fake_demo, capsys):
    out = tmp_path / "retinexgs-demo"
    code, _, err = _demo(out, capsys)
    assert code == 0, err
    (out / "run" / "notes.txt").write_text("my notes")
    (out / "scene" / "export").mkdir()
    (out / "scene" / "export" / "fox.ply").write_bytes(b"ply")
    code, _, err = _demo(out, capsys, "--overwrite")
    _one_line(code, err, "2 file(s)", "run/notes.txt", "scene/export/fox.ply")
    assert (out / "run" / "notes.txt").read_text() == "my notes"
    assert (out / "scene" / "export" / "fox.ply").read_bytes() == b"ply"
    assert (out / "run" / "checkpoints" / "c.pt").is_file()  # nothing deleted either


def test_demo_overwrite_replaces_what_the_demo_wrote(tmp_path, fake_demo, capsys):
    out = tmp_path / "retinexgs-demo"
    assert _demo(out, capsys)[0] == 0
    (out / "run" / "checkpoints" / "c.pt").write_bytes(b"old")  # the demo's own file, changed: still its own
    (out / "notes.txt").write_text("beside the demo")
    code, said, err = _demo(out, capsys, "--overwrite")
    assert code == 0, err
    assert (out / "run" / "checkpoints" / "c.pt").read_bytes() == b"ckpt"
    assert (out / "notes.txt").read_text() == "beside the demo"
    assert "kept: notes.txt" in said, said


def test_demo_overwrite_without_a_record_of_its_files_refuses(tmp_path, capsys):
    """A demo killed before it recorded its files (or from before the record): yours and its cannot be told
    apart."""
    out = tmp_path / "d"
    (out / "run").mkdir(parents=True)
    (out / "run" / "mine.txt").write_text("x")
    (out / ".retinexgs-demo").write_text("made by `retinexgs demo`\n")
    code, _, err = _demo(out, capsys, "--overwrite")
    _one_line(code, err, "did not record the files it wrote")
    assert (out / "run" / "mine.txt").is_file()


# ---- 7: eval on a read-only run -------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    return tiny_trained_run(tmp_path_factory.mktemp("eval_ro"))[1]


def _inside(path, folder: Path) -> bool:
    return path is not None and Path(path).resolve().is_relative_to(folder.resolve())


def test_eval_on_a_read_only_run_is_one_line(trained, monkeypatch, capsys):
    """As root chmod does not stop a write, so the read-only file system is simulated: every temporary file
    (the write probe's and atomic_write's) in the run folder fails with EROFS."""
    real = tempfile.mkstemp

    def read_only(*a, **k):
        if _inside(k.get("dir"), trained):
            raise OSError(errno.EROFS, "Read-only file system")
        return real(*a, **k)

    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    before = (trained / "metrics.json").read_bytes()
    code, _, err = run_cli(["eval", "--run", trained, "--device", "cpu"], capsys)
    _one_line(code, err, f"--run {trained}", "Read-only file system", "metrics.json")
    assert (trained / "metrics.json").read_bytes() == before


def test_eval_whose_write_is_refused_late_is_one_line(trained, monkeypatch, capsys):
    """A write refused after the up-front check (renders/test/ made read-only: os.replace into it fails)."""
    real = os.replace

    def refuse(src, dst, *a, **k):
        if _inside(dst, trained / "renders"):
            raise PermissionError(errno.EACCES, "Permission denied", str(dst))
        return real(src, dst, *a, **k)

    monkeypatch.setattr(os, "replace", refuse)
    code, _, err = run_cli(["eval", "--run", trained, "--device", "cpu"], capsys)
    _one_line(code, err, "Permission denied", str(trained / "renders" / "test"), "writable")
    assert not [p for p in trained.rglob(".tmp-*")]


# ---- 8a: an all-black photo is named as the user knows it -----------------------------------------------------

def test_an_all_black_photo_names_the_users_file_not_the_cache_copy(tmp_path, capsys):
    """At data.downscale=2 the decomposer sees the loader's copy, retinexgs_cache/...-<hash>.png."""
    scene = make_demo_scene(tmp_path / "scene", n_train=3, n_test=1, width=48, height=36, n_points=100)
    black = scene / "low" / "0000.png"
    Image.fromarray(np.zeros((36, 48, 3), np.uint8)).save(black)
    code, _, err = run_cli(["decompose", "--data", scene, "--method", "lime", "--device", "cpu", "--quiet",
                            "--set", "data.downscale=2"], capsys)
    line = _one_line(code, err, f"cannot decompose {black}:", "all zero (black)")
    assert "cache" not in line, line
