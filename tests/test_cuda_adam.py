"""GroupAdam's CUDA kernel against its CPU kernel and against torch's fused Adam (run on a GPU machine; skipped
cleanly where there is none)."""
import pytest
import torch
from torch import nn

from retinexgs.render import has_cuda
from retinexgs.train.adam import GroupAdam
from test_adam import _grads, _groups

pytestmark = pytest.mark.skipif(not (torch.cuda.is_available() and has_cuda()),
                                reason="needs a CUDA GPU and retinexgs built with its CUDA kernels")


def _steps(params, groups, opt, steps=5):
    for step in range(steps):
        _grads(params, step, skip=(3,) if step == 2 else ())  # drawn on the CPU, then moved: the same numbers
        opt.step()
    return params


def _on(device, dtype):
    params, groups = _groups(dtype)
    if device == "cuda":
        moved = [nn.Parameter(p.detach().cuda()) for p in params]
        index = {id(p): q for p, q in zip(params, moved)}
        groups = [{**g, "params": [index[id(p)] for p in g["params"]]} for g in groups]
        params = moved
    return params, groups


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-6)])
def test_cuda_matches_cpu(dtype, tol):
    cpu_params, cpu_groups = _on("cpu", dtype)
    gpu_params, gpu_groups = _on("cuda", dtype)
    _steps(cpu_params, cpu_groups, GroupAdam(cpu_groups, eps=1e-15))
    _steps(gpu_params, gpu_groups, GroupAdam(gpu_groups, eps=1e-15))
    for a, b in zip(cpu_params, gpu_params):
        torch.testing.assert_close(b.detach().cpu(), a.detach(), rtol=tol, atol=tol)


def test_cuda_matches_torch_fused():
    ours_p, ours_g = _on("cuda", torch.float32)
    ref_p, ref_g = _on("cuda", torch.float32)
    _steps(ours_p, ours_g, GroupAdam(ours_g, eps=1e-15))
    _steps(ref_p, ref_g, torch.optim.Adam(ref_g, eps=1e-15, fused=True))
    for a, b in zip(ours_p, ref_p):
        torch.testing.assert_close(a, b, rtol=2e-6, atol=2e-6)


def test_many_tensors_span_launches():
    """More tensors than one launch carries (kAdamBatch = 32), some empty: every one updated as on the CPU."""
    g = torch.Generator().manual_seed(3)
    cpu = [nn.Parameter(torch.randn(int(n), generator=g, dtype=torch.float64)) for n in
           torch.randint(0, 3000, (77,), generator=g)]
    gpu = [nn.Parameter(p.detach().cuda()) for p in cpu]
    for p, q in zip(cpu, gpu):
        p.grad = torch.randn(p.shape, generator=g, dtype=torch.float64)
        q.grad = p.grad.cuda()
    GroupAdam(cpu, lr=1e-2).step()
    GroupAdam(gpu, lr=1e-2).step()
    for p, q in zip(cpu, gpu):
        torch.testing.assert_close(q.detach().cpu(), p.detach(), rtol=1e-12, atol=1e-12)
