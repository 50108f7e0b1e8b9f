"""Issue 32's noise-aware training: the camera's clipped noise (losses.camera_expectation), the capture's noise
measured at set-up and the exposed SSIM's gain capped at the noise floor (train/noise.py), in the trainer."""
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
from retinexgs.train.losses import camera_expectation
from retinexgs.train.trainer import Trainer


def _srgb(y):
    y = np.maximum(y, 0.0)
    return np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.maximum(y, 0.0031308) ** (1 / 2.4) - 0.055)


def _lin(x):
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


@pytest.mark.parametrize("a,b", [(1 / 1500, (4 / 1500) ** 2), (1 / 3000, (2 / 3000) ** 2)])
def test_camera_expectation_is_the_mean_of_the_clipped_noisy_encoding(a, b):
    """E[srgb(max(0, lin(x) + n))], n ~ N(0, a·lin(x) + b), against a Monte Carlo mean: the blacks rise (clipped
    noise is positive on average), the mid-tones fall a little (the sRGB curve bends down)."""
    x = np.array([0.0, 0.01, 0.05, 0.1, 0.2, 0.4, 0.7])
    m = _lin(x)
    z = np.random.default_rng(0).standard_normal(400_000)
    mc = np.array([_srgb(mi + np.sqrt(a * mi + b) * z).mean() for mi in m])
    got = camera_expectation(torch.tensor(x).reshape(1, 1, 1, -1), torch.tensor(a), torch.tensor(b))
    np.testing.assert_allclose(got.flatten().numpy(), mc, atol=1.5e-3)
    assert float(got.flatten()[0]) > 3e-3  # a black render is recorded above black (about one 8-bit level)
    assert float(got.flatten()[3]) < 0.1  # a dark mid-tone a little below its light


def test_camera_expectation_without_noise_is_the_render_and_keeps_a_gradient():
    x = torch.rand(1, 3, 5, 7, dtype=torch.float64) * 0.9 + 0.05
    zero = torch.zeros(1, 3, 1, 1, dtype=torch.float64)
    torch.testing.assert_close(camera_expectation(x, zero, zero), x, atol=1e-5, rtol=0)
    a = torch.tensor([1e-3, 5e-4, 2e-3], dtype=torch.float64).reshape(1, 3, 1, 1)
    b = torch.tensor([1e-5, 4e-6, 2e-5], dtype=torch.float64).reshape(1, 3, 1, 1)
    x = (torch.rand(1, 3, 4, 4, dtype=torch.float64) * 0.8 + 0.1).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: camera_expectation(t, a, b), (x,), eps=1e-7, atol=1e-6)


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
    for name, extra in [("default", []), ("blind", ["loss.rec_noise_floor=false", "loss.rec_camera_noise=false"])]:
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


# ---- density.noise_aware: the noise probe and the densification statistic ---------------------------------------
def test_noise_share_is_the_noise_part_of_the_gradient_energy():
    from retinexgs.strategy import noise_share
    t = lambda *v: torch.tensor(v, dtype=torch.float32)  # noqa: E731
    share = noise_share(grad_sq=t(8.0, 8.0, 2.0, 5.0, 0.0), count=t(2, 2, 2, 0, 1),
                        noise_sq=t(1.0, 0.0, 9.0, 1.0, 1.0), noise_count=t(1, 3, 1, 1, 1))
    # 1/4 of a mean energy of 4; none; more than all (clamped); never seen by the training; no training gradient
    torch.testing.assert_close(share, t(0.25, 0.0, 1.0, 0.0, 0.0))


@pytest.mark.parametrize("aware", [False, True])
def test_densification_statistic_keeps_the_gradient_the_noise_does_not_explain(aware):
    from retinexgs.strategy import DefaultStrategy
    from retinexgs.model.schedule import build_schedule
    cfg = load_config([], [f"density.noise_aware={str(aware).lower()}"])
    d = DefaultStrategy(cfg.density, 1.0, build_schedule(cfg))
    d._ensure(3, torch.device("cpu"))
    d.grad_accum += torch.tensor([4.0, 4.0, 4.0])
    d.grad_sq += torch.tensor([16.0, 16.0, 16.0])
    d.count += 2
    d.noise_sq += torch.tensor([0.0, 6.0, 100.0])  # no noise; 6 / (16 / 2) = 3/4 of the energy; all of it
    d.noise_count += torch.tensor([1.0, 1.0, 1.0])
    want = torch.tensor([2.0, 1.0, 0.0]) if aware else torch.tensor([2.0, 2.0, 2.0])
    torch.testing.assert_close(d.densification_statistic(), want)


