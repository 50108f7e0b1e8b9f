"""retinexgs/model/tone.py: the three tone forms against hand-written formulas, the sRGB pair, gradients."""
import math

import pytest
import torch

from retinexgs.model.tone import exposure_gain, linear_to_srgb, srgb_to_linear, tone_map


def _srgb_scalar(v: float) -> float:
    v = min(max(v, 0.0), 1.0)
    return 12.92 * v if v <= 0.0031308 else 1.055 * v ** (1 / 2.4) - 0.055


def _lin_scalar(v: float) -> float:
    return v / 12.92 if v <= 0.04045 else ((v + 0.055) / 1.055) ** 2.4


def test_srgb_pair_matches_the_standard_and_inverts():
    xs = [0.0, 0.001, 0.003, 0.0031308, 0.01, 0.2, 0.5, 1.0]
    t = torch.tensor(xs, dtype=torch.float64)
    assert torch.allclose(linear_to_srgb(t), torch.tensor([_srgb_scalar(v) for v in xs], dtype=torch.float64))
    assert torch.allclose(srgb_to_linear(t), torch.tensor([_lin_scalar(v) for v in xs], dtype=torch.float64))
    u = torch.linspace(0, 1, 1001, dtype=torch.float64)
    assert torch.allclose(linear_to_srgb(srgb_to_linear(u)), u, atol=1e-12)
    # Past white the encoding clips (what the camera does): no value above 1.
    assert float(linear_to_srgb(torch.tensor([3.0]))) == pytest.approx(1.0, abs=1e-6)
    # 18 % grey encodes near 0.46 (the sRGB mid-grey).
    assert float(linear_to_srgb(torch.tensor([0.18]))) == pytest.approx(0.4614, abs=1e-3)


def test_exposure_tone_is_a_gain_in_linear_light():
    torch.manual_seed(0)
    R = torch.rand(4, 5, 3, dtype=torch.float64)
    L = 0.05 + 0.2 * torch.rand(4, 5, 3, dtype=torch.float64)
    ref = torch.tensor(0.3, dtype=torch.float64)
    for g in (1.0, 0.7, 0.4):
        gamma = torch.tensor([g], dtype=torch.float64)
        rgb, light = tone_map(R, L, ref, gamma, "exposure")
        k = math.exp(-math.log(_lin_scalar(0.3)) / g)
        assert float(exposure_gain(ref, gamma)) == pytest.approx(k, rel=1e-12)
        want = torch.tensor([_srgb_scalar(k * _lin_scalar(v)) for v in (R * L).reshape(-1).tolist()],
                            dtype=torch.float64).reshape(R.shape)
        want_l = torch.tensor([_srgb_scalar(k * _lin_scalar(v)) for v in L.reshape(-1).tolist()],
                              dtype=torch.float64).reshape(L.shape)
        assert torch.allclose(rgb, want, atol=1e-12) and torch.allclose(light, want_l, atol=1e-12)
    # g = 1 maps the full light L_ref to white; a smaller g is brighter everywhere it is not clipped.
    _, light = tone_map(R, torch.full_like(L, 0.3), ref, torch.tensor([1.0], dtype=torch.float64), "exposure")
    assert torch.allclose(light, torch.ones_like(light))
    lo, _ = tone_map(R, L, ref, torch.tensor([0.9], dtype=torch.float64), "exposure")
    hi, _ = tone_map(R, L, ref, torch.tensor([0.6], dtype=torch.float64), "exposure")
    assert bool((hi >= lo).all()) and float((hi - lo).mean()) > 0.01
    # A gain keeps ratios in linear light (until the clip): lin(S_enh) / lin(R̂∘L̂) is the same k everywhere.
    small = L * 0.05
    rgb, _ = tone_map(R, small, ref, torch.tensor([0.9], dtype=torch.float64), "exposure")
    ratio = srgb_to_linear(rgb) / srgb_to_linear(R * small).clamp_min(1e-300)
    keep = srgb_to_linear(rgb) < 0.99
    assert ratio[keep].std() / ratio[keep].mean() < 1e-9


