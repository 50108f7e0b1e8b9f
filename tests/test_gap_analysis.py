"""scripts/gap_analysis.py: its tone oracles recover a pure tone change and leave structure alone."""
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from scenes import load_script


def load():
    return load_script("gap_analysis")


def fake_run(tmp: Path, name: str, make_output) -> Path:
    """A run folder with two 3-panel evaluation PNGs: low | output | truth."""
    rng = np.random.default_rng(0)
    run = tmp / name
    (run / "renders" / "test").mkdir(parents=True)
    (run / "metrics.json").write_text(json.dumps({"panels": "low input | output | ground truth"}))
    for i in range(2):
        y, x = np.mgrid[0:48, 0:64] / 64.0
        truth = np.stack([0.2 + 0.6 * x, 0.3 + 0.4 * y, 0.5 + 0.3 * np.sin(6 * x)], -1)
        truth += 0.05 * rng.standard_normal(truth.shape)
        truth = np.clip(truth, 0, 1)
        out = np.clip(make_output(truth, rng), 0, 1)
        img = np.concatenate([truth * 0.1, out, truth], axis=1)
        Image.fromarray((img * 255 + 0.5).astype(np.uint8)).save(run / "renders" / "test" / f"{i}.png")
    return run


def test_a_tone_change_is_recovered_by_the_oracles(tmp_path):
    ga = load()
    m = ga.analyse(fake_run(tmp_path, "tone", lambda t, rng: 0.6 * t + 0.2))
    assert m["psnr"] < 25  # the tone change costs PSNR
    assert m["psnr_affine"] > 40 and m["ssim_affine"] > 0.99  # an affine fit undoes it exactly (up to 8 bits)
    assert all(1.5 < m[f"slope_{c}"] < 1.8 for c in "rgb")  # output flatter than the truth: slope 1/0.6
    assert m["views"] == 2


def test_noise_is_not_recovered_by_the_oracles_but_by_blur(tmp_path):
    ga = load()
    m = ga.analyse(fake_run(tmp_path, "noise", lambda t, rng: t + 0.08 * rng.standard_normal(t.shape)))
    assert m["ssim_affine"] < 0.9 and m["ssim_hist"] < 0.9
    assert m["term_std_ratio"] > 1.2  # more local variance than the truth
    assert m["term_l"] > 0.99  # the tone is right


def test_missing_renders_is_a_clear_error(tmp_path):
    ga = load()
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit, match="no renders/test"):
        ga.analyse(tmp_path / "empty")


def test_an_exposure_change_is_recovered_by_the_best_gain(tmp_path):
    """An output that is the truth with 0.8 of its light: the exposure oracle finds the gain 1/0.8 and undoes it
    (up to 8 bits); the meters at 0.5 only see the output, so they land where its statistic says."""
    ga = load()
    from retinexgs.model.tone import linear_to_srgb, srgb_to_linear
    import torch

    def darker(t, rng):
        return linear_to_srgb(0.8 * srgb_to_linear(torch.from_numpy(t))).numpy()

    m = ga.analyse(fake_run(tmp_path, "exposure", darker))
    assert m["psnr"] < 30 and m["psnr_gain"] > 40
    assert m["gain"] == pytest.approx(1.25, abs=0.02)
    assert m["mean_out"] < m["mean_truth"]
    assert m["p50_out"] < m["p50_truth"] and m["p99_out"] < m["p99_truth"]
    assert 0 <= m["p1_out"] <= m["p50_out"] <= m["p99_out"] <= 1
    for meter in ("mean", "centre"):
        assert m["psnr"] - 10 < m[f"psnr_{meter}_meter"] < m["psnr_gain"]


def test_the_centre_weights_and_the_meter_bisection():
    ga = load()
    import torch
    w = ga.centre_weights(30, 40)
    assert float(w.sum()) == pytest.approx(1.0)
    assert torch.allclose(w, w.flip(0)) and torch.allclose(w, w.flip(1))  # symmetric about the centre
    assert float(w[14:16, 19:21].min()) == float(w.max()) > 2 * float(w[0, 0])  # highest at the centre
    lin = torch.full((4, 4, 3), 0.1, dtype=torch.float64)
    c = ga.exposure_for(lambda x: float(x.mean()), lin, 0.5)
    assert float(ga.linear_to_srgb(c * lin).mean()) == pytest.approx(0.5, abs=1e-6)
