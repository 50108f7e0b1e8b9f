"""Evaluation metrics: PSNR, SSIM (against an independent scipy version) and LPIPS in the evaluation."""
import math

import numpy as np
import pytest
import torch
from scipy.signal import correlate2d

from retinexgs.evaluate import metrics as M


pytestmark = pytest.mark.usefixtures("one_thread")


def _ssim_scipy(x: np.ndarray, y: np.ndarray) -> float:
    """Wang et al. SSIM, 11×11 Gaussian σ=1.5, valid filtering, per channel then mean ([H,W,C])."""
    r = np.arange(11) - 5.0
    g = np.exp(-r ** 2 / (2 * 1.5 ** 2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    out = []
    for c in range(x.shape[2]):
        a, b = x[..., c], y[..., c]
        f = lambda z: correlate2d(z, w, mode="valid")  # noqa: E731
        ma, mb = f(a), f(b)
        va, vb, cov = f(a * a) - ma ** 2, f(b * b) - mb ** 2, f(a * b) - ma * mb
        out.append(((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma ** 2 + mb ** 2 + c1) * (va + vb + c2)))
    return float(np.mean(out))


def test_psnr_known_values():
    x = torch.full((8, 8, 3), 0.5)
    assert M.psnr(x, x + 0.1) == pytest.approx(20.0, abs=1e-5)
    assert M.psnr(x, x - 0.01) == pytest.approx(40.0, abs=1e-3)
    assert M.psnr(x, x) == math.inf
    # 2 of 8 values off by 1: MSE = 0.25.
    a = np.zeros((2, 2, 2))
    b = a.copy()
    b[0, :, 0] = 1.0
    assert M.psnr(a, b) == pytest.approx(10 * math.log10(4.0))


def test_ssim_metric_matches_scipy_and_properties():
    rng = np.random.default_rng(0)
    x = rng.random((24, 30, 3))
    y = np.clip(x + rng.normal(0, 0.1, x.shape), 0, 1)
    assert M.ssim_metric(torch.tensor(x), torch.tensor(y)) == pytest.approx(_ssim_scipy(x, y), abs=1e-10)
    assert M.ssim_metric(x, x) == pytest.approx(1.0, abs=1e-12)
    s_small = M.ssim_metric(x, np.clip(x + rng.normal(0, 0.02, x.shape), 0, 1))
    s_big = M.ssim_metric(x, np.clip(x + rng.normal(0, 0.2, x.shape), 0, 1))
    assert 1.0 > s_small > s_big
    # Constant images: (2ab + C1)/(a² + b² + C1).
    a = np.full((16, 16, 3), 0.3)
    assert M.ssim_metric(a, a + 0.2) == pytest.approx((2 * 0.3 * 0.5 + 1e-4) / (0.09 + 0.25 + 1e-4))


def test_metrics_reject_bad_shapes():
    with pytest.raises(ValueError):
        M.psnr(torch.zeros(4, 4, 3), torch.zeros(4, 5, 3))
    with pytest.raises(ValueError):
        M.ssim_metric(torch.zeros(1, 16, 16, 3), torch.zeros(1, 16, 16, 3))


def test_gt_mean_align_matches_the_grey_mean_and_clips():
    rng = np.random.default_rng(1)
    y = rng.random((12, 16, 3)) * 0.8
    x = y * 0.4  # the truth at another brightness: aligned, nothing is left of the error
    a = M.gt_mean_align(x, y)
    assert a.dtype == torch.float64 and a.shape == (12, 16, 3)
    assert M.psnr(a, y) > 100 and M.psnr(x, y) < 15
    grey = lambda z: float((np.asarray(z) @ np.array([0.299, 0.587, 0.114])).mean())  # noqa: E731
    # an image with a different structure: its grey mean is moved onto the truth's, up to the clip at 1
    z = rng.random((12, 16, 3)) * 0.2
    assert grey(M.gt_mean_align(z, y)) == pytest.approx(grey(y), rel=1e-12)
    bright = M.gt_mean_align(np.full((4, 4, 3), 0.1) + np.eye(4)[..., None] * 0.5, np.full((4, 4, 3), 0.9))
    # grey mean 0.225 -> factor 4: 0.1 -> 0.4, 0.6 -> 2.4, clipped at white
    assert float(bright.max()) == 1.0 and float(bright.min()) == pytest.approx(0.4, abs=1e-12)
    # the colour balance is kept: one factor for all three channels
    c = np.stack([y[..., 0] * 0.5, y[..., 1] * 0.5, y[..., 2] * 0.5], -1)
    np.testing.assert_allclose(np.asarray(M.gt_mean_align(c, y)), y, atol=1e-12)
    # grey images, and a black output (nothing to scale) stays black
    g = M.gt_mean_align(y[..., 0] * 0.5, y[..., 0])
    assert g.shape == (12, 16) and M.psnr(g, y[..., 0]) > 100
    assert float(M.gt_mean_align(np.zeros((4, 4, 3)), np.ones((4, 4, 3))).abs().max()) == 0.0


def test_gt_mean_align_rejects_bad_input():
    with pytest.raises(ValueError, match="shape mismatch"):
        M.gt_mean_align(torch.zeros(4, 4, 3), torch.zeros(4, 5, 3))
    with pytest.raises(ValueError, match="channels"):
        M.gt_mean_align(torch.zeros(4, 4, 2), torch.zeros(4, 4, 2))
    bad = torch.ones(4, 4, 3)
    bad[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        M.gt_mean_align(bad, torch.ones(4, 4, 3))


def test_lpips_metric_is_the_port_on_hwc_images():
    """LPIPS (issue 62): the package's own port, always available (shipped weights, no lpips package, no download)."""
    from retinexgs.evaluate.lpips import lpips_distance

    assert M.lpips_available() == (True, "")
    gen = torch.Generator().manual_seed(0)
    y = torch.rand(40, 48, 3, generator=gen)
    xs = [(y + 0.1 * torch.randn(y.shape, generator=gen)).clamp(0, 1), y.flip(0), y]
    values = M.lpips_metrics(xs, y)
    assert values[2] == 0.0 and values[0] > 0.0 and values[1] > 0.0
    # one batch with the reference's features once == each pair alone == the [B,3,H,W] port itself
    assert values[:2] == pytest.approx([M.lpips_metric(x, y) for x in xs[:2]], abs=1e-6)
    assert values[0] == pytest.approx(float(lpips_distance(xs[0].permute(2, 0, 1)[None], y.permute(2, 0, 1)[None])),
                                      abs=1e-6)
    assert M.lpips_metric(xs[0].numpy().astype(np.float64), y.numpy()) == pytest.approx(values[0], abs=1e-6)
    # a grey image is the RGB image with three equal channels
    g = y[..., 0]
    assert M.lpips_metric(g.flip(1), g) == pytest.approx(M.lpips_metric(g.flip(1)[..., None].expand(-1, -1, 3),
                                                                         g[..., None].expand(-1, -1, 3)), abs=1e-7)
    assert M.lpips_metrics([], y) == []


@pytest.mark.parametrize("x, y, match", [
    (np.zeros((40, 40, 4)), np.zeros((40, 40, 4)), r"\[H,W,3\]"),
    (np.zeros((40, 40, 3)), np.zeros((40, 41, 3)), "shape mismatch"),
    (np.zeros((20, 40, 3)), np.zeros((20, 40, 3)), "at least 31x31"),
    (np.full((40, 40, 3), 255, np.uint8), np.zeros((40, 40, 3)), r"in \[0, 1\]"),
])
def test_lpips_metric_rejects_bad_input_in_one_line(x, y, match):
    with pytest.raises(ValueError, match=match) as e:
        M.lpips_metric(x, y)
    assert "\n" not in str(e.value)


def _eval_scene(tmp_path, width, height):
    from retinexgs.data import load_scene
    from retinexgs.demo.synthetic import make_demo_scene

    return load_scene(make_demo_scene(tmp_path / f"scene{width}", n_train=2, n_test=2, width=width, height=height,
                                      n_points=50, supersample=1))


def test_evaluate_reports_lpips_like_psnr_and_ssim(tmp_path):
    """eval.lpips (on by default): metrics.json holds lpips, lpips_gt_mean and low_lpips per view and in the mean,
    each the port's figure for the output (clipped to [0, 1] as its PNG), its GT-mean alignment and the dark input."""
    import json

    from retinexgs.evaluate.evaluate import evaluate
    from retinexgs.run.config import load_config

    assert load_config([]).eval.lpips is True
    scene = _eval_scene(tmp_path, 48, 40)
    outputs = {}

    def render(view):
        out = (view.paired_image.float() * 0.6 + 0.1 * torch.rand(view.paired_image.shape)).clamp(0, 1)
        out[0, 0] = 1.3  # a render may leave [0, 1]: LPIPS sees it clipped, as the PNG holds it
        outputs[view.name] = out
        return {"rgb": out}

    logs = []
    m = evaluate(render, scene, tmp_path / "run", use_lpips=True, log=logs.append)
    assert "lpips_unavailable" not in m and not [ln for ln in logs if "LPIPS not reported" in ln]
    for row, view in zip(m["views"], [v for v in scene.test if v.paired_path is not None]):
        out, gt = outputs[view.name], view.paired_image
        want = M.lpips_metrics([out.clamp(0, 1), M.gt_mean_align(out, gt), view.image], gt)
        assert [row["lpips"], row["lpips_gt_mean"], row["low_lpips"]] == pytest.approx(want, abs=1e-6)
        assert row["lpips"] > 0.0 and row["lpips"] != row["low_lpips"]
    for k in ("lpips", "lpips_gt_mean", "low_lpips"):
        assert m["mean"][k] == pytest.approx(np.mean([r[k] for r in m["views"]]))
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["mean"]["lpips"] == m["mean"]["lpips"]
    assert any(f"LPIPS {m['mean']['lpips']:.3f}" in ln for ln in logs)
    off = evaluate(render, scene, tmp_path / "off", use_lpips=False, log=lambda s: None)
    assert not [k for k in off["mean"] if "lpips" in k] and "lpips_unavailable" not in off


def test_evaluate_says_once_why_lpips_is_missing(tmp_path, monkeypatch):
    """Images smaller than the network takes, or a broken install without the weights file: no LPIPS figures, the
    reason in metrics.json and one log line; the other figures as always."""
    from retinexgs.evaluate import lpips as L
    from retinexgs.evaluate.evaluate import evaluate

    render = lambda view: {"rgb": view.paired_image.float()}  # noqa: E731
    small = _eval_scene(tmp_path, 32, 24)
    logs = []
    m = evaluate(render, small, tmp_path / "small", use_lpips=True, log=logs.append)
    assert not [k for k in m["mean"] if "lpips" in k] and m["mean"]["psnr"] == math.inf
    assert "smaller than LPIPS's 31x31" in m["lpips_unavailable"]
    assert len([ln for ln in logs if ln.startswith("LPIPS not reported")]) == 1
    monkeypatch.setattr(L, "WEIGHTS", tmp_path / "missing.npz")
    logs = []
    m = evaluate(render, _eval_scene(tmp_path, 48, 40), tmp_path / "broken", use_lpips=True, log=logs.append)
    assert "missing.npz is missing" in m["lpips_unavailable"] and "lpips" not in m["mean"]
    assert len([ln for ln in logs if ln.startswith("LPIPS not reported")]) == 1


def test_black_lift_sees_lifted_and_crushed_blacks_not_the_exposure():
    """Issue 32's black-level measure: the 1st percentile in linear light after GT-mean alignment, minus the truth's."""
    from retinexgs.evaluate.metrics import black_lift

    rng = np.random.default_rng(0)
    truth = rng.uniform(0.0, 0.7, size=(40, 40, 3))
    assert black_lift(truth, truth) == pytest.approx(0.0, abs=1e-12)
    # one exposure factor is not a black lift (the alignment takes it out; no value reaches the clip at white)
    assert black_lift(truth * 0.6, truth) == pytest.approx(0.0, abs=1e-9)

    def lin(x):
        return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)

    def srgb(m):
        return np.where(m <= 0.0031308, 12.92 * m, 1.055 * np.clip(m, 0, None) ** (1 / 2.4) - 0.055)

    # a floor of 0.05 added in linear light (what clipped noise averages to): the blacks sit about 0.05 higher
    lifted = srgb(lin(truth) + 0.05)
    value = black_lift(lifted, truth)
    lows = np.quantile(lin(truth).reshape(-1, 3), 0.01, axis=0)
    assert 0.02 < value < 0.05  # the alignment scales the floor down a little with the rest of the image
    # the same floor taken away (clipped at 0): crushed blacks read negative
    crushed = srgb(np.clip(lin(truth) - 0.05, 0, None))
    assert black_lift(crushed, truth) < -0.9 * float(lows.mean())
    assert black_lift(crushed, truth) < 0
    with pytest.raises(ValueError, match="quantile"):
        black_lift(truth, truth, q=1.5)


def test_colour_error_sees_a_cast_not_the_exposure():
    """Issue 32's colour measure: ΔE of the average colours after GT-mean alignment."""
    from retinexgs.evaluate.metrics import colour_error, mean_colour_lab

    rng = np.random.default_rng(0)
    truth = rng.uniform(0.1, 0.6, size=(16, 16, 3))
    assert colour_error(truth, truth) == pytest.approx(0.0, abs=1e-9)
    # darker by one factor: removed by the alignment (up to the clip at white, not reached here)
    assert colour_error(truth * 0.5, truth) < 0.5
    # a blue cast is a colour error, in the blue direction (CIELAB b* lower)
    cast = np.clip(truth * np.array([0.8, 1.0, 1.3]), 0, 1)
    assert colour_error(cast, truth) > 5.0
    assert mean_colour_lab(cast)[2] < mean_colour_lab(truth)[2]
    # white is L* 100, a* = b* = 0 (D65); mid-grey sRGB 0.5 is L* ≈ 53.4
    L, a, b = mean_colour_lab(np.ones((4, 4, 3)))
    assert (L, a, b) == pytest.approx((100.0, 0.0, 0.0), abs=0.05)
    assert mean_colour_lab(np.full((4, 4, 3), 0.5))[0] == pytest.approx(53.39, abs=0.05)
    with pytest.raises(ValueError, match="RGB"):
        mean_colour_lab(np.zeros((4, 4, 1)))


def test_colour_error_linear_scores_the_light_without_a_tone():
    """The render's linear light against the truth: exposure-free, unbounded, and a cast scores what the same cast
    scores as an sRGB image's average colour (mean_colour_lab, the independent route)."""
    from retinexgs.data.srgb import linear_to_srgb, srgb_to_linear
    from retinexgs.evaluate.metrics import colour_error_linear, mean_colour_lab

    rng = np.random.default_rng(1)
    truth = torch.from_numpy(rng.uniform(0.05, 0.9, size=(12, 12, 3)))
    light = srgb_to_linear(truth)
    assert colour_error_linear(light, truth) == pytest.approx(0.0, abs=1e-9)
    # any exposure, far past white (no clip in linear light): still 0
    assert colour_error_linear(light * 7.5, truth) == pytest.approx(0.0, abs=1e-9)
    assert colour_error_linear(light * 0.01, truth) == pytest.approx(0.0, abs=1e-9)
    # a cast on a uniform grey: ΔE of the Lab colours of the cast light at the truth's luminance
    grey = torch.full((4, 4, 3), 0.5, dtype=torch.float64)
    gains = torch.tensor([1.2, 1.0, 0.8], dtype=torch.float64)
    cast = srgb_to_linear(grey) * gains
    lum = torch.tensor([0.2126729, 0.7151522, 0.0721750], dtype=torch.float64)
    at_truth = cast * float((srgb_to_linear(grey)[0, 0] @ lum) / (cast[0, 0] @ lum))
    want = np.linalg.norm(np.subtract(mean_colour_lab(linear_to_srgb(at_truth)), mean_colour_lab(grey)))
    assert want > 5.0
    assert colour_error_linear(cast * 3.0, grey) == pytest.approx(want, rel=1e-6)
    with pytest.raises(ValueError, match="RGB"):
        colour_error_linear(torch.zeros(4, 4, 1), torch.zeros(4, 4, 1))


def test_tone_colour_floor_is_what_the_shoulder_does_to_a_clipped_sky():
    """The truth through the tone at its own exposure: nothing without a shoulder or below the knee; a white
    (clipped) sky beside a bright blue one rolls off channel by channel, which moves the average colour."""
    from retinexgs.data.srgb import linear_to_srgb
    from retinexgs.evaluate.metrics import tone_colour_floor

    rng = np.random.default_rng(2)
    dim = torch.from_numpy(rng.uniform(0.02, 0.7, size=(8, 8, 3)))  # linear < 0.45: below a knee of 0.5
    assert tone_colour_floor(dim, 0.5) == pytest.approx(0.0, abs=1e-9)
    sky = torch.ones(8, 8, 3, dtype=torch.float64)
    sky[:, 4:] = linear_to_srgb(torch.tensor([0.35, 0.6, 0.98], dtype=torch.float64))
    assert tone_colour_floor(sky, 1.0) == pytest.approx(0.0, abs=1e-9)
    assert tone_colour_floor(sky, 0.5) > 0.5
    assert tone_colour_floor(sky, 0.5) > tone_colour_floor(sky, 0.8)
    # exposed brighter, the clip alone costs colour too (the blue sky's blue clips first); exposed darker, the
    # metric itself charges a little, growing with the distance (the GT-mean scales sRGB values, not the light)
    assert tone_colour_floor(sky, 1.0, exposure=1.5) > 0.5
    assert 0.0 < tone_colour_floor(dim, 1.0, exposure=0.8) < tone_colour_floor(dim, 1.0, exposure=0.5)


def test_colour_split_is_the_three_figures_at_once():
    from retinexgs.data.srgb import srgb_to_linear
    from retinexgs.evaluate.metrics import colour_error_linear, colour_split, exposure_ratio, tone_colour_floor

    truth = torch.from_numpy(np.random.default_rng(4).uniform(0.05, 1.0, size=(8, 8, 3)))
    light = srgb_to_linear(truth) * torch.tensor([1.6, 1.4, 1.1], dtype=torch.float64)
    split = colour_split(light, truth, 0.5)
    assert split["delta_e_linear"] == pytest.approx(colour_error_linear(light, truth), abs=1e-12)
    assert split["exposure_ratio"] == pytest.approx(exposure_ratio(light, truth), abs=1e-12)
    assert split["delta_e_tone_floor"] == pytest.approx(tone_colour_floor(truth, 0.5, split["exposure_ratio"]),
                                                        abs=1e-12)
    assert split["delta_e_linear"] > 1.0 and split["delta_e_tone_floor"] > 0.0


def test_exposure_ratio_is_the_light_over_the_truth_in_linear_luminance():
    from retinexgs.data.srgb import srgb_to_linear
    from retinexgs.evaluate.metrics import exposure_ratio

    truth = torch.from_numpy(np.random.default_rng(3).uniform(0.05, 0.95, size=(6, 6, 3)))
    assert exposure_ratio(srgb_to_linear(truth) * 2.5, truth) == pytest.approx(2.5, rel=1e-12)
    assert exposure_ratio(torch.zeros(6, 6, 3), truth) == 0.0
    assert exposure_ratio(srgb_to_linear(truth), torch.zeros(6, 6, 3)) == 0.0


@pytest.mark.parametrize("pad", [0, 5])
def test_float64_filter_by_shifted_sums_is_the_depthwise_convolution(pad):
    """The evaluation's float64 CPU filter (sums of shifted slices) gives the conv2d filter's values and
    gradients."""
    import torch.nn.functional as F
    from retinexgs.evaluate.metrics import gaussian_filter, gaussian_filter_weights

    x = torch.rand(2, 3, 23, 31, dtype=torch.float64, requires_grad=True)
    wx, wy = gaussian_filter_weights(3, 11, 1.5, torch.float64, "cpu")
    ref = F.conv2d(F.conv2d(x, wx, padding=(0, pad), groups=3), wy, padding=(pad, 0), groups=3)
    out = gaussian_filter(x, 11, 1.5, pad)
    assert out.shape == ref.shape
    torch.testing.assert_close(out, ref, rtol=1e-13, atol=1e-15)
    g = torch.rand_like(ref)
    (ga,) = torch.autograd.grad(out, x, g)
    (gb,) = torch.autograd.grad(ref, x, g)
    torch.testing.assert_close(ga, gb, rtol=1e-13, atol=1e-15)


def test_a_contact_sheet_shrinks_its_panels_and_keeps_the_figures_full_size(tmp_path):
    """eval.sheet_max_side: each panel shrunk by the smallest whole factor that fits (block means), the PNG that
    much narrower; PSNR / SSIM are those of the full-size images, the same as with no shrinking."""
    from PIL import Image

    from retinexgs.evaluate.evaluate import LABEL_ROWS, evaluate, shrink_panel
    from retinexgs.run.config import load_config

    assert load_config([]).eval.sheet_max_side == 1920
    img = torch.arange(7 * 9 * 3, dtype=torch.float32).reshape(7, 9, 3)
    assert torch.equal(shrink_panel(img, 9), img)
    small = shrink_panel(img, 4)  # 9 / 4 -> factor 3: 7x9 -> 2x3, the partial last row dropped
    assert small.shape == (2, 3, 3)
    assert small[1, 2].tolist() == img[3:6, 6:9].reshape(-1, 3).mean(0).tolist()
    assert shrink_panel(img[..., :1], 9).shape == (7, 9, 3)  # a grey map shown as RGB
    scene = _eval_scene(tmp_path, 48, 40)
    render = lambda view: {"rgb": (view.paired_image.float() * 0.8).clamp(0, 1)}  # noqa: E731
    full = evaluate(render, scene, tmp_path / "full", use_lpips=False, log=lambda s: None)
    shrunk = evaluate(render, scene, tmp_path / "shrunk", use_lpips=False, log=lambda s: None, sheet_max_side=20)
    assert shrunk["mean"] == full["mean"]
    name = sorted((tmp_path / "full" / "renders" / "test").glob("*.png"))[0].name
    w_full, h_full = Image.open(tmp_path / "full" / "renders" / "test" / name).size
    w, h = Image.open(tmp_path / "shrunk" / "renders" / "test" / name).size
    assert (w_full, h_full) == (3 * 48, 40 + LABEL_ROWS) and (w, h) == (3 * 16, 13 + LABEL_ROWS)
