"""Issue 52, stage 2: the raw night-capture simulator (retinexgs.data.raw_sim, ``retinexgs darken --raw``).

Fixtures are tiny synthetic photos and demo scenes in tmp_path. DNGs are read back with rawpy directly (the tags
are right for LibRaw) and with read_raw (the package's own reader).
"""
from __future__ import annotations

import json

import numpy as np
import pytest
import rawpy

from retinexgs.data import load_scene
from retinexgs.data.camera_raw import exposure_scale, normalised_mosaic, read_raw
from retinexgs.data.images import read_image_float
from retinexgs.data.raw_sim import (CFA_PATTERNS, RawCamera, capture_mosaic, noise_profile, process, to_uint8,
                                    unprocess, write_raw_view)
from retinexgs.data.sensor import SensorModel, darken_scene, jpeg_roundtrip, linear_to_srgb, srgb_to_linear
from retinexgs.demo.synthetic import make_demo_scene
from scenes import run_cli


def _flat(value: float, size: int = 256) -> np.ndarray:
    return np.full((size, size, 3), value)


def test_dngs_read_back_with_the_camera_s_tags(tmp_path):
    """Black level, CFA pattern, white balance, NoiseProfile and EXIF exposure, read by rawpy and read_raw, for
    every CFA and both bit depths; the exposure times give the views' relative exposures."""
    src = make_demo_scene(tmp_path / "src", n_train=2, n_test=1, width=48, height=36, n_points=100)
    model = SensorModel(exposure=0.05, exposure_jitter=0.2, full_well=1000.0, read_noise=6.0)
    for cfa, bits in zip(CFA_PATTERNS, (14, 12, 14, 12)):
        cam = RawCamera(bits=bits, cfa=cfa)
        out = tmp_path / f"{cfa}{bits}"
        darken_scene(src, out, model, seed=1, progress=False, raw=cam)
        info = json.loads((out / "sensor.json").read_text())
        black, white = info["camera"]["black_level"], 2 ** bits - 1
        assert info["camera"]["white_level"] == white and info["camera"]["cfa"] == cfa
        s, o = noise_profile(cam, 1000.0, 6.0)
        photos = []
        for name in ("0000", "0001", "0002"):
            path = out / "raw" / "low" / f"{name}.dng"
            with rawpy.imread(str(path)) as raw:
                assert raw.white_level == white
                assert list(raw.black_level_per_channel) == [black] * 4
                pattern = "".join("RGBG"[c] for c in np.asarray(raw.raw_pattern).reshape(-1))
                assert pattern == cfa
                wb = np.array(raw.camera_whitebalance[:3])
                assert np.allclose(wb / wb[1], [2.0, 1.0, 1.6], rtol=1e-5)  # 1 / AsShotNeutral
            ph = read_raw(path)
            assert ph.cfa_pattern == cfa and ph.notes == []
            assert np.allclose(ph.white_balance, [2.0, 1.0, 1.6], rtol=1e-6)
            assert np.allclose(ph.xyz_to_cam, cam.xyz_to_cam, atol=1e-6)
            assert np.allclose(ph.cam_to_srgb, cam.cam_to_srgb(), atol=1e-5)
            assert np.allclose(ph.noise_profile, [[s, o]] * 3, rtol=1e-9)
            t = info["raw_exposure_times"][f"low/{name}.dng"]  # normal_time * the view's exposure
            assert t == pytest.approx(info["view_exposures"][f"low/{name}.png"] * cam.normal_time, abs=1e-6)
            assert ph.exposure_time == pytest.approx(t, rel=1e-5)
            assert ph.iso == cam.iso and ph.f_number == pytest.approx(cam.f_number)
            photos.append(ph)
        ks = np.array([info["raw_exposure_times"][f"low/{n}.dng"] for n in ("0000", "0001", "0002")])
        assert np.allclose(exposure_scale(photos), ks / np.median(ks), rtol=1e-5)


def test_noise_variance_per_cfa_plane_follows_the_noise_profile(tmp_path):
    """A flat grey patch: in each of the four CFA planes the variance of the normalised raw is S*x + O (the DNG's
    own NoiseProfile) within 5 % (16384 samples per plane: the sample variance's spread is about 1.1 %), and the
    mean is the unprocessed signal."""
    model = SensorModel(exposure=0.2, exposure_jitter=0.0, full_well=1500.0, read_noise=4.0)
    cam = RawCamera(bits=14, cfa="GRBG")
    grey = _flat(0.5)
    dn = capture_mosaic(grey, model, cam, 0.2, np.random.default_rng(0))
    path = write_raw_view(tmp_path / "grey.dng", dn, cam, model, 0.2)
    ph = read_raw(path)
    x = normalised_mosaic(ph).astype(np.float64)
    s, o = ph.noise_profile[0]
    want = unprocess(grey[:2, :2], cam)[0, 0] * 0.2  # R, G, B of the flat patch at the exposure
    for i in range(2):
        for j in range(2):
            plane = x[i::2, j::2]
            c = int(ph.cfa[i, j])
            assert plane.mean() == pytest.approx(want[c], rel=0.01)
            assert plane.var() == pytest.approx(s * plane.mean() + o, rel=0.05), (i, j)


