"""Tile culling on the GPU (run on a GPU machine; skipped cleanly where there is none): the CUDA binning keeps
exactly the CPU's tiles (rgs::TileReach is written in unfused double operations, so nvcc's FMA contraction cannot
move a decision), and culling leaves the CUDA render unchanged."""
import pytest
import torch

from retinexgs.render import has_cuda, rasterize_gaussians
from retinexgs.render._backend import kernels
from retinexgs.render.functions import ProjectGaussians, RasterizeGaussians, bin_gaussians
from scenes import make_camera, random_gaussians
from test_raster_tile_cull import anisotropic_scene, synthetic_inputs

pytestmark = pytest.mark.skipif(not (torch.cuda.is_available() and has_cuda()),
                                reason="needs a CUDA GPU and retinexgs built with its CUDA kernels")


def projected(n, width, height, dtype, seed):
    """Binning inputs of a random scene of elongated Gaussians, projected on the CPU (so both devices bin the
    same values)."""
    means, quats, scales, opacities, _ = random_gaussians(n, 1, seed=seed, dtype=dtype, spread=1.3,
                                                          scale_range=(-4.5, -1.5))
    scales[: n // 2, 1] = scales[: n // 2, 0] * 0.08
    cam = make_camera(width=width, height=height)
    means2d, depths, conics, radii, _ = kernels().project_forward(means, quats, scales, opacities, *cam.kernel_args)
    return means2d, radii, depths, conics, opacities


def bins_on(device, inputs, width, height, cull):
    means2d, radii, depths, conics, opacities = (t.to(device) for t in inputs)
    extra = (conics, opacities) if cull else ()
    ids, ranges = bin_gaussians(means2d, radii, depths, width, height, *extra)
    return ids.cpu(), ranges.cpu()


def empty_as_zero(ranges):
    """Tile ranges with every empty tile written [0, 0]: the CUDA binning leaves empty tiles at their zeroed
    [0, 0], the CPU writes [k, k]; both mean "no pairs" to the compositing."""
    return torch.where((ranges[:, :1] == ranges[:, 1:]), torch.zeros_like(ranges), ranges)


@pytest.mark.parametrize("size", [(64, 48), (640, 360), (1920, 1080)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("cull", [False, True])
def test_cuda_binning_equals_cpu(size, dtype, cull):
    width, height = size
    inputs = projected(20000 if width > 100 else 2000, width, height, dtype, seed=width)
    cpu_ids, cpu_ranges = bins_on("cpu", inputs, width, height, cull)
    assert cpu_ids.numel() > 0
    if cull:  # the culling must drop something, or this would not test it
        assert cpu_ids.numel() < 0.9 * bins_on("cpu", inputs, width, height, False)[0].numel()
    gpu_ids, gpu_ranges = bins_on("cuda", inputs, width, height, cull)
    assert torch.equal(gpu_ids, cpu_ids)
    assert torch.equal(empty_as_zero(gpu_ranges), empty_as_zero(cpu_ranges))


@pytest.mark.parametrize("size", [(173, 131), (640, 360), (1920, 1080)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_binning_equals_cpu_on_borderline_inputs(size, dtype):
    """Oversized rectangles, conics up to 1:60, opacities just above 1/255: many tiles close to the cut."""
    width, height = size
    for seed in range(3):
        inputs = synthetic_inputs(n=20000, width=width, height=height, seed=seed, dtype=dtype)
        cpu_ids, cpu_ranges = bins_on("cpu", inputs, width, height, True)
        gpu_ids, gpu_ranges = bins_on("cuda", inputs, width, height, True)
        assert torch.equal(gpu_ids, cpu_ids), seed
        assert torch.equal(empty_as_zero(gpu_ranges), empty_as_zero(cpu_ranges)), seed


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_render_unchanged_by_culling(dtype):
    """Same image (bit for bit: each pixel composites the same Gaussians in the same order) and the same
    gradients up to the order of the backward's atomic additions; rasterize_gaussians culls on the GPU too."""
    args, cam = anisotropic_scene(C=4, dtype=dtype)
    res = {}
    for cull in (False, True):
        a = tuple(x.detach().to("cuda").requires_grad_() for x in args)
        means, quats, scales, opacities, colors = a
        means2d, depths, conics, radii, _ = ProjectGaussians.apply(means, quats, scales, opacities, cam)
        extra = (conics, opacities) if cull else ()
        ids, ranges = bin_gaussians(means2d, radii, depths, cam.width, cam.height, *extra)
        image, alpha = RasterizeGaussians.apply(means2d, conics, colors, opacities, ids, ranges, cam.width,
                                                cam.height)
        w = torch.randn(image.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
        loss = (image * w.to(image)).sum() + alpha.sum()
        res[cull] = (image, alpha) + torch.autograd.grad(loss, a) + (ids.numel(),)
    assert res[True][-1] < 0.85 * res[False][-1]
    assert torch.equal(res[True][0], res[False][0]) and torch.equal(res[True][1], res[False][1])
    tol = 1e-4 if dtype == torch.float32 else 1e-10
    for a, b in zip(res[True][2:-1], res[False][2:-1]):
        torch.testing.assert_close(a, b, rtol=tol, atol=tol * float(b.abs().max()))
    out = rasterize_gaussians(*(x.to("cuda") for x in args), cam)
    assert out.num_pairs == res[True][-1] == rasterize_gaussians(*args, cam).num_pairs
    assert torch.equal(out.image, res[True][0])


@pytest.mark.parametrize("which", ["means", "quats", "scales", "opacities", "colors"])
def test_cuda_non_finite_input_is_refused_after_binning(which):
    """The public render reads its finiteness verdict after binning (one host sync per render): a NaN still
    raises a ValueError naming the argument, and a clean render after it works."""
    means, quats, scales, opacities, colors = (t.cuda() for t in random_gaussians(500, 3, seed=1))
    cam = make_camera(width=96, height=64)
    args = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors)
    bad = dict(args)
    bad[which] = args[which].clone()
    bad[which].view(-1)[7] = float("nan")
    with pytest.raises(ValueError, match=rf"{which} contains non-finite values"):
        rasterize_gaussians(**bad, camera=cam)
    out = rasterize_gaussians(**args, camera=cam)
    assert torch.isfinite(out.image).all() and out.num_pairs > 0
