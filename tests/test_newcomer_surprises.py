"""Issue 62, item 9: small surprises a newcomer met, one test (or a few) each.

a. a RAW + JPEG pair whose raw file drops an odd row keeps the JPEG's camera, cropped (not rescaled 1 x 0.97);
b. checkpoints get the umask's permissions like every other output (not mkstemp's 0600);
c. ``view --help`` names the white-balance controls;
d. ``render --out o.exr`` (a folder of files) is refused instead of making a folder ``o.exr``;
e. ``--white-balance gains:`` is bounded, as temperatures are;
f. a failed write (a full disk) removes the empty folders it made, never the user's;
g. GoPro ``.GPR`` raw files are named and explained in one line;
h. ``retinexgs --version``;
i. ``retinexgs bench ...`` dispatches to ``python -m retinexgs.bench``.

Fixtures are made here (tiny demo scenes, DNGs written by retinexgs.data.dng); never the shared data.
"""
from __future__ import annotations

import errno
import importlib.metadata
import io
import os
import re
import shutil
import stat
from pathlib import Path

import numpy as np
import pytest
import torch

import retinexgs
from retinexgs.data.camera import Intrinsics
from retinexgs.data.dng import write_dng
from retinexgs.errors import UserError
from scenes import TINY_RUN, run_cli, tiny_trained_run

REPO = Path(__file__).resolve().parent.parent
FULL = OSError(errno.ENOSPC, "No space left on device")


def _one_line_error(code: int, err: str, *words: str) -> str:
    assert code == 2, err
    assert "Traceback" not in err, err
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("retinexgs")]
    assert len(lines) == 1, err
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


def _fail_with(exc):
    def fail(*a, **k):
        f = next((x for x in a if isinstance(x, io.IOBase)), None)
        if f is not None:
            f.write(b"partial bytes")  # some bytes reach the temporary file first
        raise exc
    return fail


def _mosaic(h: int = 36, w: int = 48, seed: int = 0) -> np.ndarray:
    return (np.random.default_rng(seed).random((h, w)) * 4000 + 100).astype(np.uint16)


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """A run trained for 3 steps on a 24x18 demo scene."""
    _, run = tiny_trained_run(tmp_path_factory.mktemp("surprises"), TINY_RUN)
    return run


# ---- a. RAW + JPEG: one camera model for both views --------------------------------------------------------------

def test_a_raw_view_whose_camera_is_one_row_taller_is_cropped_not_rescaled(tmp_path):
    """The camera of a RAW + JPEG pair comes from the JPEG (SfM on the JPEGs): 48x37 for a raw file read as 48x36
    (its odd last row dropped). The view keeps the focal lengths and centre (the top-left crop), as a raw LOM view
    does against its truth; a rescale would give fy x 36/37 and fx x 1: two camera models for one photo."""
    from retinexgs.data.declared import DeclaredView
    from retinexgs.data.load import _fit_camera

    dng = write_dng(tmp_path / "0000.dng", _mosaic(36, 48))
    jpeg_camera = Intrinsics(48, 37, 50.0, 50.0, 24.0, 18.5)
    fitted = _fit_camera(DeclaredView("0000", dng, jpeg_camera, np.eye(4)))
    assert (fitted.width, fitted.height) == (48, 36)
    assert (fitted.fx, fitted.fy, fitted.cx, fitted.cy) == (50.0, 50.0, 24.0, 18.5)
    for cam in (Intrinsics(49, 36, 50.0, 50.0, 24.5, 18.0), Intrinsics(49, 37, 50.0, 50.0, 24.5, 18.5)):
        fitted = _fit_camera(DeclaredView("0000", dng, cam, np.eye(4)))  # an odd column, or both
        assert (fitted.width, fitted.height, fitted.fx, fitted.fy) == (48, 36, 50.0, 50.0)
    # a camera of another size is still rescaled, uniformly (a JPEG at half the raw's size)
    fitted = _fit_camera(DeclaredView("0000", dng, Intrinsics(24, 18, 25.0, 25.0, 12.0, 9.0), np.eye(4)))
    assert (fitted.width, fitted.height, fitted.fx, fitted.fy, fitted.cx) == (48, 36, 50.0, 50.0, 24.0)


