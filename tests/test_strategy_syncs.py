"""Density steps with few host reads (issue 65): the default strategy's densification reads two numbers' worth
from the device (the clone/split counts together, then the kept indices) and MCMC's relocation one, with results
bit-identical to the straightforward boolean-mask implementation kept here as the reference."""
import math

import pytest
import torch

from retinexgs.bench.syncs import SyncFinder
from retinexgs.model.gaussians import GaussianModel
from retinexgs.model.schedule import build_schedule
from retinexgs.render.rotation import quat_to_rotmat
from retinexgs.run.config import load_config
from retinexgs.strategy import build_strategy, edit_gaussians
from retinexgs.strategy.default import MAXIMA, SUMMED
from retinexgs.strategy.ops import mask_indices
from test_host_syncs import counted_steps, one_thread, scene_dir, trained  # noqa: F401  (the fixtures)


@torch.no_grad()
def reference_densify_and_prune(s, step, model, optimizer, image_size):
    """The densification as it was before issue 65 (boolean masks and a read per decision): the reference."""
    c = s.cfg
    n = len(model)
    avg = s.densification_statistic()
    selected = avg >= c.grad_threshold
    room = max(0, int(c.max_gaussians) - n)
    if int(selected.sum()) > room:
        keep = avg.topk(room).indices if room > 0 else avg.new_zeros(0, dtype=torch.long)
        selected = torch.zeros_like(selected)
        selected[keep] = True
    scales = model.scales
    big = scales.max(-1).values > c.percent_dense * s.extent
    clone, split = selected & ~big, selected & big
    params = model.tensors()
    new = {k: v.detach()[clone] for k, v in params.items()}
    idx = split.nonzero().squeeze(-1).repeat(2)
    if idx.numel():
        R = quat_to_rotmat(params["quats"].detach()[idx])
        offs = (R @ (torch.randn(idx.numel(), 3, 1, device=R.device) * scales[idx].unsqueeze(-1))).squeeze(-1)
        split_new = {k: v.detach()[idx] for k, v in params.items()}
        split_new["means"] = split_new["means"] + offs
        split_new["log_scales"] = split_new["log_scales"] - math.log(1.6)
        new = {k: torch.cat([new[k], split_new[k]]) for k in new}
    n_new = new["means"].shape[0]
    edit_gaussians(model, optimizer, lambda name, t, is_state: torch.cat(
        [t, torch.zeros_like(new[name]) if is_state else new[name].to(t)]))
    prune = torch.cat([split, torch.zeros(n_new, dtype=torch.bool, device=split.device)])
    prune |= model.opacities < c.prune_opacity
    if s.schedule.prune_large_at(step):
        radius = torch.cat([s.max_radius, torch.zeros(n_new, device=split.device)])
        prune |= radius > c.max_screen_fraction * image_size
        prune |= model.scales.max(-1).values > 0.1 * s.extent
    if bool(prune.all()):
        prune[model.opacities.argmax()] = False
    keep = ~prune
    edit_gaussians(model, optimizer, lambda name, t, is_state: t[keep])
    for key in SUMMED + MAXIMA:
        setattr(s, key, None)
    return f"densify +{int(clone.sum())} clone +{int(split.sum())} split -{int(prune.sum())} pruned"


def _setup(overrides=(), n=3000, seed=0):
    """A fixed random model with Adam moments and densification statistics that clone, split and prune some."""
    cfg = load_config([], ["steps=100", *overrides])  # densify 6..50 every step, opacity reset every 30
    s = build_strategy(cfg.density, 1.0, build_schedule(cfg), seed=0)
    g = torch.Generator().manual_seed(seed)
    model = GaussianModel.from_points(torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g), sh_degree=1)
    with torch.no_grad():
        model.log_scales.copy_(torch.rand(n, 3, generator=g) * 4 - 7)         # 0.0009 .. 0.05: both sides of 0.01
        model.quats.copy_(torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1))
        model.opacity_logits.copy_(torch.randn(n, generator=g) * 4)           # some under prune_opacity
        model.sh_rest.copy_(torch.randn(model.sh_rest.shape, generator=g))
    opt = torch.optim.Adam([{"params": [p], "name": name, "lr": 1e-3} for name, p in model.tensors().items()])
    sum(p.square().sum() for p in model.tensors().values()).backward()
    opt.step()
    s.grad_accum = torch.rand(n, generator=g) * 1e-3
    s.count = torch.randint(0, 3, (n,), generator=g).float()
    s.max_radius = torch.rand(n, generator=g) * 40
    return s, model, opt


CASES = {
    "densify": ([], 20),
    "prune_large": ([], 40),                                          # after the first opacity reset
    "over_budget": (["density.max_gaussians=3100"], 40),              # room for 100 of about 1000 selected
    "no_room": (["density.max_gaussians=10"], 20),
    "nothing_selected": (["density.grad_threshold=1"], 20),
    "everything_pruned": (["density.prune_opacity=1"], 40),           # the most opaque one stays
}


