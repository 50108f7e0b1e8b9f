"""Analytic gradients of every kernel against central finite differences (float64), and against autograd
through the pure-torch reference on the edge-case scenes."""
import pytest
import torch
from torch.autograd import gradcheck

from retinexgs.render import rasterize_gaussians, spherical_harmonics
from retinexgs.render.functions import ProjectGaussians, RasterizeGaussians, bin_gaussians
from retinexgs.render.reference import rasterize_gaussians_reference
from scenes import make_camera, random_gaussians
from test_raster_forward import edge_case_scene

GRADCHECK = dict(eps=1e-6, atol=1e-5, rtol=1e-4)


def small_scene(n=14, C=3, seed=3):
    cam = make_camera(width=21, height=18, eye=(0.1, -0.1, -3.5))
    return random_gaussians(n, C, seed=seed, spread=0.8, scale_range=(-2.0, -1.2), opacity_range=(0.3, 0.9)), cam


def test_projection_gradcheck():
    (means, quats, scales, opac, _), cam = small_scene()
    means, quats, scales = (t.clone().requires_grad_() for t in (means, quats, scales))

    def f(m, q, s):
        means2d, depths, conics, _, _ = ProjectGaussians.apply(m, q, s, opac, cam)
        return means2d, depths, conics

    assert gradcheck(f, (means, quats, scales), **GRADCHECK)


def test_projection_gradcheck_guard_band():
    # Means outside the guard band: the clamped Jacobian path of the backward.
    (means, quats, scales, opac, _), cam = small_scene(n=6)
    means = means.clone()
    means[:, 0] += torch.tensor([2.0, -2.0, 1.8, -1.8, 0.0, 0.0], dtype=torch.float64)
    means[:, 1] += torch.tensor([0.0, 0.0, 0.0, 0.0, 1.9, -1.9], dtype=torch.float64)
    scales = scales * 8
    opac = torch.full_like(opac, 0.95)
    _, _, _, radii, _ = ProjectGaussians.apply(means, quats, scales, opac, cam)
    assert (radii > 0).all(), "the test needs visible Gaussians beyond the guard band"
    means, quats, scales = (t.clone().requires_grad_() for t in (means, quats, scales))

    def f(m, q, s):
        return ProjectGaussians.apply(m, q, s, opac, cam)[:3]

    assert gradcheck(f, (means, quats, scales), **GRADCHECK)


@pytest.mark.parametrize("C", [1, 4])
def test_rasterize_gradcheck(C):
    (means, quats, scales, opac, colors), cam = small_scene(C=C)
    means2d, depths, conics, radii, _ = ProjectGaussians.apply(means, quats, scales, opac, cam)
    gauss_ids, tile_ranges = bin_gaussians(means2d, radii, depths, cam.width, cam.height)
    inputs = tuple(t.detach().clone().requires_grad_() for t in (means2d, conics, colors, opac))

    def f(m2, cn, col, op):
        return RasterizeGaussians.apply(m2, cn, col, op, gauss_ids, tile_ranges, cam.width, cam.height)

    assert gradcheck(f, inputs, **GRADCHECK)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_gradcheck(degree):
    g = torch.Generator().manual_seed(degree)
    dirs = torch.randn(6, 3, generator=g, dtype=torch.float64).requires_grad_()
    coeffs = torch.randn(6, 16, 3, generator=g, dtype=torch.float64).requires_grad_()
    assert gradcheck(lambda d, c: spherical_harmonics(degree, d, c), (dirs, coeffs), **GRADCHECK)


def test_render_end_to_end_gradcheck():
    (means, quats, scales, opac, colors), cam = small_scene(n=10, C=2)
    bg = torch.tensor([0.3, 0.7], dtype=torch.float64, requires_grad=True)
    inputs = tuple(t.clone().requires_grad_() for t in (means, quats, scales, opac, colors)) + (bg,)

    def f(m, q, s, o, c, b):
        out = rasterize_gaussians(m, q, s, o, c, cam, background=b, render_depth=True)
        return out.image, out.alpha, out.depth

    assert gradcheck(f, inputs, **GRADCHECK)


def test_render_with_sh_colours_end_to_end_gradcheck():
    (means, quats, scales, opac, _), cam = small_scene(n=8)
    coeffs = torch.randn(8, 16, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(5)) * 0.3
    inputs = tuple(t.clone().requires_grad_() for t in (means, coeffs))
    centre = cam.center

    def f(m, c):
        colors = spherical_harmonics(3, m - centre, c) + 0.5
        return rasterize_gaussians(m, quats, scales, opac, colors, cam).image

    assert gradcheck(f, inputs, **GRADCHECK)