def test_gamma_tones_are_the_papers_and_the_signal_form():
    torch.manual_seed(1)
    R = torch.rand(3, 4, 3, dtype=torch.float64)
    L = 0.3 * torch.rand(3, 4, 3, dtype=torch.float64)
    ref = torch.tensor(0.25, dtype=torch.float64)
    g = torch.tensor([0.5], dtype=torch.float64)
    ell = (L / 0.25).clamp(0, 1).clamp_min(1e-3)
    rgb, light = tone_map(R, L, ref, g, "illumination")
    assert torch.allclose(light, ell ** 0.5) and torch.allclose(rgb, (R * ell ** 0.5).clamp(0, 1))
    rgb, _ = tone_map(R, L, ref, g, "signal")
    assert torch.allclose(rgb, (R.clamp_min(1e-3) ** 0.5 * ell ** 0.5).clamp(0, 1))
    with pytest.raises(ValueError, match="tone must be one of"):
        tone_map(R, L, ref, g, "filmic")


@pytest.mark.parametrize("shoulder, seed, light", [(1.0, 2, (0.02, 0.1)), (0.5, 4, (0.05, 0.25))])
def test_exposure_tone_gradients_match_finite_differences(shoulder, seed, light):
    torch.manual_seed(seed)
    R = (0.1 + 0.8 * torch.rand(3, 4, 3, dtype=torch.float64)).requires_grad_()
    L = (light[0] + light[1] * torch.rand(3, 4, 3, dtype=torch.float64)).requires_grad_()
    g = torch.tensor([0.8], dtype=torch.float64, requires_grad=True)
    ref = torch.tensor(0.3, dtype=torch.float64)
    if shoulder < 1:
        with torch.no_grad():  # some pixels on each side of the knee, none at it
            lin = exposure_gain(ref, g) * srgb_to_linear(R * L)
            assert bool((lin > shoulder + 0.05).any()) and bool((lin < shoulder - 0.05).any())
    assert torch.autograd.gradcheck(lambda r, l, gg: tone_map(r, l, ref, gg, "exposure", shoulder=shoulder), (R, L, g))


def test_schema_refuses_the_exposure_tone_without_a_scene_reference():
    from retinexgs.errors import UserError
    from retinexgs.run.config import load_config
    cfg = load_config([], [])
    assert cfg.model.enhancement.tone == "exposure"  # the default since 2026-11-25
    with pytest.raises((UserError, ValueError), match="ref_quantile"):
        load_config([], ["model.enhancement.ref_quantile=null"])
    assert load_config(["paper"], []).model.enhancement.tone == "illumination"


def test_a_run_with_the_exposure_tone_renders_exports_and_follows_the_exposure_control(tmp_path):
    """End to end on a tiny run: the fast renderer equals model.render, --exposure orders brightness, and the baked
    PLY (the same tone map per Gaussian) follows the full render as closely as it does with the default tone."""
    import numpy as np
    from PIL import Image

    from retinexgs.cli import main
    from retinexgs.evaluate.metrics import psnr
    from retinexgs.export.bake import to_normalized
    from retinexgs.export.ply import read_background, read_ply
    from retinexgs.render import rasterize_gaussians, spherical_harmonics
    from retinexgs.run.folder import load_run
    from retinexgs.run.render import render_function
    from retinexgs.run.render import view_camera
    from scenes import tiny_trained_run

    tiny = ["steps=4", "checkpoint.every=4", "log.tensorboard=false", "model.sh_degree=1", "model.sh_degree_every=2",
            "model.max_init_points=1200", "model.init_opacity=0.95", "density.start=100", "decomposer.method=lime",
            "loss.enhance_from=2", "model.enhancement.tone=exposure", "model.enhancement.gamma_range=[0.25,2.0]",
            "model.enhancement.init_gamma=1.0"]
    _, run = tiny_trained_run(tmp_path, tiny, n_test=2, width=40, height=30, n_points=1200)
    cfg, scene, model, step = load_run(run, "cpu")
    assert model.tone.name == "exposure"
    fast = render_function(model, cfg, 1)
    cam = view_camera(scene.test[0])
    with torch.no_grad():
        torch.testing.assert_close(fast(scene.test[0])["rgb"], model.render(cam, 1)["rgb"], atol=1e-5, rtol=0)
    cli = lambda *a: main([*map(str, a), "--device", "cpu", "--quiet"])  # noqa: E731
    means = {}
    for exposure in ("0.5", "1", "2"):
        assert cli("render", "--run", run, "--out", tmp_path / exposure, "--exposure", exposure) == 0
        means[exposure] = np.mean(np.asarray(Image.open(tmp_path / exposure / "enhanced" / "0001.png"), float))
    assert means["0.5"] > means["1"] > means["2"], means
    assert cli("export", "--run", run, "--out", tmp_path / "s.ply") == 0
    params = to_normalized(read_ply(tmp_path / "s.ply"), scene.normalization)
    coeffs = torch.cat([params["sh_dc"], params["sh_rest"]], dim=1)
    values = []
    for view in scene.train + scene.test:
        cam = view_camera(view)
        colors = (spherical_harmonics(1, params["means"] - cam.center.float(), coeffs) + 0.5).clamp_min(0.0)
        ply = rasterize_gaussians(params["means"], params["quats"], params["log_scales"].exp(),
                                  torch.sigmoid(params["opacity_logits"]), colors, cam,
                                  background=read_background(tmp_path / "s.ply")).image  # the viewer's, as recorded
        with torch.no_grad():
            values.append(psnr(ply.clamp(0, 1), model.render(cam, 1)["rgb"]))
    assert min(values) >= 30.0, values  # measured 41.8-44.0 dB here (CPU, torch 2.13)


