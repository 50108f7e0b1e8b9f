"""The viewer's render callback (issue 14), on the CPU, without viser: the camera conversion from the viewer's
convention (round trip through a training camera), each map, exposure / gamma / resolution controls, and junk
camera input refused with a ValueError."""
import math

import numpy as np
import pytest
import torch

from retinexgs.run.folder import load_run
from retinexgs.run.render import render_function
from retinexgs.run.render import active_sh_degree, view_camera
from retinexgs.evaluate.evaluate import to_uint8
from retinexgs.viewer.camera import (ViewerCamera, average_up, camera_to_viewer, matrix_to_quat, quat_to_matrix,
                                   viewer_to_camera)
from retinexgs.viewer.frame import FrameRenderer, FrameSettings
from scenes import tiny_trained_run

TINY = ["steps=4", "checkpoint.every=4", "log.tensorboard=false", "model.sh_degree=1", "model.sh_degree_every=2",
        "model.max_init_points=800", "model.init_opacity=0.95", "density.start=100", "decomposer.method=lime",
        "loss.enhance_from=2"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A tiny RetinexGS run and a tiny plain-3DGS baseline, loaded."""
    _, run, base = tiny_trained_run(tmp_path_factory.mktemp("view"), TINY, width=40, height=30, n_points=800,
                                    baseline_overrides=["steps=2", "method=3dgs"])
    return load_run(run, "cpu"), load_run(base, "cpu")


@pytest.fixture(scope="module")
def renderer(runs):
    cfg, scene, model, step = runs[0]
    return FrameRenderer(model, cfg, active_sh_degree(cfg, step), scene.train)


def train_viewer_camera(runs, i=0):
    cfg, scene, model, step = runs[0]
    return scene.train[i], camera_to_viewer(view_camera(scene.train[i]))


def test_quaternion_round_trip():
    g = torch.Generator().manual_seed(0)
    for _ in range(50):
        q = torch.randn(4, generator=g, dtype=torch.float64)
        q = q / q.norm()
        q = -q if q[0] < 0 else q
        R = quat_to_matrix(q)
        assert torch.allclose(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-12)
        assert torch.allclose(matrix_to_quat(R), q, atol=1e-9)


def test_camera_round_trip_renders_the_training_view(runs, renderer):
    cfg, scene, model, step = runs[0]
    view, vcam = train_viewer_camera(runs)
    cam = viewer_to_camera(vcam)
    ref = view_camera(view)
    assert torch.allclose(cam.viewmat, ref.viewmat, atol=1e-9)
    assert (cam.width, cam.height) == (ref.width, ref.height)
    assert math.isclose(cam.fy, ref.fy, rel_tol=1e-9) and math.isclose(cam.cx, ref.cx)
    expected = to_uint8(render_function(model, cfg, active_sh_degree(cfg, step))(view)["rgb"])
    frame = renderer.render(vcam)
    assert frame.dtype == np.uint8 and frame.shape == (ref.height, ref.width, 3)
    assert np.abs(frame.astype(int) - expected.astype(int)).max() <= 1
    assert frame.mean() > 5  # not blank


def test_viewer_axes_are_opencv(runs):
    # viser: wxyz is R in P_world = R p_camera + t, camera looks down +z; identity looks down world +z.
    cam = viewer_to_camera(ViewerCamera((1, 0, 0, 0), (0, 0, -2), 1.0, 8, 6))
    assert torch.allclose(cam.viewmat[:3, :3], torch.eye(3, dtype=torch.float64))
    assert torch.allclose(cam.center, torch.tensor([0.0, 0.0, -2.0], dtype=torch.float64))


def test_every_map_renders_and_differs(renderer, runs):
    _, vcam = train_viewer_camera(runs)
    frames = {m: renderer.render(vcam, FrameSettings(map=m)) for m in renderer.maps}
    assert set(frames) == {"enhanced", "R", "L", "low", "depth"}
    for m, f in frames.items():
        assert f.shape == (30, 40, 3) and f.dtype == np.uint8 and f.max() > 0, m
    means = {m: float(f.mean()) for m, f in frames.items()}
    assert means["low"] < means["enhanced"]  # the dark reconstruction is darker than the enhanced image
    assert len({round(v, 3) for v in means.values()}) == len(means)
    depth = frames["depth"]
    assert (depth[..., 0] != depth[..., 2]).any()  # colourised, not grey


def test_exposure_and_gamma(renderer, runs):
    _, vcam = train_viewer_camera(runs)
    base = renderer.render(vcam).mean()
    assert renderer.render(vcam, FrameSettings(exposure=0.5)).mean() > base
    assert renderer.render(vcam, FrameSettings(exposure=2.0)).mean() < base
    low_g = renderer.render(vcam, FrameSettings(gamma=0.2))
    high_g = renderer.render(vcam, FrameSettings(gamma=1.0, exposure=0.3))  # gamma overrides exposure
    assert low_g.mean() > high_g.mean()
    assert np.array_equal(high_g, renderer.render(vcam, FrameSettings(gamma=1.0, exposure=3.0)))


def test_resolution_scale_changes_the_size(renderer, runs):
    _, vcam = train_viewer_camera(runs)
    assert renderer.render(vcam, FrameSettings(scale=0.5)).shape == (15, 20, 3)
    assert renderer.render(vcam, FrameSettings(scale=2.0)).shape == (60, 80, 3)


def test_baseline_has_enhanced_and_depth_only(runs):
    cfg, scene, model, step = runs[1]
    r = FrameRenderer(model, cfg, active_sh_degree(cfg, step), scene.train)
    vcam = camera_to_viewer(view_camera(scene.train[0]))
    assert r.maps == ("enhanced", "depth")
    assert r.render(vcam).shape == (30, 40, 3)
    assert np.array_equal(r.render(vcam), r.render(vcam, FrameSettings(exposure=0.3)))  # no gamma to scale
    with pytest.raises(ValueError, match="map 'R' is not available"):
        r.render(vcam, FrameSettings(map="R"))


GOOD = dict(wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, -2.0), fov=1.0, width=8, height=6)


@pytest.mark.parametrize("change, message", [
    (dict(position=(float("nan"), 0.0, 0.0)), "position must be 3 finite numbers"),
    (dict(position=(0.0, 0.0)), "position must be 3 finite numbers"),
    (dict(wxyz=(0.0, 0.0, 0.0, 0.0)), "non-zero quaternion"),
    (dict(wxyz=(1.0, float("inf"), 0.0, 0.0)), "wxyz must be 4 finite numbers"),
    (dict(wxyz="abcd"), "wxyz must be 4 numbers"),
    (dict(fov=0.0), r"fov must be in \(0, pi\)"),
    (dict(fov=float("nan")), r"fov must be in \(0, pi\)"),
    (dict(fov=4.0), r"fov must be in \(0, pi\)"),
    (dict(width=-5), r"width must be an integer in \[1, 4096\]"),
    (dict(height=0), r"height must be an integer in \[1, 4096\]"),
    (dict(width=100000), r"width must be an integer in \[1, 4096\]"),
])
def test_junk_viewer_cameras_are_refused(renderer, change, message):
    with pytest.raises(ValueError, match=message):
        renderer.render(ViewerCamera(**{**GOOD, **change}))


@pytest.mark.parametrize("settings, message", [
    (FrameSettings(map="normals"), "map 'normals' is not available"),
    (FrameSettings(exposure=0.0), "exposure must be a positive finite number"),
    (FrameSettings(exposure=float("nan")), "exposure must be a positive finite number"),
    (FrameSettings(gamma=-1.0), "gamma must be a positive finite number"),
    (FrameSettings(scale=0.0), r"resolution scale must be in \(0, 4\]"),
    (FrameSettings(scale=float("inf")), r"resolution scale must be in \(0, 4\]"),
])
def test_junk_settings_are_refused(renderer, settings, message):
    with pytest.raises(ValueError, match=message):
        renderer.render(ViewerCamera(**GOOD), settings)


def test_average_up_of_the_training_cameras(runs):
    cfg, scene, model, step = runs[0]
    up = torch.tensor(average_up([view_camera(v) for v in scene.train]), dtype=torch.float64)
    assert math.isclose(float(up.norm()), 1.0, rel_tol=1e-9)
    assert float(up[1]) > 0.95  # the synthetic scene's world is y-up (its cameras are level, looking slightly down)
    for v in scene.train:  # every training camera's up is within 90 degrees of the average
        assert float(-view_camera(v).viewmat[1, :3] @ up) > 0