def _probe(a=1 / 300, b=(8 / 300) ** 2, seed=0):
    return N.NoiseProbe(N.CaptureNoise((a,) * 3, (b,) * 3, (1.0,), (0.0,), 1), torch.device("cpu"), seed)


def test_the_probe_sees_no_gradient_without_noise_and_leaves_the_random_stream_alone():
    image = torch.rand(24, 32, 6, dtype=torch.float64) * 0.8 + 0.1
    gain = torch.tensor(4.0, dtype=torch.float64)
    before = torch.get_rng_state()
    g0 = _probe(0.0, 0.0).image_gradient(image, gain, 0.2, 1.0)
    assert g0.abs().max() < 1e-9  # the render is the noise-free photo: SSIM is at its maximum
    g = _probe().image_gradient(image, gain, 0.2, 1.0)
    assert torch.equal(torch.get_rng_state(), before)
    assert g.abs().max() > 1e-5
    torch.testing.assert_close(_probe(seed=3).image_gradient(image, gain, 0.2, 1.0),
                               _probe(seed=3).image_gradient(image, gain, 0.2, 1.0), rtol=0, atol=0)


def test_the_probe_draws_the_capture_noise():
    probe = _probe(a=2e-3, b=1e-4)
    clean = torch.full((1, 3, 200, 200), 0.5)
    lin = lambda x: torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)  # noqa: E731
    diff = lin(probe.noisy(clean)) - lin(clean)
    m = float(lin(torch.tensor(0.5)))
    assert float(diff.std()) == pytest.approx(math.sqrt(2e-3 * m + 1e-4), rel=0.03)
    assert abs(float(diff.mean())) < 3e-3


def test_the_probe_gradient_is_the_backward_of_the_ssim_against_a_noisy_render(scenes, tmp_path):
    from retinexgs.evaluate.metrics import ssim
    from retinexgs.train.losses import exposed
    tr = _trainer(scenes[0], tmp_path / "run", ["density.noise_aware=true"])
    assert tr.noise.noise_probe is not None
    tv, gain = tr.views[0], tr.objective.rec_gain()
    res = tr.render_view(tv, 1, graphed=False)
    tr.noise.noise_probe.generator.manual_seed(5)
    g = tr.noise.noise_probe.means2d_gradient(res["out"], gain, 0.2, 1.0)
    res["out"].image.sum().backward()  # the render's graph survives the probe for the step's own backward
    out = tr.render_view(tv, 1, graphed=False)["out"]
    tr.noise.noise_probe.generator.manual_seed(5)
    rec = (out.image[..., :3] * out.image[..., 3:6]).permute(2, 0, 1).unsqueeze(0)
    target = tr.noise.noise_probe.noisy(rec.detach())
    (0.2 * (1.0 - ssim(exposed(rec, gain), exposed(target, gain)))).backward()
    assert g.abs().sum() > 0
    torch.testing.assert_close(g, out.means2d.grad, rtol=1e-4, atol=1e-9)


def test_training_probes_the_noise_of_a_noisy_capture_more_than_of_a_clean_one(scenes, tmp_path):
    extra = ["density.noise_aware=true", "steps=20", "density.start=0", "density.stop=10", "density.every=5",
             "checkpoint.every=100"]
    shares = []
    for k, scene in enumerate(scenes):
        tr = _trainer(scene, tmp_path / f"run{k}", extra)
        tr.train(stop_after=4)
        d = tr.strategy
        assert float(d.noise_count.sum()) > 0 and float(d.grad_sq.sum()) > 0
        seen = (d.count > 0) & (d.noise_count > 0)
        from retinexgs.strategy import noise_share
        shares.append(float(noise_share(d.grad_sq, d.count, d.noise_sq, d.noise_count)[seen].median()))
        tr.train()  # densifies on the statistic through the end of the run
        assert all(torch.isfinite(p).all() for p in tr.model.parameters())
    assert shares[0] > 2 * shares[1], shares


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


