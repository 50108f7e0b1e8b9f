"""Tile culling in the binning (rgs::TileReach): given conics and opacities, a Gaussian pairs only with the tiles of
its rectangle where it can reach alpha >= 1/255. Checked on the CPU kernels (the GPU runs the same shared test;
tests/test_cuda_tile_cull.py checks that its tile lists equal the CPU's): the kept pairs are an ordered subset of
the rectangle's, dropped pairs really composite nothing, renders and gradients are bit-identical with and without
the culling, and the pure-torch reference keeps the same pairs."""
import math

import pytest
import torch

from retinexgs.render import rasterize_gaussians
from retinexgs.render._backend import kernels
from retinexgs.render.functions import ProjectGaussians, RasterizeGaussians, bin_gaussians
from retinexgs.render.reference import (count_tile_pairs_reference, log_rn, rasterize_gaussians_reference,
                                        tile_pair_mask, tile_rects)
from scenes import make_camera, random_gaussians

TILE = 16


def anisotropic_scene(n=400, C=3, dtype=torch.float64, seed=3, width=200, height=150):
    """Rotated, elongated Gaussians (axes 10:1) over the image: their rectangles hold many tiles that the
    ellipses miss."""
    means, quats, scales, opacities, colors = random_gaussians(n, C, seed=seed, dtype=dtype, spread=1.3,
                                                               scale_range=(-4.0, -1.7))
    scales[:, 1] = scales[:, 0] * 0.1
    return (means, quats, scales, opacities, colors), make_camera(width=width, height=height)


def synthetic_inputs(n=3000, width=173, height=131, seed=0, dtype=torch.float32):
    """Binning inputs without a projection: random means (some off-image), conics from random rotated
    covariances (aspect up to 1:60), opacities down to just above 1/255, radii generous (the full-ellipse box plus
    up to 40 pixels), so the rectangles hold many tiles and many borderline ones."""
    g = torch.Generator().manual_seed(seed)
    mx = torch.rand(n, generator=g, dtype=torch.float64) * (width + 60) - 30
    my = torch.rand(n, generator=g, dtype=torch.float64) * (height + 60) - 30
    theta = torch.rand(n, generator=g, dtype=torch.float64) * math.pi
    s1 = torch.exp(torch.rand(n, generator=g, dtype=torch.float64) * 4.0 - 0.5)
    s2 = s1 / torch.exp(torch.rand(n, generator=g, dtype=torch.float64) * math.log(60.0))
    c, s = torch.cos(theta), torch.sin(theta)
    a = c * c * s1 * s1 + s * s * s2 * s2 + 0.3
    b = c * s * (s1 * s1 - s2 * s2)
    d = s * s * s1 * s1 + c * c * s2 * s2 + 0.3
    det = a * d - b * b
    conics = torch.stack([d / det, -b / det, a / det], -1)
    opacities = torch.where(torch.rand(n, generator=g, dtype=torch.float64) < 0.3,
                            1 / 255 + torch.rand(n, generator=g, dtype=torch.float64) * 0.02,
                            torch.rand(n, generator=g, dtype=torch.float64) * 0.99 + 0.01)
    k = torch.sqrt(2 * torch.log((255 * opacities).clamp_min(1.0)))
    extra = torch.rand(n, 2, generator=g, dtype=torch.float64) * 40
    radii = torch.stack([torch.ceil(k * a.sqrt()), torch.ceil(k * d.sqrt())], -1) + torch.floor(extra)
    radii = torch.where((255 * opacities > 1).unsqueeze(-1), radii, torch.zeros_like(radii)).to(torch.int32)
    depths = torch.rand(n, generator=g, dtype=torch.float64) + 0.5
    return (torch.stack([mx, my], -1).to(dtype), radii, depths.to(dtype), conics.to(dtype), opacities.to(dtype))


def project(args, cam):
    means, quats, scales, opacities, _ = args
    with torch.no_grad():
        means2d, depths, conics, radii, _ = ProjectGaussians.apply(means, quats, scales, opacities, cam)
    return means2d, depths, conics, radii, opacities


def tile_lists(ids, ranges):
    """{tile: Gaussian ids in order}."""
    return {t: ids[int(ranges[t, 0]):int(ranges[t, 1])].tolist() for t in range(ranges.shape[0])}


def max_alpha_on_tile(means2d, conics, opacities, g, t, tiles_x, width, height, dtype):
    """The largest o exp(-σ) over the pixel centres of tile t, in ``dtype`` with the kernels' formula, and in
    float64."""
    tx, ty = t % tiles_x, t // tiles_x
    xs = torch.arange(tx * TILE, min((tx + 1) * TILE, width), dtype=torch.float64) + 0.5
    ys = torch.arange(ty * TILE, min((ty + 1) * TILE, height), dtype=torch.float64) + 0.5
    py, px = torch.meshgrid(ys, xs, indexing="ij")
    out = []
    for dt in (dtype, torch.float64):
        m, cn, o = means2d[g].to(dt), conics[g].to(dt), opacities[g].to(dt)
        dx, dy = px.to(dt) - m[0], py.to(dt) - m[1]
        sigma = 0.5 * (cn[0] * dx * dx + cn[2] * dy * dy) + cn[1] * dx * dy
        out.append(float((o * torch.exp(-sigma)).max()))
    return out


