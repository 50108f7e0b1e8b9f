"""The low-light sensor model (retinexgs darken) and the noise estimate from photos (retinexgs noise), issue 32."""
import json
import math

import numpy as np
import pytest

from retinexgs.data import load_scene
from retinexgs.data.images import read_image_float
from retinexgs.data.sensor import (NOISE_LADDER, SensorModel, darken_scene, estimate_noise, linear_to_srgb,
                                   srgb_to_linear)
from retinexgs.demo.synthetic import make_demo_scene
from scenes import run_cli


def smooth_image(h=240, w=320):
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    return np.stack([0.2 + 0.5 * xx, 0.3 + 0.5 * yy, 0.5 + 0.3 * np.sin(3 * xx)], -1).clip(0, 1)


def test_capture_has_the_model_s_mean_and_variance():
    """Raw values: mean lin(x)·g·k, variance lin·g·k/W + (r/W)² (Poisson + Gaussian), per channel."""
    rng = np.random.default_rng(0)
    x = np.full((400, 400, 3), 0.5)
    m = SensorModel(exposure=0.1, exposure_jitter=0.0, full_well=2000.0, read_noise=5.0, cast=(0.8, 1.0, 1.25))
    y = m.capture(x, 0.1, rng)
    signal = srgb_to_linear(np.array(0.5)) * np.array(m.cast) * 0.1
    assert np.allclose(y.reshape(-1, 3).mean(0), signal, rtol=0.01)
    want = signal / 2000.0 + (5.0 / 2000.0) ** 2
    assert np.allclose(y.reshape(-1, 3).var(0), want, rtol=0.05)
    clean = SensorModel(full_well=None).capture(x, 0.1, rng)
    assert np.allclose(clean, srgb_to_linear(np.array(0.5)) * 0.1)


def test_noise_estimate_recovers_the_sensor_on_a_lossless_capture():
    rng = np.random.default_rng(1)
    for W, r in [(1500.0, 4.0), (8000.0, 2.0)]:
        m = SensorModel(exposure=0.1, exposure_jitter=0.0, full_well=W, read_noise=r, jpeg_quality=0)
        photo = np.round(linear_to_srgb(m.capture(smooth_image(), 0.1, rng)) * 255) / 255
        est = estimate_noise(photo)
        for c in range(3):
            assert est.full_well[c] == pytest.approx(W, rel=0.15), (W, est)
        y = 0.02
        assert np.mean(est.sigma_at(y)) == pytest.approx(math.sqrt(y / W + (r / W) ** 2), rel=0.1)
    clean = np.round(smooth_image() * 255) / 255
    assert max(estimate_noise(clean).a) < 1e-5  # no shot noise in a noise-free photo
    with pytest.raises(ValueError, match="at least 8x8"):
        estimate_noise(np.zeros((4, 4, 3)))


def test_noisier_ladder_levels_estimate_noisier(tmp_path):
    """The ladder's levels are ordered by the noise they make, as the estimate sees it through JPEG."""
    src = make_demo_scene(tmp_path / "src", n_train=2, n_test=1, width=96, height=72, n_points=300)
    sigmas = []
    for label, W, r in NOISE_LADDER:
        out = tmp_path / label
        darken_scene(src, out, SensorModel(exposure=0.2, full_well=W, read_noise=r), seed=0, progress=False)
        sigmas.append(np.mean(estimate_noise(read_image_float(out / "low" / "0000.png")).sigma_at(0.05)))
    # a tiny textured scene: its texture sets a floor under the clean level; the noisy levels rise above it
    assert sigmas[0] < sigmas[-2] < sigmas[-1], sigmas
    assert sigmas[-1] > 2 * sigmas[0], sigmas