def test_black_stays_zero_mean_in_the_raw_while_the_camera_jpeg_lifts_it(tmp_path):
    """A black region: black-subtracted, the raw values average to 0 (|mean| < 3 % of the read noise's sigma: the
    black level keeps the noise unclipped), while the camera JPEG of the same mosaic is lifted above black."""
    model = SensorModel(exposure=0.05, exposure_jitter=0.0, full_well=1000.0, read_noise=6.0)
    cam = RawCamera(bits=12)
    dn = capture_mosaic(_flat(0.0), model, cam, 0.05, np.random.default_rng(2))
    ph = read_raw(write_raw_view(tmp_path / "black.dng", dn, cam, model, 0.05))
    x = normalised_mosaic(ph).astype(np.float64)
    sigma = np.sqrt(ph.noise_profile[0, 1])
    assert sigma == pytest.approx(6.0 / 1000.0, rel=0.01)
    assert abs(x.mean()) < 0.03 * sigma, (x.mean(), sigma)
    assert x.std() == pytest.approx(sigma, rel=0.03)  # whole: nothing clipped at 0 DN
    assert dn.min() > 0
    jpeg = jpeg_roundtrip(to_uint8(process(dn, cam, ph.black_level[0, 0])), 90)
    lifted = srgb_to_linear(jpeg / 255.0).mean(axis=(0, 1))
    assert np.all(lifted > 0.3 * sigma), lifted  # the ISP's clip at black: the JPEG's bias


def test_unprocess_then_process_returns_the_srgb_input():
    """Without noise: sRGB -> camera raw (every CFA, 14 bit, exposure 1) -> the camera ISP gives the input back
    within 1/255 away from the border (bilinear demosaicing is exact on a ramp that is linear in light); the
    colour steps alone invert to float precision."""
    h, w = 40, 48
    yy, xx = np.mgrid[0:h, 0:w]
    lin = np.stack([0.02 + 0.7 * xx / w, 0.05 + 0.6 * yy / h, 0.3 + 0.3 * (xx + yy) / (h + w)], -1)
    srgb = linear_to_srgb(lin)
    clean = SensorModel(full_well=None)
    for cfa in CFA_PATTERNS:
        cam = RawCamera(bits=14, cfa=cfa)
        dn = capture_mosaic(srgb, clean, cam, 1.0, None)
        back = process(dn, cam, cam.black_level(None, 0.0))
        err = np.abs(back - srgb)[1:-1, 1:-1]
        assert err.max() <= 1 / 255, (cfa, err.max())
    rng = np.random.default_rng(3)
    colours = rng.uniform(0.05, 0.95, (50, 1, 3))
    cam = RawCamera()
    cam_rgb = unprocess(colours, cam)
    again = (cam_rgb * np.asarray(cam.white_balance)) @ cam.cam_to_srgb().T
    assert np.allclose(linear_to_srgb(again), colours, atol=1e-9)


def test_camera_jpeg_is_the_isp_of_the_same_noisy_mosaic(tmp_path):
    """The JPEG beside each DNG is exactly the ISP of the DNG's own mosaic (the same photons), and it matches the
    ISP of the noise-free mosaic within the noise: unbiased in mid-tones, its error the size of the noise."""
    src = make_demo_scene(tmp_path / "src", n_train=2, n_test=1, width=48, height=36, n_points=100)
    model = SensorModel(exposure=0.3, exposure_jitter=0.1, full_well=1500.0, read_noise=4.0, jpeg_quality=90)
    cam = RawCamera()
    out = tmp_path / "out"
    darken_scene(src, out, model, seed=5, progress=False, raw=cam)
    for name in ("0000", "0002"):
        ph = read_raw(out / "raw" / "low" / f"{name}.dng")
        isp = jpeg_roundtrip(to_uint8(process(ph.mosaic, cam, ph.black_level[0, 0])), 90)
        assert np.array_equal(isp, np.round(read_image_float(out / "jpeg" / "low" / f"{name}.png") * 255))

    # noisy against noise-free, on a smooth photo large enough for statistics
    yy, xx = np.mgrid[0:128, 0:128] / 128.0
    srgb = np.stack([0.4 + 0.4 * xx, 0.5 + 0.3 * yy, 0.45 + 0.2 * xx * yy], -1)
    k = 0.3
    noisy = process(capture_mosaic(srgb, model, cam, k, np.random.default_rng(7)), cam, 512)
    clean = process(capture_mosaic(srgb, SensorModel(full_well=None), cam, k, None), cam, 512)
    diff = srgb_to_linear(noisy) - srgb_to_linear(clean)
    # an upper bound of the noise per channel: one sample's variance through white balance and matrix (the
    # demosaic's averaging only lowers it)
    cam_sig = unprocess(srgb, cam).mean(axis=(0, 1)) * k
    var_cam = (cam_sig / model.full_well + (model.read_noise / model.full_well) ** 2) * np.square(cam.white_balance)
    bound = np.sqrt(np.square(cam.cam_to_srgb()) @ var_cam)
    rms = np.sqrt((diff ** 2).mean(axis=(0, 1)))
    assert np.all(rms <= bound) and np.all(rms >= 0.2 * bound), (rms, bound)
    assert np.all(np.abs(diff.mean(axis=(0, 1))) < 0.05 * bound), (diff.mean(axis=(0, 1)), bound)


