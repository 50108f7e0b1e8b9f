"""Issue 62 (items 1 and part of 8): ``retinexgs noise`` on camera raw files and on all-black photos.

Fixtures are made here: a 48x36 demo scene darkened with ``darken --raw`` (DNGs with a NoiseProfile), DNGs written by
``write_dng`` (without a profile, or all at the black level) and all-black JPEG/PNG photos. No dev data is used.
"""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import PIL.Image
import pytest
from PIL import Image

from retinexgs.data.camera_raw import is_raw_path
from retinexgs.data.dng import write_dng
from retinexgs.data.raw_noise import scene_noise
from retinexgs.demo.synthetic import make_demo_scene
from scenes import run_cli

W, H = 48, 36
CM = np.array([[0.6461, -0.1164, -0.0857], [-0.3825, 1.1597, 0.2534], [-0.0416, 0.1540, 0.6039]])


@pytest.fixture(scope="module")
def night(tmp_path_factory) -> Path:
    """``darken --raw`` of a 48x36 demo scene (3 train, 1 test): NIGHT/raw/low/*.dng, each with a NoiseProfile."""
    base = tmp_path_factory.mktemp("noise_raw")
    src = make_demo_scene(base / "src", n_train=3, n_test=1, width=W, height=H, n_points=200)
    from retinexgs.cli import main
    assert main(["darken", "--data", str(src), "--out", str(base / "night"), "--raw", "--quiet"]) == 0
    return base / "night"


@pytest.fixture
def no_pil_on_raw(monkeypatch):
    """Fail the test when anything opens a camera raw file with PIL (PIL cannot read a DNG or CRW, and reads a
    NEF as its TIFF preview)."""
    real = PIL.Image.open

    def guarded(fp, *args, **kwargs):
        if isinstance(fp, (str, Path)) and is_raw_path(fp):
            raise AssertionError(f"PIL opened the raw file {fp}")
        return real(fp, *args, **kwargs)

    monkeypatch.setattr(PIL.Image, "open", guarded)


def _channel_lines(out: str):
    """{channel: (full well, a, b)} from the R/G/B lines ``noise`` prints."""
    got = {}
    for line in out.splitlines():
        line = line.strip()
        if line[:2] in ("R:", "G:", "B:") and "full well" in line:
            fw = line.split("full well ")[1].split(" e-")[0]
            a = float(line.split("a=")[1].split(",")[0])
            b = float(line.split("b=")[1])
            got[line[0]] = (float(fw), a, b)
    return got


def _one_line_error(code: int, err: str, *words: str) -> str:
    assert code == 2, err
    assert "Traceback" not in err, err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, err
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


def _dng(path: Path, mosaic: np.ndarray, **kw) -> Path:
    args = dict(cfa="RGGB", black_level=512, white_level=16383, as_shot_neutral=(0.5, 1.0, 0.625),
                color_matrix1=CM, exposure_time=1 / 30, iso=1600, f_number=2.8)
    args.update(kw)
    return write_dng(path, mosaic, **args)


# ---- item 1: raw files ----------------------------------------------------------------------------------------

def test_noise_on_a_folder_of_dngs_prints_the_noise_model_training_uses(night, no_pil_on_raw, capsys):
    raw = night / "raw"
    code, out, err = run_cli(["noise", "--data", raw, "--quiet"], capsys)
    assert code == 0, err
    assert "Traceback" not in err
    low = raw / "low"
    dngs = sorted(low.glob("*.dng"))
    assert f"{low}: {len(dngs)} camera raw photos (.dng)" in out
    assert "from their DNG NoiseProfile" in out  # darken --raw writes one
    # one line per photo read, with its own model
    for p in dngs:
        assert f"  {p.name} (NoiseProfile): a = " in out, out
    # the median model, in the JPEG path's format, is the one training weighs the raw views by
    model = scene_noise(dngs)
    lines = _channel_lines(out)
    assert sorted(lines) == ["B", "G", "R"], out
    for c, name in enumerate("RGB"):
        fw, a, b = lines[name]
        assert a == pytest.approx(model.a[c], rel=6e-3) and b == pytest.approx(model.b[c], rel=6e-3)
        assert fw == pytest.approx(1.0 / model.a[c], abs=1.0)
        assert 0 < a and np.isfinite(fw)
    assert "sigma at the 50th-percentile level" in out and "SNR" in out
    assert "black is not lifted" in out  # raw values are not clipped at black
    assert "training (loss.rec_noise_floor): the exposed SSIM's gain is" in out