def test_exposure_control_divides_the_light_with_the_exposure_tone_and_scales_g_with_the_gamma_tones():
    from retinexgs.model.tone import apply_exposure, exposure_gain, linear_to_srgb, srgb_to_linear
    g0 = torch.Generator().manual_seed(3)
    R = torch.rand(6, 5, 3, generator=g0, dtype=torch.float64)
    L = torch.rand(6, 5, 3, generator=g0, dtype=torch.float64) * 0.05
    ref, g = torch.tensor(0.3, dtype=torch.float64), torch.tensor([0.9], dtype=torch.float64)
    k = exposure_gain(ref, g)
    for x in (0.25, 0.5, 2.0, 3.0):
        ge = apply_exposure(g, x, ref, "exposure")
        torch.testing.assert_close(exposure_gain(ref, ge), k / x)  # one stop per factor of two
        S, _ = tone_map(R, L, ref, ge, "exposure")
        torch.testing.assert_close(S, linear_to_srgb(k / x * srgb_to_linear(R * L)))
        # the frame graph passes the factor as a device tensor: same value
        torch.testing.assert_close(apply_exposure(g, torch.tensor(x, dtype=torch.float64), ref, "exposure"), ge)
        for tone in ("illumination", "signal"):
            torch.testing.assert_close(apply_exposure(g, x, ref, tone), g * x)
    assert apply_exposure(g, 1.0, ref, "exposure") is g  # no change at all when unset
    # Far darker than the capture: the gain stops near 1 (g large, finite), never negative or infinite.
    dark = apply_exposure(g, 1e6, ref, "exposure")
    assert torch.isfinite(dark).all() and float(exposure_gain(ref, dark)) == pytest.approx(1.0, abs=0.01)


def test_the_exposure_tone_stays_finite_at_extreme_gammas():
    """A tiny fixed gamma (``--gamma 0.001``) is an enormous gain: black stays black and the rest saturates, no
    NaN from inf · 0."""
    R = torch.tensor([[0.0, 0.5, 1.0]])
    L = torch.tensor([[0.0, 0.1, 0.2]])
    for g in (1e-4, 1e-3, 0.01, 50.0):
        S, light = tone_map(R, L, torch.tensor(0.2), torch.tensor([g]), "exposure")
        assert torch.isfinite(S).all() and torch.isfinite(light).all(), g
        assert float(S[0, 0]) == 0.0
    S, _ = tone_map(R, L, torch.tensor(0.2), torch.tensor([1e-3]), "exposure")
    assert float(S[0, 1]) == pytest.approx(1.0, abs=1e-6) and float(S[0, 2]) == pytest.approx(1.0, abs=1e-6)


