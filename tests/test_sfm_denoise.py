"""SfM's previews of dark photos go through the noise-aware denoiser before they are brightened (``sfm --denoise``;
issue 62 item 3, issue 64 item 5): the preview is closer to the clean photo's, bad values of the flag give one line,
the recipe keys the cached copies and model, and ``sfm --denoise auto`` runs end to end on small dark folders (photos
and ``darken --raw`` DNGs). Small synthetic fixtures; SfM's three stages are a stand-in (a hand-made model of the
photos it is told to register), so nothing here runs a real SfM."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from retinexgs.train.sfm_preview import (AUTO_MIN_SIGMA, check_denoise, linear_denoiser, preview_recipe,
                                         previews_noise_sigma, sfm_preview_denoise)
from retinexgs.data.sfm import ENHANCED_MANIFEST, META_NAME, PreviewDenoise, _bright_preview, _photo_preview
from retinexgs.data.srgb import linear_to_srgb
from retinexgs.errors import UserError
from scenes import run_cli

pycolmap = pytest.importorskip("pycolmap")

A, B = 0.004, 3e-4  # a night capture's noise in linear light (fox-dark at 1000 e-: a ~ 0.002-0.004, b ~ 1e-4-3e-4)
W, H = 96, 72


def _clean(seed: int = 0) -> np.ndarray:
    """A dark clean linear image [H,W,3]: a light gradient over coloured patches with sharp edges, some blobs."""
    rng = np.random.default_rng(seed)
    yy, xx = np.meshgrid(np.linspace(0, 1, H), np.linspace(0, 1, W), indexing="ij")
    colour = np.empty((H, W, 3))
    colour[:] = [0.9, 0.6, 0.4]
    colour[: H // 2, : W // 2] = [0.3, 0.8, 0.5]
    colour[H // 3:, 2 * W // 3:] = [0.5, 0.4, 0.9]
    for _ in range(6):
        cy, cx, r = rng.uniform(0, H), rng.uniform(0, W), rng.uniform(4, 10)
        colour[(yy * H - cy) ** 2 + (xx * W - cx) ** 2 < r * r] = rng.uniform(0.2, 1.0, 3)
    return (0.015 + 0.06 * xx)[..., None] * colour


def _noisy(clean: np.ndarray, seed: int, a: float = A, b: float = B) -> np.ndarray:
    """``clean`` with Poisson-Gaussian noise: mean ``clean``, variance a·clean + b."""
    rng = np.random.default_rng(seed)
    return a * rng.poisson(clean / a) + math.sqrt(b) * rng.standard_normal(clean.shape)


def _png(path: Path, lin: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((np.asarray(linear_to_srgb(np.clip(lin, 0, 1))) * 255 + 0.5).astype(np.uint8)).save(path)
    return path


def test_the_preview_is_denoised_before_it_is_brightened(tmp_path):
    clean = _clean()
    photo = _png(tmp_path / "dark.png", _noisy(clean, 1))
    truth = _bright_preview(clean.astype(np.float32)).astype(np.float64)
    noise = ((A,) * 3, (B,) * 3)
    # the same brightening without the denoiser: the noisy preview
    plain = _photo_preview(photo, PreviewDenoise("identity", lambda lin, a, b: lin, noise)).astype(np.float64)
    for method in ("chroma", "nlm"):
        denoised = _photo_preview(photo, PreviewDenoise(method, linear_denoiser(method), noise)).astype(np.float64)
        assert denoised.shape == truth.shape and denoised.dtype == np.float64
        before, after = np.mean((plain - truth) ** 2), np.mean((denoised - truth) ** 2)
        assert after < 0.5 * before, (method, before, after)


@pytest.mark.parametrize("value", ["bm3d", "", "Auto"])
def test_a_bad_denoise_value_is_one_line(tmp_path, capsys, value):
    _png(tmp_path / "photos" / "a.png", _clean())
    code, _, err = run_cli(["sfm", "--images", tmp_path / "photos", "--denoise", value, "--quiet"], capsys)
    assert code == 2 and "Traceback" not in err, err
    lines = [ln for ln in err.strip().splitlines() if "error:" in ln]
    assert len(lines) == 1 and "--denoise" in lines[0] and "invalid choice" in lines[0], err
    assert not (tmp_path / "retinexgs_sfm").exists()
    with pytest.raises(UserError, match=r"^--denoise must be one of auto, none, nlm, chroma .* got 'bm3d'$"):
        check_denoise("bm3d")


def test_a_named_denoiser_without_a_measurable_noise_is_one_line(tmp_path, capsys):
    photos = tmp_path / "black"
    for i in range(3):  # all black: dark, and nothing to measure the noise on
        _png(photos / f"p{i}.png", np.zeros((H, W, 3)))
    code, _, err = run_cli(["sfm", "--images", photos, "--denoise", "nlm", "--quiet"], capsys)
    assert code == 2 and "Traceback" not in err, err
    lines = [ln for ln in err.strip().splitlines() if "error:" in ln]
    assert len(lines) == 1 and "--denoise nlm: the noise of the photos" in lines[0], err
    assert sfm_preview_denoise(photos, "auto") is None  # auto: not denoised, as before


def test_photos_too_small_to_measure_are_left_alone_or_named(tmp_path, capsys):
    photos = tmp_path / "tiny"
    photos.mkdir()
    for i in range(3):  # 2×2 dark photos: no 3×3 window to read the noise on
        Image.fromarray(np.random.default_rng(i).integers(0, 30, (2, 2, 3), dtype=np.uint8)).save(photos / f"p{i}.png")
    assert sfm_preview_denoise(photos, "auto") is None
    code, _, err = run_cli(["sfm", "--images", photos, "--denoise", "chroma", "--quiet"], capsys)
    assert code == 2 and "Traceback" not in err, err
    lines = [ln for ln in err.strip().splitlines() if "error:" in ln]
    assert len(lines) == 1 and "--denoise chroma: the noise of the photos" in lines[0], err


def test_the_recipe_names_the_method_and_the_noise():
    noise = ((A,) * 3, (B,) * 3)
    keys = {preview_recipe("chroma"), preview_recipe("nlm"), preview_recipe("chroma", noise),
            preview_recipe("chroma", ((2 * A,) * 3, (B,) * 3))}
    assert len(keys) == 4 and all(len(k) == 12 for k in keys)
    assert preview_recipe("chroma", noise) == preview_recipe("chroma", ([A] * 3, [B] * 3))


# ---- end to end with SfM's stages replaced ----------------------------------------------------------------------

def _reconstruction(names, size):
    w, h = size
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=w, height=h,
                                                    params=[w * 0.8, w * 0.8, w / 2, h / 2], camera_id=1))
    for i, n in enumerate(names):
        c = np.array([0.3 * i, 0.1 * (i % 2), 0.05 * i])
        w2c = np.hstack([np.eye(3), -c.reshape(3, 1)])
        rec.add_image_with_trivial_frame(pycolmap.Image(name=n, keypoints=np.full((20, 2), 8.0), camera_id=1,
                                                        image_id=i + 1), pycolmap.Rigid3d(w2c))
    # every point seen by every photo, as in a real model (the night guard drops photos sharing too few points)
    for k, p in enumerate(np.random.default_rng(0).uniform(-1, 1, (20, 3)) + [0, 0, 4]):
        track = pycolmap.Track()
        for i in range(len(names)):
            track.add_element(i + 1, k)
        rec.add_point3D(p, track, np.array([10, 20, 30], np.uint8))
    return rec


class FakeColmap:
    """pycolmap with SfM's stages replaced: every photo it extracted features from is registered; it keeps the
    previews it was given (``feature_dir``), as they were when features were extracted."""

    def __init__(self):
        self.maps, self.previews = 0, {}

    def __getattr__(self, name):
        return getattr(pycolmap, name)

    def extract_features(self, db, feature_dir, image_names=(), **kwargs):
        Path(db).write_bytes(b"stand-in database")
        self.names = sorted(image_names)
        self.previews = {n: np.asarray(Image.open(Path(feature_dir) / n).convert("RGB")) for n in self.names}

    def match_exhaustive(self, db, **kwargs):
        pass

    def incremental_mapping(self, db, image_dir, out, **kwargs):
        self.maps += 1
        size = Image.open(Path(image_dir) / self.names[0]).size
        return {0: _reconstruction(self.names, size)}


@pytest.fixture
def fake(monkeypatch) -> FakeColmap:
    import retinexgs.data.sfm as sfm_module

    f = FakeColmap()
    monkeypatch.setattr(sfm_module, "_pycolmap", lambda: f)
    return f


def _dark_photos(folder: Path, n: int = 4, a: float = A, b: float = B) -> Path:
    """``n`` dark photos of a night capture (default: about 1000 e- full well, the brightened noise above auto's
    threshold)."""
    for i in range(n):
        _png(folder / f"p{i}.png", _noisy(_clean(i), 10 + i, a, b))
    return folder


def _rough(x: np.ndarray) -> float:
    """Mean absolute change between horizontal neighbours: noise raises it."""
    return float(np.mean(np.abs(np.diff(np.asarray(x, np.float64), axis=1))))


def _record(out: Path):
    meta = json.loads((out / META_NAME).read_text())
    return meta["signature"]["options"], json.loads((out / ENHANCED_MANIFEST).read_text())["method"]


def test_sfm_denoise_auto_end_to_end_and_the_recipe_keys_the_cache(tmp_path, capsys, fake):
    photos, out = _dark_photos(tmp_path / "photos"), tmp_path / "proj"
    code, outp, err = run_cli(["sfm", "--images", photos, "--out", out, "--denoise", "none"], capsys)
    assert code == 0 and "registered views: 4/4" in outp, err
    options, method = _record(out)
    assert "denoise" not in options and "denoise" not in method  # as before the flag: old caches still match
    noisy = {n: p.astype(np.float64) for n, p in fake.previews.items()}

    code, outp, err = run_cli(["sfm", "--images", photos, "--out", out], capsys)  # the default: auto
    assert code == 0 and "registered views: 4/4" in outp and "(cached)" not in outp, err
    assert fake.maps == 2 and "denoising them (chroma)" in err
    options, method = _record(out)
    assert options["denoise"].startswith("chroma-") and method.endswith(f"+denoise-{options['denoise']}")
    # the copies were remade through the denoiser: smoother than the noisy previews (less pixel-to-pixel change)
    for n, p in fake.previews.items():
        assert _rough(p) < 0.7 * _rough(noisy[n]), n

    code, outp, _ = run_cli(["sfm", "--images", photos, "--out", out], capsys)
    assert code == 0 and "(cached)" in outp and fake.maps == 2  # the same recipe: the cached model
    code, outp, _ = run_cli(["sfm", "--images", photos, "--out", out, "--denoise", "nlm"], capsys)
    assert code == 0 and "(cached)" not in outp and fake.maps == 3  # another recipe: SfM again, on new copies
    options, method = _record(out)
    assert options["denoise"].startswith("nlm-") and method.endswith(f"+denoise-{options['denoise']}")


def test_auto_leaves_dark_photos_of_low_noise_alone(tmp_path, capsys, fake):
    """Dark photos whose brightened noise is low (a 16 000 e- capture): the denoiser would cost SIFT texture, so auto
    keeps the plain enhanced copies; a named method still denoises them."""
    photos = _dark_photos(tmp_path / "photos", a=A / 16, b=B / 16)
    assert previews_noise_sigma(sorted(photos.iterdir()), raw=False) < AUTO_MIN_SIGMA
    assert sfm_preview_denoise(photos, "auto") is None
    assert sfm_preview_denoise(photos, "chroma").recipe.startswith("chroma-")
    code, outp, err = run_cli(["sfm", "--images", photos, "--out", tmp_path / "proj"], capsys)
    assert code == 0 and "registered views: 4/4" in outp and "denoising them" not in err, err
    options, method = _record(tmp_path / "proj")
    assert "denoise" not in options and "denoise" not in method
    noisier = _dark_photos(tmp_path / "night")
    assert previews_noise_sigma(sorted(noisier.iterdir()), raw=False) > AUTO_MIN_SIGMA
    assert sfm_preview_denoise(noisier, "auto").recipe.startswith("chroma-")


def test_sfm_denoise_leaves_a_bright_folder_alone(tmp_path, capsys, fake):
    photos = tmp_path / "bright"
    for i in range(3):
        _png(photos / f"p{i}.png", np.clip(_clean(i) * 6, 0, 1))
    assert sfm_preview_denoise(photos, "chroma") is None  # no enhanced copies: nothing to denoise
    code, outp, err = run_cli(["sfm", "--images", photos, "--out", tmp_path / "proj"], capsys)
    assert code == 0 and "registered views: 3/3" in outp and "denoising them" not in err, err


def test_sfm_denoise_auto_on_raw_night_captures(tmp_path, capsys, fake):
    """``darken --raw`` DNGs (a bare folder, each file's own noise model): the previews COLMAP reads are denoised."""
    src = tmp_path / "bright"
    for i in range(3):
        _png(src / f"p{i}.png", np.clip(_clean(i) * 6, 0, 1))
    code, _, err = run_cli(["darken", "--data", src, "--out", tmp_path / "night", "--raw", "--full-well", "1000",
                            "--read-noise", "6", "--quiet"], capsys)
    assert code == 0, err
    raws = sorted((tmp_path / "night" / "raw").rglob("*.dng"))
    assert len(raws) == 3
    bare = tmp_path / "bare"
    bare.mkdir()
    for p in raws:
        (bare / p.name).write_bytes(p.read_bytes())
    code, outp, err = run_cli(["sfm", "--images", bare, "--out", tmp_path / "plain", "--denoise", "none"], capsys)
    assert code == 0 and "registered views: 3/3" in outp, err
    plain = {n: p.astype(np.float64) for n, p in fake.previews.items()}
    code, outp, err = run_cli(["sfm", "--images", bare, "--out", tmp_path / "proj"], capsys)
    assert code == 0 and "registered views: 3/3" in outp, err
    options, method = _record(tmp_path / "proj")
    assert options["denoise"].startswith("chroma-") and "denoise-chroma-" in method
    assert set(fake.previews) == set(plain)
    for n in plain:  # the denoised previews were used: far smoother than the plain ones (bilateral filter only)
        assert _rough(fake.previews[n]) < 0.5 * _rough(plain[n]), n


# ---- train's own SfM on a bare folder (data.sfm_denoise) ---------------------------------------------------------

def test_train_on_a_bare_night_folder_denoises_sfm_previews_and_reads_its_model_back(tmp_path, capsys, fake):
    """``train`` on a bare folder of night photos runs SfM on denoised previews by ``data.sfm_denoise`` (default
    auto, the rule of ``sfm --denoise``); ``none`` is the plain previews of before the key; a finished run read back
    (no denoiser at hand: eval, render) takes the model its training cached instead of running SfM again."""
    from retinexgs.run.config import load_config
    from retinexgs.run.folder import open_scene
    from retinexgs.train.sfm_preview import scene_sfm_denoise
    from scenes import TINY_RUN

    photos = _dark_photos(tmp_path / "night")
    cache = tmp_path / "night" / "retinexgs_sfm"
    plain = load_config(overrides=["data.sfm_denoise=none"])
    auto = load_config()
    assert auto.data.sfm_denoise == "auto" and scene_sfm_denoise("none") is None

    open_scene(photos, plain, sfm_denoise=scene_sfm_denoise("none"))
    options, method = _record(cache)
    assert fake.maps == 1 and "denoise" not in options and "denoise" not in method  # as runs before the key
    scene = open_scene(photos, auto, sfm_denoise=scene_sfm_denoise("auto"))
    options, method = _record(cache)
    assert fake.maps == 2 and options["denoise"].startswith("chroma-")  # another recipe: SfM again
    assert len(scene.train) + len(scene.test) == 4
    open_scene(photos, auto)  # a finished run read back: the cached model, whichever recipe made it
    open_scene(photos, auto, sfm_denoise=scene_sfm_denoise("auto"))  # train again, or --resume: the same recipe
    assert fake.maps == 2
    open_scene(photos, plain)  # a run recorded before the key (none): its own recipe, as before
    assert fake.maps == 3 and "denoise" not in _record(cache)[0]

    # the train command end to end: its SfM goes through the denoiser, and says so
    sets = [a for s in TINY_RUN for a in ("--set", s)]
    code, out, err = run_cli(["train", "--data", photos, "--out", tmp_path / "run", "--config", "demo", *sets,
                            "--device", "cpu"], capsys)
    assert code == 0, err
    assert fake.maps == 4 and _record(cache)[0]["denoise"].startswith("chroma-")
    assert "denoising them (chroma)" in out + err, out  # train's log names the denoiser, as `sfm` does
    code, _, err = run_cli(["train", "--data", photos, "--out", tmp_path / "run2", "--set", "data.sfm_denoise=fast",
                            "--device", "cpu"], capsys)
    assert code == 2 and "sfm_denoise" in err and err.strip().count("\n") == 0, err


def test_runs_recorded_before_sfm_denoise_read_none():
    """A run of format 2 (before the key) posed its bare folder from plain previews: it reads ``none``, so its
    resume finds the SfM model it trained on; a run of today's format without the key gets today's default."""
    from retinexgs.config.versions import FORMAT, migrate_config

    old, filled = migrate_config({"format": 2, "data": {"reader": "auto"}}, "old/config.yaml")
    assert old["data"]["sfm_denoise"] == "none" and "data.sfm_denoise" in filled
    kept, _ = migrate_config({"format": 2, "data": {"sfm_denoise": "nlm"}}, "old/config.yaml")
    assert kept["data"]["sfm_denoise"] == "nlm"
    new, _ = migrate_config({"format": FORMAT, "data": {"reader": "auto"}}, "new/config.yaml")
    assert new["data"]["sfm_denoise"] == "auto"


def test_chroma_blotches_read_correlated_colour_noise_not_white_noise():
    """bright_chroma_blotch (what decomposer.denoise: auto reads on photos): colour noise of one per-pixel σ reads
    4× lower as white pixel noise than as 4×4-pixel blotches, across PHOTO_BLOTCH_MIN; luma noise alone reads
    nothing; at data.downscale 2 the same blotches are 2×2 pixels of the view and read half as high; a view smaller
    than BLOTCH_MIN_SIDE is not read (its texture cannot be told from noise)."""
    from retinexgs.data.capture import PHOTO_BLOTCH_MIN
    from retinexgs.train.colour_blotches import BLOTCH_MIN_SIDE, bright_chroma_blotch

    rng = np.random.default_rng(0)
    h, w, s = 2 * BLOTCH_MIN_SIDE, 2 * BLOTCH_MIN_SIDE + 64, 0.1
    grey = np.full((h, w, 3), 0.5, np.float32)
    white = grey + rng.normal(0, s, (h, w, 3)).astype(np.float32)
    coarse = rng.normal(0, s, (h // 4, w // 4, 3)).astype(np.float32)
    blotchy = grey + np.repeat(np.repeat(coarse, 4, axis=0), 4, axis=1)
    luma_only = grey + np.repeat(np.repeat(coarse[..., :1], 4, axis=0), 4, axis=1)  # the same in every channel
    b_white, b_blotchy = bright_chroma_blotch(white), bright_chroma_blotch(blotchy)
    assert b_white < PHOTO_BLOTCH_MIN < b_blotchy
    assert b_blotchy == pytest.approx(s, rel=0.15) and b_white == pytest.approx(s / 4, rel=0.15)
    assert bright_chroma_blotch(luma_only) < 1e-6
    assert bright_chroma_blotch(blotchy, downscale=2) == pytest.approx(b_blotchy / 2, rel=0.15)
    assert bright_chroma_blotch(blotchy, downscale=3) == 0.0  # 170 px of view: too small to read
    assert bright_chroma_blotch(blotchy[:BLOTCH_MIN_SIDE - 1]) == 0.0
    as_uint8 = np.clip(np.round(blotchy * 255), 0, 255).astype(np.uint8)
    assert bright_chroma_blotch(as_uint8) == pytest.approx(b_blotchy, rel=0.05)
