"""Binning without a host sync (issue 65) on the CPU kernels, which implement the same capacity semantics as the
GPU's (tests/test_cuda_pair_budget.py checks the GPU against its synced path): with capacity >= M the ids and ranges
equal the synced binning's, M lands in ``count``, a smaller capacity drops the highest-index Gaussians' pairs
deterministically; renders through a capacity are identical; and PairBudget's bookkeeping, with a stand-in for the
GPU's late read."""
import math

import pytest
import torch

from retinexgs.render import rasterize_gaussians
from retinexgs.render.functions import bin_gaussians
from retinexgs.render.pair_budget import PairBudget
from test_raster_tile_cull import anisotropic_scene, synthetic_inputs, tile_lists

W, H = 173, 131


def binned(inputs, cull, capacity=None):
    means2d, radii, depths, conics, opacities = inputs
    extra = (conics, opacities) if cull else (None, None)
    if capacity is None:
        return bin_gaussians(means2d, radii, depths, W, H, *extra)
    count = torch.full((1,), -7, dtype=torch.int64)
    ids, ranges = bin_gaussians(means2d, radii, depths, W, H, *extra, capacity=capacity, count=count)
    return ids, ranges, int(count[0])


def kept_by_capacity(full_ids, full_ranges, capacity):
    """The tile lists a binning of ``capacity`` slots must hold: the pairs at offsets < capacity, where a
    Gaussian's pairs follow those of the lower indices and, within it, ascend by tile (row-major rectangle
    walk); each tile's list keeps the full binning's depth order."""
    full = tile_lists(full_ids, full_ranges)
    pairs = sorted((g, t) for t, lst in full.items() for g in lst)[:capacity]
    keep = set(pairs)
    return {t: [g for g in lst if (g, t) in keep] for t, lst in full.items()}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("cull", [False, True])
def test_capacity_at_least_m_equals_the_synced_binning(dtype, cull):
    inputs = synthetic_inputs(n=800, dtype=dtype)
    full_ids, full_ranges = binned(inputs, cull)
    m = full_ids.numel()
    assert m > 1000
    for capacity in (m, m + 1, m + 333):
        ids, ranges, count = binned(inputs, cull, capacity)
        assert count == m and ids.numel() == capacity
        assert torch.equal(ids[:m], full_ids) and torch.equal(ranges, full_ranges)
        assert bool((ids[m:] == -1).all())  # padding, covered by no range