def test_a_checkpoint_from_before_the_squared_statistics_resumes():
    """Density state written before grad_sq / noise_sq existed: they restart at zero, the old sums are kept."""
    from retinexgs.strategy import DefaultStrategy
    from retinexgs.model.schedule import build_schedule
    cfg = load_config([], ["density.noise_aware=true"])
    d = DefaultStrategy(cfg.density, 1.0, build_schedule(cfg))
    d.load_state_dict({"grad_accum": torch.tensor([1.0, 2.0]), "count": torch.tensor([1.0, 1.0]),
                       "max_radius": torch.tensor([3.0, 4.0])}, torch.device("cpu"))
    assert torch.equal(d.grad_sq, torch.zeros(2)) and torch.equal(d.noise_count, torch.zeros(2))
    torch.testing.assert_close(d.densification_statistic(), torch.tensor([1.0, 2.0]))  # no noise measured yet
    assert set(d.state_dict()) == {"grad_accum", "count", "grad_sq", "noise_sq", "noise_count", "max_radius"}


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


def test_a_resume_draws_the_probe_noise_where_the_run_stopped(scenes, tmp_path):
    extra = ["density.noise_aware=true", "steps=20", "density.start=0", "density.stop=10", "density.every=5",
             "checkpoint.every=4"]
    tr = _trainer(scenes[0], tmp_path / "run", extra)
    tr.train(stop_after=4)
    saved = load_checkpoint(latest_checkpoint(tmp_path / "run"))["noise_probe_rng"]
    assert torch.equal(saved, tr.noise.noise_probe.generator.get_state())
    fresh = _trainer(scenes[0], tmp_path / "other", extra).noise.noise_probe.generator.get_state()
    assert not torch.equal(saved, fresh)  # the probe drew noise in those steps
    resumed = _trainer(scenes[0], tmp_path / "run", extra, resume=True)
    assert torch.equal(resumed.noise.noise_probe.generator.get_state(), saved)


# ---- model.enhancement.debias_black: the tone takes the clipped noise's mean out of R̂∘L̂ -------------------------

def test_black_table_without_noise_is_the_srgb_decoding():
    from retinexgs.model.tone import black_table, scene_linear, srgb_to_linear
    y = torch.rand(4, 9, 3, generator=torch.Generator().manual_seed(0))
    assert float((scene_linear(y, black_table()) - srgb_to_linear(y)).abs().max()) < 1e-6


def test_black_table_inverts_the_cameras_mean_record():
    """A render that matches the photos' mean (the clipped, encoded noise's mean, camera_mean) is read back as the
    light that made it; below the record of black, as black. 1000 e- full well, read noise 6 e- (the ladder's
    noisiest level)."""
    from retinexgs.model.tone import black_table, camera_mean, linear_to_srgb, scene_linear
    a, b = torch.tensor([1e-3, 1e-3, 2e-3]), torch.tensor([3.6e-5, 3.6e-5, 7.2e-5])
    table = black_table(a, b)
    mu = torch.tensor([0.0, 3e-4, 1e-3, 3e-3, 1e-2, 5e-2, 0.2, 0.6]).reshape(-1, 1).expand(-1, 3)
    record = camera_mean(linear_to_srgb(mu), a, b)
    assert float(record[0, 0]) > 0.02  # black is recorded far above black: what the table undoes
    back = scene_linear(record, table)
    torch.testing.assert_close(back, mu, atol=2e-5, rtol=2e-3)
    below = scene_linear(record[:1] * 0.5, table)
    assert float(below.abs().max()) < 1e-5


def test_scene_linear_through_a_table_has_the_interpolations_gradient():
    from retinexgs.model.tone import black_table, scene_linear
    table = black_table([1e-3] * 3, [3.6e-5] * 3).double()
    n = table.shape[-1]
    idx = torch.tensor([[40, 700, 2000], [90, 1500, 3900]], dtype=torch.float64)
    y = ((idx + 0.5) / (n - 1)).requires_grad_(True)  # between knots: the interpolation is smooth there
    assert torch.autograd.gradcheck(lambda v: scene_linear(v, table), (y,), eps=1e-7, atol=1e-6)


