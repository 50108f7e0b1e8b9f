"""model.near_fraction: the scene's near plane (retinexgs/model/near_plane.py) — its depth statistic, the renders
that use it, the trainer that sets it, checkpoints and old runs."""
import math

import pytest
import torch
import yaml

from retinexgs.config.versions import FORMAT
from retinexgs.model.gaussians import GaussianModel
from retinexgs.model.inference import InferenceRenderer
from retinexgs.model.near_plane import CONTENT_QUANTILE, MIN_POINTS, content_depth, with_near
from retinexgs.model.retinex_model import RetinexGSModel
from retinexgs.render import Camera
from retinexgs.run.config import load_config
from scenes import tiny_trained_run

W, H = 32, 24


def camera(center_x=0.0):
    """A camera at (center_x, 0, 0) looking down +z (world = camera axes)."""
    vm = torch.eye(4, dtype=torch.float64)
    vm[0, 3] = -center_x
    return Camera(vm, 30.0, 30.0, W / 2, H / 2, W, H)


def test_content_depth_is_the_median_over_views_of_the_nearest_in_frame_content():
    g = torch.Generator().manual_seed(0)
    z = 1.0 + torch.rand(400, generator=g, dtype=torch.float64)  # content at depths 1..2, inside the frame
    inside = torch.stack([(torch.rand(400, generator=g, dtype=torch.float64) - 0.5) * 0.5 * z,
                          (torch.rand(400, generator=g, dtype=torch.float64) - 0.5) * 0.5 * z, z], dim=-1)
    beside = torch.tensor([[5.0, 0.0, 0.1]] * 50, dtype=torch.float64)  # out of frame: not the view's content
    behind = torch.tensor([[0.0, 0.0, -5.0]] * 50, dtype=torch.float64)
    pts = torch.cat([inside, beside, behind])
    expected = float(torch.quantile(z, CONTENT_QUANTILE))
    assert content_depth(pts, [camera()]) == pytest.approx(expected, rel=1e-9)
    # the median over the views: a view that sees fewer than MIN_POINTS points says nothing
    blind = camera(center_x=100.0)
    assert content_depth(pts, [camera(), blind]) == pytest.approx(expected, rel=1e-9)
    def back(d):  # the same camera moved back by d: every in-frame point stays in frame, d farther
        vm = torch.eye(4, dtype=torch.float64)
        vm[2, 3] = d
        return Camera(vm, 30.0, 30.0, W / 2, H / 2, W, H)
    got = content_depth(pts, [back(1.0), camera(), back(0.5)])
    assert got == pytest.approx(float(torch.quantile(z + 0.5, CONTENT_QUANTILE)), rel=1e-9)
    assert content_depth(pts[:MIN_POINTS - 1], [camera()]) == 0.0
    assert content_depth(pts, []) == 0.0 and content_depth(torch.zeros(0, 3), [camera()]) == 0.0


def test_with_near_raises_the_plane_and_keeps_a_farther_one():
    cam = camera()
    raised = with_near(cam, 0.3)
    assert raised.near == 0.3 and raised.far == cam.far and torch.equal(raised.viewmat, cam.viewmat)
    assert with_near(raised, 0.1) is raised  # already farther: the same camera
    assert with_near(cam, cam.far * 2) is cam  # no empty range


def veil_model(near_fraction=0.2):
    """A wall of Gaussians at depth 2 and one wide, opaque Gaussian 0.05 in front of the camera (a veil)."""
    g = torch.Generator().manual_seed(1)
    xy = (torch.rand(300, 2, generator=g) - 0.5) * 2.0
    wall = torch.cat([xy, torch.full((300, 1), 2.0)], dim=-1)
    pts = torch.cat([wall, torch.tensor([[0.0, 0.0, 0.05]])])
    cols = torch.rand(301, 3, generator=g)
    cfg = load_config(overrides=[f"model.near_fraction={near_fraction}", "model.sh_degree=0"])
    gaussians = GaussianModel.from_points(pts, cols, 0, 0.9)
    with torch.no_grad():
        gaussians.log_scales[-1] = math.log(0.05)
    return RetinexGSModel(gaussians, cfg.model, True).eval()


def test_a_gaussian_nearer_than_the_plane_is_not_drawn():
    model = veil_model()
    cam = camera()
    with torch.no_grad():
        veiled = model.render(cam, 0, near=False)["R"]
        model.near.fill_(0.2 * 2.0)  # a fifth of the wall's depth
        drawn = model.render(cam, 0)["R"]
        # the same as a model without the veil at all
        model.gaussians.opacity_logits[-1] = -30.0
        without = model.render(cam, 0, near=False)["R"]
    assert model.near_plane() == pytest.approx(0.4)
    assert (veiled - without).abs().max() > 0.05  # the veil shows without the plane
    torch.testing.assert_close(drawn, without, rtol=0, atol=1e-6)


def test_the_inference_renderer_draws_with_the_same_plane():
    model = veil_model()
    with torch.no_grad():
        model.near.fill_(0.4)
        ref = model.render(camera(), 0)
        fast = InferenceRenderer(model, 0).render(camera())
    torch.testing.assert_close(fast["R"], ref["R"], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(fast["rgb"], ref["rgb"], rtol=1e-4, atol=1e-4)


def test_without_the_key_there_is_no_plane_and_no_buffer():
    model = veil_model(near_fraction=0.0)
    assert not model.has_near and "near" not in model.state_dict() and model.near_plane() == 0.0
    cam = camera()
    assert model.camera_for(cam) is cam


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    scene, run = tiny_trained_run(tmp_path_factory.mktemp("near"), ["steps=2", "checkpoint.every=2",
                                                                     "log.tensorboard=false"])
    return scene, run


def test_the_trainer_sets_the_plane_from_the_initial_points_and_the_run_keeps_it(tiny_run):
    from retinexgs.run.folder import load_run
    from retinexgs.run.render import view_camera
    _, run = tiny_run
    cfg, scene, model, _ = load_run(run, "cpu")
    depth = content_depth(scene.points, [view_camera(v) for v in scene.train])
    assert depth > 0 and cfg.model.near_fraction == 0.2
    assert model.near_plane() == pytest.approx(0.2 * depth, rel=1e-5)


def test_a_run_from_before_the_key_renders_as_it_did(tiny_run, tmp_path):
    """A run whose config.yaml predates model.near_fraction gets 0 (its format-0 migration, FORMAT_0_VALUES): no
    buffer, no plane."""
    import shutil

    from retinexgs.config.versions import FORMAT_0_VALUES
    from retinexgs.run.folder import load_run
    _, run = tiny_run
    old = tmp_path / "old"
    shutil.copytree(run, old)
    raw = yaml.safe_load((old / "config.yaml").read_text())
    cfg_part = raw.get("config", raw)
    del cfg_part["model"]["near_fraction"], cfg_part["model"]["near_in_training"]
    assert raw.pop("format") == FORMAT  # written today; a run from before the key had no format (format 0)
    (old / "config.yaml").write_text(yaml.safe_dump(raw))
    ckpt = sorted((old / "checkpoints").glob("step_*.pt"))[-1]
    state = torch.load(ckpt, weights_only=False)
    del state["model"]["near"]
    del state["format"]
    torch.save(state, ckpt)
    assert FORMAT_0_VALUES["model.near_fraction"] == 0.0
    cfg, _, model, _ = load_run(old, "cpu")
    assert cfg.model.near_fraction == 0.0 and not model.has_near and model.near_plane() == 0.0
