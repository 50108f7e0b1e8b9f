"""The denoiser's luma strength set by the views that see each point (issue 64, ``decomposer.denoise_luma_views``):
the scene's statistic (Scene.views_per_point), the scaling (DenoiseParams.for_views), where training and
``decompose`` read it, and the run format that keeps older runs' priors."""
from __future__ import annotations

import math

import pytest
import torch

from retinexgs.errors import UserError
from retinexgs.retinex.denoise import DenoiseParams
from retinexgs.run.config import load_config


def test_the_luma_keeps_its_strength_up_to_the_reference_and_falls_as_the_square_root_above():
    base = DenoiseParams()
    for n, ref in ((None, 9), (5.0, 9), (9.0, 9), (36.0, 0)):  # unknown, fewer, equal, switched off
        assert base.for_views(n, ref) is base
    out = base.for_views(36.0, 9)
    assert out.h_luma == pytest.approx(base.h_luma * 0.5)
    assert (out.h_chroma, out.patch, out.search, out.radius, out.eps, out.calibrate) == \
        (base.h_chroma, base.patch, base.search, base.radius, base.eps, base.calibrate)
    tuned = DenoiseParams.from_mapping({"h_luma": 0.6}).for_views(18.0, 9)
    assert tuned.h_luma == pytest.approx(0.6 / math.sqrt(2))  # the user's h_luma is the strength at few views


def _brute_force_views_per_point(scene) -> float:
    """The same statistic by the cameras' matrices: K·[R|t]·X, in front and inside the frame."""
    counts = []
    for p in scene.points.to(torch.float64):
        n = 0
        for v in scene.train:
            w2c = v.world_to_camera()
            pc = w2c[:3, :3] @ p + w2c[:3, 3]
            if pc[2] <= 0:
                continue
            uv = v.K() @ (pc / pc[2])
            n += int(0 <= uv[0] < v.width and 0 <= uv[1] < v.height)
        counts.append(n)
    return float(torch.tensor(counts, dtype=torch.float64).median())


def test_views_per_point_counts_the_training_frusta(tmp_path):
    from retinexgs.data import load_scene
    from retinexgs.demo.synthetic import make_demo_scene

    src = make_demo_scene(tmp_path / "s", n_train=6, n_test=1, width=48, height=36, n_points=120)
    scene = load_scene(src)
    got = scene.views_per_point()
    assert got == _brute_force_views_per_point(scene) and 1 <= got <= 6
    assert type(scene)(**{**scene.__dict__, "train": scene.train[:2]}).views_per_point() <= 2
    assert scene.views_per_point(max_points=7) == _brute_force_views_per_point(
        type(scene)(**{**scene.__dict__, "points": scene.points[::-(-len(scene.points) // 7)]}))
    # random points say nothing about the scene; nor does a scene without training views
    assert type(scene)(**{**scene.__dict__, "points_source": "random"}).views_per_point() is None
    assert type(scene)(**{**scene.__dict__, "train": []}).views_per_point() is None


def test_training_s_denoiser_takes_the_scene_s_views_per_point(night):
    """denoise_spec: the luma lightened by √(ref / n) where more than ``decomposer.denoise_luma_views`` views see a
    point (said in one line), with its own cache recipe; unchanged at or under the reference and with the key at 0."""
    from retinexgs.data import load_scene
    from retinexgs.train import view_setup

    scene = load_scene(night / "raw")
    n = scene.views_per_point()
    assert n is not None and n > 1
    cfg = load_config(overrides=["data.downscale=2", "decomposer.denoise_luma_views=1"])
    notes = []
    spec = view_setup.denoise_spec(scene.train, cfg, "cpu", note=notes.append, views_per_point=lambda: n)
    plain = view_setup.denoise_spec(scene.train, load_config(overrides=["data.downscale=2"]), "cpu",
                                    views_per_point=scene.views_per_point)
    assert spec.params.h_luma == pytest.approx(DenoiseParams().h_luma / math.sqrt(n))
    assert plain.params == DenoiseParams() and spec.recipe != plain.recipe
    assert len(notes) == 1 and "luma NLM at" in notes[0] and f"{n:g} training views" in notes[0]
    off = view_setup.denoise_spec(scene.train, load_config(overrides=["data.downscale=2",
                                                                      "decomposer.denoise_luma_views=0"]),
                                  "cpu", views_per_point=lambda: n)
    assert off.params == DenoiseParams() and off.recipe == plain.recipe
    asked = []  # where nothing is denoised the statistic is not computed (it walks every training camera)
    assert view_setup.denoise_spec(scene.train, load_config(overrides=["decomposer.denoise=none"]), "cpu",
                                   views_per_point=lambda: asked.append(1)) is None and asked == []


def test_redenoise_reads_the_same_settings_as_the_priors(night):
    from retinexgs.data import load_scene
    from retinexgs.train import view_setup
    from retinexgs.train.redenoise import Redenoise

    scene = load_scene(night / "raw")
    cfg = load_config(overrides=["decomposer.denoise_luma_views=1", "decomposer.redenoise_at=[0.5]"])
    red = Redenoise.for_run(cfg, scene, False, "cpu")
    assert red.params == view_setup.denoise_params(cfg, scene.views_per_point())
    assert red.params.h_luma < DenoiseParams().h_luma


def test_runs_of_format_3_keep_the_luma_they_trained_with():
    from retinexgs.config.versions import FORMAT, migrate_config

    old, filled = migrate_config({"format": 3, "decomposer": {"denoise": "chroma"}}, "old/config.yaml")
    assert old["decomposer"]["denoise_luma_views"] == 0 and "decomposer.denoise_luma_views" in filled
    kept, _ = migrate_config({"format": 3, "decomposer": {"denoise_luma_views": 4}}, "old/config.yaml")
    assert kept["decomposer"]["denoise_luma_views"] == 4
    new, _ = migrate_config({"format": FORMAT, "decomposer": {}}, "new/config.yaml")
    assert new["decomposer"]["denoise_luma_views"] == load_config().decomposer.denoise_luma_views == 9


def test_a_bad_reference_is_one_line():
    with pytest.raises(UserError) as info:
        load_config(overrides=["decomposer.denoise_luma_views=-1"])
    assert "decomposer.denoise_luma_views" in str(info.value) and "\n" not in str(info.value)