@pytest.mark.parametrize("cull", [False, True])
def test_a_smaller_capacity_keeps_the_lowest_offsets_and_reports_m(cull):
    inputs = synthetic_inputs(n=800, dtype=torch.float32)
    full_ids, full_ranges = binned(inputs, cull)
    m = full_ids.numel()
    full = tile_lists(full_ids, full_ranges)
    for capacity in (1, 97, m // 2, m - 1):
        ids, ranges, count = binned(inputs, cull, capacity)
        assert count == m > capacity  # the overflow shows in the count
        assert ids.numel() == capacity
        assert int(ranges[:, 1].max()) <= capacity and int((ranges[:, 1] - ranges[:, 0]).sum()) == capacity
        kept = tile_lists(ids, ranges)
        assert kept == kept_by_capacity(full_ids, full_ranges, capacity)
        for t, lst in kept.items():  # every stored pair is one the full binning has
            assert set(lst) <= set(full[t])
        again = binned(inputs, cull, capacity)
        assert torch.equal(again[0], ids) and torch.equal(again[1], ranges)  # deterministic


def test_capacity_zero_and_no_gaussians():
    inputs = synthetic_inputs(n=300)
    ids, ranges, count = binned(inputs, True, 0)
    assert ids.numel() == 0 and count == binned(inputs, True)[0].numel() > 0
    assert bool((ranges == 0).all())
    empty = tuple(t[:0] for t in inputs)
    ids, ranges, count = binned(empty, True, 5)
    assert count == 0 and ids.tolist() == [-1] * 5 and bool((ranges == 0).all())


def test_bad_capacity_arguments_raise_one_clear_error():
    means2d, radii, depths, conics, opacities = synthetic_inputs(n=50)
    count = torch.zeros(1, dtype=torch.int64)
    with pytest.raises(ValueError, match="both capacity and count"):
        bin_gaussians(means2d, radii, depths, W, H, capacity=10)
    with pytest.raises(ValueError, match="capacity must be in"):
        bin_gaussians(means2d, radii, depths, W, H, capacity=2 ** 31, count=count)
    with pytest.raises(ValueError, match="capacity must be in"):
        bin_gaussians(means2d, radii, depths, W, H, capacity=-1, count=count)
    with pytest.raises(TypeError, match="count must be int64"):
        bin_gaussians(means2d, radii, depths, W, H, capacity=10, count=count.int())
    with pytest.raises(ValueError, match="count must be a contiguous"):
        bin_gaussians(means2d, radii, depths, W, H, capacity=10, count=torch.zeros(2, dtype=torch.int64))


class LateReads:
    """The GPU's late read stood in for on the CPU: the value is taken when the read starts, handed over when it
    is finished; ``inflate`` adds to it (to make a render look as if it had overflowed)."""

    def __init__(self, inflate=0):
        self.inflate, self.started, self.finished = inflate, 0, 0

    def __call__(self, count):
        value = int(count[0]) + self.inflate
        self.started += 1

        def finish():
            self.finished += 1
            return value
        return finish


def loss_and_grads(args, cam, pairs=None):
    a = tuple(x.detach().clone().requires_grad_() for x in args)
    out = rasterize_gaussians(*a, cam, render_depth=True, validate=pairs is None, pairs=pairs)
    w = torch.randn(out.image.shape, generator=torch.Generator().manual_seed(2), dtype=out.image.dtype)
    loss = (out.image * w).sum() + (out.depth * 0.3).sum() + out.alpha.sum()
    return out, (out.image, out.alpha, out.depth) + torch.autograd.grad(loss, a)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_renders_through_a_budget_are_identical(dtype):
    args, cam = anisotropic_scene(n=300, C=3, dtype=dtype)
    ref_out, ref = loss_and_grads(args, cam)
    reads = LateReads()
    budget = PairBudget(1.5, reader=reads)
    first, got = loss_and_grads(args, cam, budget)  # the first render measures: synced
    assert first.num_pairs == ref_out.num_pairs > 0 and budget.synced == 1
    for _ in range(2):
        out, got = loss_and_grads(args, cam, budget)  # sync-free: a buffer of ceil(1.5 M) pairs
        assert out.num_pairs is None
        for a, b in zip(got, ref):
            assert torch.equal(a, b)
    assert (budget.steps, budget.synced, budget.overflows, reads.started) == (3, 1, 0, 2)
    assert budget.plan(args[0].shape[0], args[0].device, (cam.width, cam.height)) == math.ceil(
        1.5 * ref_out.num_pairs)


def test_an_overflowing_render_drops_pairs_and_the_next_one_is_synced():
    args, cam = anisotropic_scene(n=300, C=3)
    small = list(args)
    small[2] = args[2] * 0.5  # the same Gaussians, smaller: fewer pairs
    _, ref = loss_and_grads(args, cam)
    budget = PairBudget(1.0, reader=LateReads())
    m_small = loss_and_grads(small, cam, budget)[0].num_pairs  # measures the small view's M
    out, got = loss_and_grads(args, cam, budget)  # a buffer of m_small: pairs dropped
    assert out.num_pairs is None and not torch.equal(got[0], ref[0])
    assert all(bool(torch.isfinite(g).all()) for g in got)
    out, got = loss_and_grads(args, cam, budget)  # the overflow seen: synced, exact
    assert budget.overflows == 1 and out.num_pairs > m_small
    assert all(torch.equal(a, b) for a, b in zip(got, ref))


def test_a_budget_needs_validate_off():
    args, cam = anisotropic_scene(n=20)
    with pytest.raises(ValueError, match="validate=False"):
        rasterize_gaussians(*args, cam, pairs=PairBudget())


# ---- PairBudget's bookkeeping ------------------------------------------------------------------------------------
CPU = torch.device("cpu")


def count(m):
    return torch.tensor([m], dtype=torch.int64)


def test_capacity_is_the_largest_count_times_the_margin():
    b = PairBudget(1.5, reader=LateReads())
    assert b.plan(10, CPU) is None  # first call: synced
    b.observe_synced(101)
    assert b.plan(10, CPU) == 152  # ceil(151.5)
    b.observe(count(120), 152)
    assert b.plan(10, CPU) == 180  # the late read of 120 folded in
    b.observe(count(30), 180)
    assert b.plan(10, CPU) == 180  # the largest since the last reset, not the last
    b.observe(count(30), 180)
    assert (b.steps, b.synced, b.overflows) == (4, 1, 0)


def test_a_new_gaussian_count_size_or_reset_measures_again():
    b = PairBudget(2.0, reader=LateReads())
    assert b.plan(10, CPU, (8, 8)) is None
    b.observe_synced(50)
    assert b.plan(10, CPU, (8, 8)) == 100
    b.observe(count(60), 100)
    assert b.plan(11, CPU, (8, 8)) is None  # densification changed N
    b.observe_synced(5)
    assert b.plan(11, CPU, (8, 8)) == 10  # the old set's 60 forgotten
    b.observe(count(5), 10)
    assert b.plan(11, CPU, (16, 16)) is None  # a size not seen
    b.observe_synced(40)
    assert b.plan(11, CPU, (8, 8)) == 10 and b.plan(11, CPU, (16, 16)) == 80
    b.observe(count(300), 80)  # this render overflows ...
    b.reset()
    assert b.plan(11, CPU, (16, 16)) is None  # ... and after the reset its count does not size the buffer
    assert b.overflows == 1
    b.observe_synced(40)
    assert b.plan(11, CPU, (16, 16)) == 80


def test_an_overflow_is_counted_and_the_next_render_synced():
    reads = LateReads()
    b = PairBudget(1.5, reader=reads)
    b.plan(10, CPU)
    b.observe_synced(100)
    assert b.plan(10, CPU) == 150
    b.observe(count(151), 150)
    assert b.plan(10, CPU) is None and b.overflows == 1
    b.observe_synced(151)
    assert b.plan(10, CPU) == 227  # ceil(1.5 * 151): the overflowed count counts
    b.observe(count(200), 227)
    assert b.summary().startswith("1 of 4 renders") and b.overflows == 1  # the last read: no new overflow
    b.plan(10, CPU)
    b.observe(count(1000), 300)
    line = b.summary()  # finishes the pending read: counted
    assert b.overflows == 2 and "2 of " in line and "\n" not in line
    assert reads.started == reads.finished == 3


def test_cpu_tensors_and_margin_zero_always_bin_synced():
    b = PairBudget()  # the default reader: CUDA only, the CPU pays no sync
    for _ in range(3):
        assert b.plan(10, CPU) is None
        b.observe_synced(100)
    assert b.summary() is None  # nothing dropped: nothing to log
    z = PairBudget(0, reader=LateReads())
    for _ in range(3):
        assert z.plan(10, CPU) is None
        z.observe_synced(100)
    assert (b.synced, z.synced) == (3, 3)
    for bad in (0.5, -1, float("inf"), True, "2"):
        with pytest.raises(ValueError, match="margin must be"):
            PairBudget(bad)


def test_config_key_pair_margin():
    from retinexgs.errors import UserError
    from retinexgs.run.config import load_config
    assert load_config().train.pair_margin == 1.5
    assert load_config([], ["train.pair_margin=0"]).train.pair_margin == 0
    with pytest.raises(UserError, match="pair_margin"):
        load_config([], ["train.pair_margin=0.5"])


# ---- the trainer -------------------------------------------------------------------------------------------------
def test_training_renders_through_the_budget_and_logs_the_overflows(tmp_path):
    """The trainer's renders go through its PairBudget (train.pair_margin); here with the CPU stand-in for the
    late read, whose first read reports far more pairs than the buffer held: one overflow, logged at the end."""
    from retinexgs.data import load_scene
    from retinexgs.demo.synthetic import make_demo_scene
    from retinexgs.run.config import load_config
    from retinexgs.train.trainer import Trainer

    scene = make_demo_scene(tmp_path / "demo", n_train=3, n_test=1, width=32, height=24, n_points=200)
    cfg = load_config([], ["steps=12", "log.every=6", "log.tensorboard=false", "model.max_init_points=200",
                           "checkpoint.every=1000", "decomposer.method=lime", "density.start=1000",
                           "density.reset_opacity_every=0", "train.pair_margin=2"])
    lines = []
    (tmp_path / "run").mkdir()
    tr = Trainer(cfg, load_scene(scene), tmp_path / "run", "cpu", progress=False, log=lines.append)
    assert tr.pairs.margin == 2.0
    reads = LateReads()
    first = reads.__call__

    def one_big_read(c):  # the first sync-free render's count: above any buffer the budget sized
        reads.inflate = 10_000 if reads.started == 0 else 0
        return first(c)

    tr.pairs = PairBudget(2.0, reader=one_big_read)
    tr.train()
    assert tr.pairs.steps == 12 and tr.pairs.overflows == 1
    assert tr.pairs.synced == 2  # the first render, and the one after the overflow
    assert reads.started == 10 and reads.finished == 10  # the last one finished for the end-of-run line
    assert sum("1 of 12 renders dropped tile pairs" in line for line in lines) == 1


def test_a_density_event_makes_the_next_render_re_measure(tmp_path):
    """A density event may move Gaussians without changing their count (MCMC's relocation, an opacity reset): the
    trainer resets its budget, so the render after it bins synced."""
    from retinexgs.data import load_scene
    from retinexgs.demo.synthetic import make_demo_scene
    from retinexgs.run.config import load_config
    from retinexgs.train.trainer import Trainer

    scene = make_demo_scene(tmp_path / "demo", n_train=3, n_test=1, width=32, height=24, n_points=200)
    cfg = load_config([], ["steps=8", "log.every=8", "log.tensorboard=false", "model.max_init_points=200",
                           "checkpoint.every=1000", "decomposer.method=lime", "density.start=1000",
                           "density.reset_opacity_every=0"])
    (tmp_path / "run").mkdir()
    tr = Trainer(cfg, load_scene(scene), tmp_path / "run", "cpu", progress=False, log=lambda line: None)
    tr.pairs = PairBudget(1.5, reader=LateReads())
    real = tr.strategy.step
    tr.strategy.step = lambda step, *a: "relocated 0" if step == 4 else real(step, *a)
    tr.train()
    assert tr.pairs.steps == 8 and tr.pairs.overflows == 0
    assert tr.pairs.synced == 2  # the first render, and the one after the event
