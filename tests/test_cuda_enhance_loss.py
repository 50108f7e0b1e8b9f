"""L_enhance's kernels on the GPU against the CPU's (rgs/enhance_loss.h), deterministic and graph-capturable (run
on a GPU machine; skipped cleanly where there is none)."""
import pytest
import torch

from retinexgs.render import has_cuda
from retinexgs.render._backend import kernels
from retinexgs.train.fused_enhance import enhance_loss
from test_fused_enhance import scene

pytestmark = pytest.mark.skipif(not (torch.cuda.is_available() and has_cuda()),
                                reason="needs a CUDA GPU and retinexgs built with its CUDA kernels")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("H,W", [(360, 640), (375, 501), (4, 4), (1500, 2002)])
@pytest.mark.parametrize("scale_invariant,exp_l1", [(True, False), (False, True)])
def test_cuda_matches_cpu(dtype, H, W, scale_invariant, exp_l1):
    x, s = scene(H, W, dtype)
    k = torch.tensor([3.0, 4.5, 6.0], dtype=dtype)
    E = torch.tensor([0.45], dtype=dtype)
    cpu = kernels().enhance_loss(x, s, k, E, 4, 0.5, 0, 0, exp_l1, scale_invariant)
    gpu = kernels().enhance_loss(x.cuda(), s.cuda(), k.cuda(), E.cuda(), 4, 0.5, 0, 0, exp_l1, scale_invariant)
    # the same sums in another order (per cell alike; the cells' and pairs' reductions by blocks); float32's curve
    # in --use_fast_math's powf/expf
    tol = 1e-11 if dtype == torch.float64 else 2e-4
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=tol, atol=tol * float(cpu.abs().max()))


@pytest.mark.parametrize("pool,H,W", [(3, 97, 130), (5, 64, 81), (7, 50, 50), (260, 530, 600), (4, 3000, 4000)])
def test_cuda_matches_cpu_any_pool_and_at_12_mp(pool, H, W):
    """Cells of rows that do not fill a warp (pool 3, 5, 7), taller than a block (pool 260: a thread takes every
    256th row) and a 12 MP view (750k cells, thousands of blocks in each pass)."""
    x, s = scene(H, W, torch.float64)
    k = torch.tensor([3.0, 4.5, 6.0], dtype=torch.float64)
    E = torch.tensor([0.45], dtype=torch.float64)
    cpu = kernels().enhance_loss(x, s, k, E, pool, 0.5, 0, 0, False, True)
    gpu = kernels().enhance_loss(x.cuda(), s.cuda(), k.cuda(), E.cuda(), pool, 0.5, 0, 0, False, True)
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-10, atol=1e-10 * float(cpu.abs().max()))


def test_cuda_is_deterministic_and_captures_in_a_graph():
    x, s = scene(360, 640, torch.float32)
    x, s = x.cuda(), s.cuda()
    E = torch.tensor([0.45], device="cuda")
    k = torch.tensor([3.0, 4.0, 5.0], device="cuda", requires_grad=True)
    first = [kernels().enhance_loss(x, s, k.detach(), E, 4, 0.5, 0, 0, False, True) for _ in range(3)]
    assert all(torch.equal(first[0], f) for f in first[1:])
    weights = torch.tensor([0.1, 1.0, 0.5], device="cuda")
    out = {}

    def step():
        terms = enhance_loss(x, s, k, E, 0.5)
        out["grad"], = torch.autograd.grad((terms * weights).sum(), k)
        out["terms"] = terms.detach()

    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        step()
    torch.cuda.current_stream().wait_stream(side)
    eager = {n: v.clone() for n, v in out.items()}
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        step()
    graph.replay()
    torch.cuda.synchronize()
    for name in eager:
        torch.testing.assert_close(out[name], eager[name], rtol=0, atol=0)
