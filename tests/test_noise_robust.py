"""Issue 32's noise-aware training: the capture's noise measured at set-up and the exposed SSIM's gain capped at the
noise floor (train/noise.py), in the trainer."""
import math

import numpy as np
import pytest
import torch

from retinexgs.data import load_scene
from retinexgs.data.sensor import SensorModel, linear_to_srgb
from retinexgs.demo.synthetic import make_demo_scene
from retinexgs.run.checkpoint import latest_checkpoint, load_checkpoint
from retinexgs.run.config import load_config
from retinexgs.train import noise as N
from retinexgs.train.trainer import Trainer


def _noise(sigma, gains=N.GAINS):
    return N.CaptureNoise((0.0,) * 3, (0.0,) * 3, tuple(gains), tuple(sigma), 1)


def test_gain_cap_interpolates_where_the_exposed_noise_reaches_the_limit():
    # σ = 0.01·g: the limit 0.03 is reached at g = 3, between the grid's 2.83 and 4 (log-linear is exact here)
    assert _noise([0.01 * g for g in N.GAINS]).gain_cap() == pytest.approx(3.0, rel=1e-9)
    assert math.isinf(_noise([1e-4 * g for g in N.GAINS]).gain_cap())  # a clean capture: no cap
    assert _noise([0.05] * len(N.GAINS)).gain_cap() == N.GAINS[0]  # noisy even at gain 1: the smallest gain
    assert _noise([0.01 * g for g in N.GAINS]).gain_cap(limit=0.08) == pytest.approx(8.0, rel=1e-9)
    # a flat (e.g. black) photo measures no noise at the low gains: a finite cap at the first gain above the limit
    cap = _noise([0.0] * 4 + [0.05] * (len(N.GAINS) - 4)).gain_cap()
    assert N.GAINS[3] < cap <= N.GAINS[4]


def test_sigma_limit_is_the_noise_at_which_a_flat_render_loses_that_share_of_the_structure_term():
    assert N.sigma_limit(0.5) == pytest.approx(N.SSIM_K2)
    for share in (0.1, 0.3, 0.9):
        s2, c2 = N.sigma_limit(share) ** 2, N.SSIM_K2 ** 2
        assert 1.0 - c2 / (c2 + s2) == pytest.approx(share)  # cs of a flat render against noise of that σ
    for bad in (0.0, 1.0, -0.1):
        with pytest.raises(ValueError, match="share"):
            N.sigma_limit(bad)


def test_the_trainer_places_the_cap_at_the_configured_share(tmp_path):
    # moderate noise (the fixture's noisy scene is capped at gain 1 by either share)
    scene = make_demo_scene(tmp_path / "scene", full_well=3000.0, read_noise=3.0, n_train=3, n_test=1, width=96,
                            height=72, n_points=300)
    half = _trainer(scene, tmp_path / "half")
    most = _trainer(scene, tmp_path / "most", ["loss.rec_noise_share=0.9"])
    noise = half.noise.capture_noise
    assert float(most.noise.rec_gain_cap) == pytest.approx(noise.gain_cap(N.sigma_limit(0.9)))
    assert float(most.noise.rec_gain_cap) > float(half.noise.rec_gain_cap)  # more noise let through: a higher gain


def _photo(model, seed=0, size=(160, 200)):
    h, w = size
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    smooth = np.stack([0.3 + 0.5 * xx, 0.35 + 0.4 * yy, 0.5 + 0.3 * np.sin(3 * xx)], -1).clip(0, 1)
    return np.round(linear_to_srgb(model.capture(smooth, model.exposure, np.random.default_rng(seed))) * 255) / 255


def test_noise_meter_caps_a_noisy_capture_and_not_a_clean_one():
    noisy, clean = N.NoiseMeter(), N.NoiseMeter()
    for s in range(3):
        noisy.add(_photo(SensorModel(exposure=0.03, exposure_jitter=0, full_well=1000.0, read_noise=6.0,
                                     jpeg_quality=0), s))
        clean.add(_photo(SensorModel(exposure=0.03, exposure_jitter=0, full_well=None, jpeg_quality=0), s))
    n, c = noisy.result(), clean.result()
    assert n.views == 3 and n.sigma[0] > 5 * c.sigma[0]
    assert math.isfinite(n.gain_cap()) and n.gain_cap() < 30
    assert c.gain_cap() > n.gain_cap() * 4
    assert min(n.a) > 0  # shot noise seen
    # a training image d times smaller: white noise's σ / d, its variance model / d²
    half = noisy.result(downscale=2)
    assert half.sigma == pytest.approx(tuple(s / 2 for s in n.sigma))
    assert half.a == pytest.approx(tuple(v / 4 for v in n.a)) and half.b == pytest.approx(tuple(v / 4 for v in n.b))
    assert N.NoiseMeter().result() is None