def check_subset_and_dropped(means2d, radii, depths, conics, opacities, width, height, dtype):
    """Culled lists are ordered subsets of the full ones, and every dropped pair composites nothing. Returns
    (kept pairs, full pairs, dropped pairs)."""
    full_ids, full_ranges = bin_gaussians(means2d, radii, depths, width, height)
    ids, ranges = bin_gaussians(means2d, radii, depths, width, height, conics, opacities)
    full, kept = tile_lists(full_ids, full_ranges), tile_lists(ids, ranges)
    tiles_x = (width + TILE - 1) // TILE
    dropped = 0
    for t, lst in full.items():
        keep = set(kept[t])
        assert [g for g in lst if g in keep] == kept[t], t  # same order, a subset
        for g in lst:
            if g in keep:
                continue
            dropped += 1
            a_dt, a_64 = max_alpha_on_tile(means2d, conics, opacities, g, t, tiles_x, width, height, dtype)
            assert a_dt < 1 / 255 and a_64 < 1 / 255, (t, g, a_dt, a_64)
    return ids.numel(), full_ids.numel(), dropped


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_culled_pairs_are_an_ordered_subset_and_composite_nothing(dtype):
    args, cam = anisotropic_scene(dtype=dtype)
    means2d, depths, conics, radii, opacities = project(args, cam)
    kept, full, dropped = check_subset_and_dropped(means2d, radii, depths, conics, opacities, cam.width,
                                                   cam.height, dtype)
    assert kept < 0.85 * full, (kept, full)  # the culling does something here
    assert dropped == full - kept > 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_culling_is_conservative_on_borderline_gaussians(dtype):
    """Random conics up to 1:60, opacities just above 1/255 and oversized rectangles: many tiles near the
    1/255 level line. Every dropped tile stays below 1/255 at each pixel centre; with these rectangles most
    pairs go."""
    means2d, radii, depths, conics, opacities = synthetic_inputs(dtype=dtype)
    kept, full, dropped = check_subset_and_dropped(means2d, radii, depths, conics, opacities, 173, 131, dtype)
    assert kept < 0.5 * full and dropped > 1000, (kept, full)
    # And compositing the culled lists gives the same image as compositing the full ones.
    colors = torch.rand(means2d.shape[0], 3, generator=torch.Generator().manual_seed(5), dtype=dtype)
    images = []
    for extra in ((), (conics, opacities)):
        ids, ranges = bin_gaussians(means2d, radii, depths, 173, 131, *extra)
        images.append(kernels().rasterize_forward(means2d, conics, colors, opacities, ids, ranges, 173, 131))
    for a, b in zip(images[0][:2], images[1][:2]):  # image, transmittance (last_ids index the pair lists)
        assert torch.equal(a, b)


def render(args, cam, cull):
    """Image, alpha, depth and the gradients of a fixed loss, with and without culling (rasterize_gaussians
    with the binning's conics and opacities left out or not)."""
    a = tuple(x.detach().clone().requires_grad_() for x in args)
    means, quats, scales, opacities, colors = a
    means2d, depths, conics, radii, _ = ProjectGaussians.apply(means, quats, scales, opacities, cam)
    ids, ranges = bin_gaussians(means2d, radii, depths, cam.width, cam.height, *((conics, opacities) if cull else ()))
    channels = torch.cat([colors, depths.unsqueeze(-1)], -1)
    image, alpha = RasterizeGaussians.apply(means2d, conics, channels, opacities, ids, ranges, cam.width,
                                            cam.height)
    g = torch.Generator().manual_seed(1)
    w = torch.randn(image.shape, generator=g, dtype=torch.float64).to(image.dtype)
    loss = (image * w).sum() + alpha.sum()
    return (image, alpha) + torch.autograd.grad(loss, a), int(ids.numel())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_renders_and_gradients_identical_with_and_without_culling(dtype):
    args, cam = anisotropic_scene(C=4, dtype=dtype)
    culled, m_culled = render(args, cam, True)
    full, m_full = render(args, cam, False)
    assert m_culled < 0.85 * m_full
    for a, b in zip(culled, full):
        assert torch.equal(a, b)
    # rasterize_gaussians culls: it reports the culled count and renders the same image.
    out = rasterize_gaussians(*args, cam, render_depth=True)
    assert out.num_pairs == m_culled
    assert torch.equal(out.image, culled[0][..., :4]) and torch.equal(out.depth, culled[0][..., 4:])


