"""CUDA kernels against the CPU kernels (run on a GPU machine; skipped cleanly where there is none)."""
import pytest
import torch

from retinexgs.render import has_cuda, rasterize_gaussians, spherical_harmonics
from scenes import make_camera, random_gaussians
from test_raster_forward import edge_case_scene

pytestmark = pytest.mark.skipif(not (torch.cuda.is_available() and has_cuda()),
                                reason="needs a CUDA GPU and retinexgs built with its CUDA kernels")


def rel_err(a, b):
    return float((a.double() - b.double()).norm() / b.double().norm().clamp_min(1e-30))


def run(args, cam, device, dtype, seed=0):
    args = tuple(a.detach().to(device=device, dtype=dtype).requires_grad_() for a in args)
    depth = args[4].shape[1] < 64  # 64 channels is the CUDA limit, depth included
    out = rasterize_gaussians(*args, cam, render_depth=depth)
    g = torch.Generator().manual_seed(seed)
    wi = torch.randn(out.image.shape, generator=g, dtype=torch.float64).to(device=device, dtype=dtype)
    wa = torch.randn(out.alpha.shape, generator=g, dtype=torch.float64).to(device=device, dtype=dtype)
    loss = (out.image * wi).sum() + (out.alpha * wa).sum()
    if depth:
        loss = loss + 0.1 * out.depth.sum()
    grads = torch.autograd.grad(loss, args)
    return (out.image, out.alpha, out.depth if depth else out.alpha, out.radii, out.num_pairs) + grads


SCENES = {
    "edge_cases": lambda C: edge_case_scene(C),
    "dense": lambda C: (random_gaussians(4000, C, seed=9, dtype=torch.float64),
                        make_camera(width=173, height=91)),
    # Gaussians of a pixel or two: most warps they reach have one lane touched (the backward's path without sums).
    "small": lambda C: (random_gaussians(3000, C, seed=11, dtype=torch.float64, scale_range=(-6.0, -4.5)),
                        make_camera(width=173, height=91)),
}


@pytest.mark.parametrize("C", [1, 2, 3, 6, 7, 33, 64])  # + depth: CMAX 2, 3, 4, 8, 8 (full), 64, 64
@pytest.mark.parametrize("scene", sorted(SCENES))
def test_cuda_matches_cpu_float32(C, scene):
    args, cam = SCENES[scene](C)
    cpu = run(args, cam, "cpu", torch.float32)
    gpu = run(args, cam, "cuda", torch.float32)
    assert gpu[4] == cpu[4], "different number of tile pairs"
    assert torch.equal(gpu[3].cpu(), cpu[3])
    for name, a, b in zip(("image", "alpha", "depth"), gpu[:3], cpu[:3]):
        assert rel_err(a.cpu(), b) < 1e-4, name
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors"), gpu[5:], cpu[5:]):
        assert torch.isfinite(a).all(), name
        assert rel_err(a.cpu(), b) < 1e-3, name


def test_cuda_matches_cpu_float64():
    args, cam = edge_case_scene(6)
    cpu = run(args, cam, "cpu", torch.float64)
    gpu = run(args, cam, "cuda", torch.float64)
    for a, b in zip(gpu[:3] + gpu[5:], cpu[:3] + cpu[5:]):
        assert rel_err(a.cpu(), b) < 1e-9


def run_packed(args, cam, device, dtype, bg, seed=0):
    """The training's render: channels + depth + alpha in one tensor, a background on the channels."""
    args = tuple(a.detach().to(device=device, dtype=dtype).requires_grad_() for a in args)
    out = rasterize_gaussians(*args, cam, render_depth=True, background=bg.to(device=device, dtype=dtype),
                              packed=True)
    g = torch.Generator().manual_seed(seed)
    w = torch.randn(out.packed.shape, generator=g, dtype=torch.float64).to(device=device, dtype=dtype)
    return (out.packed,) + torch.autograd.grad((out.packed * w).sum(), args)


