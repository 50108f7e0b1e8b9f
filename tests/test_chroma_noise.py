"""Issue 64's colour-noise figure (retinexgs.evaluate.metrics.chroma_noise): what it scores, what it leaves alone,
its bad inputs, and eval / bench quality reporting it. Fixtures are made here: a 96x128 "photo" with luma texture,
soft colour regions and two sharp-edged colour patches (band energy ≈ 80 a*/b* units², like LOM's truths: 15-210)."""
import json
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from retinexgs.evaluate import metrics as M

pytestmark = pytest.mark.usefixtures("one_thread")

_XYZ = torch.tensor(M._RGB_TO_XYZ, dtype=torch.float64)
_WHITE = torch.tensor(M._D65, dtype=torch.float64)


def _blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """[H,W,C] blurred by a sampled Gaussian, mirrored borders (the test's own filter, not the metric's)."""
    r = int(math.ceil(3 * sigma))
    g = torch.exp(-(torch.arange(-r, r + 1, dtype=torch.float64) ** 2) / (2 * sigma ** 2))
    g = g / g.sum()
    c = img.shape[-1]
    x = F.pad(img.permute(2, 0, 1)[None], (r, r, r, r), mode="reflect")
    x = F.conv2d(x, g.reshape(1, 1, 1, -1).repeat(c, 1, 1, 1), groups=c)
    x = F.conv2d(x, g.reshape(1, 1, -1, 1).repeat(c, 1, 1, 1), groups=c)
    return x[0].permute(1, 2, 0)


def _field(h, w, c, sigma, gen):
    """Gaussian noise blurred at ``sigma``, scaled to unit standard deviation."""
    f = _blur(torch.randn(h, w, c, generator=gen, dtype=torch.float64), sigma)
    return f / f.std()


def _truth(h=96, w=128, seed=0):
    gen = torch.Generator().manual_seed(seed)
    img = 0.45 + 0.12 * _field(h, w, 1, 4.0, gen) + 0.05 * _field(h, w, 1, 1.0, gen) + 0.04 * _field(h, w, 3, 6.0, gen)
    img[20:50, 30:70] *= torch.tensor([1.25, 0.95, 0.8], dtype=torch.float64)  # a warm patch, sharp edges
    img[60:85, 80:120] *= torch.tensor([0.85, 1.0, 1.2], dtype=torch.float64)  # a cool one
    return img.clamp(0.02, 0.98)


def _srgb_of_lab(lab: torch.Tensor) -> torch.Tensor:
    """CIELAB (D65) [H,W,3] -> sRGB, the inverse of the metric's conversion (the test's own, from the CIE formulas)."""
    fy = (lab[..., 0] + 16) / 116
    f = torch.stack([fy + lab[..., 1] / 500, fy, fy - lab[..., 2] / 200], dim=-1)
    d = 6 / 29
    xyz = torch.where(f > d, f ** 3, 3 * d * d * (f - 4 / 29)) * _WHITE
    lin = xyz @ torch.linalg.inv(_XYZ).T
    return torch.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin.clamp_min(0.0031308) ** (1 / 2.4) - 0.055)


def _lab(srgb: torch.Tensor) -> torch.Tensor:
    lin = torch.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    t = (lin @ _XYZ.T) / _WHITE
    d = 6 / 29
    f = torch.where(t > d ** 3, t ** (1 / 3), t / (3 * d * d) + 4 / 29)
    return torch.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], -1)


def test_the_truth_scores_one_a_softer_render_a_little_below_and_the_exposure_nothing():
    y = _truth()
    assert M.chroma_noise(y, y) == pytest.approx(1.0, abs=1e-12)
    # a slightly soft render (σ = 0.7 px): a little less chroma detail than the truth, never more (within 10 %)
    soft = M.chroma_noise(_blur(y, 0.7), y)
    assert 0.9 < soft < 1.0
    # a darker render of the same picture: the GT-mean alignment takes the exposure out (x0.5 is exact in binary)
    assert M.chroma_noise(y * 0.5, y) == pytest.approx(1.0, abs=1e-9)
    # luma noise alone is not colour noise (within 2 %)
    gen = torch.Generator().manual_seed(3)
    grey_noise = 0.05 * torch.randn(*y.shape[:2], 1, generator=gen, dtype=torch.float64)
    assert M.chroma_noise((y + grey_noise).clamp(0, 1), y) == pytest.approx(1.0, abs=0.02)


def test_per_pixel_colour_noise_scores_high_and_rises_with_the_noise():
    y = _truth()
    gen = torch.Generator().manual_seed(1)
    n = torch.randn(y.shape, generator=gen, dtype=torch.float64)
    scores = [M.chroma_noise((y + sd * n).clamp(0, 1), y) for sd in (0.03, 0.06, 0.12)]
    assert scores[0] < scores[1] < scores[2]
    assert scores[1] > 1.5  # speckle of 0.06 (15/255) per channel: plainly visible, over issue 64's bar
    assert scores[2] > 3.0