def test_a_raw_plus_jpeg_folder_of_odd_height_loads_with_the_jpegs_camera(tmp_path, monkeypatch, capsys):
    """End to end: ``darken --raw`` of a 48x35 scene gives 48x35 JPEGs and DNGs read as 48x34; the folder of
    pairs is posed from the JPEGs (the demo's COLMAP model stands in for SfM) and every raw view keeps the JPEG
    camera's focal lengths and centre, with no "rescaled" warning."""
    from retinexgs.cli import main
    from retinexgs.data import load, sfm
    from retinexgs.data.colmap import read_model
    from retinexgs.demo.synthetic import make_demo_scene

    src = make_demo_scene(tmp_path / "src", n_train=3, n_test=1, width=48, height=35, n_points=200)
    assert main(["darken", "--data", str(src), "--out", str(tmp_path / "night"), "--raw", "--quiet"]) == 0
    night = tmp_path / "night"
    folder = tmp_path / "capture"
    folder.mkdir()
    for p in sorted((night / "raw" / "low").glob("*.dng")):
        shutil.copy2(p, folder / p.name)
        shutil.copy2(night / "jpeg" / "low" / (p.stem + ".png"), folder / (p.stem + ".png"))
    model_dir = night / "raw" / "colmap_sparse" / "0"  # the demo's model, naming the NNNN.png photos (48x35)
    monkeypatch.setattr(load, "run_sfm", lambda image_dir, out, **kw: sfm.SfmResult(model_dir, Path(image_dir), 4,
                                                                                     [], 0, 0.0, False))
    (jpeg_cam,) = set(read_model(model_dir).cameras.values())  # one camera, of the JPEGs' size
    assert (jpeg_cam.width, jpeg_cam.height) == (48, 35)
    capsys.readouterr()
    scene = load.load_scene(folder, reader="sfm", cache_dir=tmp_path / "cache")
    assert "rescaled" not in capsys.readouterr().err
    views = scene.train + scene.test
    assert len(views) == 4 and all(v.image_path.suffix == ".dng" for v in views)
    for v in views:
        assert (v.width, v.height) == (48, 34)
        assert (v.fx, v.fy, v.cx, v.cy) == (jpeg_cam.fx, jpeg_cam.fy, jpeg_cam.cx, jpeg_cam.cy)


# ---- b. checkpoints follow the umask -------------------------------------------------------------------------------

@pytest.mark.parametrize("umask", [0o022, 0o002, 0o077])
def test_checkpoints_get_the_umasks_permissions_like_every_other_output(tmp_path, umask):
    from retinexgs.fileio import atomic_write_text
    from retinexgs.run.checkpoint import save_checkpoint

    old = os.umask(umask)
    try:
        ckpt = save_checkpoint(tmp_path, 1, {"step": 1, "model": {"w": torch.ones(2)}})
        other = atomic_write_text(tmp_path / "config.yaml", "x: 1\n")
    finally:
        os.umask(old)
    want = 0o666 & ~umask
    assert stat.S_IMODE(ckpt.stat().st_mode) == want
    assert stat.S_IMODE(other.stat().st_mode) == want


# ---- c. view --help ------------------------------------------------------------------------------------------------

def test_view_help_names_the_white_balance_controls():
    import argparse

    from retinexgs.cli import build_parser

    subs = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    text = " ".join(subs.choices["view"].format_help().split())
    for words in ("white balance", "temperature/tint", "Pick a neutral", "render --white-balance"):
        assert words in text, (words, text)


# ---- d. render --out with a file's name for a folder of files -------------------------------------------------------