def test_cli_writes_a_complete_raw_scene_and_a_jpeg_scene_that_loads(tmp_path, capsys):
    src = make_demo_scene(tmp_path / "src", n_train=3, n_test=1, width=48, height=36, n_points=200)
    out = tmp_path / "night"
    code, stdout, err = run_cli(["darken", "--data", src, "--out", out, "--raw", "--bits", "12", "--cfa", "bggr",
                                 "--full-well", "1000", "--read-noise", "6", "--quiet"], capsys)
    assert code == 0, err
    assert "dark raw photos (DNG)" in stdout
    raw, jpeg = out / "raw", out / "jpeg"
    # the raw scene: poses copied, every transforms frame names an existing DNG, split.json too
    names = []
    for js in ("transforms_train.json", "transforms_test.json"):
        data = json.loads((raw / js).read_text())
        for frame in data["frames"]:
            assert frame["file_path"].startswith("low/") and frame["file_path"].endswith(".dng")
            assert (raw / frame["file_path"]).is_file()
            names.append(frame["file_path"])
    assert sorted(names) == [f"low/{i:04d}.dng" for i in range(4)]
    split = json.loads((raw / "split.json").read_text())
    assert sorted(split["train"] + split["test"]) == [f"{i:04d}.dng" for i in range(4)]
    assert sorted(p.name for p in (raw / "high").iterdir()) == sorted(p.name for p in (src / "high").iterdir())
    assert read_raw(raw / "low" / "0003.dng").cfa_pattern == "BGGR"
    info = json.loads((raw / "sensor.json").read_text())
    assert info["camera"]["bits"] == 12 and info["camera"]["cfa"] == "BGGR" and len(info["raw_exposure_times"]) == 4
    assert info == json.loads((out / "sensor.json").read_text()) == json.loads((jpeg / "sensor.json").read_text())
    # the JPEG scene trains today: it loads, full size, darker than the truth
    scene = load_scene(jpeg)
    assert len(scene.train) == 3 and len(scene.test) == 1
    low, high = read_image_float(jpeg / "low" / "0000.png"), read_image_float(src / "high" / "0000.png")
    assert low.shape == high.shape and low.mean() < 0.6 * high.mean()

    # a plain folder of photos: raw/NAME.dng beside jpeg/NAME
    plain = tmp_path / "plain"
    plain.mkdir()
    for p in (src / "high").iterdir():
        (plain / p.name).write_bytes(p.read_bytes())
    code, stdout, err = run_cli(["darken", "--data", plain, "--out", tmp_path / "p", "--raw", "--quiet"], capsys)
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "p" / "raw").glob("*.dng")) == [f"{i:04d}.dng" for i in range(4)]
    assert sorted(p.name for p in (tmp_path / "p" / "jpeg").glob("*.png")) == [f"{i:04d}.png" for i in range(4)]


def test_cli_raw_bad_input_gets_one_line_and_leaves_nothing(tmp_path, capsys):
    src = make_demo_scene(tmp_path / "src", n_train=2, n_test=1, width=32, height=24, n_points=100)
    cases = [(["--raw", "--bits", "10"], "--bits must be 12 or 14"),
             (["--raw", "--cfa", "RGBG"], "--cfa must be one of RGGB, BGGR, GRBG, GBRG"),
             (["--bits", "12"], "--bits applies only to raw files: add --raw"),
             (["--cfa", "RGGB"], "--cfa applies only to raw files: add --raw"),
             (["--raw", "--full-well", "20", "--read-noise", "10"], "black level would need more than half"),
             ]
    for extra, message in cases:
        code, out, err = run_cli(["darken", "--data", src, "--out", tmp_path / "o", "--quiet", *extra], capsys)
        assert code == 2 and message in err and "Traceback" not in err, (extra, err)
        assert len(err.strip().splitlines()) == 1, err
        assert not (tmp_path / "o").exists()
    small = make_demo_scene(tmp_path / "small", n_train=2, n_test=1, width=20, height=16, n_points=50)
    code, out, err = run_cli(["darken", "--data", small, "--out", tmp_path / "o", "--raw", "--quiet"], capsys)
    assert code == 2 and "too small for a DNG" in err and "Traceback" not in err, err
    assert not (tmp_path / "o").exists()  # nothing half-made is left
    clash = tmp_path / "clash"
    clash.mkdir()
    img = (src / "high" / "0000.png").read_bytes()
    (clash / "a.png").write_bytes(img)
    (clash / "a.jpg").write_bytes((src / "high" / "0001.png").read_bytes())
    code, out, err = run_cli(["darken", "--data", clash, "--out", tmp_path / "o", "--raw", "--quiet"], capsys)
    assert code == 2 and "would both become a.dng" in err, err
