"""experiments/contact_sheets.py: input (brightened) | today | new | truth per capture, from two fabricated
``bench quality`` run folders (no training)."""
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from retinexgs.data.srgb import linear_to_srgb, srgb_to_linear

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("contact_sheets", ROOT / "experiments" / "contact_sheets.py")
sheets = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(sheets)

W, H, TOP = 10, 8, 3  # a panel's size and the label strip above eval's side-by-side PNGs


def _run(run: Path, output: int, views=("v0", "v1", "v2", "v3"), low: int = 30, truth: int = 200):
    """A fabricated evaluated run: side-by-side PNGs low | output | R | L | truth (flat panels; R, L = 7) under
    a TOP-row label strip, and its metrics.json."""
    (run / "renders" / "test").mkdir(parents=True)
    for k, name in enumerate(views):
        img = np.full((TOP + H, 5 * W, 3), 7, np.uint8)
        img[:TOP] = 255
        for p, v in ((0, low + k), (1, output + k), (4, truth + k)):
            img[TOP:, p * W:(p + 1) * W] = v
        Image.fromarray(img).save(run / "renders" / "test" / f"{name}.png")
    (run / "metrics.json").write_text(json.dumps({
        "mean": {"psnr": 20.0}, "views": [{"view": f"{v}.jpg"} for v in views], "label_rows": TOP,
        "panels": "low input | output | R̂ | L̂ / L_ref | ground truth"}))


def _expected_input(value: int, gain: float) -> int:
    return int(np.round(linear_to_srgb(min(srgb_to_linear(value / 255.0) * gain, 1.0)) * 255.0))


def test_one_sheet_per_capture_input_today_new_truth(tmp_path, capsys):
    today, new = tmp_path / "none", tmp_path / "chroma"
    for seed in (0, 1):
        _run(today / "lom" / "buu" / "default" / f"seed{seed}", 100 + 10 * seed)
        _run(new / "lom" / "buu" / "ablations-denoise_chroma" / f"seed{seed}", 150 + 10 * seed)
    _run(today / "fox@1000e-raw" / "default" / "seed0", 90)  # only in one folder: no sheet
    out = tmp_path / "sheets"
    args = ["--today", str(today), "--new", str(new), "--new-config", "ablations/denoise_chroma", "--out", str(out),
            "--gain", "8"]
    assert sheets.main(args) == 0
    assert sorted(p.name for p in out.iterdir()) == ["sheet_lom-buu.png"]
    img = np.asarray(Image.open(out / "sheet_lom-buu.png").convert("RGB")).astype(int)
    pad = 14  # write_sheet's label strip per row
    assert img.shape == (3 * (H + pad), 4 * W, 3)  # 3 test views (the default), 4 columns
    for row in range(3):
        y = row * (H + pad) + pad + H // 2
        got = [img[y, c * W + W // 2, 0] for c in range(4)]
        # seed 0 (the lowest both hold); the input brightened by the stated gain in linear light
        assert got == [_expected_input(30 + row, 8.0), 100 + row, 150 + row, 200 + row], (row, got)
    # the label strip is drawn (not the panels' colour)
    assert (img[:pad, :, 0] < 128).any()

    # auto gain: the truth's mean linear light over the input's, 2 significant digits; --seed picks the runs
    assert sheets.main([*args[:-2], "--seed", "1", "--views", "2", "--overwrite"]) == 0
    img = np.asarray(Image.open(out / "sheet_lom-buu.png").convert("RGB")).astype(int)
    lin = lambda v: srgb_to_linear(v / 255.0)  # noqa: E731
    gain = float(f"{(lin(200) + lin(201)) / (lin(30) + lin(31)):.2g}")
    assert img.shape[0] == 2 * (H + 14)
    assert img[14 + H // 2, W // 2, 0] == _expected_input(30, gain) and img[14 + H // 2, W + 1, 0] == 110


@pytest.mark.parametrize("extra, message", [
    (["--gain", "0"], "--gain must be 'auto' or a positive number"),
    (["--scenes", "fox"], "no evaluated runs of fox in both"),
    (["--seed", "5"], "seed 5 is not in both folders"),
    (["--names", "a"], "--names must be two names"),
])
def test_bad_arguments_are_one_line(tmp_path, capsys, extra, message):
    _run(tmp_path / "a" / "s1" / "default" / "seed0", 100)
    _run(tmp_path / "b" / "s1" / "default" / "seed0", 150)
    rc = sheets.main(["--today", str(tmp_path / "a"), "--new", str(tmp_path / "b"), "--out", str(tmp_path / "o"),
                      *extra])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and err.count("\n") == 1, err
    assert not (tmp_path / "o").exists()


def test_an_existing_sheet_is_kept_and_folders_without_shared_runs_are_one_line(tmp_path, capsys):
    _run(tmp_path / "a" / "s1" / "default" / "seed0", 100)
    _run(tmp_path / "b" / "s1" / "default" / "seed0", 150, views=("v9",))
    out = tmp_path / "o"
    out.mkdir()
    (out / "sheet_s1.png").write_bytes(b"mine")
    args = ["--today", str(tmp_path / "a"), "--new", str(tmp_path / "b"), "--out", str(out)]
    assert sheets.main(args) == 2 and "exists; pass --overwrite" in capsys.readouterr().err
    assert (out / "sheet_s1.png").read_bytes() == b"mine"
    assert sheets.main([*args, "--overwrite"]) == 2  # the runs share no test view
    assert "share no test view" in capsys.readouterr().err
    assert sheets.main([*args[:2], "--new", str(tmp_path / "nothing"), "--out", str(out)]) == 2
    assert "is not a folder" in capsys.readouterr().err
    _run(tmp_path / "c" / "s2" / "default" / "seed0", 150)
    assert sheets.main([*args[:2], "--new", str(tmp_path / "c"), "--out", str(out)]) == 2
    assert "share no scene" in capsys.readouterr().err