def test_darken_scene_writes_a_trainable_scene_and_records_the_model(tmp_path):
    src = make_demo_scene(tmp_path / "src", n_train=3, n_test=1, width=48, height=36, n_points=200)
    out = tmp_path / "dark"
    m = SensorModel(exposure=0.05, full_well=1000.0, read_noise=6.0, cast=(0.8, 1.0, 1.25))
    report = darken_scene(src, out, m, seed=3, progress=False)
    assert report.photos == 4
    scene = load_scene(out)
    assert len(scene.train) == 3 and len(scene.test) == 1
    high = read_image_float(src / "high" / "0000.png")
    low = read_image_float(out / "low" / "0000.png")
    assert low.mean() < 0.6 * high.mean()
    # the cast: blue over red, relative to the normal-light photo
    assert low[..., 2].mean() / low[..., 0].mean() > high[..., 2].mean() / high[..., 0].mean()
    info = json.loads((out / "sensor.json").read_text())
    assert info["seed"] == 3 and info["model"]["full_well"] == 1000.0 and len(info["view_exposures"]) == 4
    # the same seed gives the same photos
    darken_scene(src, tmp_path / "again", m, seed=3, progress=False)
    assert (out / "low" / "0001.png").read_bytes() == (tmp_path / "again" / "low" / "0001.png").read_bytes()


def test_darken_refuses_bad_input_and_leaves_nothing(tmp_path, capsys):
    src = make_demo_scene(tmp_path / "src", n_train=2, n_test=1, width=32, height=24, n_points=100)
    cases = [(["--exposure", "0"], "--exposure must be in (0, 1]"),
             (["--full-well", "-5"], "--full-well must be a positive"),
             (["--read-noise", "nan"], "--read-noise must be >= 0"),
             (["--cast", "1,0,1"], "--cast must be three positive"),
             (["--jpeg-quality", "101"], "--jpeg-quality must be 0"),
             ]
    for extra, message in cases:
        code, out, err = run_cli(["darken", "--data", src, "--out", tmp_path / "o", "--quiet", *extra], capsys)
        assert code == 2 and message in err and "Traceback" not in err, (extra, err)
        assert not (tmp_path / "o").exists()
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "mine.txt").write_text("user file")
    code, out, err = run_cli(["darken", "--data", src, "--out", tmp_path / "full", "--quiet"], capsys)
    assert code == 2 and "already exists and is not empty" in err
    assert (tmp_path / "full" / "mine.txt").read_text() == "user file"
    code, out, err = run_cli(["darken", "--data", tmp_path / "nope", "--out", tmp_path / "o2"], capsys)
    assert code == 2 and "is not a folder" in err
    (tmp_path / "empty").mkdir()
    code, out, err = run_cli(["noise", "--data", tmp_path / "empty"], capsys)
    assert code == 2 and "no photos" in err


def test_noise_command_prints_the_estimate(tmp_path, capsys):
    src = make_demo_scene(tmp_path / "src", n_train=2, n_test=1, width=96, height=72, n_points=300)
    code, out, err = run_cli(["noise", "--data", src], capsys)
    assert code == 0, err
    assert "full well" in out and "sigma at the 50th-percentile level" in out
    assert "measured as they are (not JPEG)" in out  # the demo's photos are PNG
    lift = [float(v) for v in out.split("black is recorded on average at linear ")[1].split(" (R, G, B")[0].split(", ")]
    assert all(v > 0 for v in lift)  # the demo's photos are noisy: clipped noise lifts their black
    # the demo's noise reaches SSIM's constant: training caps the exposed SSIM's gain (train/noise.py)
    assert "training (loss.rec_noise_floor): the exposed SSIM's gain is capped at" in out
    assert "loss.rec_noise_share 0.5;" in out  # the default config's share
    # 96x72 photos are too small to tell colour blotches from texture: decomposed as they are
    assert "training (decomposer.denoise: auto): photos under 256 px are not read" in out
    assert "decomposed as they are" in out


def _printed_cap(out):
    line = next(ln for ln in out.splitlines() if "the exposed SSIM's gain is" in ln)
    return float(line.split("capped at ")[1].split()[0]) if "capped at" in line else float("inf")


def test_noise_command_places_the_cap_at_the_given_share(tmp_path, capsys):
    src = make_demo_scene(tmp_path / "src", n_train=2, n_test=1, width=96, height=72, n_points=300, full_well=3000.0,
                          read_noise=3.0)
    caps = {}
    for share in ("0.1", "0.5", "0.9"):
        code, out, err = run_cli(["noise", "--data", src, "--share", share], capsys)
        assert code == 0, err
        caps[share] = _printed_cap(out)
    assert caps["0.1"] < caps["0.5"] < caps["0.9"]  # more noise let through: a higher gain
    for bad in ("0", "1", "-0.2"):
        code, out, err = run_cli(["noise", "--data", src, "--share", bad], capsys)
        assert code == 2 and "--share must lie between 0 and 1" in err