@pytest.mark.parametrize("sigma", [4.0, 8.0])
def test_low_frequency_colour_blotches_score_high(sigma):
    y = _truth()
    gen = torch.Generator().manual_seed(2)
    blotches = 0.1 * _field(*y.shape, sigma, gen)  # colour blotches of 0.1 (26/255) per channel, σ px wide
    assert M.chroma_noise((y + blotches).clamp(0, 1), y) > 3.0


def test_a_colour_cast_does_not_raise_it():
    y = 0.15 + 0.7 * _truth()  # away from black and white: the shifted colours stay in gamut
    lab = _lab(y)
    assert torch.allclose(_srgb_of_lab(lab), y, atol=1e-9)  # the test's inverse is right
    shifted = _srgb_of_lab(lab + torch.tensor([0.0, 6.0, 0.0], dtype=torch.float64))  # a* + 6 everywhere
    assert bool(((shifted > 0) & (shifted < 1)).all())  # in gamut: nothing clipped
    # a constant does not pass a band-pass; what is left is the GT-mean alignment: the shift moves the Rec. 601 grey
    # that it matches, and the factor it applies scales a*/b* a little (here 1.6 %)
    assert M.chroma_noise(shifted, y) == pytest.approx(1.0, abs=0.03)
    # a white-balance cast (per-channel gains of ±10 %) scales a*/b* detail a little, not like noise
    assert M.chroma_noise((y * torch.tensor([1.1, 1.0, 0.9], dtype=torch.float64)).clamp(0, 1), y) < 1.1


def test_the_definition_on_a_pure_a_star_grating():
    """A flat truth and a render whose a* is A·cos(2πx/8) (L*, b* constant): the score is exactly
    (mean of (A·g·cos)² + floor) / floor, g the DoG's transfer at 1/8 cycle per pixel."""
    h, w, amp = 66, 65, 10.0  # 64 = (w - 1) is a whole number of half periods: the mirror continues the grating
    x = torch.arange(w, dtype=torch.float64)
    lab = torch.zeros(h, w, 3, dtype=torch.float64)
    lab[..., 0] = 55.0
    lab[..., 1] = amp * torch.cos(2 * math.pi * x / 8)
    render = _srgb_of_lab(lab)
    flat = _srgb_of_lab(lab * torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64))
    f2 = 2 * math.pi ** 2 / 64
    g = math.exp(-f2 * 0.5 ** 2) - math.exp(-f2 * 16 ** 2)
    energy = float(((amp * g * torch.cos(2 * math.pi * x / 8)) ** 2).mean())
    assert energy > 40
    # the grey means of render and flat truth differ a little: align the render's brightness as the metric does
    render = M.gt_mean_align(render, flat)
    expected = (energy + M.CHROMA_FLOOR) / M.CHROMA_FLOOR
    assert M.chroma_noise(render, flat) == pytest.approx(expected, rel=0.005)


def test_a_flat_grey_truth_divides_by_the_floor_not_by_zero():
    flat = torch.full((40, 48, 3), 0.5, dtype=torch.float64)
    assert M.chroma_noise(flat, flat) == pytest.approx(1.0, abs=1e-12)
    assert M.chroma_noise(torch.zeros_like(flat), flat) == pytest.approx(1.0, abs=1e-12)  # black: no chroma either
    gen = torch.Generator().manual_seed(4)
    noisy = (flat + 0.03 * torch.randn(flat.shape, generator=gen, dtype=torch.float64)).clamp(0, 1)
    score = M.chroma_noise(noisy, flat)
    assert math.isfinite(score) and score > 3.0


def test_small_views_use_the_scales_that_fit():
    assert M.chroma_band_px(96, 128) == (2, 32) and M.chroma_band_px(64, 64) == (2, 32)
    assert M.chroma_band_px(63, 500) == (2, 16) and M.chroma_band_px(30, 40) == (2, 8)
    assert M.chroma_band_px(8, 9) == (2, 4)
    y = _truth(30, 40)
    assert M.chroma_noise(y, y) == pytest.approx(1.0, abs=1e-12)
    gen = torch.Generator().manual_seed(5)
    assert M.chroma_noise((y + 0.12 * torch.randn(y.shape, generator=gen, dtype=torch.float64)).clamp(0, 1), y) > 3
    with pytest.raises(ValueError, match="at least 8x8 pixels, got 20x7") as e:
        M.chroma_noise(torch.rand(7, 20, 3), torch.rand(7, 20, 3))
    assert "\n" not in str(e.value)


def test_numpy_float32_and_the_batch_agree():
    y = _truth(64, 72)
    gen = torch.Generator().manual_seed(6)
    x = (y + 0.05 * torch.randn(y.shape, generator=gen, dtype=torch.float64)).clamp(0, 1)
    one = M.chroma_noise(x, y)
    assert M.chroma_noise(x.numpy(), y.numpy()) == pytest.approx(one, rel=1e-12)
    assert M.chroma_noise(x.float(), y.float()) == pytest.approx(one, rel=1e-4)
    assert M.chroma_noises([x, y, x], y) == pytest.approx([one, 1.0, one], rel=1e-12)


