"""SfM's night settings (``sfm --night``, issue 64 item 5): where the previews are denoised (``--night auto``) SIFT
skips the upsampled octave and pools its descriptors, and the mapper starts a model and adds photos at the inlier
counts a night pair holds; elsewhere COLMAP's own settings, and the cached model's signature, are as before. Small
synthetic photos; SfM's stages are a stand-in that records the options it is handed (no real SfM runs here)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from retinexgs.data.sfm import (META_NAME, NIGHT_MAPPER, NIGHT_SIFT, NIGHT_TRIANGULATION, PreviewDenoise, check_night,
                                night_settings, run_sfm)
from retinexgs.data.srgb import linear_to_srgb
from retinexgs.errors import UserError
from scenes import run_cli

pycolmap = pytest.importorskip("pycolmap")

W, H = 96, 72


def _photo(path: Path, seed: int, scale: float, noise: float) -> None:
    """A photo of patches and blobs in linear light ``scale``, with Poisson-Gaussian noise of strength ``noise``."""
    rng = np.random.default_rng(seed)
    yy, xx = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    lin = np.full((H, W, 3), 0.5)
    for _ in range(8):
        cy, cx, r = rng.uniform(0, H), rng.uniform(0, W), rng.uniform(4, 12)
        lin[(yy - cy) ** 2 + (xx - cx) ** 2 < r * r] = rng.uniform(0.1, 1.0, 3)
    lin = lin * scale
    if noise:
        lin = noise * rng.poisson(lin / noise) + math.sqrt(noise / 10) * rng.standard_normal(lin.shape)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((np.asarray(linear_to_srgb(np.clip(lin, 0, 1))) * 255 + 0.5).astype(np.uint8)).save(path)


class Recorder:
    """pycolmap with SfM's stages replaced: records the SIFT and mapper options, registers every photo."""

    def __init__(self):
        self.sift, self.mapper, self.tri = None, None, None

    def __getattr__(self, name):
        return getattr(pycolmap, name)

    def extract_features(self, db, feature_dir, image_names=(), extraction_options=None, **kwargs):
        Path(db).write_bytes(b"stand-in database")
        self.names, self.sift = sorted(image_names), extraction_options.sift

    def match_exhaustive(self, db, **kwargs):
        pass

    def incremental_mapping(self, db, image_dir, out, options=None, **kwargs):
        self.mapper, self.tri = options.mapper, options.triangulation
        rec = pycolmap.Reconstruction()
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=W, height=H,
                                                        params=[80.0, 80.0, W / 2, H / 2], camera_id=1))
        for i, n in enumerate(self.names):
            w2c = np.hstack([np.eye(3), -np.array([[0.3 * i], [0.0], [0.0]])])
            rec.add_image_with_trivial_frame(pycolmap.Image(name=n, camera_id=1, image_id=i + 1),
                                             pycolmap.Rigid3d(w2c))
        return {0: rec}


@pytest.fixture
def rec(monkeypatch) -> Recorder:
    import retinexgs.data.sfm as sfm_module

    r = Recorder()
    monkeypatch.setattr(sfm_module, "_pycolmap", lambda: r)
    return r


def _stand_in_denoise() -> PreviewDenoise:
    return PreviewDenoise("stand-in", lambda lin, a, b: lin, ((1e-3,) * 3, (1e-4,) * 3))


def test_night_settings_follow_the_denoised_previews():
    assert night_settings("auto", None) is None and night_settings("off", _stand_in_denoise()) is None
    on = night_settings("auto", _stand_in_denoise())
    assert on == {"sift": NIGHT_SIFT, "mapper": NIGHT_MAPPER, "triangulation": NIGHT_TRIANGULATION}
    assert on == night_settings("on", None)
    assert night_settings(True, None) == on and night_settings(False, _stand_in_denoise()) is None
    # every key is a real option of the installed pycolmap (a misspelt one would be a new Python attribute or fail)
    defaults = (pycolmap.SiftExtractionOptions(), pycolmap.IncrementalMapperOptions(),
                pycolmap.IncrementalTriangulatorOptions())
    for options, part in zip(defaults, ("sift", "mapper", "triangulation")):
        for key, value in on[part].items():
            assert key in dir(options) and getattr(options, key) != value, (part, key)
    for bad in ("yes", "", None, 1):
        with pytest.raises(UserError, match="--night must be one of auto, on, off"):
            check_night(bad)