def test_highlight_shoulder_passes_the_light_below_its_knee_and_rolls_off_above():
    from retinexgs.model.tone import highlight_shoulder
    v = torch.linspace(0, 6, 6001, dtype=torch.float64)
    for knee in (0.2, 0.5, 0.8):
        s = highlight_shoulder(v, knee)
        below = v <= knee
        assert torch.equal(s[below], v[below])
        span = 1 - knee
        want = knee + span * (1 - torch.exp(-(v[~below] - knee) / span))
        assert torch.allclose(s[~below], want, rtol=0, atol=1e-15)
        assert bool((s < 1).all()) and bool((torch.diff(s) > 0).all())  # below white, rising: no clip
        # C¹ at the knee: slope 1 on both sides
        h = 1e-7
        up = (highlight_shoulder(torch.tensor([knee + h], dtype=torch.float64), knee) - knee) / h
        assert float(up) == pytest.approx(1.0, abs=1e-6)
    assert torch.equal(highlight_shoulder(v, 1.0), v)  # knee 1: the light as is (the sRGB encoding clips it)
    nan = highlight_shoulder(torch.tensor([float("nan")]), 0.5)
    assert torch.isnan(nan).all()  # a broken pixel stays visible


def test_exposure_tone_with_a_shoulder_keeps_the_shadows_and_lowers_the_highlights():
    torch.manual_seed(3)
    R = torch.rand(6, 7, 3, dtype=torch.float64)
    L = 0.02 + 0.3 * torch.rand(6, 7, 3, dtype=torch.float64)
    ref = torch.tensor(0.3, dtype=torch.float64)
    g = torch.tensor([0.7], dtype=torch.float64)
    plain, plain_l = tone_map(R, L, ref, g, "exposure")
    rolled, rolled_l = tone_map(R, L, ref, g, "exposure", shoulder=0.5)
    knee = float(linear_to_srgb(torch.tensor(0.5, dtype=torch.float64)))
    low = plain <= knee
    assert low.any() and (~low).any()
    assert torch.allclose(rolled[low], plain[low], rtol=0, atol=1e-15)
    assert bool((rolled[~low] < plain[~low]).all()) and bool((rolled < 1).all())
    assert bool((rolled_l <= plain_l + 1e-15).all())  # L_enh the same way


def test_exposure_tone_with_a_shoulder_has_finite_gradients_far_past_the_knee():
    """A huge gain puts every pixel far past the knee: the gradient is finite there, not inf · 0."""
    torch.manual_seed(4)
    R = 0.1 + 0.8 * torch.rand(3, 4, 3, dtype=torch.float64)
    L = 0.05 + 0.25 * torch.rand(3, 4, 3, dtype=torch.float64)
    ref = torch.tensor(0.3, dtype=torch.float64)
    big = torch.tensor([0.05], dtype=torch.float64, requires_grad=True)
    out, _ = tone_map(R, L, ref, big, "exposure", shoulder=0.5)
    out.sum().backward()
    assert torch.isfinite(big.grad).all()


def test_schema_takes_a_shoulder_in_0_1():
    from retinexgs.errors import UserError
    from retinexgs.run.config import load_config
    assert load_config([], []).model.enhancement.shoulder == 0.5  # the default since stop 28
    assert load_config(["ablations/no_shoulder"], []).model.enhancement.shoulder == 1.0
    for pinned in ("paper", "ablations/background_black", "ablations/aniso_cap"):
        assert load_config([pinned], []).model.enhancement.shoulder == 1.0, pinned
    for bad in ("0", "1.5", "-0.2"):
        with pytest.raises((UserError, ValueError), match="shoulder"):
            load_config([], [f"model.enhancement.shoulder={bad}"])
    # the gamma tones do not read it: switching the default's tone needs no second setting
    assert load_config([], ["model.enhancement.tone=illumination"]).model.enhancement.shoulder == 0.5
    R, L = torch.rand(4, 4, 3, dtype=torch.float64), 0.3 * torch.rand(4, 4, 3, dtype=torch.float64)
    ref, g = torch.tensor(0.3, dtype=torch.float64), torch.tensor([0.5], dtype=torch.float64)
    for tone in ("illumination", "signal"):
        assert torch.equal(tone_map(R, L, ref, g, tone, shoulder=0.5)[0], tone_map(R, L, ref, g, tone)[0])


