"""``density.prune_single_view`` (issue 64 item 3, retinexgs/strategy/views_seen.py): which training views saw each
Gaussian, tracked exactly on the device; the evidence rule (one view in at least 8 hits); the statistics follow
every index edit (clone, split, prune, MCMC relocation) and the checkpoint; the steady step reads nothing from the
device; and a tiny training run prunes and logs them, on one rank and on two."""
import json
import re
from types import SimpleNamespace

import pytest
import torch

from retinexgs.bench.syncs import SyncFinder
from retinexgs.model.gaussians import GaussianModel
from retinexgs.model.schedule import build_schedule
from retinexgs.run.checkpoint import latest_checkpoint, load_checkpoint
from retinexgs.run.config import load_config
from retinexgs.strategy import build_strategy, edit_gaussians
from retinexgs.strategy.views_seen import FALSE_PRUNE, ViewsSeen, min_hits
from retinexgs.train.trainer import Trainer
from test_train import scene_dir, trainer_for  # noqa: F401  (the fixture)

ON = "density.prune_single_view=true"


def _tracker(on=True, overrides=()):
    cfg = load_config([], ["steps=100", f"density.prune_single_view={str(on).lower()}", *overrides])
    return ViewsSeen(cfg.density, build_schedule(cfg))


def _mask(n, seen):
    m = torch.zeros(n, dtype=torch.bool)
    m[list(seen)] = True
    return m


def test_the_distinct_view_flag_is_exact_on_a_hand_made_sequence():
    t = _tracker()
    # 0: view 3 alone, ten times; 1: view 1 nine times then view 2 once (two views, never consecutively alike
    # until the end); 2: never seen; 3: view 0 alone, 5 times; 4: views 2 and 5 alternating; 5: an unknown view.
    seq = [(3, {0}), (1, {1})] * 9 + [(3, {0}), (2, {1}), (0, {3})] + [(0, {3})] * 4
    seq += [(2, {4}), (5, {4})] * 5 + [(-1, {5})] * 12
    for view, seen in seq:
        t.add(_mask(6, seen), view)
    t.fold()
    assert t.multi.tolist() == [False, True, False, False, True, False]
    assert t.last_view.tolist() == [3, 2, -1, 0, 5, -1]
    assert t.hits.tolist() == [10, 10, 0, 5, 10, 0]
    # pruned: only the one view 3 alone saw, in enough hits; never the unseen one, nor one seen too few times
    assert t.single_view(6, torch.device("cpu")).tolist() == [True, False, False, False, False, False]


def test_the_flag_matches_the_set_of_views_on_random_sequences():
    g = torch.Generator().manual_seed(3)
    t, n = _tracker(), 200
    views = [set() for _ in range(n)]
    for _ in range(60):
        view = int(torch.randint(0, 4, (1,), generator=g))  # few views: repeats of one view are common
        seen = torch.rand(n, generator=g) < 0.03
        t.add(seen, view)
        for i in seen.nonzero().squeeze(-1).tolist():
            views[i].add(view)
    assert t.multi.tolist() == [len(v) >= 2 for v in views]
    assert {len(v) for v in views} >= {0, 1, 2}  # the sequence has all three cases


def test_the_evidence_rule_needs_8_hits_of_one_view():
    assert FALSE_PRUNE == 0.01 and min_hits() == 8
    assert 2 * 0.5 ** 8 < FALSE_PRUNE <= 2 * 0.5 ** 7  # the fewest hits for which one view alone is < 1 % likely
    assert min_hits(0.05) == 6 and min_hits(0.001) == 11
    t = _tracker()
    for h in range(1, 10):
        t.add(_mask(2, {0} if h <= 7 else {0, 1}), 4)  # Gaussian 0: 9 hits; Gaussian 1: 2 hits
        single = t.single_view(2, torch.device("cpu")).tolist()
        assert single == [h >= 8, False], h


def test_off_it_allocates_nothing_and_saves_nothing():
    t = _tracker(on=False)
    t.add(torch.ones(5, dtype=torch.bool), 1)
    assert t.last_view is None and t.state_dict() == {} and not t.decides_at(20)
    assert t.single_view(5, torch.device("cpu")).tolist() == [False] * 5


def test_the_final_decision_is_at_last_event_after_the_densification_window():
    t = _tracker(overrides=["density.start=10", "density.every=10", "density.stop=0.5", "density.last_event=0.8"])
    assert t.final_step == 80 and t.final_at(80) and t.decides_at(80) and t.decides_at(50)
    assert not t.final_at(50) and not t.decides_at(55) and not t.decides_at(90)
    # last_event inside the window: the last densification is the last decision
    t = _tracker(overrides=["density.stop=0.5", "density.last_event=0.4"])
    assert t.final_step is None


