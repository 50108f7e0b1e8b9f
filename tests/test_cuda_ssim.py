"""The fused SSIM's CUDA kernels against its CPU kernels (run on a GPU machine; skipped cleanly where there is none)."""
import pytest
import torch

from retinexgs.evaluate.metrics import gaussian_window
from retinexgs.render import has_cuda
from retinexgs.render.ssim import fused_ssim_map

pytestmark = pytest.mark.skipif(not (torch.cuda.is_available() and has_cuda()),
                                reason="needs a CUDA GPU and retinexgs built with its CUDA kernels")
C1, C2 = 0.01 ** 2, 0.03 ** 2


def both(shape, dtype, taps, sigma, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g, dtype=torch.float64).to(dtype)
    y = torch.rand(shape, generator=g, dtype=torch.float64).to(dtype)
    gs = torch.randn(shape, generator=g, dtype=torch.float64).to(dtype)
    w = gaussian_window(taps, sigma, dtype=torch.float64)
    out = []
    for device in ("cpu", "cuda"):
        xd = x.to(device).requires_grad_()
        s = fused_ssim_map(xd, y.to(device), w, C1, C2)
        dx, = torch.autograd.grad((s * gs.to(device)).sum(), xd)
        out.append((s.cpu(), dx.cpu()))
    return out


# tiles cut by the image's edge, images smaller than the window, one plane and many
@pytest.mark.parametrize("shape", [(1, 1, 1, 1), (1, 3, 5, 7), (1, 9, 360, 640), (2, 3, 33, 17), (1, 2, 100, 3)])
@pytest.mark.parametrize("taps,sigma", [(11, 1.5), (15, 3.0), (1, 1.0)])
def test_cuda_matches_cpu_float64(shape, taps, sigma):
    (s_cpu, dx_cpu), (s_gpu, dx_gpu) = both(shape, torch.float64, taps, sigma)
    torch.testing.assert_close(s_gpu, s_cpu, rtol=0, atol=1e-12)
    # to rounding of the largest gradient (a 1-tap window's reach 1/c2 ~ 1e3): the sums run in another order
    torch.testing.assert_close(dx_gpu, dx_cpu, rtol=1e-10, atol=1e-13 * float(dx_cpu.abs().max()))


def test_cuda_matches_cpu_float32():
    (s_cpu, dx_cpu), (s_gpu, dx_gpu) = both((1, 9, 360, 640), torch.float32, 11, 1.5)
    torch.testing.assert_close(s_gpu, s_cpu, rtol=0, atol=1e-5)
    # float32 moments cancel (sxx = exx - mx²): agreement to ~1e-6 of the largest gradient, not per element
    torch.testing.assert_close(dx_gpu, dx_cpu, rtol=1e-4, atol=1e-5 * float(dx_cpu.abs().max()))


def test_more_planes_than_one_launch_takes():
    """The grid's z limit (65,535 planes a launch): the launcher runs the planes in chunks."""
    (s_cpu, dx_cpu), (s_gpu, dx_gpu) = both((70000, 2, 3), torch.float64, 3, 0.8)
    torch.testing.assert_close(s_gpu, s_cpu, rtol=0, atol=1e-12)
    torch.testing.assert_close(dx_gpu, dx_cpu, rtol=1e-10, atol=1e-12)


def test_captured_in_a_cuda_graph():
    """The training's loss graph captures the kernels: a replay on new inputs gives the eager values."""
    w = gaussian_window(11, 1.5, dtype=torch.float64)
    x = torch.rand(1, 9, 64, 80, device="cuda", requires_grad=True)
    y = torch.rand(1, 9, 64, 80, device="cuda")
    stream = torch.cuda.Stream()
    stream.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(stream):  # warm-up outside the capture
        fused_ssim_map(x, y, w, C1, C2).mean().backward()
    torch.cuda.current_stream().wait_stream(stream)
    x.grad = None
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        loss = fused_ssim_map(x, y, w, C1, C2).mean()
        dx, = torch.autograd.grad(loss, x)
    with torch.no_grad():
        x.copy_(torch.rand_like(x)), y.copy_(torch.rand_like(y))
    graph.replay()
    xe = x.detach().clone().requires_grad_()
    le = fused_ssim_map(xe, y, w, C1, C2).mean()
    de, = torch.autograd.grad(le, xe)
    torch.testing.assert_close(loss, le, rtol=0, atol=1e-6)
    torch.testing.assert_close(dx, de, rtol=1e-5, atol=1e-9)
