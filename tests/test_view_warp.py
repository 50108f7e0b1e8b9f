"""retinexgs.train.view_warp: neighbouring views warped into a view through depth and averaged (issue 64,
``decomposer.redenoise_source: views``), checked against scenes whose warp is known in closed form."""
import math

import pytest
import torch

from retinexgs.render.camera import Camera
from retinexgs.train.view_warp import WarpSource, neighbours, warp_average

W, H, F = 48, 32, 40.0
PLANE_Z = 2.0


def camera_at(x: float, yaw_deg: float = 0.0) -> Camera:
    """A camera at (x, 0, 0) looking along +z turned by ``yaw_deg`` about y (world-to-camera viewmat)."""
    a = math.radians(yaw_deg)
    R = torch.tensor([[math.cos(a), 0.0, -math.sin(a)], [0.0, 1.0, 0.0], [math.sin(a), 0.0, math.cos(a)]],
                     dtype=torch.float64)  # rows: the camera's axes in world coordinates
    vm = torch.eye(4, dtype=torch.float64)
    vm[:3, :3] = R
    vm[:3, 3] = -R @ torch.tensor([x, 0.0, 0.0], dtype=torch.float64)
    return Camera(vm, F, F, W / 2, H / 2, W, H)


def texture(X: torch.Tensor, Y: torch.Tensor) -> torch.Tensor:
    """A smooth colour field on the plane z = PLANE_Z, [H,W,3]."""
    return torch.stack([0.5 + 0.3 * torch.sin(2.0 * X), 0.5 + 0.3 * torch.cos(1.5 * Y), 0.4 + 0.2 * X], -1)


def plane_view(cam: Camera) -> WarpSource:
    """What ``cam`` (unturned) sees of the textured plane: its light, depth PLANE_Z everywhere, alpha 1."""
    ys = (torch.arange(H, dtype=torch.float64) + 0.5 - cam.cy) / cam.fy
    xs = (torch.arange(W, dtype=torch.float64) + 0.5 - cam.cx) / cam.fx
    X = cam.center[0] + xs[None, :].expand(H, -1) * PLANE_Z
    Y = ys[:, None].expand(-1, W) * PLANE_Z
    return WarpSource(cam, texture(X, Y), torch.full((H, W), PLANE_Z, dtype=torch.float64),
                      torch.ones(H, W, dtype=torch.float64))


def test_a_view_warped_into_itself_is_itself_counted_twice():
    me = plane_view(camera_at(0.0))
    avg, count = warp_average(me, [me])
    assert torch.allclose(avg, me.light, atol=1e-12)
    assert torch.equal(count, torch.full((H, W), 2.0, dtype=torch.float64))


def test_a_shifted_view_lands_where_the_geometry_says():
    """A camera 0.5 to the side sees the plane shifted by F·0.5/2 = 10 pixels: the target's pixels that it also
    sees are averaged with the same texture (up to bilinear interpolation), the others keep their own light."""
    me, other = plane_view(camera_at(0.0)), plane_view(camera_at(0.5))
    avg, count = warp_average(me, [other])
    shift = int(F * 0.5 / PLANE_Z)  # 10 pixels
    # the target's column j lands at source column j - 10: inside for j ≥ 10 (the edge half-pixel aside)
    assert torch.equal(count[:, shift + 1:W - 1], torch.full((H, W - shift - 2), 2.0, dtype=torch.float64))
    assert torch.equal(count[:, :shift], torch.ones(H, shift, dtype=torch.float64))
    assert torch.equal(avg[:, :shift], me.light[:, :shift])
    assert (avg[:, shift + 1:W - 1] - me.light[:, shift + 1:W - 1]).abs().max() < 1e-3
    # and it is the source's light that came in: a source of another colour moves the average by half of it
    painted = WarpSource(other.camera, other.light + 0.2, other.depth, other.alpha)
    avg2, _ = warp_average(me, [painted])
    assert torch.allclose(avg2[:, shift + 1:W - 1] - avg[:, shift + 1:W - 1],
                          torch.full_like(avg[:, shift + 1:W - 1], 0.1), atol=1e-9)


def test_noise_averages_down_by_the_count():
    torch.manual_seed(0)
    me = plane_view(camera_at(0.0))
    clean = me.light.clone()
    views = []
    for _ in range(8):  # the same camera, independent noise: the average's variance is σ²/9
        v = plane_view(camera_at(0.0))
        views.append(WarpSource(v.camera, v.light + 0.1 * torch.randn_like(v.light), v.depth, v.alpha))
    noisy = WarpSource(me.camera, clean + 0.1 * torch.randn_like(clean), me.depth, me.alpha)
    avg, count = warp_average(noisy, views)
    assert torch.equal(count, torch.full((H, W), 9.0, dtype=torch.float64))
    assert (avg - clean).std() == pytest.approx(0.1 / 3, rel=0.1)


def test_occluded_and_uncovered_pixels_are_not_averaged():
    me, other = plane_view(camera_at(0.0)), plane_view(camera_at(0.0))
    front = WarpSource(other.camera, other.light + 1.0, other.depth * 0.9, other.alpha)  # something in front
    avg, count = warp_average(me, [front])
    assert torch.equal(count, torch.ones(H, W, dtype=torch.float64)) and torch.equal(avg, me.light)
    near = WarpSource(other.camera, other.light + 1.0, other.depth * 0.98, other.alpha)  # within the tolerance
    assert torch.equal(warp_average(me, [near])[1], torch.full((H, W), 2.0, dtype=torch.float64))
    bare = WarpSource(me.camera, me.light, me.depth, torch.zeros(H, W, dtype=torch.float64))
    avg, count = warp_average(bare, [other])
    assert torch.equal(count, torch.ones(H, W, dtype=torch.float64)) and torch.equal(avg, me.light)
    empty = WarpSource(other.camera, other.light + 1.0, other.depth, torch.zeros(H, W, dtype=torch.float64))
    assert torch.equal(warp_average(me, [empty])[1], torch.ones(H, W, dtype=torch.float64))


def test_neighbours_are_the_nearest_cameras_facing_the_same_way():
    cams = [camera_at(0.0), camera_at(3.0), camera_at(0.5), camera_at(-1.0), camera_at(0.1, yaw_deg=90.0),
            camera_at(1.2, yaw_deg=30.0)]
    assert neighbours(cams, 0, 3) == [2, 3, 5]  # 0.5, 1.0, then 1.2 (turned 30°: inside 60°)
    assert 4 not in neighbours(cams, 0, 10)  # turned 90°: sees other surfaces
    assert neighbours(cams, 0, 0) == []
    assert torch.allclose(cams[1].center, torch.tensor([3.0, 0.0, 0.0], dtype=torch.float64))