def test_centre_crop_bounds_the_measured_pixels():
    assert N.centre_crop(np.zeros((3000, 2000, 3)), 1024).shape == (1024, 1024, 3)
    assert N.centre_crop(np.zeros((500, 2000, 3)), 1024).shape == (500, 1024, 3)


TINY = ["steps=4", "checkpoint.every=2", "log.every=1", "log.tensorboard=false", "model.sh_degree=1",
        "model.max_init_points=300", "decomposer.method=lime", "eval.lpips=false"]


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    base = tmp_path_factory.mktemp("noise")
    kw = dict(n_train=3, n_test=1, width=96, height=72, n_points=300)
    return (make_demo_scene(base / "noisy", full_well=300.0, read_noise=8.0, **kw),
            make_demo_scene(base / "clean", full_well=1e9, read_noise=0.0, **kw))


def _trainer(scene, run, extra=(), resume=False, log=lambda s: None):
    cfg = load_config(["demo"], TINY + list(extra))
    run.mkdir(parents=True, exist_ok=True)
    return Trainer(cfg, load_scene(scene), run, "cpu", resume=resume, progress=False, log=log)


def test_trainer_caps_the_exposed_ssim_of_a_noisy_capture_and_resumes_with_the_same_figures(scenes, tmp_path,
                                                                                         monkeypatch):
    lines = []
    tr = _trainer(scenes[0], tmp_path / "run", log=lines.append)
    noise = tr.noise.capture_noise
    assert noise is not None and math.isfinite(noise.gain_cap())
    assert float(tr.noise.rec_gain_cap) == pytest.approx(noise.gain_cap())
    assert any(line.startswith("capture noise") for line in lines)
    tr.train(stop_after=2)
    assert load_checkpoint(latest_checkpoint(tmp_path / "run"))["capture_noise"] == noise.state_dict()

    def no_measure(*a, **k):
        raise AssertionError("a resume measures the noise again")

    monkeypatch.setattr("retinexgs.train.capture_setup.measure_capture_noise", no_measure)
    resumed = _trainer(scenes[0], tmp_path / "run", resume=True)
    assert resumed.noise.capture_noise == noise and float(resumed.noise.rec_gain_cap) == float(tr.noise.rec_gain_cap)
    resumed.train()


def test_a_clean_capture_trains_exactly_as_the_noise_blind_default(scenes, tmp_path):
    """No cap is reached on a clean capture: the losses and parameters equal ablations/noise_blind's."""
    runs = {}
    for name, extra in [("default", []), ("blind", ["loss.rec_noise_floor=false"])]:
        torch.manual_seed(0)
        tr = _trainer(scenes[1], tmp_path / name, extra)
        if name == "default":
            assert tr.noise.capture_noise is not None and math.isinf(tr.noise.capture_noise.gain_cap())
            assert tr.noise.rec_gain_cap is None
        else:
            assert tr.noise.capture_noise is None
        tr.train()
        runs[name] = {k: v.detach().clone() for k, v in tr.model.state_dict().items()}
    for k, v in runs["default"].items():
        torch.testing.assert_close(runs["blind"][k], v, rtol=0, atol=0, msg=k)


def test_the_cap_changes_training_on_a_noisy_capture(scenes, tmp_path):
    """The switch does something where the noise reaches the floor (the test above cannot pass vacuously)."""
    states = []
    for name, extra in [("default", []), ("blind", ["loss.rec_noise_floor=false"])]:
        tr = _trainer(scenes[0], tmp_path / name, extra)
        tr.train()
        states.append(tr.model.gaussians.sh_dc.detach().clone())
    assert not torch.equal(states[0], states[1])


def _local_sigma(n):
    """The noise σ that SSIM's window sees in a noise field n [1,C,H,W]: its Gaussian-weighted (σ 1.5 px, 11 px)
    local variance, averaged over the image; the largest channel."""
    import torch.nn.functional as F
    g = torch.exp(-(torch.arange(11) - 5.0) ** 2 / (2 * 1.5 ** 2))
    g = g / g.sum()
    k = (g[:, None] * g[None, :]).expand(n.shape[1], 1, 11, 11).contiguous()
    m, m2 = F.conv2d(n, k, groups=n.shape[1]), F.conv2d(n * n, k, groups=n.shape[1])
    return float((m2 - m * m).mean(dim=(0, 2, 3)).max().sqrt())