def test_tone_map_with_the_table_puts_the_noise_floor_at_black():
    from retinexgs.model.tone import black_table, camera_mean, tone_map
    a, b = torch.full((3,), 1e-3), torch.full((3,), 3.6e-5)
    floor = camera_mean(torch.zeros(1, 3), a, b)  # the average record of black
    R, L = floor / 0.5, torch.full((1, 3), 0.5)
    ref, g = torch.tensor(0.5), torch.tensor([0.4])
    lifted = tone_map(R, L, ref, g, "exposure", shoulder=0.5)[0]
    fixed = tone_map(R, L, ref, g, "exposure", shoulder=0.5, noise=black_table(a, b))[0]
    assert float(lifted.min()) > 0.2 and float(fixed.max()) < 0.01


def test_debias_black_trains_with_the_measured_noise_and_resumes(scenes, tmp_path):
    from retinexgs.model.tone import black_table
    tr = _trainer(scenes[0], tmp_path / "run", ["model.enhancement.debias_black=true"])
    noise = tr.noise.capture_noise
    assert noise is not None and tr.model.tone_noise() is tr.model.black_table
    torch.testing.assert_close(tr.model.black_table, black_table(noise.a, noise.b))
    assert not torch.allclose(tr.model.black_table, black_table())  # a noisy capture: not the identity
    tr.train(stop_after=2)
    saved = load_checkpoint(latest_checkpoint(tmp_path / "run"))["model"]["black_table"]
    torch.testing.assert_close(saved, tr.model.black_table)
    resumed = _trainer(scenes[0], tmp_path / "run", ["model.enhancement.debias_black=true"], resume=True)
    resumed.train()
    off = _trainer(scenes[0], tmp_path / "off")
    assert off.model.tone_noise() is None and not hasattr(off.model, "black_table")


def test_black_filter_reads_the_noise_over_the_training_views_and_is_checkpointed(scenes, tmp_path):
    """model.enhancement.black_filter: ε of the filter before the black table is the capture's noise (a, b at the
    training images' scale) over the number of training views, set at set-up and carried by the checkpoint."""
    extra = ["model.enhancement.debias_black=true", "model.enhancement.black_filter=2"]
    tr = _trainer(scenes[0], tmp_path / "run", extra)
    noise, views = tr.noise.capture_noise, len(tr.scene.train)
    expected = torch.tensor([noise.a, noise.b], dtype=torch.float32) / views
    assert views == 3 and float(expected.min()) > 0
    torch.testing.assert_close(tr.model.black_spread, expected)
    tr.train(stop_after=2)
    saved = load_checkpoint(latest_checkpoint(tmp_path / "run"))["model"]["black_spread"]
    torch.testing.assert_close(saved, expected)
    # the enhanced frame is the filtered reading: not the unfiltered one of the same maps
    from retinexgs.run.render import view_camera
    with torch.no_grad():
        res = tr.model.render(view_camera(tr.scene.test[0]), 0)
        tr.model.black_filter = 0
        unfiltered = tr.model.tone_map(res["R"], res["L"], res["gamma"])[0]
    assert float((res["rgb"] - unfiltered).abs().max()) > 1e-4
    off = _trainer(scenes[0], tmp_path / "off", ["model.enhancement.debias_black=true"])
    assert not hasattr(off.model, "black_spread")


def test_the_camera_s_mean_record_uses_the_noise_before_the_downscale():
    """A d×d average divides the noise's variance by d², not the mean of noise clipped at black: the SSIM cap and
    the probe read the averaged noise, the camera's mean record (black table, camera expectation) the captured."""
    meter = N.NoiseMeter()
    for s in range(2):
        meter.add(_photo(SensorModel(exposure=0.03, exposure_jitter=0, full_well=1000.0, read_noise=6.0,
                                     jpeg_quality=0), s))
    full, half = meter.result(1.0), meter.result(2.0)
    assert half.downscale == 2.0 and full.downscale == 1.0
    assert half.b[0] == pytest.approx(full.b[0] / 4) and half.a[1] == pytest.approx(full.a[1] / 4)
    for got, want in zip(half.at_capture(), full.at_capture()):
        assert got == pytest.approx(want)
    a, b = half.camera("cpu")
    assert a.shape == (1, 3, 1, 1) and float(b[0, 2, 0, 0]) == pytest.approx(full.b[2], rel=1e-6)
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