@pytest.mark.parametrize("C", [3, 6])  # + depth + alpha: CMAX 8 with 5 and 8 values a pixel
@pytest.mark.parametrize("scene", sorted(SCENES))
def test_cuda_packed_render_with_background_matches_cpu(C, scene):
    args, cam = SCENES[scene](C)
    bg = torch.linspace(0.2, 0.7, C, dtype=torch.float64)
    for dtype, tol in ((torch.float32, (1e-4, 1e-3)), (torch.float64, (1e-9, 1e-9))):
        cpu = run_packed(args, cam, "cpu", dtype, bg)
        gpu = run_packed(args, cam, "cuda", dtype, bg)
        assert rel_err(gpu[0].cpu(), cpu[0]) < tol[0], "packed image"
        for name, a, b in zip(("means", "quats", "scales", "opacities", "colors"), gpu[1:], cpu[1:]):
            assert torch.isfinite(a).all(), name
            assert rel_err(a.cpu(), b) < tol[1], (name, dtype)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_cuda_sh_matches_cpu(degree):
    g = torch.Generator().manual_seed(degree)
    dirs = torch.randn(1000, 3, generator=g)
    coeffs = torch.randn(1000, 16, 3, generator=g)
    v = torch.randn(1000, 3, generator=g)
    res = {}
    for dev in ("cpu", "cuda"):
        d, c = dirs.to(dev).requires_grad_(), coeffs.to(dev).requires_grad_()
        out = spherical_harmonics(degree, d, c)
        res[dev] = (out,) + torch.autograd.grad((out * v.to(dev)).sum(), (d, c))
    for a, b in zip(res["cuda"], res["cpu"]):
        assert rel_err(a.cpu(), b) < 1e-5


@pytest.mark.parametrize("n,K,D,degree,dtype", [(1000, 16, 3, 3, torch.float32), (1000, 16, 3, 2, torch.float64),
                                                 (333, 4, 3, 1, torch.float32), (129, 9, 1, 2, torch.float32),
                                                 (257, 16, 7, 3, torch.float64), (70, 16, 40, 3, torch.float32),
                                                 (1, 1, 3, 0, torch.float32)])
def test_cuda_sh_tiled_and_direct_paths_match_cpu(n, K, D, degree, dtype):
    # Partial last blocks, K < 16, odd D, and D = 40 (a row too wide for shared memory: the direct kernels).
    g = torch.Generator().manual_seed(n + K + D)
    dirs = torch.randn(n, 3, generator=g, dtype=dtype)
    coeffs = torch.randn(n, K, D, generator=g, dtype=dtype)
    v = torch.randn(n, D, generator=g, dtype=dtype)
    res = {}
    for dev in ("cpu", "cuda"):
        d, c = dirs.to(dev).requires_grad_(), coeffs.to(dev).requires_grad_()
        out = spherical_harmonics(degree, d, c)
        res[dev] = (out,) + torch.autograd.grad((out * v.to(dev)).sum(), (d, c))
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    for a, b in zip(res["cuda"], res["cpu"]):
        assert rel_err(a.cpu(), b) < tol
    if K > sh_bases(degree):  # bases above the degree get exactly zero gradient
        assert res["cuda"][2][:, sh_bases(degree):].abs().max().item() == 0.0


def sh_bases(degree):
    return (degree + 1) ** 2


def test_cuda_memory_does_not_grow():
    args, cam = SCENES["dense"](7)
    args = tuple(a.float().cuda().requires_grad_() for a in args)
    sizes = []
    for _ in range(6):
        out = rasterize_gaussians(*args, cam, render_depth=True)
        out.image.sum().backward()
        del out
        torch.cuda.synchronize()
        sizes.append(torch.cuda.memory_allocated())
    assert len(set(sizes[1:])) == 1, sizes


def test_cuda_rejects_too_many_channels():
    args, cam = SCENES["dense"](65)
    args = tuple(a.float().cuda() for a in args)
    with pytest.raises(ValueError, match="at most 64"):
        rasterize_gaussians(*args, cam)
    with pytest.raises(ValueError, match="at most 64"):
        rasterize_gaussians(*args[:4], args[4][:, :64], cam, render_depth=True)


def test_the_evaluation_figures_on_the_gpu_are_the_cpus():
    """eval scores a test view on the render's device (float64 there): every figure within float64 rounding of
    the CPU's, on a view whose sides are not multiples of anything."""
    from retinexgs.evaluate import metrics as M

    g = torch.Generator().manual_seed(3)
    gt = torch.rand(83, 121, 3, generator=g, dtype=torch.float64)
    x = (gt * 0.7 + 0.1 * torch.rand(83, 121, 3, generator=g, dtype=torch.float64)).clamp(0, 1).float()
    light = torch.rand(83, 121, 3, generator=g, dtype=torch.float64) * 1.5
    for f in (M.psnr, M.ssim_metric, M.colour_error, M.black_lift):
        assert f(x.cuda(), gt.cuda()) == pytest.approx(f(x, gt), rel=1e-9, abs=1e-12), f.__name__
    assert torch.allclose(M.gt_mean_align(x.cuda(), gt.cuda()).cpu(), M.gt_mean_align(x, gt), atol=1e-12)
    gpu, cpu = M.colour_split(light.cuda(), gt.cuda(), 0.8), M.colour_split(light, gt, 0.8)
    assert gpu == pytest.approx(cpu, rel=1e-9, abs=1e-12)