def test_noise_estimate_sees_the_read_noise_under_the_clip_at_black():
    """A dark capture (k = 0.05, 1000 e-, read noise 6 e-: the ladder's noisiest level) puts many pixels at black,
    where the recorded noise is clipped: its variance smaller, its mean higher. A straight line through the bins read
    b = (r/W)² 2.4-8x too low; the clipped model's fit reads it within 45 %, lossless."""
    from retinexgs.data.sensor import clipped_moments, fit_clipped_noise
    yy, xx = np.mgrid[0:240, 0:320] / 320
    dark = np.stack([0.8 * xx, 0.05 + 0.6 * yy, 0.1 + 0.4 * np.sin(3 * xx) ** 2], -1).clip(0, 1)
    m = SensorModel(exposure=0.05, exposure_jitter=0.0, full_well=1000.0, read_noise=6.0, jpeg_quality=0)
    photo = np.round(linear_to_srgb(m.capture(dark, 0.05, np.random.default_rng(0))) * 255) / 255
    est = estimate_noise(photo)
    for c in range(3):
        assert est.b[c] == pytest.approx(3.6e-5, rel=0.45), est
    # the moments: no clip far above black; at black the mean is σ/√(2π) and the variance σ²(1/2 − 1/(2π))
    mean, var = clipped_moments(np.array([0.5, 0.0]), np.array([0.01, 0.01]))
    assert mean[0] == pytest.approx(0.5) and var[0] == pytest.approx(1e-4, rel=1e-4)
    assert mean[1] == pytest.approx(0.01 / math.sqrt(2 * math.pi), rel=1e-5)
    assert var[1] == pytest.approx(1e-4 * (0.5 - 1 / (2 * math.pi)), rel=1e-4)
    # the fit recovers exact clipped moments of a known (a, b)
    mu = np.linspace(0.0, 0.05, 12)
    mean, var = clipped_moments(mu, np.sqrt(2e-3 * mu + 4e-5))
    a, b = fit_clipped_noise(mean, var, np.ones_like(mu))
    assert a == pytest.approx(2e-3, rel=0.05) and b == pytest.approx(4e-5, rel=0.1)


def test_noise_through_the_photo_s_own_jpeg_sees_the_noise_near_black(tmp_path):
    """JPEG at q 90 removes most of a dark photo's noise near black, so the plain estimate reads too little there;
    fitted by simulating the file's own JPEG (its tables, read back from the file), the noise near black reads
    within 35 % of the sensor's at the ladder's noisy levels. A PNG has no codec to model."""
    from PIL import Image

    from retinexgs.data.sensor import JpegCodec, estimate_noise_through_codec
    yy, xx = np.mgrid[0:256, 0:320] / 320
    scene = np.stack([0.15 + 0.7 * xx, 0.1 + 0.6 * yy, 0.2 + 0.5 * np.sin(4 * xx + 2 * yy) ** 2], -1).clip(0, 1)
    for W, r in [(1500.0, 4.0), (1000.0, 6.0)]:
        m = SensorModel(exposure=0.05, exposure_jitter=0.0, full_well=W, read_noise=r)
        path = tmp_path / f"{W:.0f}.jpg"
        u8 = m.darken(scene, 0.05, np.random.default_rng(0))
        Image.fromarray(u8).save(path, quality=90)
        codec = JpegCodec.of_file(path)
        assert codec is not None and len(codec.qtables) == 2
        photo = read_image_float(path).astype(np.float64)
        # the codec read back from the file encodes the camera's pixels into exactly the file's
        assert np.array_equal(codec.roundtrip(u8), np.round(photo * 255).astype(np.uint8))
        truth = [math.sqrt(y / W + (r / W) ** 2) for y in (0.0, 0.002)]
        plain = estimate_noise(photo)
        fitted = estimate_noise_through_codec(photo, codec)
        for y, t in zip((0.0, 0.002), truth):
            assert np.mean(plain.sigma_at(y)) < 0.7 * t, (W, y, plain)
            assert np.mean(fitted.sigma_at(y)) == pytest.approx(t, rel=0.35), (W, y, fitted)
    png = tmp_path / "lossless.png"
    Image.fromarray((scene * 255).astype(np.uint8)).save(png)
    assert JpegCodec.of_file(png) is None
