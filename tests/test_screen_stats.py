"""Densification's fused screen-space statistics (csrc/include/rgs/screen_stats.h) against their torch twin, the
strategy's use of them, and their one-line errors (CPU kernels; the CUDA ones: tests/test_cuda_screen_stats.py)."""
import pytest
import torch

from retinexgs.render.screen_stats import screen_stats, screen_stats_reference


def case(n, dtype=torch.float32, seed=0, device="cpu"):
    """Pixel gradients, radii with Gaussians culled (0, 0), half-culled (one radius 0) and seen, accumulators
    already holding earlier views' sums."""
    g = torch.Generator().manual_seed(seed)
    grad = (torch.randn(n, 2, generator=g, dtype=torch.float64) * 1e-3).to(dtype)
    radii = torch.randint(0, 40, (n, 2), generator=g, dtype=torch.int32)
    radii[::5] = 0
    radii[1::7, 0] = 0
    acc = [torch.rand(n, generator=g) * k for k in (1e-2, 5.0, 30.0)]
    return [t.to(device) for t in (grad, radii, *acc)]


def run_both(n, dtype, width=640, height=360, seed=0, views=3):
    fused = case(n, dtype, seed)
    ref = [t.clone() for t in fused]
    for v in range(views):
        grad = case(n, dtype, seed + 100 + v)[0]
        screen_stats(grad, fused[1], width, height, *fused[2:])
        screen_stats_reference(grad, ref[1], width, height, *ref[2:])
    return fused[2:], ref[2:]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [0, 1, 7, 1000, 70_001])
def test_fused_matches_the_torch_twin(n, dtype):
    fused, ref = run_both(n, dtype)
    for a, b, name in zip(fused, ref, ("grad_accum", "count", "max_radius")):
        assert a.dtype == torch.float32
        torch.testing.assert_close(a, b, rtol=2e-6, atol=0, msg=name)


def test_the_statistics_by_hand():
    """Seen: |g * (W/2, H/2)| added and one more view; half-culled or culled: nothing added; the radius maximum of
    every Gaussian (a half-culled one's too)."""
    grad = torch.tensor([[3.0, 4.0], [1.0, 1.0], [5.0, 5.0]])
    radii = torch.tensor([[2, 9], [0, 6], [0, 0]], dtype=torch.int32)
    acc, count, rmax = torch.zeros(3), torch.zeros(3), torch.tensor([1.0, 2.0, 3.0])
    screen_stats(grad, radii, 2, 2, acc, count, rmax)  # NDC scale (1, 1)
    assert acc.tolist() == [5.0, 0.0, 0.0] and count.tolist() == [1.0, 0.0, 0.0]
    assert rmax.tolist() == [9.0, 6.0, 3.0]
    screen_stats(grad, radii, 4, 2, acc, count, rmax)  # x scaled by 2: |(6, 4)|
    assert acc[0].item() == pytest.approx(5.0 + 52 ** 0.5) and count.tolist() == [2.0, 0.0, 0.0]


def test_a_non_finite_gradient_counts_only_where_seen():
    grad = torch.tensor([[float("nan"), 0.0], [float("inf"), 1.0]])
    radii = torch.tensor([[0, 0], [3, 3]], dtype=torch.int32)
    acc, count, rmax = torch.zeros(2), torch.zeros(2), torch.zeros(2)
    screen_stats(grad, radii, 10, 10, acc, count, rmax)
    assert acc[0].item() == 0.0 and acc[1].item() == float("inf")


@pytest.mark.parametrize("bad, match", [
    (dict(acc=torch.zeros(4, dtype=torch.float64)), "grad_accum must be float32"),
    (dict(count=torch.zeros(5)), r"count must be \[4\]"),
    (dict(rmax=torch.zeros(8)[::2]), "max_radius must be contiguous"),
    (dict(radii=torch.zeros(4, 2, dtype=torch.int64)), "radii must be int32"),
    (dict(grad=torch.zeros(4, 3)), r"grad2d must be \[N, 2\]"),
    (dict(grad=torch.zeros(4, 2, dtype=torch.int32)), "grad2d must be float32 or float64"),
])
def test_bad_inputs_give_one_line(bad, match):
    args = dict(grad=torch.zeros(4, 2), radii=torch.ones(4, 2, dtype=torch.int32), acc=torch.zeros(4),
                count=torch.zeros(4), rmax=torch.zeros(4))
    args.update(bad)
    with pytest.raises((TypeError, ValueError), match=match) as info:
        screen_stats(args["grad"], args["radii"], 8, 8, args["acc"], args["count"], args["rmax"])
    assert "\n" not in str(info.value)


def test_the_default_strategy_accumulates_through_the_fused_kernel():
    """DefaultStrategy.after_backward over two views of different sizes gives the torch twin's statistics."""
    from types import SimpleNamespace

    from retinexgs.model.schedule import build_schedule
    from retinexgs.run.config import load_config
    from retinexgs.strategy import DefaultStrategy

    cfg = load_config([], [])
    strategy = DefaultStrategy(cfg.density, 1.0, build_schedule(cfg))
    n = 500
    ref = [torch.zeros(n) for _ in range(3)]
    for v, (w, h) in enumerate([(640, 360), (100, 300)]):
        grad, radii = case(n, seed=v)[:2]
        means2d = torch.zeros(n, 2, requires_grad=True)
        means2d.grad = grad
        strategy.after_backward(SimpleNamespace(means2d=means2d, radii=radii), w, h)
        screen_stats_reference(grad, radii, w, h, *ref)
    for name, r in zip(("grad_accum", "count", "max_radius"), ref):
        torch.testing.assert_close(getattr(strategy, name), r, rtol=2e-6, atol=0, msg=name)
    # A checkpoint's statistics (even of another dtype) come back as the float32 the kernel adds to.
    state = {k: v.double() for k, v in strategy.state_dict().items()}
    strategy.load_state_dict(state, torch.device("cpu"))
    assert all(getattr(strategy, k).dtype == torch.float32 for k in state)
