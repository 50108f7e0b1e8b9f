"""Issue 52, stage 3b: raw scenes train in linear light on their unclipped values, weighted by their noise.

Fixtures: synthetic DNGs written by the simulator's pieces (retinexgs.data.raw_sim) and tiny demo scenes turned
into raw scenes by ``darken --raw``; never the shared data.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from retinexgs.config.versions import FORMAT
from retinexgs.data.camera_raw import read_raw, read_view_srgb
from retinexgs.data.dng import write_dng
from retinexgs.data.raw_noise import DISAGREEMENT, scene_noise, view_noise
from retinexgs.data.raw_sim import RawCamera, capture_mosaic, write_raw_view
from retinexgs.data.sensor import SensorModel
from retinexgs.data.srgb import (linear_to_srgb, linear_to_srgb_extended,
                                 srgb_to_linear_extended)
from retinexgs.demo.synthetic import make_demo_scene
from retinexgs.train import losses
from scenes import TINY_RUN, run_cli


# ---- the unclipped encoding -----------------------------------------------------------------------------------

def test_the_extended_encoding_is_the_srgb_curve_on_0_1_and_inverts_exactly_beyond_it():
    x = np.linspace(-0.3, 4.0, 4001)
    y = linear_to_srgb_extended(x)
    assert np.all(np.diff(y) > 0)  # monotone: a median commutes with it
    assert np.allclose(srgb_to_linear_extended(y), x, atol=1e-12, rtol=0)
    inside = (x >= 0) & (x <= 1)
    assert np.array_equal(y[inside], linear_to_srgb(x[inside]))
    assert np.allclose(y[x < 0], 12.92 * x[x < 0])  # the linear segment, continued
    t = torch.tensor([-0.01, 0.5, 2.0], dtype=torch.float64)
    assert torch.allclose(srgb_to_linear_extended(linear_to_srgb_extended(t)), t)


# ---- the linear reconstruction --------------------------------------------------------------------------------

def _target(mode: str, a=(0.004, 0.002, 0.002), b=(3e-4, 1e-4, 1e-4)) -> losses.LinearTarget:
    return losses.LinearTarget(mode, torch.tensor(a, dtype=torch.float64).reshape(1, 3, 1, 1),
                               torch.tensor(b, dtype=torch.float64).reshape(1, 3, 1, 1))


def test_linear_weights_follow_the_noise_model_or_rawnerf_and_average_one():
    x = torch.rand(2, 3, 5, 7, dtype=torch.float64) * 0.1
    t = _target("noise")
    w = losses.linear_weights(x, t, torch.tensor(10.0, dtype=torch.float64))
    want = 1.0 / (t.a * x + t.b)
    assert torch.allclose(w, want / want.mean(dim=(1, 2, 3), keepdim=True))
    assert torch.allclose(w.mean(dim=(1, 2, 3)), torch.ones(2, dtype=torch.float64))
    w = losses.linear_weights(x, _target("relative"), torch.tensor(10.0, dtype=torch.float64))
    want = 1.0 / (10.0 * x + losses.RELATIVE_EPS) ** 2
    assert torch.allclose(w, want / want.mean(dim=(1, 2, 3), keepdim=True))
    with pytest.raises(ValueError, match="unknown linear"):
        losses.linear_weights(x, _target("median"), torch.tensor(1.0))


def test_the_linear_fit_of_noisy_views_is_their_mean_light_where_the_clipped_photo_lifts_black():
    """Many views of one dark grey point (light μ, noise σ ≫ μ, so a quarter of the values are negative): the
    render that zeroes the linear term's gradient is the views' mean light, to float64 precision, in both weight
    modes. The same views as clipped photos average well above μ (the lift that stage 3a kept)."""
    rng = np.random.default_rng(0)
    mu, sigma, n = 0.004, 0.01, 4096
    views = mu + sigma * rng.standard_normal((1, 3, 1, n))
    S = torch.tensor(linear_to_srgb_extended(views), dtype=torch.float64)
    gain = torch.tensor(20.0, dtype=torch.float64)
    mean = torch.tensor(views.mean(axis=-1, keepdims=True))
    for mode in ("noise", "relative"):
        rec = linear_to_srgb(mean).expand(1, 3, 1, n).clone().requires_grad_(True)
        losses.linear_reconstruction(rec, S, _target(mode), gain).backward()
        assert rec.grad.sum(dim=-1).abs().max() < 1e-12, mode
    # off the mean, the gradient points back to it
    rec = linear_to_srgb(mean * 2).expand(1, 3, 1, n).clone().requires_grad_(True)
    losses.linear_reconstruction(rec, S, _target("noise"), gain).backward()
    assert torch.all(rec.grad.sum(dim=-1) > 0)
    clipped = np.clip(views, 0, None).mean()
    assert clipped > mu + 0.2 * sigma  # E[max(0, X)]: 0.23σ above μ here; what fitting clipped photos gives


def test_supervision_loss_uses_the_linear_term_for_the_reconstruction_only():
    torch.manual_seed(0)
    R_hat, L_hat = torch.rand(1, 3, 16, 16), torch.rand(1, 1, 16, 16)
    R, L = torch.rand(1, 3, 16, 16), torch.rand(1, 1, 16, 16)
    S = torch.randn(1, 3, 16, 16) * 0.05 + 0.1  # negative values present
    gain = torch.tensor(4.0)
    t = losses.LinearTarget("noise", torch.full((1, 3, 1, 1), 0.01), torch.full((1, 3, 1, 1), 1e-3))
    _, plain = losses.supervision_loss(R_hat, L_hat, R, L, S.clamp(0, 1), rec_gain=gain, rec_l1_exposed=False)
    _, lin = losses.supervision_loss(R_hat, L_hat, R, L, S, rec_gain=gain, rec_l1_exposed=False, linear=t)
    assert torch.allclose(plain["sup_r"], lin["sup_r"]) and torch.allclose(plain["sup_l"], lin["sup_l"])
    rec = R_hat * L_hat
    ssim = losses.ssim(losses.exposed(rec, gain), losses.exposed(S, gain, extended=True))
    want = 0.8 * losses.linear_reconstruction(rec, S, t, gain) + 0.2 * (1 - ssim)
    assert torch.allclose(lin["sup_rec"], want, atol=1e-6)
    alone = losses.reconstruction_loss(rec, S, 0.2, gain, False, linear=t)
    assert torch.allclose(alone, want, atol=1e-6)


# ---- the views' noise model -----------------------------------------------------------------------------------

def _grey_dng(tmp_path, name="grey.dng", value=0.3, profile_scale=1.0, size=192):
    model = SensorModel(exposure=0.1, exposure_jitter=0.0, full_well=1000.0, read_noise=6.0)
    cam = RawCamera(bits=14, cfa="RGGB")
    grey = np.full((size, size, 3), value)
    dn = capture_mosaic(grey, model, cam, 0.1, np.random.default_rng(1))
    path = write_raw_view(tmp_path / name, dn, cam, model, 0.1)
    if profile_scale != 1.0:  # the same pixels with a NoiseProfile that misstates them
        p = read_raw(path)
        s, o = p.noise_profile[0]
        write_dng(path, p.mosaic, cfa=p.cfa_pattern, black_level=float(p.black_level[0, 0]),
                  white_level=int(p.white_level), as_shot_neutral=tuple(1 / p.white_balance),
                  color_matrix1=p.xyz_to_cam, exposure_time=p.exposure_time, iso=p.iso, f_number=p.f_number,
                  noise_profile=[s * profile_scale, o * profile_scale])
    return path


def test_the_view_noise_model_predicts_the_views_own_variance(tmp_path):
    """A flat grey DNG: the variance of its view's unclipped linear values, per channel, is the model's a·y + b
    within 15 % (white balance, demosaic and matrix carried through; 36864 pixels, neighbours correlated by the
    demosaic)."""
    path = _grey_dng(tmp_path)
    a, b, source, note = view_noise(read_raw(path))
    assert source == "profile" and note is None
    y = srgb_to_linear_extended(read_view_srgb(path, clip=False).astype(np.float64))[8:-8, 8:-8]
    for c in range(3):
        m = y[..., c].mean()
        assert y[..., c].var() == pytest.approx(a[c] * m + b[c], rel=0.15), c


def test_a_noise_profile_that_disagrees_with_its_pixels_is_named_and_not_used(tmp_path):
    path = _grey_dng(tmp_path, profile_scale=4 * DISAGREEMENT)
    a, b, source, note = view_noise(read_raw(path))
    assert source == "estimate" and note is not None
    assert str(path) in note and "NoiseProfile disagrees" in note and "\n" not in note
    good = view_noise(read_raw(_grey_dng(tmp_path, "good.dng")))
    m = srgb_to_linear_extended(read_view_srgb(path, clip=False).astype(np.float64)).mean(axis=(0, 1))
    assert np.allclose(a * m + b, good[0] * m + good[1], rtol=0.3)  # one grey level: the variance there
    noise = scene_noise([path])
    assert noise.source == "estimate" and len(noise.notes) == 1


# ---- training ---------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def night(tmp_path_factory):
    base = tmp_path_factory.mktemp("raw_linear")
    src = make_demo_scene(base / "src", n_train=3, n_test=1, width=48, height=36, n_points=200)
    from retinexgs.cli import main
    assert main(["darken", "--data", str(src), "--out", str(base / "night"), "--raw", "--quiet"]) == 0
    return base / "night"


def _train(scene, out, capsys, *extra):
    sets = [a for s in (*TINY_RUN, *extra) for a in ("--set", s)]
    return run_cli(["train", "--data", scene, "--out", out, "--config", "demo", *sets, "--device", "cpu"], capsys)


@pytest.mark.parametrize("mode", ["noise", "relative", "photo"])
def test_a_raw_scene_trains_in_the_chosen_domain_and_says_so(night, tmp_path, capsys, mode):
    code, out, err = _train(night / "raw", tmp_path / "run", capsys, f"loss.raw.mode={mode}")
    assert code == 0, err
    said = "reconstruction in linear light" in out + err
    assert said == (mode != "photo"), (mode, out + err)
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert all(np.isfinite(v["psnr"]) for v in metrics["views"])
    if mode == "noise":  # the noise model travels with the checkpoint (a resume weighs pixels alike)
        ckpt = sorted((tmp_path / "run" / "checkpoints").iterdir())[-1]
        state = torch.load(next(ckpt.glob("*.pt")) if ckpt.is_dir() else ckpt, map_location="cpu",
                           weights_only=False)
        assert state["raw_noise"]["source"] == "profile" and len(state["raw_noise"]["a"]) == 3


def test_a_jpeg_scene_is_not_touched_by_rec_raw(night, tmp_path, capsys):
    code, out, err = _train(night / "jpeg", tmp_path / "run", capsys, "loss.raw.mode=noise")
    assert code == 0, err
    assert "linear light" not in out + err


def test_the_training_target_of_a_raw_view_keeps_its_negative_noise(night):
    from retinexgs.data.load import load_scene
    scene = load_scene(night / "raw")
    assert scene.raw
    v = scene.train[0]
    target, shown = v.load_target(), v.load_image()
    assert target.min() < 0 and shown.min() >= 0  # the noise around black, unclipped for training only
    assert torch.equal(shown.half().float(), target.clamp(0, 1))  # the target is rounded to float16
    jpeg = load_scene(night / "jpeg")
    assert not jpeg.raw and torch.equal(jpeg.train[0].load_target(), jpeg.train[0].load_image())


def test_the_linear_term_is_measured_at_its_own_gain_not_the_noise_floors_cap():
    """The noise floor caps the reconstruction's gain for its SSIM; the linear term keeps the scene's exposure
    (its target's gain), so a cap does not shrink it by the cap² beside the priors."""
    torch.manual_seed(1)
    rec, S = torch.rand(1, 3, 8, 8) * 0.2, torch.randn(1, 3, 8, 8) * 0.05 + 0.1
    t = losses.LinearTarget("noise", torch.full((1, 3, 1, 1), 0.01), torch.full((1, 3, 1, 1), 1e-3))
    own = losses.linear_reconstruction(rec, S, t._replace(gain=torch.tensor(12.0)), torch.tensor(1.0))
    assert torch.allclose(own, losses.linear_reconstruction(rec, S, t, torch.tensor(12.0)))
    capped = losses.linear_reconstruction(rec, S, t, torch.tensor(1.0))
    assert torch.allclose(own, capped * 144.0)


def test_a_photo_of_odd_size_becomes_a_raw_scene_whose_truth_is_cropped_alike(tmp_path, capsys):
    """The DNG of a 48x35 photo is read as 48x34 (whole 2x2 quads): the view keeps its focal length and centre
    (a crop, not a rescale), and its truth is cropped to the same rows; no "rescaled" warning."""
    from retinexgs.cli import main
    from retinexgs.data.load import load_scene
    src = make_demo_scene(tmp_path / "src", n_train=3, n_test=1, width=48, height=35, n_points=200)
    assert main(["darken", "--data", str(src), "--out", str(tmp_path / "night"), "--raw", "--quiet"]) == 0
    capsys.readouterr()
    raw = load_scene(tmp_path / "night" / "raw")
    assert "rescaled" not in capsys.readouterr().err
    jpeg = load_scene(tmp_path / "night" / "jpeg")
    for r, j in zip(raw.test, jpeg.test):
        assert (r.width, r.height) == (48, 34) and (j.width, j.height) == (48, 35)
        assert (r.fx, r.fy, r.cx, r.cy) == (j.fx, j.fy, j.cx, j.cy)
        assert torch.equal(r.paired_image, j.paired_image[:34])


# ---- the priors' photo ----------------------------------------------------------------------------------------------

def test_the_denoised_preview_keeps_a_dark_flat_area_s_light_and_an_edge():
    """A dark flat area (light 0.002, noise σ 0.01: a third of the values negative) beside a bright one: through the
    preview the dark area's mean light stays within 0.001 of the truth, where clipping first lifts it by about 0.3σ,
    and the step between the two areas keeps over 90 % of its height."""
    from retinexgs.data.raw_noise import denoised_preview
    rng = np.random.default_rng(3)
    light = np.full((64, 64, 3), 0.002)
    light[:, 32:] = 0.2
    views = light + 0.01 * rng.standard_normal(light.shape)
    image = torch.tensor(linear_to_srgb_extended(views), dtype=torch.float32)
    out = srgb_to_linear_extended(denoised_preview(image).double()).numpy()
    dark = out[8:-8, 4:24]
    assert abs(dark.mean() - 0.002) < 0.001, dark.mean()
    assert np.clip(views[8:-8, 4:24], 0, None).mean() > 0.002 + 0.003  # the clipped photo's lift
    assert out[8:-8, 40:60].mean() - dark.mean() > 0.9 * 0.198
    assert out[8:-8, 40:60].std() < 0.5 * 0.01  # the flat bright area smoothed too
    assert out.min() >= 0 and out.max() <= 1


def test_a_raw_view_s_priors_are_keyed_by_the_preview_they_come_from(night, tmp_path):
    from retinexgs.data.load import load_scene
    from retinexgs.retinex.cache import content_hash, iter_decompositions, prior_key
    raw, jpeg = load_scene(night / "raw"), load_scene(night / "jpeg")
    p, q = raw.train[0].image_path, jpeg.train[0].image_path
    assert prior_key(p, True) != prior_key(p, False) == content_hash(p)
    assert prior_key(q, True) == prior_key(q, False) == content_hash(q)  # a JPEG: no preview, one entry
    paths = [v.image_path for v in raw.train]
    on = list(iter_decompositions(paths, "lr3m", None, tmp_path / "c", progress=False, raw_denoise=True))
    off = list(iter_decompositions(paths, "lr3m", None, tmp_path / "c", progress=False))
    entries = sorted((tmp_path / "c").rglob("*.npz"))
    assert len(entries) == 2 * len(paths)  # both kept, neither read as the other
    assert not torch.equal(on[0][0], off[0][0])


def test_an_odd_sized_distorted_raw_scene_undistorts_its_truth_with_the_cropped_camera(tmp_path):
    """Lens distortion declared (the undistort cache runs): the truth, one row taller than the raw view, is cropped
    to the view before the remap, so truth and view share one pinhole camera."""
    from retinexgs.cli import main
    from retinexgs.data.load import load_scene
    src = make_demo_scene(tmp_path / "src", n_train=3, n_test=1, width=48, height=35, n_points=200)
    for f in src.glob("transforms_*.json"):
        d = json.loads(f.read_text())
        d.update(k1=0.02, k2=-0.01)
        f.write_text(json.dumps(d))
    assert main(["darken", "--data", str(src), "--out", str(tmp_path / "night"), "--raw", "--quiet"]) == 0
    raw = load_scene(tmp_path / "night" / "raw")
    v = raw.test[0]
    assert v.paired_path.suffix == ".png" and "undistorted" in str(v.paired_path)
    assert v.image_path.suffix == ".npy"
    assert tuple(v.paired_image.shape[:2]) == tuple(v.load_target().shape[:2]) == (34, 48)


def test_a_raw_scene_s_views_are_stored_as_float16_and_stream_as_they_preload(night, tmp_path):
    """The raw target is rounded to float16 when read (an exact float16 array, 6 B per pixel in the store), so the
    streamed views equal the preloaded ones bit for bit, negative noise included."""
    from retinexgs.data.load import load_scene
    from retinexgs.run.config import load_config
    from retinexgs.train.trainer import Trainer

    def make(run, mode):
        cfg = load_config(["demo"], [*TINY_RUN, f"train.stream_views={mode}"])
        run.mkdir(parents=True)
        return Trainer(cfg, load_scene(night / "raw"), run, "cpu", progress=False, log=lambda s: None)

    pre, st = make(tmp_path / "pre", "never"), make(tmp_path / "st", "always")
    for i in range(len(pre.views)):
        assert st.views.store.photo(i).dtype == np.float16
        a, b = pre.views[i], st.views[i]
        assert torch.equal(a.S, b.S) and a.S.min() < 0
        assert torch.equal(a.S.half().float(), a.S)


def test_the_sigma_unit_pulls_a_pixel_at_one_sigma_with_force_one_and_keeps_the_weights_ratios():
    """loss.raw.unit sigma: Σ w·e² / (2·sqrt(mean w)) per image, w = 1 / var of the exposed error: on an image
    of one noise level σ the force on the exposed error at e = σ is 1 (an L1's), where plain's is 2σ; between
    pixels the weights keep the noise model's ratios (each pixel's minimiser is plain's)."""
    a = torch.zeros(1, 3, 1, 1)
    b = torch.full((1, 3, 1, 1), 1e-4)  # σ = 0.01 in linear light
    gain = torch.tensor(4.0, dtype=torch.float64)  # σ = 0.04 exposed
    y = torch.full((1, 3, 5, 5), 0.2, dtype=torch.float64)  # the views' light
    S = linear_to_srgb_extended(y)
    n = y.numel()
    force = {}
    for unit in ("plain", "sigma"):
        x = (y + 0.01).requires_grad_(True)  # the render's light, one σ above
        target = losses.LinearTarget("noise", a.double(), b.double(), unit=unit)
        (losses.linear_reconstruction(linear_to_srgb_extended(x), S, target, gain) * n).backward()
        force[unit] = float((x.grad / gain).mean())  # d(per-pixel term)/d(exposed error)
    assert force["sigma"] == pytest.approx(1.0, rel=1e-4)
    assert force["plain"] == pytest.approx(2 * 0.04, rel=1e-4)
    # two noise levels in one image: the weights' ratio is the noise model's in both units
    b2 = torch.tensor([1e-4, 4e-4, 1e-4]).reshape(1, 3, 1, 1)
    xs = torch.full((1, 3, 4, 4), 0.2)
    wp = losses.linear_weights(xs, losses.LinearTarget("noise", a, b2), torch.tensor(4.0))
    ws = losses.linear_weights(xs, losses.LinearTarget("noise", a, b2, unit="sigma"), torch.tensor(4.0),
                               normalise=False)
    assert torch.allclose(wp[:, 1] / wp[:, 0], ws[:, 1] / ws[:, 0])
    assert float((ws[:, 1] / ws[:, 0]).mean()) == pytest.approx(0.25)
    with pytest.raises(ValueError, match="unit"):
        losses.linear_reconstruction(linear_to_srgb_extended(y), S, losses.LinearTarget("noise", a, b, unit="stops"),
                                     gain)


def test_rec_raw_unit_is_a_config_key_whose_runs_from_before_it_keep_plain():
    from retinexgs.run.config import load_config
    from retinexgs.config.versions import FORMAT_0_VALUES
    assert load_config().loss.raw.unit == "plain"
    assert load_config(["ablations/raw_sigma"]).loss.raw.unit == "sigma"
    assert FORMAT_0_VALUES["loss.rec_raw_unit"] == "plain"


def test_the_priors_fade_where_their_preview_cannot_resolve_the_light():
    """loss.raw.prior_snr k: the priors' L1 weighs each pixel by min(1, m / (k·σ_m)), m the 9×9 mean of the
    view's light, σ_m its noise: 0 on black, 1 well above the noise; k = 0 leaves every pixel alike."""
    a, b = torch.zeros(1, 3, 1, 1), torch.full((1, 3, 1, 1), 1e-2)  # σ = 0.1 a pixel, 0.1 / 9 for a 9×9 mean
    light = torch.zeros(1, 3, 24, 48)
    light[..., 24:] = 0.5  # right half bright, left half black
    S = linear_to_srgb_extended(light)
    conf = losses.prior_confidence(S, losses.LinearTarget("noise", a, b, prior_snr=3.0))
    assert conf.shape == (1, 1, 24, 48)
    assert float(conf[..., :12].max()) == 0.0 and float(conf[..., 36:].min()) == 1.0
    # the priors' terms: an error only in the black half counts with k > 0 only when the preview could see it
    R_hat, L_hat = torch.full((1, 3, 24, 48), 0.5), torch.full((1, 1, 24, 48), 0.5)
    R, L = R_hat.clone(), L_hat.clone()
    R[..., :12] = 0.9
    off = losses.LinearTarget("noise", a, b)
    on = off._replace(prior_snr=3.0)
    _, t_off = losses.supervision_loss(R_hat, L_hat, R, L, S, rec_gain=torch.tensor(2.0), linear=off, lambda_ssim=0)
    _, t_on = losses.supervision_loss(R_hat, L_hat, R, L, S, rec_gain=torch.tensor(2.0), linear=on, lambda_ssim=0)
    assert float(t_off["sup_r"]) == pytest.approx(0.4 / 4) and float(t_on["sup_r"]) == 0.0
    assert torch.equal(t_on["sup_rec"], t_off["sup_rec"])
    from retinexgs.run.config import load_config
    from retinexgs.config.versions import FORMAT_0_VALUES
    assert load_config().loss.raw.prior_snr == 3.0
    assert load_config(["ablations/raw_prior_uniform"]).loss.raw.prior_snr == 0.0
    assert FORMAT_0_VALUES["loss.rec_raw_prior_snr"] == 0.0


def test_the_highlight_knee_is_the_raw_shoulder_on_a_raw_scene_and_shoulder_on_a_photo_scene():
    from retinexgs.run.config import load_config
    from retinexgs.config.versions import FORMAT_0_VALUES
    from retinexgs.data.capture import PHOTO, RAW
    enh = load_config().model.enhancement
    assert (enh.shoulder, enh.raw.shoulder) == (0.5, 1.0)
    assert PHOTO.knee(enh) == 0.5 and RAW.knee(enh) == 1.0
    old = load_config(["ablations/raw_shoulder"]).model.enhancement
    assert old.raw.shoulder is None and RAW.knee(old) == 0.5 == PHOTO.knee(old)
    assert RAW.knee(load_config(overrides=["model.enhancement.raw.shoulder=0.7"]).model.enhancement) == 0.7
    assert FORMAT_0_VALUES["model.enhancement.shoulder_raw"] is None  # runs from before it keep the photos' knee
    with pytest.raises(Exception, match="model.enhancement.raw.shoulder"):
        load_config(overrides=["model.enhancement.raw.shoulder=0"])


def test_a_raw_run_trains_and_renders_with_its_knee_and_a_run_from_before_the_key_keeps_the_photos(
        night, tmp_path, capsys):
    """The trainer's model, the run read back (eval, render, export) and a run whose config predates the key."""
    import yaml
    from retinexgs.run.folder import load_run
    for scene, knee in (("raw", 1.0), ("jpeg", 0.5)):
        code, _, err = _train(night / scene, tmp_path / scene, capsys)
        assert code == 0, err
        cfg, loaded, model, _ = load_run(tmp_path / scene, "cpu")
        assert loaded.raw == (scene == "raw") and model.shoulder == knee and model.capture is loaded.capture
        assert model.with_enhancement(cfg.model.enhancement).shoulder == knee  # retone keeps the scene's knee
    path = tmp_path / "raw" / "config.yaml"
    recorded = yaml.safe_load(path.read_text())
    del recorded["model"]["enhancement"]["raw"]
    assert recorded.pop("format") == FORMAT  # written today; a run from before the key had no format (format 0)
    path.write_text(yaml.safe_dump(recorded))
    assert load_run(tmp_path / "raw", "cpu")[2].shoulder == 0.5


def test_the_extended_targets_mean_is_dragged_down_by_the_noise_and_the_photos_is_not():
    """Why loss.raw.spa reads the photo: L_spa normalises by the input's mean. Light 0.01 under noise σ 0.03: the
    extended encoding's mean falls far below the sRGB of the light (the negative half is ×12.92, the positive
    half compressed); the clipped photo's stays near it."""
    torch.manual_seed(0)
    light = 0.01 + 0.03 * torch.randn(200_000, dtype=torch.float64)
    ext, photo = linear_to_srgb_extended(light).mean(), linear_to_srgb(light.clamp(0, 1)).mean()
    want = float(linear_to_srgb(torch.tensor(0.01, dtype=torch.float64)))
    assert float(ext) < 0.3 * want and abs(float(photo) - want) < 0.5 * want


@pytest.mark.parametrize("spa_raw", ["photo", "extended"])
def test_l_spa_of_a_raw_view_compares_with_the_photo_it_shows(night, tmp_path, spa_raw):
    from retinexgs.run.config import load_config
    from retinexgs.config.versions import FORMAT_0_VALUES
    from retinexgs.run.folder import open_scene
    from retinexgs.train.trainer import Trainer, enhancement_objective
    assert load_config().loss.raw.spa == "photo" and FORMAT_0_VALUES["loss.spa_raw"] == "extended"
    assert load_config(["ablations/spa_raw_extended"]).loss.raw.spa == "extended"
    cfg = load_config(["demo"], overrides=[*TINY_RUN, f"loss.raw.spa={spa_raw}"])
    for kind in ("raw", "jpeg"):
        scene = open_scene(night / kind, cfg)
        tr = Trainer(cfg, scene, tmp_path / f"{kind}-{spa_raw}", "cpu", progress=False, log=lambda m: None)
        S = scene.train[0].load_target()
        assert (S.min() < 0) == (kind == "raw")  # the raw target keeps its noise below black
        image = torch.rand(*S.shape[:2], 6) * 0.2
        _, terms = tr.objective.image_loss(image, S, None, None, enhance=True)
        S_b = S.permute(2, 0, 1).unsqueeze(0)
        read = S_b.clamp(0, 1) if kind == "raw" and spa_raw == "photo" else S_b
        _, want = enhancement_objective(tr.model, cfg.loss, image[..., :3], image[..., 3:6], read)
        assert float(terms["spa"].detach()) == pytest.approx(float(want["spa"].detach()), rel=1e-6)
        if kind == "raw":  # and the two readings differ on this view
            _, other = enhancement_objective(tr.model, cfg.loss, image[..., :3], image[..., 3:6],
                                             S_b if spa_raw == "photo" else S_b.clamp(0, 1))
            assert float(other["spa"].detach()) != pytest.approx(float(want["spa"].detach()), rel=1e-3)


def test_a_balanced_raw_scene_scales_its_noise_model_with_the_gains(night, tmp_path):
    """data.white_balance on a raw scene multiplies each channel's light by g, so the weights' noise model becomes
    g·a·y + g²·b; the as-shot scene keeps the model as measured."""
    from retinexgs.run.config import load_config
    from retinexgs.run.folder import open_scene
    from retinexgs.train.trainer import Trainer
    models = {}
    for name, extra in (("shot", []), ("balanced", ["ablations/train_white_balance"])):
        cfg = load_config(["demo", *extra], overrides=TINY_RUN)
        scene = open_scene(night / "raw", cfg)
        tr = Trainer(cfg, scene, tmp_path / name, "cpu", progress=False, log=lambda m: None)
        models[name] = (tr.noise.linear_target, scene.train[0].balance)
    (shot, none), (bal, g) = models["shot"], models["balanced"]
    assert none is None and g is not None and abs(g[0] - 1.0) + abs(g[2] - 1.0) > 1e-3
    gt = torch.tensor(g).reshape(1, 3, 1, 1)
    assert torch.allclose(bal.a, shot.a * gt) and torch.allclose(bal.b, shot.b * gt * gt)