@pytest.mark.parametrize("case", list(CASES))
def test_densification_is_bit_identical_to_the_mask_reference(case):
    overrides, step = CASES[case]
    results = []
    for densify in (reference_densify_and_prune, None):
        s, model, opt = _setup(overrides)
        torch.manual_seed(123)  # the split's offsets
        note = densify(s, step, model, opt, 64) if densify else s.densify_and_prune(step, model, opt, 64)
        results.append((note, model, opt, s))
    (note_ref, ref, opt_ref, s_ref), (note, got, opt_got, s_got) = results
    assert note == note_ref
    counts = [int(x) for x in note.replace("+", " ").replace("-", " ").split() if x.isdigit()]
    if case in ("nothing_selected", "no_room"):
        assert counts[:2] == [0, 0]
    else:
        assert counts[0] > 0 and counts[1] > 0  # the case clones and splits
    if case == "over_budget":
        assert counts[0] + counts[1] == 100
    if case in ("densify", "prune_large", "everything_pruned"):
        assert counts[2] > 0
    if case == "everything_pruned":
        assert len(got) == 1
    for name, p in ref.tensors().items():
        q = getattr(got, name)
        assert p.shape == q.shape and torch.equal(p, q), name
        st_ref, st = opt_ref.state[p], opt_got.state[q]
        assert st_ref.keys() == st.keys()
        for key in st_ref:
            assert torch.equal(st_ref[key], st[key]), (name, key)
    assert [g["params"][0] is getattr(got, g["name"]) for g in opt_got.param_groups] == [True] * 6
    assert all(getattr(s_got, k) is None for k in SUMMED + MAXIMA)


def test_a_densification_reads_the_device_twice_and_the_reference_many_times():
    reads = []
    for densify in (reference_densify_and_prune, None):
        s, model, opt = _setup()
        with SyncFinder() as finder:
            finder.begin_step(40)
            densify(s, 40, model, opt, 64) if densify else s.densify_and_prune(40, model, opt, 64)
        reads.append(sum(finder.by_kind()["ordinary"][1].values()))
    assert reads[0] > 20 and reads[1] == 2, reads


def test_an_mcmc_relocation_reads_the_device_once():
    cfg = load_config([], ["density.kind=mcmc", "steps=100", "density.mcmc.growth=0.1"])
    s = build_strategy(cfg.density, 1.0, build_schedule(cfg), seed=0)
    _, model, opt = _setup(n=400)
    n_dead = int((model.opacities <= cfg.density.mcmc.min_opacity).sum())
    assert 0 < n_dead < 400
    with SyncFinder() as finder:
        finder.begin_step(20)
        note = s.step(20, model, opt, 64)
    assert note == f"mcmc: {n_dead} relocated, +40 added" and len(model) == 440
    assert sum(finder.by_kind()["ordinary"][1].values()) == 1, finder.by_kind()


@pytest.mark.parametrize("n", [0, 1, 7, 64, 1000])
def test_mask_indices_are_nonzero_without_a_read(n):
    g = torch.Generator().manual_seed(n)
    for p in (0.0, 0.3, 1.0):
        mask = torch.rand(n, generator=g) < p
        expected = mask.nonzero().squeeze(-1)
        assert torch.equal(mask_indices(mask, expected.numel()), expected)


def test_a_training_density_step_makes_at_most_three_reads(scene_dir, tmp_path, one_thread):  # noqa: F811
    tr = trained(scene_dir, tmp_path / "run")
    n, counts = counted_steps(tr, 30).by_kind()["density"]
    # the divergence check's one .tolist() and the densification's two; an opacity reset reads nothing
    assert n >= 3 and sum(counts.values()) <= 3 * n, counts
    assert all("strategy/" not in site or c <= 2 * n for (_, site), c in counts.items())


def test_mcmc_moves_as_with_nonzero_and_bincount(monkeypatch):
    import retinexgs.strategy.mcmc as mcmc
    cfg = load_config([], ["density.kind=mcmc", "steps=100", "density.mcmc.growth=0.1"])
    results = []
    for reference in (True, False):
        if reference:  # the index sets and counts as the masks' own nonzero and bincount give them
            monkeypatch.setattr(mcmc, "mask_indices", lambda m, k: m.nonzero().squeeze(-1))
            scatter_add = torch.Tensor.scatter_add_
            monkeypatch.setattr(torch.Tensor, "scatter_add_", lambda t, dim, index, src: t.copy_(
                torch.bincount(index, minlength=t.numel())) if t.dim() == 1 else scatter_add(t, dim, index, src))
        s = build_strategy(cfg.density, 1.0, build_schedule(cfg), seed=0)
        _, model, opt = _setup(n=400)
        results.append((s.step(20, model, opt, 64), model, opt))
        monkeypatch.undo()
    (note_ref, ref, opt_ref), (note, got, opt_got) = results
    assert note == note_ref and len(got) == 440
    for name, p in ref.tensors().items():
        q = getattr(got, name)
        assert torch.equal(p, q), name
        assert all(torch.equal(v, opt_got.state[q][k]) for k, v in opt_ref.state[p].items()), name
