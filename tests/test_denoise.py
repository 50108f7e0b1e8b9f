"""The noise-level-aware denoising prior (issue 64 item 1, retinexgs/retinex/denoise.py): the generalised Anscombe
transform and its unbiased inverse, the denoisers, the content-keyed cache, the config key and bad inputs."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from retinexgs.data.srgb import linear_to_srgb
from retinexgs.errors import UserError
from retinexgs.retinex.cache import clean_cache, iter_decompositions, prior_key, read_image
from retinexgs.retinex.denoise import (DenoiseParams, DenoiseSpec, denoise_linear, denoised_view, gat_forward,
                                       gat_inverse, noise_model)
from retinexgs.run.config import load_config

A, B = 0.004, 3e-4  # a night raw view's noise (fox-dark at 1000 e⁻: a ≈ 0.002–0.004, b ≈ 1e-4–3e-4)


def _poisson_gaussian(x: torch.Tensor, a: float, b: float, seed: int = 0) -> torch.Tensor:
    """y = a·Poisson(x / a) + N(0, b): mean x, variance a·x + b."""
    g = torch.Generator().manual_seed(seed)
    return a * torch.poisson(x / a, generator=g) + math.sqrt(b) * torch.randn(x.shape, generator=g, dtype=x.dtype)


@pytest.mark.parametrize("level", [0.02, 0.1, 0.5])  # 5, 25 and 125 photo-electrons' worth of signal
def test_gat_makes_the_noise_unit_variance(level):
    x = torch.full((200_000, 1, 3), level, dtype=torch.float64)
    y = _poisson_gaussian(x, A, B)
    assert float(y.var()) == pytest.approx(A * level + B, rel=0.02)  # the simulation is what it says
    d = gat_forward(y, (A,) * 3, (B,) * 3)
    assert float(d.var()) == pytest.approx(1.0, abs=0.05)


@pytest.mark.parametrize("level", [0.02, 0.1, 0.5])
def test_the_inverse_of_the_expected_transform_keeps_the_mean(level):
    """What a perfect denoiser returns is E[f(y)]; the closed-form unbiased inverse maps it back to the light within
    1 %. The algebraic inverse (D²/4 − 3/8 − s²)·a is off by about a/8 (2.5 % at the lowest level): the test
    tells them apart."""
    x = torch.full((400_000, 1, 3), level, dtype=torch.float64)
    d_mean = gat_forward(_poisson_gaussian(x, A, B, seed=1), (A,) * 3, (B,) * 3).mean(dim=0, keepdim=True)
    back = gat_inverse(d_mean, (A,) * 3, (B,) * 3)
    assert float((back - level).abs().max()) < 0.01 * level
    if level == 0.02:
        algebraic = (d_mean ** 2 / 4 - 0.375 - B / A ** 2) * A
        assert float((algebraic - level).abs().max()) > 0.015 * level


def test_the_round_trip_of_a_noisy_image_keeps_its_mean():
    """Without any denoising (h = 0) the transform and its inverse keep the image's mean light per channel."""
    clean = torch.rand(128, 128, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 0.3 + 0.05
    noisy = _poisson_gaussian(clean, A, B, seed=4)
    back = denoise_linear(noisy, noise_model(((A,) * 3, (B,) * 3)), "nlm", DenoiseParams(h_luma=0.0, h_chroma=0.0))
    assert torch.allclose(back.mean(dim=(0, 1)), clean.mean(dim=(0, 1)), rtol=0.03)


def _scene(h: int = 96, w: int = 128) -> torch.Tensor:
    """A clean linear image: a smooth light gradient over flat coloured patches with sharp edges."""
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h, dtype=torch.float64), torch.linspace(0, 1, w, dtype=torch.float64),
                            indexing="ij")
    light = (0.08 + 0.3 * xx)[..., None]
    colour = torch.tensor([0.9, 0.6, 0.4], dtype=torch.float64).expand(h, w, 3).clone()
    colour[: h // 2, : w // 2] = torch.tensor([0.3, 0.8, 0.5], dtype=torch.float64)
    colour[h // 3:, 2 * w // 3:] = torch.tensor([0.5, 0.4, 0.9], dtype=torch.float64)
    return light * colour


@pytest.mark.parametrize("method", ["nlm", "chroma"])
def test_each_denoiser_reduces_the_error(method):
    clean = _scene()
    noisy = _poisson_gaussian(clean, A, B, seed=5)
    out = denoise_linear(noisy.float(), noise_model(((A,) * 3, (B,) * 3)), method)
    assert out.shape == noisy.shape and out.dtype == torch.float32 and torch.isfinite(out).all()
    before = float(((noisy - clean) ** 2).mean())
    after = float(((out.double() - clean) ** 2).mean())
    assert after < 0.4 * before, (before, after)


def test_none_is_the_identity():
    x = torch.rand(8, 8, 3)
    assert denoise_linear(x, noise_model(((A,) * 3, (B,) * 3)), "none") is x


def _write_png(path: Path, lin: torch.Tensor) -> Path:
    arr = (linear_to_srgb(lin.clamp(0, 1)).numpy() * 255 + 0.5).astype(np.uint8)
    Image.fromarray(arr).save(path)
    return path


def test_the_denoised_view_is_cached_by_content(tmp_path):
    clean = _scene(64, 80)
    photo = _write_png(tmp_path / "a.png", _poisson_gaussian(clean, A, B, seed=6))
    spec = DenoiseSpec("chroma", noise_model(((A,) * 3, (B,) * 3)))
    image = read_image(photo)
    first, hit1 = denoised_view(photo, image, spec.noise, spec.method, False, tmp_path / "cache", spec.params,
                                content=prior_key(photo))
    second, hit2 = denoised_view(photo, image, spec.noise, spec.method, False, tmp_path / "cache", spec.params,
                                 content=prior_key(photo))
    assert (hit1, hit2) == (False, True) and torch.equal(first, second)
    assert not torch.equal(first, image)
    # A renamed copy of the same photo reuses it; other settings do not.
    copy = tmp_path / "b.png"
    copy.write_bytes(photo.read_bytes())
    assert denoised_view(copy, image, spec.noise, spec.method, False, tmp_path / "cache", spec.params,
                         content=prior_key(copy))[1]
    other = DenoiseSpec("nlm", spec.noise)
    assert not denoised_view(photo, image, other.noise, other.method, False, tmp_path / "cache", other.params,
                             content=prior_key(photo))[1]


def test_the_priors_of_denoised_views_are_their_own_entries(tmp_path):
    """decomposer.denoise keys the decomposition by the recipe too: the plain photo's priors are never reused for
    the denoised one's, and a second pass reads both from the cache."""
    photo = _write_png(tmp_path / "a.png", _poisson_gaussian(_scene(48, 64), A, B, seed=7))
    spec = DenoiseSpec("nlm", noise_model(((A,) * 3, (B,) * 3)))
    assert prior_key(photo, denoise=spec) != prior_key(photo)
    runs = []
    for _ in range(2):
        for denoise in (None, spec):
            report: dict = {}
            (r, l), = list(iter_decompositions([photo], "lime", cache_dir=tmp_path / "cache", progress=False,
                                               report=report, denoise=denoise))
            runs.append((report["computed"], report["reused"], r))
    assert [c for c, _, _ in runs] == [1, 1, 0, 0] and [u for _, u, _ in runs] == [0, 0, 1, 1]
    assert not torch.equal(runs[0][2], runs[1][2])
    assert len(list((tmp_path / "cache" / "denoised").rglob("*.npz"))) == 1
    mine = tmp_path / "cache" / "denoised" / "notes.txt"  # a file the cache did not write stays
    mine.write_text("mine")
    clean_cache(tmp_path / "cache")
    assert not list((tmp_path / "cache").rglob("*.npz")) and mine.read_text() == "mine"


def _one_line(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text and text
    return text


def test_bad_inputs_are_one_line_errors():
    ok = noise_model(((A,) * 3, (B,) * 3))
    with pytest.raises(UserError) as e:
        denoise_linear(torch.rand(8, 8, 3), ok, "bm3d")
    assert "unknown denoiser 'bm3d'" in _one_line(e)
    with pytest.raises(UserError) as e:
        DenoiseSpec("ffdnet", ok)
    assert "decomposer.denoise" in _one_line(e)
    with pytest.raises(UserError) as e:  # RawNoise's fallback when nothing could be measured
        noise_model(((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)))
    assert "no shot noise" in _one_line(e)
    floored = noise_model(((A, -1.0, 0.0), (B, B, B)))  # one channel with shot noise is enough: the others take its a
    assert floored.a == (A, A, A)
    with pytest.raises(UserError) as e:
        noise_model(((float("nan"),) * 3, (B,) * 3))
    assert "not finite" in _one_line(e)
    with pytest.raises(UserError) as e:
        noise_model(((A,) * 3, (-B, B, B)))
    assert "negative" in _one_line(e)
    with pytest.raises(UserError) as e:
        DenoiseParams.from_mapping({"strength": 3})
    assert "unknown denoiser parameter 'strength'" in _one_line(e)


def test_the_config_key_defaults_to_auto_and_names_its_choices():
    assert load_config().decomposer.denoise == "auto"
    assert load_config(overrides=["decomposer.denoise=chroma"]).decomposer.denoise == "chroma"
    with pytest.raises(UserError) as e:
        load_config(overrides=["decomposer.denoise=bm3d"])
    assert "decomposer.denoise must be one of auto, none, nlm, chroma" in _one_line(e)


def test_calibration_catches_a_model_that_under_reads_the_noise():
    """A model 16× below the true variance (as a pixel-scale estimate through JPEG reads): the filters calibrated
    on the view's own stabilised noise remove far more of it than ones that trust the model's unit σ."""
    clean = _scene()
    noisy = _poisson_gaussian(clean, A, B, seed=8).float()
    weak = noise_model(((A / 16,) * 3, (B / 16,) * 3))
    errs = {}
    for calibrate in (False, True):
        out = denoise_linear(noisy, weak, "nlm", DenoiseParams(calibrate=calibrate))
        errs[calibrate] = float(((out.double() - clean) ** 2).mean())
    assert errs[True] < 0.6 * errs[False], errs


@pytest.mark.parametrize("kind,stream", [("raw", "never"), ("jpeg", "never"), ("raw", "always")])
def test_training_reads_its_priors_from_the_denoised_views(night, tmp_path, capsys, kind, stream):
    """decomposer.denoise=chroma on a raw scene and on its camera JPEGs: training measures the views' noise, caches
    one denoised view per training photo beside the decompositions, and trains; streamed views get a view store of
    their own (not the plain priors' one)."""
    import shutil

    from scenes import TINY_RUN, run_cli

    scene = tmp_path / kind
    shutil.copytree(night / kind, scene)
    sets = [a for s in TINY_RUN + ["decomposer.denoise=chroma", f"train.stream_views={stream}"]
            for a in ("--set", s)]
    code, _, err = run_cli(["train", "--data", scene, "--out", tmp_path / "run", "--config", "demo", *sets,
                            "--device", "cpu", "--quiet"], capsys)
    assert code == 0, err
    denoised = list((scene / "retinex_cache" / "denoised").rglob("*.npz"))
    assert len(denoised) == 3 and all(p.parent.name.startswith("chroma-") for p in denoised)
    stores = [p.name for p in (scene / "retinex_cache").glob("views-*.bin")]
    assert (stores and all("-dn" in n for n in stores)) if stream == "always" else stores == []


def test_a_capture_whose_noise_cannot_be_measured_is_one_line(night, tmp_path, capsys, monkeypatch):
    import shutil

    from retinexgs.train import view_setup
    from scenes import TINY_RUN, run_cli

    scene = tmp_path / "jpeg"
    shutil.copytree(night / "jpeg", scene)
    monkeypatch.setattr(view_setup, "measure_capture_noise", lambda *a, **k: None)  # no flat area anywhere
    sets = [a for s in TINY_RUN + ["decomposer.denoise=nlm"] for a in ("--set", s)]
    code, _, err = run_cli(["train", "--data", scene, "--out", tmp_path / "run", "--config", "demo", *sets,
                            "--device", "cpu", "--quiet"], capsys)
    assert code == 2 and "Traceback" not in err, err
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("retinexgs")]
    assert len(lines) == 1 and "decomposer.denoise=nlm" in lines[0] and "could not be measured" in lines[0], err


@pytest.mark.parametrize("kind,blotch,want", [("raw", None, "chroma"), ("jpeg", 2.0, "chroma"), ("jpeg", 0.5, None)])
def test_auto_denoises_raw_scenes_and_photos_with_blotchy_colour_noise(night, kind, blotch, want):
    """decomposer.denoise=auto (the default): chroma on camera raw views (a measured noise model, the photos' blotches
    not even read), and on photos whose previews' colour noise on 4×4-pixel averages is above PHOTO_BLOTCH_MIN
    (said in one line), nothing on the others; a raw scene with no flat area to measure on falls back to the noisy
    views instead of stopping."""
    from retinexgs.data import load_scene
    from retinexgs.data.capture import PHOTO_BLOTCH_MIN
    from retinexgs.train import view_setup

    scene = load_scene(night / kind)
    notes, read = [], []

    def blotches(paths, downscale=1.0):
        read.append((len(paths), downscale))
        return blotch * PHOTO_BLOTCH_MIN

    with pytest.MonkeyPatch.context() as m:
        m.setattr(view_setup, "previews_chroma_blotch", blotches)
        spec = view_setup.denoise_spec(scene.train, load_config(overrides=["data.downscale=2"]), "cpu",
                                       note=notes.append)
    assert (spec.method if spec is not None else None) == want
    if kind == "jpeg":
        assert read == [(len(scene.train), 2.0)]  # the views' own photos, at training's size
        assert len(notes) == (1 if want else 0)
        assert all("decomposer.denoise=none" in n and "\n" not in n for n in notes)
    else:
        assert read == [] and notes == []
    if spec is not None:  # decomposer.denoise_params reach the spec, and with it the cache's recipe
        tuned = view_setup.denoise_spec(scene.train, load_config(overrides=[
            "data.downscale=2", "decomposer.denoise=chroma", "decomposer.denoise_params.h_luma=0.4"]), "cpu")
        assert tuned.params.h_luma == 0.4 and spec.params.h_luma != 0.4 and tuned.recipe != spec.recipe
    if kind == "raw":
        import unittest.mock as mock
        from retinexgs.data import capture  # the raw capture measures its noise (retinexgs/data/capture.py)
        with mock.patch.object(capture, "scene_noise", lambda *a, **k: None):
            assert view_setup.denoise_spec(scene.train, load_config(), "cpu") is None
            with pytest.raises(UserError):
                view_setup.denoise_spec(scene.train, load_config(overrides=["decomposer.denoise=chroma"]), "cpu")


@pytest.mark.parametrize("kind,sets", [("raw", []), ("jpeg", ["decomposer.denoise=chroma"])])
def test_decompose_fills_the_entries_train_reads_through_the_denoiser(night, tmp_path, kind, sets):
    """`retinexgs decompose` reads the views through the denoiser train uses (decomposer.denoise: auto on the raw
    views, chroma asked for on the JPEGs): its entries are the ones train then finds, none computed again."""
    import shutil

    from retinexgs.cli import main
    from retinexgs.data import load_scene
    from retinexgs.retinex.cache import iter_decompositions, scene_cache_root
    from retinexgs.train import view_setup

    scene = tmp_path / kind
    shutil.copytree(night / kind, scene)
    assert main(["decompose", "--data", str(scene), "--device", "cpu", "--quiet",
                 *[a for v in sets for a in ("--set", v)]]) == 0
    denoised = list((scene / "retinex_cache" / "denoised").rglob("*.npz"))
    assert len(denoised) == 3 and all(p.parent.name.startswith("chroma-") for p in denoised)
    train = load_scene(scene).train
    cfg = load_config(overrides=sets)
    report = {}
    for _ in iter_decompositions([v.image_path for v in train], "lr3m", None, scene_cache_root(scene, None), "cpu",
                                 progress=False, report=report, raw_denoise=cfg.decomposer.raw.preview_denoise,
                                 balance=train[0].balance, denoise=view_setup.denoise_spec(train, cfg, "cpu")):
        pass
    assert (report["computed"], report["reused"]) == (0, 3)


def test_each_rank_decomposes_its_share_through_the_trainer_s_denoiser(night, monkeypatch):
    """With --gpus N every rank fills its share of the cache before training: through the same denoiser (same
    recipe) the trainer then reads the entries with, not the plain views (which the trainer would not use)."""
    from retinexgs.data import load_scene
    from retinexgs.train import distributed, view_setup

    scene = load_scene(night / "raw")
    cfg = load_config()
    seen = []
    monkeypatch.setattr(distributed, "decompose_images", lambda paths, *a, **k: seen.append((list(paths), k)))
    ranks = distributed.Distributed()
    ranks.rank, ranks.world = 1, 2
    monkeypatch.setattr(ranks, "barrier", lambda what: None)
    ranks.decompose_shard(scene, cfg, "cpu", progress=False)
    (paths, kwargs), = seen
    assert paths == [v.image_path for v in scene.train[1::2]]
    want = view_setup.denoise_spec(scene.train, cfg, "cpu")
    assert want is not None and kwargs["denoise"].recipe == want.recipe