def test_two_ranks_reduce_to_the_union_of_their_views():
    """Rank A saw Gaussian 0 with view 1 only, rank B with view 2 only (each alone would prune it; together it is
    multi-view); both saw Gaussian 1 with view 3 only (single, and 8 hits only in sum); Gaussian 2 only rank B saw
    (view 0); Gaussian 3 nobody. Reduced, both ranks hold what one rank that saw every view holds."""
    a, b, one = _tracker(), _tracker(), _tracker()
    seq = [(1, {0}, a)] * 4 + [(3, {1}, a)] * 2 + [(2, {0}, b)] * 4 + [(3, {1}, b), (0, {2}, b)]
    for view, seen, rank in seq:
        for r in (rank, one):
            r.add(_mask(4, seen), view)
    a.hits += 5  # agreed at an earlier decision: the same on both ranks
    b.hits += 5
    one.hits += 5
    calls = {}
    for name, rank in (("a", a), ("b", b)):  # the collectives' inputs, then their results
        calls[name] = []
        probe = ViewsSeen.__new__(ViewsSeen)
        probe.__dict__.update({k: (v.clone() if isinstance(v, torch.Tensor) else v) for k, v in rank.__dict__.items()})
        probe.reduce(lambda x, c=calls[name]: c.append(("sum", x.clone())) or x,
                     lambda x, c=calls[name]: c.append(("max", x.clone())) or x, 4, torch.device("cpu"))
    results = []
    for (op, x), (_, y) in zip(calls["a"], calls["b"]):
        results.append(x + y if op == "sum" else torch.maximum(x, y))
    for rank in (a, b):
        it = iter(results)
        rank.reduce(lambda x: next(it), lambda x: next(it), 4, torch.device("cpu"))
    one.fold()
    for rank in (a, b):
        assert rank.multi.tolist() == one.multi.tolist() == [True, False, False, False]
        assert rank.hits.tolist() == one.hits.tolist() == [13, 8, 6, 5]
        assert (rank.last_view >= 0).tolist() == [True, True, True, False]
        assert rank.single_view(4, torch.device("cpu")).tolist() == [False, True, False, False]
    assert a.last_view.tolist() == b.last_view.tolist()  # the ranks agree
    # reduced again with nothing new: idempotent (no hit counted twice)
    for rank in (a, b):
        rank.reduce(lambda x: x, lambda x: x, 4, torch.device("cpu"))
        assert rank.hits.tolist() == [13, 8, 6, 5]


# ---- the strategies' index edits ---------------------------------------------------------------------------------
def _model(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    model = GaussianModel.from_points(torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g), sh_degree=1)
    with torch.no_grad():
        model.log_scales.copy_(torch.rand(n, 3, generator=g) * 4 - 7)         # both sides of percent_dense
        model.opacity_logits.copy_(torch.randn(n, generator=g) * 4)           # some under prune_opacity
        model.sh_dc.copy_(torch.arange(n, dtype=torch.float32).reshape(n, 1, 1).expand_as(model.sh_dc))  # a tag
    opt = torch.optim.Adam([{"params": [p], "name": name, "lr": 1e-3} for name, p in model.tensors().items()])
    return model, opt


def _views_stats(t, n, seed=0):
    """Distinct statistics per Gaussian: a third single-view with 8+ hits (to be pruned), the rest mixed."""
    g = torch.Generator().manual_seed(seed)
    t.reset(n, torch.device("cpu"))
    t.last_view = torch.randint(0, 50, (n,), generator=g)
    t.multi = torch.rand(n, generator=g) < 0.5
    t.hits = torch.randint(1, 16, (n,), generator=g)
    t.fresh = torch.randint(0, 3, (n,), generator=g)
    return {k: getattr(t, k).clone() for k in ("last_view", "multi")} | {"hits": t.hits + t.fresh}


def _origin(model):
    return model.sh_dc.detach()[:, 0, 0].round().long()  # the tag: which first Gaussian each one copies


