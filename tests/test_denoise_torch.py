"""Torch's non-local means for the noise-aware denoiser (issue 64 item 1, "Time"; retinexgs/retinex/denoise.py):
the formula against a plain numpy reference, its quality against OpenCV's on a noisy fixture, who runs it
(decomposer.denoise_backend), its cache recipe, and its bad inputs."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from retinexgs.bench.denoise import dark_capture, main as bench_main, synthetic_photo, _psnr
from retinexgs.errors import UserError
from retinexgs.retinex.denoise import (DenoiseSpec, _patch_mean, denoise_key, denoise_linear, denoised_view,
                                       nlm_torch, noise_model, resolve_backend)
from retinexgs.run.config import load_config

W, R = 1000.0, 6.0  # the raw ladder's 1000 e- rung
NOISE = noise_model(((1 / W,) * 3, ((R / W) ** 2,) * 3))


def _reference_nlm(x: np.ndarray, h: float, patch: int, search: int) -> np.ndarray:
    """The NLM formula pixel by pixel in float64: reflect-101 borders, weight exp(-mean squared patch difference /
    h²), weights under 1e-3 dropped, the weighted mean of the search window's pixels."""
    t, s = patch // 2, search // 2
    p = np.pad(x.astype(np.float64), s + t, mode="reflect")
    out = np.zeros(x.shape)
    for i in range(x.shape[0]):
        for j in range(x.shape[1]):
            ci, cj = i + s + t, j + s + t
            centre = p[ci - t:ci + t + 1, cj - t:cj + t + 1]
            num = den = 0.0
            for dy in range(-s, s + 1):
                for dx in range(-s, s + 1):
                    other = p[ci + dy - t:ci + dy + t + 1, cj + dx - t:cj + dx + t + 1]
                    w = np.exp(-np.mean((other - centre) ** 2) / h ** 2)
                    w = w if w >= 1e-3 else 0.0
                    num += w * p[ci + dy, cj + dx]
                    den += w
            out[i, j] = num / den
    return out


@pytest.mark.parametrize("patch,search,block", [(7, 21, 1 << 30), (3, 9, 1)])  # block 1: one row at a time
def test_torch_nlm_is_the_reference_formula(patch, search, block):
    rng = np.random.default_rng(1)
    x = (rng.random((16, 16)) + np.linspace(0, 2, 16)[None]).astype(np.float32)  # a ramp: weights of every size
    ref = _reference_nlm(x, 0.4, patch, search)
    out = nlm_torch(torch.from_numpy(x), 0.4, patch, search, block_bytes=block).numpy()
    assert np.abs(out - ref).max() < 1e-5
    assert np.abs(out - x).max() > 0.05  # it did filter


def test_the_pooled_and_the_shifted_patch_means_agree():
    d = torch.rand(3, 20, 24, generator=torch.Generator().manual_seed(2))
    a, b = _patch_mean(d, 5, pooled=True), _patch_mean(d, 5, pooled=False)
    assert a.shape == (3, 16, 20)
    assert torch.allclose(a, b, atol=1e-6)
    assert torch.allclose(a[1, 3, 4], d[1, 3:8, 4:9].mean(), atol=1e-6)


@pytest.mark.parametrize("method", ["chroma", "nlm"])
def test_torch_is_no_worse_than_opencv_on_a_night_capture(method):
    clean = synthetic_photo(96, 128, seed=3)
    noisy = dark_capture(clean, W, R, seed=3)
    psnr = {be: _psnr(denoise_linear(noisy, NOISE, method, backend=be), clean) for be in ("opencv", "torch")}
    assert psnr["opencv"] > _psnr(noisy, clean) + 3.0  # the fixture is one a denoiser helps
    assert psnr["torch"] >= psnr["opencv"] - 0.1, psnr


def test_auto_runs_torch_on_cuda_and_opencv_on_the_cpu():
    assert resolve_backend("auto", "cpu") == "opencv"
    assert resolve_backend("auto", None) == "opencv"
    assert resolve_backend("auto", "cuda:0") == "torch"
    assert resolve_backend("torch", "cpu") == "torch" and resolve_backend("opencv", "cuda") == "opencv"
    assert DenoiseSpec("chroma", NOISE, device="cuda").implementation == "torch"
    assert DenoiseSpec("chroma", NOISE).implementation == "opencv"
    assert load_config().decomposer.denoise_backend == "auto"
    assert load_config(overrides=["decomposer.denoise_backend=torch"]).decomposer.denoise_backend == "torch"


def test_the_recipe_names_torch_and_keeps_opencvs_keys():
    assert DenoiseSpec("chroma", NOISE, device="cuda").recipe != DenoiseSpec("chroma", NOISE).recipe
    assert DenoiseSpec("chroma", NOISE, backend="torch").recipe == DenoiseSpec("chroma", NOISE, device="cuda").recipe
    # OpenCV's recipe is the one written before torch's NLM existed: those caches stay valid.
    assert DenoiseSpec("chroma", NOISE).recipe == denoise_key("chroma", NOISE)


