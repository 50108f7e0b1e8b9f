"""The training step reads nothing back from the device (issue 65): retinexgs.bench.syncs.SyncFinder counts the
host reads of tensor values (.item(), bool(t), .tolist(), a mask index, nonzero ...) per step, on the CPU too, and
an ordinary step (not the first, a logging, checkpoint or density step) must make none. On CUDA binning's pair
count is read a render late (retinexgs.render.pair_budget, train.pair_margin): the extension waits for it only in
a render the budget bins synced (re-measuring after a density event or an overflow)."""
import inspect

import pytest
import torch

from retinexgs.bench.syncs import SyncFinder
from retinexgs.data import load_scene
from retinexgs.demo.synthetic import make_demo_scene
from retinexgs.run.config import load_config
from retinexgs.train.trainer import Trainer
from scenes import needs_cuda

# Every part of the ordinary step at work in a few steps: densification statistics (and events to report apart),
# the enhancement losses, an SH degree step, logging checks.
STEPS = ["steps=100", "log.every=10", "log.tensorboard=false", "model.sh_degree=1", "model.sh_degree_every=12",
         "model.max_init_points=300", "loss.enhance_from=4", "density.start=8", "density.stop=60",
         "density.every=7", "checkpoint.every=1000", "decomposer.method=lime"]


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return make_demo_scene(tmp_path_factory.mktemp("scene") / "demo", n_train=3, n_test=1, width=32, height=24,
                           n_points=300)


@pytest.fixture
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: one thread avoids oversubscription stalls on a shared machine
    yield
    torch.set_num_threads(n)


def trained(scene_dir, run, device="cpu", emulate=False, warm_up=6):
    run.mkdir(parents=True)
    tr = Trainer(load_config([], STEPS), load_scene(scene_dir), run, device, progress=False, log=lambda s: None,
                 emulate_graphs=emulate)
    tr.train(stop_after=warm_up)
    return tr


def counted_steps(tr, n, **finder_args) -> SyncFinder:
    finder = SyncFinder(**finder_args)
    unwatch = finder.watch_trainer(tr)
    try:
        with finder:
            tr.train(stop_after=n)
    finally:
        unwatch()
    return finder


def test_the_finder_counts_each_read_by_its_line_and_restores_torch():
    before = {name: getattr(torch.Tensor, name) for name in ("item", "__bool__", "__getitem__", "tolist")}
    x = torch.arange(6.0)
    mask = x > 2
    line = inspect.currentframe().f_lineno
    with SyncFinder() as finder:
        finder.begin_step(1)
        x.sum().item()                                           # line + 3
        if x.max() > 0:                                          # line + 4: bool(tensor)
            x[mask]                                              # line + 5: a mask index
        torch.nonzero(x)                                         # line + 6
        x.repeat_interleave(torch.tensor([1, 2, 1, 1, 1, 1]))    # line + 7: without output_size
        x.repeat_interleave(torch.tensor([1, 2, 1, 1, 1, 1]), output_size=7)  # line + 8: none
        x[torch.tensor([0, 2])]                                  # line + 9: an integer index, none
        f"{x.max():.2f}"                                         # line + 10: .item() inside torch, once
        finder.begin_step(2)
        finder.set_kind("check")
        x.tolist()                                               # line + 13
    kinds = finder.by_kind()
    sites = {(what, int(site.split(":")[1].split()[0]) - line) for what, site in kinds["ordinary"][1]}
    assert sites == {(".item()", 3), ("bool(tensor)", 4), ("mask index", 5), ("nonzero", 6),
                     ("repeat_interleave", 7), (".item()", 10)}
    assert sum(kinds["ordinary"][1].values()) == 6
    assert all("test_host_syncs.py:" in site for _, site in kinds["ordinary"][1])
    assert any(site.endswith("via torch/_tensor.py") for _, site in kinds["ordinary"][1])
    assert kinds["check"] == (1, {(".tolist()", next(iter(kinds["check"][1]))[1]): 1})
    assert {name: getattr(torch.Tensor, name) for name in before} == before  # torch as it was


@pytest.mark.parametrize("emulate", [False, True], ids=["eager", "graphed"])
def test_an_ordinary_training_step_reads_nothing_back(scene_dir, tmp_path, one_thread, emulate):
    tr = trained(scene_dir, tmp_path / "run", emulate=emulate)
    finder = counted_steps(tr, 30)
    kinds = finder.by_kind()
    assert kinds["ordinary"][0] >= 12 and {"density", "check", "after_event"} <= set(kinds)
    assert not finder.ordinary(), finder.ordinary()
    # The finder sees the trainer's reads: the density steps decide on the host, the checks read the losses.
    assert sum(kinds["density"][1].values()) > 0 and sum(kinds["check"][1].values()) > 0
    assert finder.ignored  # the CPU's non-fused Adam reads its step count (fused on CUDA): counted apart


def test_a_read_added_to_the_step_is_found(scene_dir, tmp_path, one_thread, monkeypatch):
    tr = trained(scene_dir, tmp_path / "run")
    loss = tr.objective.loss

    def reading_loss(res, view, step):
        terms = loss(res, view, step)
        terms["total"].item()  # what the step must not do
        return terms

    monkeypatch.setattr(tr.objective, "loss", reading_loss)
    finder = counted_steps(tr, 6)
    sites = {site for what, site in finder.ordinary() if what == ".item()"}
    assert len(sites) == 1 and "test_host_syncs.py" in sites.pop() and finder.by_kind()["ordinary"][0] >= 2


@needs_cuda
def test_an_ordinary_cuda_step_syncs_only_for_a_synced_binning(scene_dir, tmp_path):
    tr = trained(scene_dir, tmp_path / "run", "cuda")
    synced = tr.pairs.synced
    finder = counted_steps(tr, 30, cuda_warn=True, ignore_via=(), cuda_profile=True)
    synced = tr.pairs.synced - synced  # renders of the counted steps binned with the synced path
    n, counts = finder.by_kind()["ordinary"]
    # the pair budget's late read of a count copied a render ago (its event long passed): allowed
    reads = {k: v for k, v in counts.items() if k[0] != "cuda-runtime" and "pair_budget.py" not in k[1]}
    assert n >= 12 and not reads, reads
    runtime = {k[1]: v for k, v in counts.items() if k[0] == "cuda-runtime"}
    assert set(runtime) <= {"cudaStreamSynchronize", "cudaEventSynchronize"}, runtime
    # the extension's pair count only in a synced binning, and most ordinary steps bin without one
    assert runtime.get("cudaStreamSynchronize", 0) <= synced and runtime.get("cudaStreamSynchronize", 0) < n
