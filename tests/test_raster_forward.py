"""Forward of every CPU kernel against the pure-torch reference (float64), on scenes with edge cases."""
import math

import pytest
import torch

from retinexgs.render import Camera, rasterize_gaussians, spherical_harmonics
from retinexgs.render.functions import ProjectGaussians, RasterizeGaussians, bin_gaussians
from retinexgs.render.reference import (composite_reference, project_reference, rasterize_gaussians_reference,
                                        spherical_harmonics_reference, tile_rects)
from scenes import make_camera, random_gaussians


def edge_case_scene(C=3, dtype=torch.float64, seed=1):
    """A random scene plus Gaussians that exercise every culling and clamping rule."""
    means, quats, scales, opac, colors = random_gaussians(60, C, seed=seed, dtype=dtype)
    cam = make_camera(width=45, height=37)
    eye = cam.center.to(dtype)
    fwd = cam.viewmat[2, :3].to(dtype)  # camera z axis in world space
    g = torch.Generator().manual_seed(seed + 100)
    extra = [
        (eye + 0.05 * fwd, 0.01, 0.9),          # just past the near plane, huge on screen
        (eye + 0.005 * fwd, 0.01, 0.9),         # in front of the near plane: culled
        (eye - 1.0 * fwd, 0.1, 0.9),            # behind the camera: culled
        (eye + 4.0 * fwd + torch.tensor([30.0, 0, 0], dtype=dtype), 0.1, 0.9),  # far off-screen
        (eye + 4.0 * fwd + torch.tensor([2.2, 0, 0], dtype=dtype), 0.3, 0.9),   # past the guard band, visible edge
        (torch.zeros(3, dtype=dtype), 1e-4, 0.95),  # tiny
        (torch.zeros(3, dtype=dtype), 5.0, 0.2),    # huge
        (torch.tensor([0.3, 0.1, 0.0], dtype=dtype), 0.1, 0.003),   # opacity below 1/255: culled
        (torch.tensor([-0.3, 0.1, 0.0], dtype=dtype), 0.1, 0.9999),  # opacity ~1: alpha clamps at 0.99
    ]
    # Heavy overlap: a stack of opaque Gaussians on one spot (saturates T).
    extra += [(torch.tensor([0.1, -0.1, 0.05 * i], dtype=dtype), 0.15, 0.95) for i in range(12)]
    for mean, s, o in extra:
        means = torch.cat([means, mean.reshape(1, 3)])
        scales = torch.cat([scales, torch.full((1, 3), s, dtype=dtype) * (1 + 0.3 * torch.rand(1, 3, generator=g,
                                                                                               dtype=dtype))])
        quats = torch.cat([quats, torch.randn(1, 4, generator=g, dtype=dtype)])
        opac = torch.cat([opac, torch.tensor([o], dtype=dtype)])
        colors = torch.cat([colors, torch.rand(1, C, generator=g, dtype=dtype)])
    return (means, quats, scales, opac, colors), cam


@pytest.mark.parametrize("C", [1, 3, 6, 33, 64])
def test_render_matches_reference(C):
    args, cam = edge_case_scene(C)
    out = rasterize_gaussians(*args, cam, render_depth=True)
    ref = rasterize_gaussians_reference(*args, cam, render_depth=True)
    assert torch.equal(out.radii, ref.radii)
    assert out.num_pairs == ref.num_pairs > 0
    for name in ("image", "alpha", "depth", "means2d"):
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), rtol=1e-9, atol=1e-10)
    # The scene really exercises the rules it is meant to.
    assert (out.radii == 0).any() and (out.radii > 0).any()
    assert float(out.alpha.max()) > 1 - 2e-4  # a saturated pixel exists


def test_culling_rules():
    (means, quats, scales, opac, colors), cam = edge_case_scene()
    _, _, _, radii, _ = ProjectGaussians.apply(means, quats, scales, opac, cam)
    n = 60
    culled = (radii == 0).all(-1)
    assert not culled[n] and culled[n + 1] and culled[n + 2] and culled[n + 3]
    assert culled[n + 7] and not culled[n + 8]


@pytest.mark.parametrize("size", [(45, 37), (16, 16), (70, 33), (1, 1), (17, 5)])
def test_projection_and_binning_match_reference(size):
    args, _ = edge_case_scene()
    means, quats, scales, opac, _ = args
    cam = make_camera(width=size[0], height=size[1])
    got = ProjectGaussians.apply(means, quats, scales, opac, cam)[:4]
    want = project_reference(means, quats, scales, opac, cam)
    assert torch.equal(got[3], want[3])
    for a, b in zip(got[:3], want[:3]):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)
    means2d, depths, _, radii = got
    gauss_ids, tile_ranges = bin_gaussians(means2d, radii, depths, *size)
    rect = tile_rects(means2d, radii, *size)
    tiles_x = math.ceil(size[0] / 16)
    for t in range(tile_ranges.shape[0]):
        tx, ty = t % tiles_x, t // tiles_x
        hit = (rect[:, 0] <= tx) & (tx < rect[:, 2]) & (rect[:, 1] <= ty) & (ty < rect[:, 3])
        idx = torch.nonzero(hit).flatten()
        idx = idx[torch.argsort(depths[idx], stable=True)]
        b, e = tile_ranges[t].tolist()
        assert gauss_ids[b:e].tolist() == idx.tolist(), f"tile {t}"
    assert tile_ranges[-1, 1] == gauss_ids.shape[0]