@pytest.mark.parametrize("C", [3, 33])
def test_gradients_match_reference_on_edge_cases(C):
    args, cam = edge_case_scene(C, seed=7)
    args = tuple(a.clone().requires_grad_() for a in args)
    g = torch.Generator().manual_seed(11)
    out = rasterize_gaussians(*args, cam, render_depth=True)
    ref = rasterize_gaussians_reference(*args, cam, render_depth=True)
    wi = torch.randn(out.image.shape, generator=g, dtype=torch.float64)
    wa = torch.randn(out.alpha.shape, generator=g, dtype=torch.float64)
    wd = torch.randn(out.depth.shape, generator=g, dtype=torch.float64)

    def loss(o):
        return (o.image * wi).sum() + (o.alpha * wa).sum() + (o.depth * wd).sum()

    got = torch.autograd.grad(loss(out), args)
    want = torch.autograd.grad(loss(ref), args)
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors"), got, want):
        assert torch.isfinite(a).all(), name
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-9, msg=name)
    # The screen-space gradient used by densification is exposed on means2d.
    assert out.means2d.grad is not None and out.means2d.grad.abs().sum() > 0


def test_rasterize_gradcheck_background_and_alpha_channel():
    # The compositing's output epilogue: a background on the first K channels and the alpha as channel C,
    # through the kernels' own gradient (dL/dT from both), against finite differences.
    (means, quats, scales, opac, colors), cam = small_scene(C=4)
    means2d, depths, conics, radii, _ = ProjectGaussians.apply(means, quats, scales, opac, cam)
    gauss_ids, tile_ranges = bin_gaussians(means2d, radii, depths, cam.width, cam.height)
    bg = torch.tensor([0.3, -0.2, 0.9], dtype=torch.float64)
    inputs = tuple(t.detach().clone().requires_grad_() for t in (means2d, conics, colors, opac, bg))
    for alpha_channel in (False, True):
        def f(m2, cn, col, op, b):
            image, alpha = RasterizeGaussians.apply(m2, cn, col, op, gauss_ids, tile_ranges, cam.width, cam.height,
                                                    b, alpha_channel)
            return image if alpha_channel else (image, alpha)

        assert gradcheck(f, inputs, **GRADCHECK), alpha_channel


@pytest.mark.parametrize("depth", [False, True])
def test_packed_render_is_the_concatenation(depth):
    # rasterize_gaussians(packed=True): [image (background closed), depth, alpha] written by the compositing equal
    # the separate outputs, and a loss on the packed tensor has the gradients of the same loss on the three.
    (means, quats, scales, opac, colors), cam = small_scene(n=12, C=6)
    bg = torch.linspace(0.1, 0.6, 6, dtype=torch.float64)
    args = tuple(t.clone().requires_grad_() for t in (means, quats, scales, opac, colors))
    plain = rasterize_gaussians(*args, cam, background=bg, render_depth=depth)
    packed = rasterize_gaussians(*args, cam, background=bg, render_depth=depth, packed=True)
    want = torch.cat([plain.image] + ([plain.depth] if depth else []) + [plain.alpha], dim=-1)
    assert plain.packed is None and packed.packed.shape == want.shape
    torch.testing.assert_close(packed.packed, want, rtol=0, atol=1e-14)
    for name in ("image", "alpha") + (("depth",) if depth else ()):
        assert getattr(packed, name).data_ptr() >= packed.packed.data_ptr(), name  # views of the one tensor
        torch.testing.assert_close(getattr(packed, name), getattr(plain, name), rtol=0, atol=1e-14)
    w = torch.randn(want.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    got = torch.autograd.grad((packed.packed * w).sum(), args)
    ref = torch.autograd.grad((want * w).sum(), args)
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors"), got, ref):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12, msg=name)
    # The background moves the image where the Gaussians leave light through: out - bg·T is the same image.
    bare = rasterize_gaussians(*args, cam, render_depth=depth)
    torch.testing.assert_close(packed.image - (1 - packed.alpha) * bg, bare.image, rtol=0, atol=1e-13)


def test_background_longer_than_the_channels_is_refused():
    (means, quats, scales, opac, colors), cam = small_scene(C=2)
    means2d, depths, conics, radii, _ = ProjectGaussians.apply(means, quats, scales, opac, cam)
    gauss_ids, tile_ranges = bin_gaussians(means2d, radii, depths, cam.width, cam.height)
    with pytest.raises(ValueError, match="background must be"):
        RasterizeGaussians.apply(means2d, conics, colors, opac, gauss_ids, tile_ranges, cam.width, cam.height,
                                 torch.zeros(3, dtype=torch.float64))