def test_the_statistics_follow_a_clone_split_and_prune():
    cfg = load_config([], ["steps=100", ON])
    s = build_strategy(cfg.density, 1.0, build_schedule(cfg))
    n = 600
    model, opt = _model(n)
    g = torch.Generator().manual_seed(1)
    s.grad_accum, s.count = torch.rand(n, generator=g) * 1e-3, torch.ones(n)
    s.max_radius = torch.rand(n, generator=g) * 10
    before = _views_stats(s.views_seen, n)
    single = ~before["multi"] & (before["hits"] >= 8)
    note = s.densify_and_prune(20, model, opt, 64)
    origin = _origin(model)
    counts = [int(x) for x in note.replace("+", " ").replace("-", " ").replace("(", " ").split() if x.isdigit()]
    n_clone, n_split, n_pruned, n_single = counts
    assert n_clone > 0 and n_split > 0 and n_single == int(single.sum()) > 0, note
    assert note.endswith(f"({n_single} single-view)")
    assert len(s.views_seen) == len(model) == n + n_clone + 2 * n_split - n_pruned
    assert not bool(single[origin].any())  # every single-view Gaussian went, and none was copied
    # copies (clones, split children) carry the statistics of the Gaussian they copy; the rest their own
    assert int((origin.bincount(minlength=n) > 1).sum()) > 0
    for key in ("last_view", "multi", "hits"):
        assert torch.equal(getattr(s.views_seen, key), before[key][origin]), key
    assert int(s.views_seen.fresh.sum()) == 0


def test_the_statistics_follow_an_mcmc_relocation_and_growth():
    cfg = load_config([], ["steps=100", ON, "density.kind=mcmc", "density.mcmc.growth=0.1"])
    s = build_strategy(cfg.density, 1.0, build_schedule(cfg))
    n = 400
    model, opt = _model(n)
    before = _views_stats(s.views_seen, n)
    single = ~before["multi"] & (before["hits"] >= 8)
    dead = model.opacities.detach() <= cfg.density.mcmc.min_opacity
    note = s.step(20, model, opt, 64)
    n_single = int((single & ~dead).sum())
    assert n_single > 0 and note == f"mcmc: {int((dead | single).sum())} relocated, +40 added ({n_single} single-view)"
    origin = _origin(model)
    assert len(model) == len(s.views_seen) == 440
    assert not bool((single | dead)[origin].any())  # relocated away, and never a source
    for key in ("last_view", "multi", "hits"):
        assert torch.equal(getattr(s.views_seen, key), before[key][origin]), key


def test_an_edit_whose_rows_do_not_match_refuses():
    model, opt = _model(10)
    t = _tracker()
    t.reset(10, torch.device("cpu"))
    keep = torch.arange(5)
    with pytest.raises(ValueError, match="rows"):
        edit_gaussians(model, opt, lambda name, x, is_state: x.index_select(0, keep), rows=torch.arange(6), stats=[t])
    with pytest.raises(ValueError, match="rows"):
        edit_gaussians(model, opt, lambda name, x, is_state: x, stats=[t])


# ---- checkpoint ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["default", "mcmc"])
def test_the_statistics_round_trip_and_an_old_state_loads(kind):
    cfg = load_config([], ["steps=100", ON, f"density.kind={kind}"])
    s = build_strategy(cfg.density, 1.0, build_schedule(cfg))
    before = _views_stats(s.views_seen, 30)
    state = s.state_dict()
    again = build_strategy(cfg.density, 1.0, build_schedule(cfg))
    again.load_state_dict(state, torch.device("cpu"))
    for key in ("last_view", "multi", "hits"):
        assert torch.equal(getattr(again.views_seen, key), before[key]), key
    old = {k: v for k, v in state.items() if not k.startswith("views_")}  # a checkpoint written before the key
    assert old != state
    again.load_state_dict(old, torch.device("cpu"))
    assert again.views_seen.last_view is None
    again.views_seen.add(torch.ones(30, dtype=torch.bool), 2)  # starts unseen
    assert again.views_seen.fresh.tolist() == [1] * 30 and not bool(again.views_seen.multi.any())
    # off: the checkpoint holds what it held before the key existed
    off = build_strategy(load_config([], ["steps=100", f"density.kind={kind}"]).density, 1.0, build_schedule(cfg))
    assert not any(k.startswith("views_") for k in off.state_dict())


# ---- the steady step ---------------------------------------------------------------------------------------------
def test_the_steady_step_reads_nothing_from_the_device():
    cfg = load_config([], ["steps=100", ON])
    s = build_strategy(cfg.density, 1.0, build_schedule(cfg))
    n = 100
    means2d = torch.zeros(n, 2, requires_grad=True)
    means2d.grad = torch.rand(n, 2)
    radii = torch.randint(0, 3, (n, 2)) * torch.randint(0, 2, (n, 1))
    out = SimpleNamespace(means2d=means2d, radii=radii, visible=(radii > 0).all(-1))
    s.after_backward(out, 40, 30, 0)  # allocations happen once
    with SyncFinder() as finder:
        finder.begin_step(7)
        for view in range(1, 6):
            s.after_backward(out, 40, 30, view)
    assert sum(finder.by_kind().get("ordinary", (0, {}))[1].values()) == 0, finder.by_kind()
    assert int(s.views_seen.fresh.sum()) == 6 * int(out.visible.sum())


