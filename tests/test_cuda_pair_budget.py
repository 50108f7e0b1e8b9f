"""Binning without a host sync on the GPU (issue 65; run on a GPU machine, skipped cleanly where there is none):
with a capacity >= M the CUDA binning equals its synced path, a smaller capacity drops exactly the CPU's pairs and
reports the true M, the call returns while the GPU is still busy, and renders through a PairBudget in a
training-like loop equal the synced renders."""
import time

import pytest
import torch

from retinexgs.render import has_cuda, rasterize_gaussians
from retinexgs.render.functions import bin_gaussians
from retinexgs.render.pair_budget import PairBudget
from scenes import make_camera, random_gaussians
from test_cuda_tile_cull import empty_as_zero, projected

pytestmark = pytest.mark.skipif(not (torch.cuda.is_available() and has_cuda()),
                                reason="needs a CUDA GPU and retinexgs built with its CUDA kernels")


def sync_free(inputs, width, height, capacity, device="cuda"):
    means2d, radii, depths, conics, opacities = (t.to(device) for t in inputs)
    count = torch.full((1,), -7, dtype=torch.int64, device=device)
    ids, ranges = bin_gaussians(means2d, radii, depths, width, height, conics, opacities, capacity=capacity,
                                count=count)
    return ids.cpu(), ranges.cpu(), int(count[0])


def synced(inputs, width, height, device="cuda"):
    means2d, radii, depths, conics, opacities = (t.to(device) for t in inputs)
    ids, ranges = bin_gaussians(means2d, radii, depths, width, height, conics, opacities)
    return ids.cpu(), ranges.cpu()