def test_a_path_render_to_exr_refuses_an_out_named_like_a_file(run, tmp_path, capsys):
    out = tmp_path / "o.exr"
    code, _, err = run_cli(["render", "--run", run, "--path", "orbit", "--format", "exr", "--out", out,
                            "--device", "cpu", "--quiet"], capsys)
    _one_line_error(code, err, f"--out {out} names an EXR file", "the path's frames render to one file each in a "
                    "folder (OUT/<map>/<name>.exr)", f"--out {tmp_path / 'o'})")
    assert not out.exists() and list(tmp_path.iterdir()) == []
    # the views to PNG, and a path video into a "folder" named like a PNG: refused alike
    code, _, err = run_cli(["render", "--run", run, "--out", tmp_path / "v.png", "--device", "cpu", "--quiet"], capsys)
    _one_line_error(code, err, "names a PNG file", "the test views render to one file each")
    code, _, err = run_cli(["render", "--run", run, "--path", "orbit", "--out", tmp_path / "v.png", "--device", "cpu",
                            "--quiet"], capsys)
    _one_line_error(code, err, "names a PNG file", "path video is one MP4", "path_orbit.mp4")
    assert list(tmp_path.iterdir()) == []


def test_an_existing_folder_named_like_a_file_is_still_written_into(run, tmp_path, capsys):
    out = tmp_path / "frames.exr"
    out.mkdir()  # the user's own folder: its name is theirs to choose
    code, _, err = run_cli(["render", "--run", run, "--path", "orbit", "--frames", "2", "--format", "exr", "--out",
                            out, "--device", "cpu", "--quiet"], capsys)
    assert code == 0, err
    assert len(list((out / "enhanced").glob("*.exr"))) == 2


# ---- e. white-balance gains are bounded --------------------------------------------------------------------------

def test_white_balance_gains_are_bounded_as_temperatures_are():
    from retinexgs.model.white_balance import (KELVIN_RANGE, MAX_GAIN_RATIO, TINT_RANGE, neutral_gains,
                                               parse_white_balance, temperature_matrix)

    for spec in ("gains:1e9,1,1", "gains:1,1,1e9", "gains:1,1,0.001", "gains:1,600,1"):
        with pytest.raises(UserError, match=r"gain ratio (R|B)/G = .* lies outside 1/512\.\.512"):
            parse_white_balance(spec)
    assert parse_white_balance("gains:512,1,1").gains == (512.0, 1.0, 1.0)
    assert parse_white_balance("gains:1,1,0.001953125").gains[2] == 1 / 512
    assert parse_white_balance("gains:1e9,1e9,1e9").gains == (1.0, 1.0, 1.0)  # brightness is --exposure's
    # The bound's reason: the widest temperature (and tint) reaches a neutral's B/G of about 418, within it.
    widest = max(abs(float((temperature_matrix(k, t) @ np.ones(3))[i]))
                 for k in KELVIN_RANGE for t in TINT_RANGE for i in (0, 2))
    assert 400 < widest <= MAX_GAIN_RATIO
    with pytest.raises(UserError, match="not a neutral"):  # a picked pixel this coloured is no neutral either
        neutral_gains([0.001, 0.9, 0.5], "pick:0000,1,1")


def test_render_refuses_an_unbounded_gain_in_one_line(run, tmp_path, capsys):
    code, _, err = run_cli(["render", "--run", run, "--white-balance", "gains:1e9,1,1", "--out", tmp_path / "r",
                            "--device", "cpu", "--quiet"], capsys)
    _one_line_error(code, err, "gains:1e9,1,1", "R/G = 1e+09", "512")
    assert not (tmp_path / "r").exists()


# ---- f. a failed write leaves no empty folders of its own --------------------------------------------------------

def test_a_failed_write_removes_the_folders_it_made_and_keeps_the_users(tmp_path):
    from retinexgs.fileio import atomic_write

    with pytest.raises(UserError, match="no space left"):
        atomic_write(tmp_path / "new" / "a" / "b.json", _fail_with(FULL))
    assert list(tmp_path.iterdir()) == []
    mine = tmp_path / "mine"
    mine.mkdir()  # the user's empty folder
    with pytest.raises(UserError, match="no space left"):
        atomic_write(mine / "sub" / "f.json", _fail_with(FULL))
    assert mine.is_dir() and list(mine.iterdir()) == []
    (mine / "sub").mkdir()
    (mine / "sub" / "keep.txt").write_text("x")  # a folder with a file in it is never removed
    with pytest.raises(UserError, match="no space left"):
        atomic_write(mine / "sub" / "deeper" / "f.json", _fail_with(FULL))
    assert sorted(p.name for p in mine.rglob("*")) == ["keep.txt", "sub"]


