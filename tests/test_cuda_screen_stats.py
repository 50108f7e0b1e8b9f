"""Densification's fused screen-space statistics: the CUDA kernel against the CPU one (run on a GPU machine;
skipped cleanly where there is none)."""
import pytest
import torch

from retinexgs.render import has_cuda
from retinexgs.render.screen_stats import screen_stats
from test_screen_stats import case  # culled, half-culled and seen Gaussians, accumulators with sums

pytestmark = pytest.mark.skipif(not (torch.cuda.is_available() and has_cuda()),
                                reason="needs a CUDA GPU and retinexgs built with its CUDA kernels")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [0, 1, 255, 257, 1_000_003])
def test_cuda_matches_cpu(n, dtype):
    cpu = case(n, dtype, seed=3)
    gpu = [t.cuda() for t in cpu]
    for v in range(3):
        grad = case(n, dtype, seed=10 + v)[0]
        screen_stats(grad, cpu[1], 1920, 1080, *cpu[2:])
        screen_stats(grad.cuda(), gpu[1], 1920, 1080, *gpu[2:])
    for a, b in zip(cpu[2:], gpu[2:]):
        torch.testing.assert_close(b.cpu(), a, rtol=1e-6, atol=0)
    assert torch.equal(cpu[3], gpu[3].cpu()) and torch.equal(cpu[4], gpu[4].cpu())  # counts and radii exactly


def test_cuda_rejects_accumulators_on_another_device():
    grad, radii, acc, count, rmax = case(10, device="cuda")
    with pytest.raises(ValueError, match="grad_accum must be on cuda"):
        screen_stats(grad, radii, 8, 8, acc.cpu(), count, rmax)
