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

from retinexgs.data.sfm import (META_NAME, NIGHT_GUARD, NIGHT_MAPPER, NIGHT_SIFT, NIGHT_TRIANGULATION, PreviewDenoise,
                                check_night, drop_loose_views, loose_views, night_settings, run_sfm)
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
        # neighbouring photos share 40 points (the night guard keeps them)
        return {0: _model(self.names, {(i, i + 1): 40 for i in range(len(self.names) - 1)})}


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
    assert on == {"sift": NIGHT_SIFT, "mapper": NIGHT_MAPPER, "triangulation": NIGHT_TRIANGULATION,
                  "guard": NIGHT_GUARD}
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


def _assert_colmaps_own_settings(rec) -> None:
    """The options the stand-in pycolmap was given are COLMAP's defaults for every key the night settings change."""
    default_sift, default_mapper = pycolmap.SiftExtractionOptions(), pycolmap.IncrementalMapperOptions()
    for key in NIGHT_SIFT:
        assert getattr(rec.sift, key) == getattr(default_sift, key), key
    for key in NIGHT_MAPPER:
        assert getattr(rec.mapper, key) == getattr(default_mapper, key), key
    for key in NIGHT_TRIANGULATION:
        assert getattr(rec.tri, key) == getattr(pycolmap.IncrementalTriangulatorOptions(), key), key


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
    assert options["night"] == {"sift": NIGHT_SIFT, "mapper": NIGHT_MAPPER, "triangulation": NIGHT_TRIANGULATION,
                                "guard": NIGHT_GUARD}

    run_sfm(photos, tmp_path / "b", denoise=_stand_in_denoise(), night="off", progress=None)
    _assert_colmaps_own_settings(rec)
    assert "night" not in json.loads((tmp_path / "b" / META_NAME).read_text())["signature"]["options"]


def test_a_bright_folder_keeps_colmaps_settings_and_its_cached_model(tmp_path, capsys, rec):
    photos = tmp_path / "day"
    for i in range(3):
        _photo(photos / f"p{i}.png", i, scale=0.8, noise=0.0)
    code, outp, err = run_cli(["sfm", "--images", photos, "--out", tmp_path / "proj"], capsys)
    assert code == 0 and "registered views: 3/3" in outp, err
    _assert_colmaps_own_settings(rec)
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


def _model(names, shared) -> "pycolmap.Reconstruction":
    """A model of the photos ``names`` in a row; ``shared[(a, b)]``: how many 3D points photos a and b both see
    (each such point is seen by those two photos only)."""
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=W, height=H,
                                                    params=[80.0, 80.0, W / 2, H / 2], camera_id=1))
    rng = np.random.default_rng(0)
    per_image = {i: [] for i in range(len(names))}
    points = []
    for (a, b), k in shared.items():
        for _ in range(k):
            points.append(((a, len(per_image[a])), (b, len(per_image[b]))))
            per_image[a].append(rng.uniform(0, W, 2))
            per_image[b].append(rng.uniform(0, W, 2))
    for i, n in enumerate(names):
        w2c = np.hstack([np.eye(3), -np.array([[0.3 * i], [0.0], [0.0]])])
        kp = np.array(per_image[i], float).reshape(-1, 2)
        rec.add_image_with_trivial_frame(pycolmap.Image(name=n, keypoints=kp, camera_id=1, image_id=i + 1),
                                         pycolmap.Rigid3d(w2c))
    for els in points:
        track = pycolmap.Track()
        for i, idx in els:
            track.add_element(i + 1, idx)
        rec.add_point3D(rng.uniform(-1, 1, 3) + [0, 0, 5], track)
    return rec


# photos a, b, c share plenty; d shares 12 points with c and 5 with b: fewer than 15 with any one photo
LOOSE = {("a.png", "b.png"): 40, ("b.png", "c.png"): 40, ("a.png", "c.png"): 20}


def _loose_model(names=("a.png", "b.png", "c.png", "d.png"), d_c=12, d_b=5):
    pairs = {(names.index(x), names.index(y)): k for (x, y), k in LOOSE.items()}
    pairs.update({(3, 2): d_c, (3, 1): d_b})
    return _model(list(names), pairs)


def test_a_view_sharing_few_points_with_every_other_is_dropped():
    min_shared = NIGHT_GUARD["min_shared_points"]
    rec = _loose_model()
    assert loose_views(rec, min_shared) == [4]
    assert drop_loose_views(rec, min_shared) == ["d.png"]
    assert sorted(rec.images[i].name for i in rec.reg_image_ids()) == ["a.png", "b.png", "c.png"]
    assert rec.num_images() == 3 and rec.num_points3D() == 100  # d's points (seen by one photo now) are gone
    assert loose_views(rec, min_shared) == [] and drop_loose_views(rec, min_shared) == []
    # at the floor (15 points shared with c) a view is kept
    kept = _loose_model(d_c=min_shared)
    assert drop_loose_views(kept, min_shared) == [] and kept.num_reg_images() == 4
    # two photos on loose matches only: nothing is left
    pair = _model(["a.png", "b.png"], {(0, 1): 5})
    assert drop_loose_views(pair, min_shared) == ["a.png", "b.png"] and pair.num_reg_images() == 0


class LooseMapper(Recorder):
    """The stand-in SfM whose model holds one photo (d.png) posed on loose matches."""

    def incremental_mapping(self, db, image_dir, out, options=None, **kwargs):
        self.mapper, self.tri = options.mapper, options.triangulation
        return {0: _loose_model(tuple(self.names))}


def test_run_sfm_drops_views_posed_on_loose_matches_at_night(tmp_path, monkeypatch, capsys):
    import retinexgs.data.sfm as sfm_module
    from retinexgs.data.colmap import read_model

    monkeypatch.setattr(sfm_module, "_pycolmap", LooseMapper)
    photos = tmp_path / "night"
    for i, n in enumerate("abcd"):
        _photo(photos / f"{n}.png", i, scale=0.03, noise=0.002)
    said = []
    r = run_sfm(photos, tmp_path / "a", denoise=_stand_in_denoise(), progress=said.append, min_registered=0.5)
    assert r.registered == ["a.png", "b.png", "c.png"]
    assert sorted(im.name for im in read_model(r.model_dir).images.values()) == ["a.png", "b.png", "c.png"]
    assert any(line.startswith("dropped 1 photo posed on loose matches") and line.endswith(": d.png")
               for line in said), said
    assert "not registered, left out of the scene: d.png" in capsys.readouterr().err
    # COLMAP's own settings (a well-lit folder, or --night off): no guard, the model as the mapper made it
    r = run_sfm(photos, tmp_path / "b", denoise=_stand_in_denoise(), night="off", progress=None)
    assert r.registered == ["a.png", "b.png", "c.png", "d.png"]


def test_a_model_of_loose_views_only_is_no_model(tmp_path, monkeypatch):
    import retinexgs.data.sfm as sfm_module

    class PairMapper(Recorder):
        def incremental_mapping(self, db, image_dir, out, options=None, **kwargs):
            return {0: _model(self.names, {(0, 1): 5})}

    monkeypatch.setattr(sfm_module, "_pycolmap", PairMapper)
    photos = tmp_path / "night"
    for i in range(2):
        _photo(photos / f"p{i}.png", i, scale=0.03, noise=0.002)
    with pytest.raises(UserError, match="share too few points with one another"):
        run_sfm(photos, tmp_path / "a", denoise=_stand_in_denoise(), progress=None, min_registered=0)
    assert not (tmp_path / "a" / "sparse" / "0").exists()