def test_a_failed_first_checkpoint_leaves_no_empty_checkpoints_folder(tmp_path, monkeypatch):
    from retinexgs.run.checkpoint import save_checkpoint

    run_dir = tmp_path / "run"
    run_dir.mkdir()
    monkeypatch.setattr(torch, "save", _fail_with(FULL))
    with pytest.raises(UserError, match="no space left"):
        save_checkpoint(run_dir, 1, {"step": 1, "model": {}})
    assert run_dir.is_dir() and list(run_dir.iterdir()) == []


def test_renders_and_exports_on_a_full_disk_leave_no_empty_folders(run, tmp_path, capsys, monkeypatch):
    import imageio
    import plyfile
    from PIL import Image

    monkeypatch.setattr(Image.Image, "save", _fail_with(FULL))
    code, _, err = run_cli(["render", "--run", run, "--out", tmp_path / "new" / "renders", "--device", "cpu",
                            "--quiet"], capsys)
    assert code == 2 and "no space left" in err, err
    mine = tmp_path / "mine"
    mine.mkdir()  # an --out the user made: kept, even empty
    code, _, err = run_cli(["render", "--run", run, "--out", mine, "--device", "cpu", "--quiet"], capsys)
    assert code == 2 and "no space left" in err, err
    monkeypatch.setattr(plyfile.PlyData, "write", _fail_with(FULL))
    code, _, err = run_cli(["export", "--run", run, "--out", tmp_path / "new" / "a" / "m.ply", "--device", "cpu",
                            "--quiet"], capsys)
    assert code == 2 and "no space left" in err, err

    class FullDisk:
        def append_data(self, frame):
            raise OSError(errno.EPIPE, "Broken pipe: av_interleaved_write_frame(): No space left on device")

        def close(self):
            pass

    monkeypatch.setattr(imageio, "get_writer", lambda *a, **k: FullDisk())
    code, _, err = run_cli(["render", "--run", run, "--path", "orbit", "--frames", "2", "--out",
                            tmp_path / "new" / "v" / "o.mp4", "--device", "cpu", "--quiet"], capsys)
    assert code == 2 and "no space left" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine"] and list(mine.iterdir()) == []


def test_a_failed_command_keeps_what_it_wrote_and_what_existed(tmp_path):
    """The command-level clean-up removes only folders that did not exist before and hold nothing."""
    from retinexgs.fileio import missing_folders, remove_empty_trees

    existing = tmp_path / "existing"
    existing.mkdir()
    roots = missing_folders([existing / "a" / "b", tmp_path / "c" / "d.ply", existing, tmp_path / "e"])
    assert roots == [existing / "a", tmp_path / "c", tmp_path / "e"]
    (existing / "a" / "b" / "empty").mkdir(parents=True)
    (tmp_path / "c" / "x").mkdir(parents=True)
    (tmp_path / "c" / "x" / "config.yaml").write_text("kept")
    (tmp_path / "c" / "y").mkdir()
    removed = remove_empty_trees(roots)
    assert not (existing / "a").exists() and existing.is_dir()
    assert (tmp_path / "c" / "x" / "config.yaml").read_text() == "kept" and not (tmp_path / "c" / "y").exists()
    assert set(removed) == {existing / "a" / "b" / "empty", existing / "a" / "b", existing / "a", tmp_path / "c" / "y"}


# ---- g. GoPro GPR -------------------------------------------------------------------------------------------------