@pytest.mark.parametrize("size", [(64, 48), (640, 360), (1920, 1080)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_sync_free_binning_equals_the_synced_one(size, dtype):
    """Same keys in the same order into a stable radix sort: the ids of the first M slots and the ranges are
    exactly the synced path's; the slots past M hold -1 (the padding keys sort after every tile)."""
    width, height = size
    inputs = projected(20000 if width > 100 else 2000, width, height, dtype, seed=width)
    full_ids, full_ranges = synced(inputs, width, height)
    m = full_ids.numel()
    assert m > 0
    for capacity in (m, m + 1, m + 4097):
        ids, ranges, count = sync_free(inputs, width, height, capacity)
        assert count == m and ids.numel() == capacity
        assert torch.equal(ranges, full_ranges)
        assert torch.equal(ids[:m], full_ids)
        assert bool((ids[m:] == -1).all())


@pytest.mark.parametrize("size", [(64, 48), (1920, 1080)])
def test_cuda_overflow_keeps_the_cpus_pairs_and_reports_m(size):
    width, height = size
    inputs = projected(20000 if width > 100 else 2000, width, height, torch.float32, seed=7)
    m = synced(inputs, width, height)[0].numel()
    for capacity in (1, m // 3, m - 1):
        ids, ranges, count = sync_free(inputs, width, height, capacity)
        cpu_ids, cpu_ranges, cpu_count = sync_free(inputs, width, height, capacity, device="cpu")
        assert count == cpu_count == m > capacity
        assert int(ranges[:, 1].max()) <= capacity and int((ranges[:, 1] - ranges[:, 0]).sum()) == capacity
        assert torch.equal(ids, cpu_ids)
        assert torch.equal(empty_as_zero(ranges), empty_as_zero(cpu_ranges))


def test_cuda_capacity_zero_and_no_gaussians():
    inputs = projected(2000, 64, 48, torch.float32, seed=3)
    ids, ranges, count = sync_free(inputs, 64, 48, 0)
    assert ids.numel() == 0 and count == synced(inputs, 64, 48)[0].numel() > 0 and bool((ranges == 0).all())
    ids, ranges, count = sync_free(tuple(t[:0] for t in inputs), 64, 48, 9)
    assert count == 0 and ids.tolist() == [-1] * 9 and bool((ranges == 0).all())


def test_cuda_sync_free_binning_does_not_wait_for_the_gpu():
    """With the GPU busy (a sleep kernel queued first), the sync-free call returns at once and the stream is
    still running; the synced call waits for it (which shows that the check can see a wait)."""
    inputs = [t.cuda() for t in projected(20000, 640, 360, torch.float32, seed=1)]
    m = synced(inputs, 640, 360)[0].numel()
    sync_free(inputs, 640, 360, 2 * m)  # warm-up: the caching allocator holds the blocks afterwards
    torch.cuda.synchronize()
    means2d, radii, depths, conics, opacities = inputs
    count = torch.empty(1, dtype=torch.int64, device="cuda")
    stream = torch.cuda.current_stream()
    for with_capacity in (True, False):
        torch.cuda._sleep(2_000_000_000)  # about a second of GPU time
        t0 = time.perf_counter()
        if with_capacity:
            bin_gaussians(means2d, radii, depths, 640, 360, conics, opacities, capacity=2 * m, count=count)
        else:
            bin_gaussians(means2d, radii, depths, 640, 360, conics, opacities)
        waited, busy = time.perf_counter() - t0, not stream.query()
        torch.cuda.synchronize()
        if with_capacity:
            assert busy and waited < 0.2, waited
            assert int(count[0]) == m
        else:
            assert waited > 0.2, waited  # it waited for the sleep (its later kernels may still run)


def test_cuda_training_like_loop_through_a_budget():
    """Steps with slightly moved Gaussians (as an optimiser moves them): the first render measures (synced),
    the rest bin without a sync into ceil(1.5 max M) slots and equal the synced renders (images bit for bit,
    gradients up to the backward's atomic order). A smaller set of Gaussians measures again; a step with
    far more pairs than the buffer overflows, is counted, and the next render is synced again."""
    means, quats, scales, opacities, colors = (t.cuda().float() for t in random_gaussians(3000, 3, seed=2))
    cam = make_camera(width=320, height=240)
    budget = PairBudget(1.5)
    g = torch.Generator(device="cuda").manual_seed(0)

    def step(means, scales, pairs):
        a = [t.detach().clone().requires_grad_() for t in (means, quats, scales, opacities, colors)]
        out = rasterize_gaussians(*a, cam, validate=pairs is None, pairs=pairs)
        loss = (out.image * torch.linspace(0, 1, 3, device="cuda")).sum() + out.alpha.sum()
        return out, (out.image, out.alpha) + torch.autograd.grad(loss, a)

    counts = []
    for i in range(8):
        moved = means + 0.002 * torch.randn(means.shape, generator=g, device="cuda")
        out, got = step(moved, scales, budget)
        ref_out, ref = step(moved, scales, None)
        counts.append(ref_out.num_pairs)
        assert (out.num_pairs is None) == (i > 0)
        assert torch.equal(got[0], ref[0]) and torch.equal(got[1], ref[1])
        for a, b in zip(got[2:], ref[2:]):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4 * float(b.abs().max()))
    assert max(counts) < 1.5 * counts[0]  # no overflow possible here
    assert (budget.steps, budget.synced, budget.overflows) == (8, 1, 0)
    # Fewer Gaussians (a prune): measured again.
    means, quats, scales, opacities, colors = (t[:2000] for t in (means, quats, scales, opacities, colors))
    out, _ = step(means, scales, budget)
    assert out.num_pairs is not None and budget.synced == 2
    step(means, scales, budget)  # sync-free, sized from the pruned set's count
    big = scales * 2.7  # e times as wide: several times the pairs
    out, got = step(means, big, budget)  # overflows: pairs dropped
    ref_out, ref = step(means, big, None)
    assert out.num_pairs is None and not torch.equal(got[0], ref[0])
    out, got = step(means, big, budget)  # the overflow read late: synced, exact
    assert budget.overflows == 1 and out.num_pairs == ref_out.num_pairs
    assert torch.equal(got[0], ref[0])
    assert budget.summary().startswith("1 of 12 renders dropped tile pairs")
