"""The illumination field's training kernels on the GPU against the CPU kernels and the torch field (run on a GPU
machine; skipped cleanly where there is none)."""
import copy

import pytest
import torch

from retinexgs.model.illumination import IlluminationField
from retinexgs.model.illumination_kernel import illumination_at, kernels_apply
from retinexgs.render import has_cuda
from test_fused_colors import SHAPES, make_field

pytestmark = pytest.mark.skipif(not (torch.cuda.is_available() and has_cuda()),
                                reason="needs a CUDA GPU and retinexgs built with its CUDA kernels")

CENTER = (0.3, -0.2, 2.5)


def _run(field, means, center, g_out, fn):
    params = list(field.parameters())
    m = means.detach().clone().requires_grad_(True)
    out = fn(field, m, center)
    grads = torch.autograd.grad(out, [m] + params, g_out, allow_unused=True)
    return [out.detach()] + [torch.zeros_like(p) if g is None else g for p, g in zip([m] + params, grads)]


def _torch(field, m, center):
    return field(m, IlluminationField.view_dirs(m, center))


@pytest.mark.parametrize("view_dependent", [True, False])
@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cuda_kernels_match_the_cpu_kernels(shape, view_dependent, dtype):
    """CUDA against the CPU kernels, same dtype; float32's encodings differ by their sin/cos (double-reduced on the
    GPU) and the products' summation order."""
    field = make_field(shape, view_dependent=view_dependent).to(dtype)
    g = torch.Generator().manual_seed(2)
    means = torch.randn(3000, 3, generator=g, dtype=torch.float64).to(dtype) * 1.5
    g_out = torch.randn(3000, 3, generator=g, dtype=torch.float64).to(dtype)
    center = torch.tensor(CENTER, dtype=dtype)
    cpu = _run(field, means, center, g_out, kernels_apply)
    gpu_field = copy.deepcopy(field).cuda()
    gpu = _run(gpu_field, means.cuda(), center.cuda(), g_out.cuda(), kernels_apply)
    tol = 1e-11 if dtype == torch.float64 else 2e-4
    for a, b in zip(cpu, gpu):
        scale = a.abs().max().clamp_min(1.0 if dtype == torch.float32 else 1e-6)
        assert (b.cpu() - a).abs().max() / scale < tol


@pytest.mark.parametrize("n", [20000, 1024, 1])
def test_cuda_kernels_match_torch_on_the_gpu(n):
    """float64: the kernels are torch's field to rounding. float32: no further from the float64 values than torch's
    own float32 field (the encodings' high octaves make the centres' gradient ill-conditioned: summation order
    alone moves it by ~1e-3 of its norm, and a pre-activation within rounding of 0 may take the other side of a ReLU)."""
    g = torch.Generator().manual_seed(3)
    means = torch.randn(n, 3, generator=g, dtype=torch.float64).cuda() * 1.5
    g_out = torch.randn(n, 3, generator=g, dtype=torch.float64).cuda()
    center = torch.tensor(CENTER, dtype=torch.float64).cuda()
    f64 = make_field(SHAPES[0]).cuda()
    truth = _run(f64, means, center, g_out, _torch)
    got64 = _run(f64, means, center, g_out, illumination_at)
    f32 = copy.deepcopy(f64).float()
    ref32 = _run(f32, means.float(), center.float(), g_out.float(), _torch)
    got32 = _run(f32, means.float(), center.float(), g_out.float(), illumination_at)
    names = ["rgb", "means"] + [name for name, _ in f64.named_parameters()]
    for name, t, k64, r32, k32 in zip(names, truth, got64, ref32, got32):
        scale = t.norm().clamp_min(1e-12)
        assert float((k64 - t).norm() / scale) < 1e-10, name
        err_torch, err_ours = float((r32.double() - t).norm() / scale), float((k32.double() - t).norm() / scale)
        assert err_ours <= 2 * err_torch + 1e-6, (name, err_ours, err_torch)


def test_cuda_kernels_capture_in_a_graph():
    """Forward and backward replayed from a CUDA graph give the eager values (the channel graph's use)."""
    field = make_field(SHAPES[0]).float().cuda()
    means = (torch.randn(5000, 3, device="cuda") * 1.5).requires_grad_(True)
    center = torch.tensor(CENTER, device="cuda")
    g_out = torch.randn(5000, 3, device="cuda")
    params = list(field.parameters())
    eager = torch.autograd.grad(kernels_apply(field, means, center), [means] + params, g_out)
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(2):
            torch.autograd.grad(kernels_apply(field, means, center), [means] + params, g_out)
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        out = kernels_apply(field, means, center)
        grads = torch.autograd.grad(out, [means] + params, g_out)
    graph.replay()
    torch.cuda.synchronize()
    for a, b in zip(eager, grads):
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-6)