def test_noise_on_dngs_without_a_profile_measures_the_mosaic(tmp_path, no_pil_on_raw, capsys):
    rng = np.random.default_rng(3)
    folder = tmp_path / "shots"
    folder.mkdir()
    for k in range(3):
        # a ramp with shot and read noise, in raw units above a black level of 512
        signal = np.tile(np.linspace(200, 6000, 96), (64, 1))
        mosaic = 512 + signal + rng.normal(0, np.sqrt(signal * 2.0 + 9.0))
        _dng(folder / f"{k:02d}.dng", np.clip(np.rint(mosaic), 0, 16383).astype(np.uint16))
    code, out, err = run_cli(["noise", "--data", folder, "--quiet"], capsys)
    assert code == 0, err
    assert "measured on their raw mosaic" in out and "(measured): a = " in out
    lines = _channel_lines(out)
    assert sorted(lines) == ["B", "G", "R"], out
    for fw, a, b in lines.values():
        assert a > 0 and b > 0 and np.isfinite(fw)


def test_noise_on_raw_files_beside_jpegs_measures_the_raw_files(night, tmp_path, no_pil_on_raw, capsys):
    folder = tmp_path / "mixed"
    folder.mkdir()
    for p in sorted((night / "raw" / "low").glob("*.dng"))[:2]:
        shutil.copy(p, folder / p.name)
    for p in sorted((night / "jpeg" / "low").iterdir())[:2]:
        shutil.copy(p, folder / (p.stem + "_cam" + p.suffix))
    code, out, err = run_cli(["noise", "--data", folder, "--quiet"], capsys)
    assert code == 0, err
    assert "2 camera raw photos" in out and "the 2 other photos beside them are left out" in out


def test_noise_photos_option_sets_how_many_raw_files_are_read(night, no_pil_on_raw, capsys):
    code, out, err = run_cli(["noise", "--data", night / "raw", "--photos", "2", "--quiet"], capsys)
    assert code == 0, err
    assert "noise from 2 " in out
    assert len([ln for ln in out.splitlines() if "(NoiseProfile): a = " in ln]) == 2


# ---- item 8: all-black photos ---------------------------------------------------------------------------------

@pytest.mark.parametrize("suffix", [".jpg", ".png"])
def test_noise_on_all_black_photos_is_one_line_exit_2(tmp_path, suffix, capsys):
    folder = tmp_path / "black"
    folder.mkdir()
    for k in range(3):
        Image.fromarray(np.zeros((40, 56, 3), np.uint8)).save(folder / f"{k:02d}{suffix}")
    code, out, err = run_cli(["noise", "--data", folder, "--quiet"], capsys)
    _one_line_error(code, err, "all zero (black)", str(folder / f"00{suffix}"))
    assert "full well" not in out and "SNR" not in out


def test_noise_with_one_all_black_photo_among_others_names_it(night, tmp_path, capsys):
    folder = tmp_path / "some"
    shutil.copytree(night / "jpeg" / "low", folder)
    photos = sorted(folder.iterdir())
    black = photos[len(photos) // 2]  # the photo whose levels the report quotes
    Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(black)
    code, out, err = run_cli(["noise", "--data", folder, "--photos", "1", "--quiet"], capsys)
    _one_line_error(code, err, "all zero (black)", str(black))


def test_noise_on_an_all_black_dng_is_one_line_exit_2(tmp_path, no_pil_on_raw, capsys):
    folder = tmp_path / "capped"
    folder.mkdir()
    for k in range(2):
        _dng(folder / f"{k:02d}.dng", np.full((36, 48), 512, np.uint16))  # every sample at the black level
    code, out, err = run_cli(["noise", "--data", folder, "--quiet"], capsys)
    _one_line_error(code, err, "all zero (black)", str(folder / "00.dng"))


def test_noise_on_all_black_photos_through_the_real_command(tmp_path):
    folder = tmp_path / "black"
    folder.mkdir()
    Image.fromarray(np.zeros((40, 56, 3), np.uint8)).save(folder / "a.jpg")
    proc = subprocess.run([sys.executable, "-m", "retinexgs", "noise", "--data", str(folder), "--quiet"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [f"retinexgs noise: error: cannot measure the noise of "
                                                f"{folder / 'a.jpg'}: the photo is all zero (black): there is "
                                                "nothing to measure"]
    assert proc.stdout == ""