def _vc5(path: Path) -> Path:
    """A DNG whose raw image says TIFF compression 9 (VC-5, as GoPro's GPR files do)."""
    data = path.read_bytes()
    entry = b"\x03\x01\x03\x00\x01\x00\x00\x00"  # tag 259 (Compression), SHORT, count 1
    assert data.count(entry + b"\x01\x00") == 1
    path.write_bytes(data.replace(entry + b"\x01\x00", entry + b"\x09\x00"))
    return path


def test_a_folder_of_gpr_files_says_what_gpr_is_and_how_to_convert_it(tmp_path, capsys):
    folder = tmp_path / "gopro"
    folder.mkdir()
    for i in range(3):
        write_dng(folder / f"GOPR{i:04d}.GPR", _mosaic(seed=i))
    code, _, err = run_cli(["decompose", "--data", folder, "--method", "lime", "--quiet"], capsys)
    _one_line_error(code, err, ".gpr", "GoPro GPR is a DNG variant compressed with VC-5", "LibRaw", "gpr_tools")


def test_a_gpr_file_named_by_a_scene_is_refused_in_one_line_not_read_by_pillow(tmp_path):
    from retinexgs.data.camera_raw import read_header, read_raw
    from retinexgs.data.images import image_size, read_image_float

    gpr = write_dng(tmp_path / "GOPR0001.GPR", _mosaic())
    for reader in (read_raw, read_header, image_size, read_image_float):
        with pytest.raises(UserError, match=r"GOPR0001\.GPR: GoPro GPR .* gpr_tools"):
            reader(gpr)
    renamed = _vc5(write_dng(tmp_path / "GOPR0002.dng", _mosaic()))  # a GPR renamed .dng: told by its compression
    with pytest.raises(UserError, match=r"GOPR0002\.dng: GoPro GPR .* convert it to a plain DNG"):
        read_raw(renamed)
    assert read_raw(write_dng(tmp_path / "plain.dng", _mosaic())).shape == (36, 48)  # a plain DNG still reads


# ---- h. --version ----------------------------------------------------------------------------------------------

def test_version_prints_the_package_version_from_its_one_source(capsys):
    code, out, err = run_cli(["--version"], capsys)
    assert code == 0, err
    assert out.strip() == f"retinexgs {retinexgs.__version__}"
    assert importlib.metadata.version("retinexgs") == retinexgs.__version__
    setup = (REPO / "setup.py").read_text()
    assert re.search(r"""version\s*=\s*['"]""", setup) is None  # setup.py reads retinexgs/__init__.py instead
    assert re.search(r"version\s*=\s*_version\(\)", setup)


# ---- i. retinexgs bench --------------------------------------------------------------------------------------------

def test_bench_help_lists_the_benchmarks(capsys):
    from retinexgs.bench.__main__ import BENCHES

    code, out, err = run_cli(["bench", "--help"], capsys)
    assert code == 0, err
    assert out.startswith("usage: retinexgs bench {") and "retinexgs bench NAME --help" in out
    entries = {ln.split()[0] for ln in out.split("benchmarks:\n", 1)[1].splitlines() if ln[2:3] != " "}
    assert entries == set(BENCHES)
    code, out, err = run_cli(["--help"], capsys)
    assert re.search(r"^\s+bench\s+run a benchmark", out, re.M), out


def test_bench_dispatches_to_the_same_benchmark_with_its_options(capsys, monkeypatch):
    from retinexgs.bench import __main__ as dispatcher

    seen = {}

    class Fake:
        @staticmethod
        def main(argv):
            seen["argv"] = list(argv)
            return 3

    monkeypatch.setattr(dispatcher, "_load", lambda name: seen.setdefault("name", name) and Fake)
    code, _, err = run_cli(["bench", "fps", "--run", "r", "--help", "-x"], capsys)
    assert code == 3, err
    assert seen == {"name": "fps", "argv": ["--run", "r", "--help", "-x"]}
    code, _, err = run_cli(["bench", "nosuch"], capsys)
    assert code == 2 and "retinexgs bench: error: unknown benchmark 'nosuch'" in err, err
    code, _, err = run_cli(["bench"], capsys)
    assert code == 2 and "choose one of" in err, err