def test_run_sfm_applies_the_night_settings_where_previews_are_denoised(tmp_path, rec):
    photos = tmp_path / "night"
    for i in range(3):
        _photo(photos / f"p{i}.png", i, scale=0.03, noise=0.002)
    run_sfm(photos, tmp_path / "a", denoise=_stand_in_denoise(), progress=None)
    for key, value in NIGHT_SIFT.items():
        assert getattr(rec.sift, key) == value, key
    for key, value in NIGHT_MAPPER.items():
        assert getattr(rec.mapper, key) == value, key
    for key, value in NIGHT_TRIANGULATION.items():
        assert getattr(rec.tri, key) == value, key
    options = json.loads((tmp_path / "a" / META_NAME).read_text())["signature"]["options"]
    assert options["night"] == {"sift": NIGHT_SIFT, "mapper": NIGHT_MAPPER, "triangulation": NIGHT_TRIANGULATION}

    run_sfm(photos, tmp_path / "b", denoise=_stand_in_denoise(), night="off", progress=None)
    default_sift, default_mapper = pycolmap.SiftExtractionOptions(), pycolmap.IncrementalMapperOptions()
    for key in NIGHT_SIFT:
        assert getattr(rec.sift, key) == getattr(default_sift, key), key
    for key in NIGHT_MAPPER:
        assert getattr(rec.mapper, key) == getattr(default_mapper, key), key
    for key in NIGHT_TRIANGULATION:
        assert getattr(rec.tri, key) == getattr(pycolmap.IncrementalTriangulatorOptions(), key), key
    assert "night" not in json.loads((tmp_path / "b" / META_NAME).read_text())["signature"]["options"]


def test_a_bright_folder_keeps_colmaps_settings_and_its_cached_model(tmp_path, capsys, rec):
    photos = tmp_path / "day"
    for i in range(3):
        _photo(photos / f"p{i}.png", i, scale=0.8, noise=0.0)
    code, outp, err = run_cli(["sfm", "--images", photos, "--out", tmp_path / "proj"], capsys)
    assert code == 0 and "registered views: 3/3" in outp, err
    default_sift, default_mapper = pycolmap.SiftExtractionOptions(), pycolmap.IncrementalMapperOptions()
    for key in NIGHT_SIFT:
        assert getattr(rec.sift, key) == getattr(default_sift, key), key
    for key in NIGHT_MAPPER:
        assert getattr(rec.mapper, key) == getattr(default_mapper, key), key
    for key in NIGHT_TRIANGULATION:
        assert getattr(rec.tri, key) == getattr(pycolmap.IncrementalTriangulatorOptions(), key), key
    assert "night" not in json.loads((tmp_path / "proj" / META_NAME).read_text())["signature"]["options"]
    # --night on forces them (and keys the cache: SfM runs again)
    code, outp, err = run_cli(["sfm", "--images", photos, "--out", tmp_path / "proj", "--night", "on"], capsys)
    assert code == 0 and "(cached)" not in outp and rec.mapper.init_min_num_inliers == NIGHT_MAPPER[
        "init_min_num_inliers"], err


def test_a_finished_run_reads_back_a_model_made_with_the_night_settings(tmp_path, rec):
    photos = tmp_path / "night"
    for i in range(3):
        _photo(photos / f"p{i}.png", i, scale=0.03, noise=0.002)
    run_sfm(photos, tmp_path / "a", denoise=_stand_in_denoise(), progress=None)
    again = run_sfm(photos, tmp_path / "a", denoise=None, denoise_cached=True, progress=None)
    assert again.cached