def test_reference_keeps_the_same_pairs():
    args, cam = anisotropic_scene(n=150)
    out = rasterize_gaussians(*args, cam)
    ref = rasterize_gaussians_reference(*args, cam)
    assert out.num_pairs == ref.num_pairs
    torch.testing.assert_close(out.image, ref.image, rtol=1e-9, atol=1e-10)
    means2d, depths, conics, radii, opacities = project(args, cam)
    mask = tile_pair_mask(means2d, conics, opacities, radii, cam.width, cam.height)
    ids, ranges = bin_gaussians(means2d, radii, depths, cam.width, cam.height, conics, opacities)
    assert int(mask.sum()) == ids.numel() < sum(len(v) for v in tile_lists(*bin_gaussians(
        means2d, radii, depths, cam.width, cam.height)).values())
    for t in range(ranges.shape[0]):
        assert sorted(ids[int(ranges[t, 0]):int(ranges[t, 1])].tolist()) == \
            torch.nonzero(mask[:, t]).flatten().tolist()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_reference_mask_equals_kernel_on_borderline_inputs(dtype):
    """The reference repeats rgs::TileReach's float64 operations, so it keeps exactly the kernel's pairs even
    where they sit next to the cut."""
    means2d, radii, depths, conics, opacities = synthetic_inputs(n=1500, seed=2, dtype=dtype)
    mask = tile_pair_mask(means2d, conics, opacities, radii, 173, 131)
    ids, ranges = bin_gaussians(means2d, radii, depths, 173, 131, conics, opacities)
    assert count_tile_pairs_reference(means2d, conics, opacities, radii, 173, 131) == int(mask.sum()) == ids.numel()
    kernel_mask = torch.zeros_like(mask)
    tiles = torch.repeat_interleave(torch.arange(ranges.shape[0]), (ranges[:, 1] - ranges[:, 0]).long())
    kernel_mask[ids.long(), tiles] = True
    assert torch.equal(kernel_mask, mask)


def test_log_rn_is_accurate():
    """rgs::log_rn (and its torch twin) stays within 1e-14 of ln: far inside the cut's 2e-3 margin."""
    x = torch.cat([torch.linspace(1.0 + 1e-12, 300.0, 20001, dtype=torch.float64),
                   torch.tensor([1.5, 2.0, 255 * 0.99, 1e10, 1e300], dtype=torch.float64)])
    ref = torch.tensor([math.log(v) for v in x.tolist()], dtype=torch.float64)
    assert float((log_rn(x) - ref).abs().max()) < 1e-14


def test_degenerate_conics_keep_every_tile():
    """A NaN, indefinite or negative conic, or an opacity <= 1/255, keeps the whole rectangle."""
    means2d = torch.tensor([[50.0, 40.0], [50.0, 40.0], [50.0, 40.0], [50.0, 40.0], [50.0, 40.0]],
                           dtype=torch.float64)
    radii = torch.full((5, 2), 40, dtype=torch.int32)
    depths = torch.ones(5, dtype=torch.float64)
    conics = torch.tensor([[math.nan, 0.0, 1.0], [1.0, 2.0, 1.0], [-1.0, 0.0, 1.0], [1.0, 0.0, 1.0],
                           [1.0, 0.0, 1.0]], dtype=torch.float64)
    opacities = torch.tensor([0.9, 0.9, 0.9, 1 / 255, 0.9], dtype=torch.float64)
    rect = tile_rects(means2d, radii, 120, 90)
    per_rect = int(((rect[0, 2] - rect[0, 0]) * (rect[0, 3] - rect[0, 1])))
    ids, ranges = bin_gaussians(means2d, radii, depths, 120, 90, conics, opacities)
    counts = torch.bincount(ids.long(), minlength=5)
    assert counts[:4].tolist() == [per_rect] * 4
    assert 0 < int(counts[4]) < per_rect  # the well-formed one is culled: a unit conic reaches ~3.3 pixels


def test_bin_gaussians_needs_conics_and_opacities_together():
    args, cam = anisotropic_scene(n=20)
    means2d, depths, conics, radii, opacities = project(args, cam)
    with pytest.raises(ValueError, match="both conics and opacities"):
        bin_gaussians(means2d, radii, depths, cam.width, cam.height, conics, None)
    with pytest.raises(ValueError, match="both conics and opacities"):
        kernels().bin_gaussians(means2d, radii, depths, cam.width, cam.height, conics)
    with pytest.raises(ValueError, match="conics"):
        kernels().bin_gaussians(means2d, radii, depths, cam.width, cam.height, conics[:, :2], opacities)
    with pytest.raises(ValueError, match="opacities"):
        kernels().bin_gaussians(means2d, radii, depths, cam.width, cam.height, conics, opacities[:-1])
    with pytest.raises(TypeError, match="opacities"):
        kernels().bin_gaussians(means2d, radii, depths, cam.width, cam.height, conics, opacities.float())