def test_runs_recorded_before_the_backend_keep_opencvs_priors():
    """A run of format 2 (before decomposer.denoise_backend) had its priors denoised by OpenCV: it reads ``opencv``,
    so a resume on a CUDA device finds the priors it trained on instead of recomputing them with torch's NLM; a
    backend it recorded is kept, and a run of today's format without the key gets today's default."""
    from retinexgs.config.versions import FORMAT, migrate_config

    old, filled = migrate_config({"format": 2, "decomposer": {"denoise": "chroma"}}, "old/config.yaml")
    assert old["decomposer"]["denoise_backend"] == "opencv" and "decomposer.denoise_backend" in filled
    kept, _ = migrate_config({"format": 2, "decomposer": {"denoise_backend": "torch"}}, "old/config.yaml")
    assert kept["decomposer"]["denoise_backend"] == "torch"
    new, _ = migrate_config({"format": FORMAT, "decomposer": {"denoise": "chroma"}}, "new/config.yaml")
    assert new["decomposer"]["denoise_backend"] == "auto"


def test_a_view_denoised_by_torch_is_cached_apart(tmp_path):
    clean = synthetic_photo(48, 64, seed=4)
    image = dark_capture(clean, W, R, seed=4).clamp(0, 1) ** (1 / 2.2)
    kw = dict(cache_root=tmp_path, content="0123456789abcdef")
    by_cv, hit = denoised_view("a.png", image, NOISE, "chroma", False, **kw)
    assert not hit
    by_torch, hit = denoised_view("a.png", image, NOISE, "chroma", False, backend="torch", **kw)
    assert not hit  # not OpenCV's entry
    again, hit = denoised_view("a.png", image, NOISE, "chroma", False, backend="torch", **kw)
    assert hit and torch.equal(again, by_torch)
    assert len(list((tmp_path / "denoised").iterdir())) == 2
    assert (by_torch - by_cv).abs().mean() < 0.02  # the same denoiser, up to OpenCV's 8-bit steps


def _one_line(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text and text
    return text


def test_bad_inputs_are_one_line_errors():
    with pytest.raises(UserError) as e:
        denoise_linear(torch.rand(24, 24, 3), NOISE, "bm3d", backend="torch")
    assert "unknown denoiser 'bm3d'" in _one_line(e)
    with pytest.raises(UserError) as e:
        denoise_linear(torch.rand(24, 24, 3), NOISE, "nlm", backend="cuda")
    assert "unknown denoiser backend 'cuda'" in _one_line(e)
    with pytest.raises(UserError) as e:
        DenoiseSpec("chroma", NOISE, backend="gpu")
    assert "decomposer.denoise_backend" in _one_line(e)
    with pytest.raises(UserError) as e:  # a capture whose noise could not be measured
        noise_model(((float("nan"),) * 3, (1e-5,) * 3))
    assert "could not be measured" in _one_line(e)
    with pytest.raises(UserError) as e:
        noise_model(((0.0,) * 3, (1e-5,) * 3))
    assert "no shot noise" in _one_line(e)
    with pytest.raises(UserError) as e:  # nlm_torch itself refuses an image smaller than its windows
        nlm_torch(torch.rand(8, 8), 1.0, 7, 21)
    assert "too small for non-local means" in _one_line(e)
    with pytest.raises(UserError) as e:
        load_config(overrides=["decomposer.denoise_backend=cuda"])
    assert "decomposer.denoise_backend must be one of auto, torch, opencv" in _one_line(e)


def test_the_bench_times_both_side_by_side(tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert bench_main(["--device", "cpu", "--size", "48x64", "--repeat", "1", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "opencv (cpu)" in text and "torch (cpu)" in text
    rows = json.loads(out.read_text())["rows"]
    assert [r["implementation"] for r in rows] == ["opencv (cpu)", "torch (cpu)"]
    assert all(r["seconds"] > 0 and r["psnr"] > 10 for r in rows)


def test_a_thumbnail_is_denoised_through_opencv_where_torch_cannot_reflect_it():
    """A view with a side within torch's reflected border: the torch backend hands it to OpenCV's NLM (the same
    formula) rather than refusing a tiny view on a GPU."""
    x = torch.rand(8, 12, 3, generator=torch.Generator().manual_seed(3)) * 0.05
    got = denoise_linear(x, NOISE, "nlm", backend="torch")
    want = denoise_linear(x, NOISE, "nlm", backend="opencv")
    assert got.shape == x.shape and torch.isfinite(got).all()
    assert torch.equal(got, want)