@pytest.mark.parametrize("x, y, match", [
    (torch.rand(16, 16, 3), torch.rand(16, 17, 3), "shape mismatch"),
    (torch.rand(16, 16), torch.rand(16, 16), r"\[H,W,3\] RGB images, got the render of shape \(16, 16\)"),
    (torch.rand(16, 16, 3), torch.rand(16, 16, 4), r"got the truth of shape \(16, 16, 4\)"),
    (np.zeros((16, 16, 3), np.uint8), np.zeros((16, 16, 3), np.uint8), "float images in \\[0, 1\\], got the render"),
    (torch.rand(16, 16, 3), torch.full((16, 16, 3), float("nan")), "non-finite"),
    (torch.full((16, 16, 3), float("inf")), torch.rand(16, 16, 3), "non-finite"),
])
def test_bad_inputs_are_one_line_value_errors(x, y, match):
    with pytest.raises(ValueError, match=match) as e:
        M.chroma_noise(x, y)
    assert "\n" not in str(e.value)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_the_gpu_gives_the_cpus_figure():
    y = _truth()
    gen = torch.Generator().manual_seed(7)
    x = (y + 0.08 * _field(*y.shape, 4.0, gen)).clamp(0, 1)
    assert M.chroma_noise(x.cuda(), y.cuda()) == pytest.approx(M.chroma_noise(x, y), rel=1e-9)
    assert M.chroma_noise(x, y, device="cuda") == pytest.approx(M.chroma_noise(x, y), rel=1e-9)


def test_eval_writes_it_per_view_and_in_the_mean(tmp_path):
    """A tiny trained run (the demo scene, 6 steps): metrics.json holds chroma_noise and low_chroma_noise per view
    and their means, each the metric's own figure for the view's render and dark input; bench quality tables it."""
    from retinexgs.bench import quality
    from retinexgs.data import load_scene
    from retinexgs.demo.synthetic import make_demo_scene
    from retinexgs.evaluate.evaluate import evaluate
    from retinexgs.train.runner import train_run

    scene_dir = make_demo_scene(tmp_path / "demo", n_train=3, n_test=2, width=40, height=30, n_points=300)
    tiny = ["steps=6", "checkpoint.every=6", "log.every=1", "log.tensorboard=false", "model.sh_degree=1",
            "model.max_init_points=300", "density.start=100", "decomposer.method=lime", "eval.lpips=false"]
    run = tmp_path / "run"
    metrics = train_run(scene_dir, run, ["demo"], tiny, "cpu", progress=False, log=lambda s: None)
    on_disk = json.loads((run / "metrics.json").read_text())
    assert on_disk["chroma_noise_band_px"] == [2, 8]  # 40x30 views: the scales that fit
    for row in on_disk["views"]:
        assert row["chroma_noise"] > 0 and row["low_chroma_noise"] > 0
    for k in ("chroma_noise", "low_chroma_noise"):
        assert on_disk["mean"][k] == pytest.approx(np.mean([r[k] for r in on_disk["views"]]))
        assert metrics["mean"][k] == pytest.approx(on_disk["mean"][k])
    # the figure is the metric's, for what was rendered: a render_fn returning known images
    scene = load_scene(scene_dir)
    noise = {}

    def render(view):
        gen = torch.Generator().manual_seed(len(noise))
        out = (view.paired_image.float() + 0.1 * torch.randn(view.paired_image.shape, generator=gen)).clamp(0, 1)
        noise[view.name] = (out, view.paired_image.clone(), view.image.clone())
        return {"rgb": out}

    m = evaluate(render, scene, tmp_path / "eval", use_lpips=False, log=lambda s: None)
    for row in m["views"]:
        out, gt, low = noise[row["view"]]
        assert row["chroma_noise"] == pytest.approx(M.chroma_noise(out, gt), rel=1e-12) and row["chroma_noise"] > 1.5
        assert row["low_chroma_noise"] == pytest.approx(M.chroma_noise(low, gt), rel=1e-12)
    # bench quality: a table of it, the dark input's first
    job = quality.Job(scene_dir, "default", 0, run)
    md = quality.chroma_table([job], ["default"])
    assert f"| low input | {on_disk['mean']['low_chroma_noise']:.2f} |" in md
    assert f"| `default` | {on_disk['mean']['chroma_noise']:.2f} |" in md and "Chroma noise" in md


def test_bench_quality_table_skips_runs_evaluated_before_it(tmp_path):
    from retinexgs.bench import quality

    jobs = quality.plan([tmp_path / "s1", tmp_path / "s2"], ["default"], [0, 1], tmp_path / "runs")
    for j in jobs:
        j.run.mkdir(parents=True)
        mean = {"psnr": 20.0, "ssim": 0.5, "low_psnr": 7.0, "low_ssim": 0.2}
        if not (j.scene.name == "s2" and j.seed == 1):  # evaluated before the key existed
            mean.update(chroma_noise=1.2 + j.seed, low_chroma_noise=9.0)
        j.metrics_path.write_text(json.dumps({"mean": mean, "views": []}))
    md = quality.chroma_table(jobs, ["default"])
    assert "| low input | 9.00 | 9.00 |" in md
    assert f"| `default` | 1.70 ± {math.sqrt(0.5):.2f} | 1.20 |" in md