def test_the_highlight_meter_caps_the_target_where_more_than_its_share_would_blow_out():
    from retinexgs.model.tone import highlight_capped_mean, highlight_shoulder

    def image(bright_share, scale=1.0, n=10000):
        lin = torch.full((n, 3), 0.02 * scale, dtype=torch.float64)
        lin[: int(bright_share * n)] = 0.2 * scale  # a 10x brighter part of the frame
        return linear_to_srgb(lin)

    def mean_at_white(lin_white):  # the tone of the dim part (linear 0.1) and the bright part at linear `lin_white`
        return lambda share: float(share * linear_to_srgb(highlight_shoulder(torch.tensor(lin_white), 0.5))
                                   + (1 - share) * linear_to_srgb(highlight_shoulder(torch.tensor(0.1), 0.5)))

    # 10 % bright, share 5 %: the exposure puts the bright part at white (1 before the shoulder), the rest at 0.1.
    got = highlight_capped_mean(image(0.10), 0.5, 0.05, shoulder=0.5)
    assert float(got) == pytest.approx(mean_at_white(1.0)(0.10), abs=1e-4) and float(got) < 0.5
    # The same frame 3x darker in linear light: the same target (the meter reads the light's distribution).
    assert float(highlight_capped_mean(image(0.10, scale=1 / 3), 0.5, 0.05, shoulder=0.5)) == pytest.approx(
        float(got), abs=1e-4)
    # 2 % bright: the exposure that blows out 5 % also blows out the dim 3 %... its mean is past 0.5: no cap.
    assert float(highlight_capped_mean(image(0.02), 0.5, 0.05, shoulder=0.5)) == 0.5
    # A larger share allowed: the cap falls away for the 10 % frame too.
    assert float(highlight_capped_mean(image(0.10), 0.5, 0.2, shoulder=0.5)) == 0.5


def test_the_highlight_meters_white_is_the_sorted_peaks_rank_exactly():
    """The meter's white point is a selection (kth_value.kth_smallest), not a sort: the same value, ties and repeats included,
    so the meter gives bit for bit what the sorting meter gave (its form until 2026-11-30, written out here)."""
    from retinexgs.model.tone import highlight_capped_mean, highlight_shoulder
    from retinexgs.model.tones.curves import srgb_to_linear

    def sorting_meter(RL, target, share, shoulder):
        lin = srgb_to_linear(RL.clamp(0, 1))
        peak = lin.amax(-1).flatten()
        rank = min(peak.numel() - 1, max(0, int(round((1.0 - share) * (peak.numel() - 1)))))
        white = torch.sort(peak).values[rank].clamp_min(1e-8)
        return linear_to_srgb(highlight_shoulder(lin / white, shoulder)).mean().clamp(max=target)

    gen = torch.Generator().manual_seed(3)
    for dtype in (torch.float32, torch.float64):
        for shape, share in (((7, 5, 3), 0.05), ((64, 48, 3), 0.05), ((64, 48, 3), 0.3), ((1, 1, 3), 0.05)):
            RL = torch.rand(shape, generator=gen, dtype=dtype)
            RL[RL > 0.7] = 0.7  # ties at the top
            got = highlight_capped_mean(RL, 0.5, share, 0.5)
            assert torch.equal(got, sorting_meter(RL.float(), 0.5, share, 0.5)), (dtype, shape, share)


def test_the_highlight_meter_acts_only_on_the_whole_image_meter_of_the_exposure_tone():
    from retinexgs.run.config import load_config
    from retinexgs.train.losses import highlight_meter_applies

    cfg = load_config([])
    assert cfg.loss.exp_highlight_share == 0.05  # the default since 2026-11-27
    assert load_config(["ablations/meter_average"]).loss.exp_highlight_share == 0.0
    assert highlight_meter_applies(cfg.model.enhancement.tone, cfg.loss)
    for extra in (["model.enhancement.tone=illumination"], ["loss.exp_on=illumination"], ["loss.exp_patch=16"]):
        c = load_config([], extra)  # accepted, and ignored there
        assert not highlight_meter_applies(c.model.enhancement.tone, c.loss), extra