@pytest.mark.parametrize("full_well,read_noise", [(3000.0, 3.0), (1500.0, 4.0)])
def test_the_exposed_noise_is_measured_as_ssim_sees_it_through_jpeg(full_well, read_noise):
    """Through 8-bit JPEG the pixel-scale estimate misses most of a dark photo's noise; on 2×2 averages it reads
    the noise that SSIM's window sees (the truth: the JPEG photo with noise minus the one without)."""
    from retinexgs.data.sensor import jpeg_roundtrip
    from retinexgs.train.losses import exposed
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[0:384, 0:384] / 384.0
    scene = np.stack([0.5 + 0.3 * np.sin(2 * np.pi * (f * xx + 0.7 * f * yy) + ph)
                      for f, ph in ((3, 0.0), (5, 1.0), (2, 2.0))], -1) * (0.6 + 0.4 * xx[..., None])
    noisy_model = SensorModel(exposure=0.05, exposure_jitter=0.0, full_well=full_well, read_noise=read_noise)
    clean_model = SensorModel(exposure=0.05, exposure_jitter=0.0, full_well=None, read_noise=0.0)
    noisy = jpeg_roundtrip(noisy_model.darken(scene, 0.05, rng), 90) / 255.0
    clean = jpeg_roundtrip(clean_model.darken(scene, 0.05, rng), 90) / 255.0
    as_t = lambda x: torch.from_numpy(np.ascontiguousarray(x)).float().permute(2, 0, 1)[None]  # noqa: E731
    gain = 8.0
    truth = _local_sigma(exposed(as_t(noisy), torch.tensor(gain)) - exposed(as_t(clean), torch.tensor(gain)))
    photo = torch.from_numpy(noisy).float()
    got = N.exposed_noise_sigma(photo, (gain,))[0]
    pixel = N.exposed_noise_sigma(photo, (gain,), scale=1)[0]
    assert got == pytest.approx(truth, rel=0.15), (got, truth)
    assert pixel < 0.6 * truth  # what the pixel scale alone read (the cap this replaced)


@pytest.mark.parametrize("scale", [1, 2])
def test_the_trainer_measures_the_noise_at_the_configured_scale(scenes, tmp_path, monkeypatch, scale):
    seen = {}
    real = N.measure_capture_noise

    def spy(*args, **kwargs):
        seen.update(kwargs)
        return real(*args, **kwargs)

    monkeypatch.setattr("retinexgs.train.capture_setup.measure_capture_noise", spy)
    tr = _trainer(scenes[0], tmp_path / "run", [f"loss.rec_noise_scale={scale}"])
    assert seen["scale"] == scale
    photos = [v.source_path or v.image_path for v in tr.scene.train]
    assert tr.noise.capture_noise == real(photos, 1.0, scale=scale)


def test_a_bad_noise_scale_is_refused_by_name():
    from retinexgs.errors import UserError
    with pytest.raises(UserError, match="rec_noise_scale"):
        load_config([], ["loss.rec_noise_scale=0"])


def test_the_camera_s_mean_record_uses_the_noise_before_the_downscale():
    """A d×d average divides the noise's variance by d², not the mean of noise clipped at black: the SSIM cap
    reads the averaged noise, the camera's mean record (black's lift in ``retinexgs noise``) the captured."""
    meter = N.NoiseMeter()
    for s in range(2):
        meter.add(_photo(SensorModel(exposure=0.03, exposure_jitter=0, full_well=1000.0, read_noise=6.0,
                                     jpeg_quality=0), s))
    full, half = meter.result(1.0), meter.result(2.0)
    assert half.downscale == 2.0 and full.downscale == 1.0
    assert half.b[0] == pytest.approx(full.b[0] / 4) and half.a[1] == pytest.approx(full.a[1] / 4)
    for got, want in zip(half.at_capture(), full.at_capture()):
        assert got == pytest.approx(want)
    assert N.CaptureNoise.from_state(half.state_dict()) == half
    old = {k: v for k, v in half.state_dict().items() if k != "downscale"}  # a checkpoint from before the field
    assert N.CaptureNoise.from_state(old).downscale == 1.0


def test_a_codec_that_cannot_be_written_back_falls_back_to_the_plain_estimate():
    from retinexgs.data.sensor import JpegCodec, estimate_noise
    photo = _photo(SensorModel(exposure=0.03, exposure_jitter=0, full_well=1000.0, read_noise=6.0, jpeg_quality=0))
    meter = N.NoiseMeter(through_codec=True)
    meter.add(photo, JpegCodec(((1, 2, 3),), 0))  # Pillow refuses this table
    plain = estimate_noise(photo.astype(np.float32))
    assert meter.result().a == pytest.approx(plain.a) and meter.result().b == pytest.approx(plain.b)