@pytest.mark.parametrize("C", [1, 6, 33])
def test_compositing_matches_reference(C):
    args, cam = edge_case_scene(C)
    means, quats, scales, opac, colors = args
    means2d, depths, conics, radii = project_reference(means, quats, scales, opac, cam)
    gauss_ids, tile_ranges = bin_gaussians(means2d, radii, depths, cam.width, cam.height)
    image, alpha = RasterizeGaussians.apply(means2d, conics, colors, opac, gauss_ids, tile_ranges, cam.width,
                                            cam.height)
    ref_image, ref_alpha = composite_reference(means2d, conics, colors, opac, depths, radii, cam.width, cam.height)
    torch.testing.assert_close(image, ref_image, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(alpha, ref_alpha, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("D", [1, 3])
def test_sh_matches_reference(degree, D):
    g = torch.Generator().manual_seed(degree)
    dirs = torch.randn(50, 3, generator=g, dtype=torch.float64) * 3
    coeffs = torch.randn(50, 16, D, generator=g, dtype=torch.float64)
    torch.testing.assert_close(spherical_harmonics(degree, dirs, coeffs),
                               spherical_harmonics_reference(degree, dirs, coeffs), rtol=1e-12, atol=1e-12)


def test_sh_basis_is_orthonormal():
    # Monte-Carlo check that the basis constants are right: ∫ B_i B_j dω = δ_ij over the sphere.
    g = torch.Generator().manual_seed(0)
    dirs = torch.randn(400_000, 3, generator=g, dtype=torch.float64)
    eye = torch.eye(16, dtype=torch.float64).unsqueeze(0).expand(dirs.shape[0], 16, 16)
    B = spherical_harmonics(3, dirs, eye.contiguous())  # [N, 16]: every basis value
    gram = 4 * math.pi * (B.T @ B) / dirs.shape[0]
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=0.02, rtol=0)


def test_float32_matches_float64():
    args, cam = edge_case_scene()
    out64 = rasterize_gaussians(*args, cam)
    out32 = rasterize_gaussians(*[a.float() for a in args], cam)
    torch.testing.assert_close(out32.image.double(), out64.image, atol=2e-4, rtol=1e-3)


def test_background_and_blank_view():
    args, cam = edge_case_scene()
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    out = rasterize_gaussians(*args, cam, background=bg)
    plain = rasterize_gaussians(*args, cam)
    torch.testing.assert_close(out.image, plain.image + (1 - plain.alpha) * bg)
    # Every Gaussian behind the camera: an empty image, not an error.
    means = args[0].clone()
    means[:, 2] = -100.0
    away = Camera(torch.eye(4, dtype=torch.float64), 40.0, 40.0, 20.0, 15.0, 40, 30)
    blank = rasterize_gaussians(means, *args[1:], away, background=bg)
    assert blank.num_pairs == 0 and float(blank.alpha.abs().max()) == 0.0
    torch.testing.assert_close(blank.image, bg.expand(30, 40, 3))


def test_depth_order_is_float32_then_index_in_every_dtype():
    """Gaussians whose depths are equal to float32 precision composite in index order, in float64 too (the GPU
    sorts float32 depth keys; the CPU kernels and the reference use the same order)."""
    cam = Camera(torch.eye(4, dtype=torch.float64), 20.0, 20.0, 8.0, 6.0, 16, 12)
    means = torch.tensor([[0.0, 0.0, 2.0 + 1e-12], [0.0, 0.0, 2.0]], dtype=torch.float64)  # 2nd is nearer
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=torch.float64)
    scales = torch.full((2, 3), 0.3, dtype=torch.float64)
    opac = torch.tensor([0.9, 0.9], dtype=torch.float64)
    colors = torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
    out = rasterize_gaussians(means, quats, scales, opac, colors, cam)
    ref = rasterize_gaussians_reference(means, quats, scales, opac, colors, cam)
    torch.testing.assert_close(out.image, ref.image, rtol=1e-12, atol=1e-12)
    centre = out.image[6, 8]
    assert float(centre[0]) > float(centre[1])  # index 0 in front: the 1e-12 depth difference is a tie