# ---- training ----------------------------------------------------------------------------------------------------
RUN = ["steps=48", "density.every=8", "density.stop=0.5", "density.last_event=0.8", "checkpoint.every=16",
       "log.every=16"]


def _events(run):
    return [r for r in map(json.loads, (run / "train_log.jsonl").read_text().splitlines()) if "event" in r]


def test_a_tiny_run_prunes_single_view_gaussians_logs_them_and_resumes(scene_dir, tmp_path):  # noqa: F811
    tr = trainer_for(scene_dir, tmp_path / "run", RUN + [ON])
    tr.train()
    events = _events(tmp_path / "run")
    assert [e["step"] for e in events] == [8, 16, 24, 38]
    assert all(e["event"].endswith("single-view)") for e in events[:3])
    final = events[-1]["event"]
    pruned = re.fullmatch(r"single-view prune -(\d+) \(seen by one view in >= 8 hits\)", final)
    assert pruned and int(pruned[1]) > 0, final
    assert len(tr.strategy.views_seen) == len(tr.model.gaussians)
    assert int(tr.strategy.views_seen.hits.max()) >= 8
    # the checkpoint holds the statistics; resumed before the final decision, the run ends as the straight one
    ckpt = load_checkpoint(latest_checkpoint(tmp_path / "run"))
    assert ckpt["density"]["views_hits"].shape[0] == len(tr.model.gaussians)
    part = trainer_for(scene_dir, tmp_path / "part", RUN + [ON])
    part.train(stop_after=32)
    resumed = Trainer(part.cfg, part.scene, tmp_path / "part", "cpu", resume=True, progress=False, log=lambda s: None)
    assert resumed.step == 32 and len(resumed.strategy.views_seen) == len(resumed.model.gaussians)
    resumed.train()
    assert _events(tmp_path / "part") == events
    for k, v in tr.model.state_dict().items():
        torch.testing.assert_close(resumed.model.state_dict()[k], v, rtol=1e-4, atol=1e-5, msg=k)
    # off, the same run prunes nothing for it and logs as before
    off = trainer_for(scene_dir, tmp_path / "off", RUN)
    off.train()
    assert [e["step"] for e in _events(tmp_path / "off")] == [8, 16, 24]
    assert not any("single-view" in e["event"] for e in _events(tmp_path / "off"))


def test_mcmc_relocates_single_view_gaussians_in_training(scene_dir, tmp_path):  # noqa: F811
    tr = trainer_for(scene_dir, tmp_path / "run", RUN + [ON, "density.kind=mcmc"])
    tr.train()
    events = _events(tmp_path / "run")
    assert [e["step"] for e in events] == [8, 16, 24, 38]
    final = events[-1]["event"]
    assert final.startswith("mcmc: ") and final.endswith(" single-view)"), final
    assert sum(int(e["event"].split("(")[1].split()[0]) for e in events) > 0


def test_two_ranks_decide_as_one_rank_with_two_views_a_step(tmp_path):
    """Data parallel (gloo, 2 processes): the ranks see different views each step, so a Gaussian each rank saw
    with one view is multi-view only in the union; the single-view decisions (and the Gaussians) must be those of
    one rank that renders both views of every step."""
    from retinexgs.demo.synthetic import make_demo_scene
    from test_distributed import plain_run, torchrun, train_args

    scene = make_demo_scene(tmp_path / "scene", n_train=4, n_test=1, width=24, height=18, n_points=200)
    extra = ["steps=24", "density.start=2", "density.every=6", "density.stop=0.5", "density.last_event=0.8",
             "checkpoint.every=24", "log.every=24", ON]
    res, _ = torchrun(train_args(scene, tmp_path / "two", extra))
    assert res.returncode == 0, res.stdout + res.stderr
    plain_run(scene, tmp_path / "one", extra + ["train.views_per_rank=2"])
    two, one = _events(tmp_path / "two"), _events(tmp_path / "one")
    assert [e["step"] for e in two] == [6, 12, 19] and all(e["ranks_agree"] is True for e in two)
    assert [(e["step"], e["event"], e["gaussians"]) for e in two] == \
        [(e["step"], e["event"], e["gaussians"]) for e in one]
    assert int(re.search(r"-(\d+)", two[-1]["event"])[1]) > 0, two[-1]
