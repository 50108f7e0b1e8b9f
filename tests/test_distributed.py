"""Training on several ranks (issue 34): data parallel over views through torch.distributed, tested on the CPU
with gloo and 2 processes (torchrun in a subprocess, one rank thread each, a 24x18 scene of 4 training views).

Tolerance: a step of B views on N ranks and on one rank with ``train.views_per_rank = B`` sees the same views
and sums the same per-view gradients (two summands: a + b is exact whatever the order), so with two ranks the
parameters, Adam moments and metrics agree bit for bit; the tests allow float32 rounding (rtol 1e-5, atol 1e-6)
for a reduction order that could differ elsewhere, and a one-rank torchrun run must equal the plain run exactly.
"""
import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from retinexgs.model.gaussians import PARAM_NAMES, GaussianModel
from retinexgs.run.checkpoint import latest_checkpoint, load_checkpoint
from retinexgs.train.distributed import lr_batch_factor, strip_gpus
from scenes import TINY_RUN, run_cli

ROOT = Path(__file__).resolve().parents[1]
# TINY_RUN for 6 steps, checkpoints at 3 and 6, and a densification at step 4 that splits Gaussians (random
# offsets) and prunes them.
OVERRIDES = [o for o in TINY_RUN if not o.startswith(("steps=", "checkpoint.every="))] + [
    "steps=6", "checkpoint.every=3", "density.start=2", "density.every=2", "density.stop=5",
    "density.grad_threshold=0.00001"]
RTOL, ATOL = 1e-5, 1e-6


def _env(extra=None):
    env = {k: v for k, v in os.environ.items()
           if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")}
    env.update(PYTHONPATH=str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else ""),
               OMP_NUM_THREADS="1", RETINEXGS_DIST_TIMEOUT="60")
    env.update(extra or {})
    return env


def torchrun(args, nproc=2, extra_env=None, timeout=180):
    """``torchrun --standalone --nproc_per_node NPROC -m retinexgs ARGS`` on the CPU: (completed process, seconds)."""
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(nproc),
           "-m", "retinexgs", *map(str, args)]
    t0 = time.time()
    res = subprocess.run(cmd, env=_env(extra_env), capture_output=True, text=True, timeout=timeout, cwd=ROOT)
    return res, time.time() - t0


def train_args(scene, out, extra=()):
    args = ["train", "--data", scene, "--out", out, "--config", "demo", "--device", "cpu", "--quiet"]
    for o in list(OVERRIDES) + list(extra):
        args += ["--set", o]
    return args


def plain_run(scene, out, extra=(), resume=False):
    """The same run in this process, one rank (one torch thread, as each rank has)."""
    from retinexgs.train.runner import train_run

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        if resume:
            return train_run(None, out, [], list(extra), "cpu", resume=True, progress=False, log=lambda s: None)
        return train_run(scene, out, ["demo"], OVERRIDES + list(extra), "cpu", progress=False, log=lambda s: None)
    finally:
        torch.set_num_threads(n)


def final_state(run):
    return load_checkpoint(latest_checkpoint(run))


def assert_same_training(a, b, exact=False):
    """The two checkpoints hold the same step, view order, parameters and Adam moments."""
    assert a["step"] == b["step"]
    assert a["order"] == b["order"]
    assert a["model"].keys() == b["model"].keys()
    for k in a["model"]:
        x, y = a["model"][k], b["model"][k]
        assert x.shape == y.shape, k
        assert torch.equal(x, y) if exact else torch.allclose(x, y, rtol=RTOL, atol=ATOL), \
            f"{k}: max difference {(x.float() - y.float()).abs().max().item():.3g}"
    sa, sb = a["optimizer"]["state"], b["optimizer"]["state"]
    assert sa.keys() == sb.keys()
    for i in sa:
        for k in ("exp_avg", "exp_avg_sq"):
            x, y = sa[i][k], sb[i][k]
            assert torch.equal(x, y) if exact else torch.allclose(x, y, rtol=RTOL, atol=ATOL), (i, k)


def without_last_checkpoint(src, dst):
    """A copy of the run folder as a kill after step 3's checkpoint would have left it."""
    shutil.copytree(src, dst)
    latest_checkpoint(dst).unlink()
    assert latest_checkpoint(dst).name == "step_000003.pt"
    return dst


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from retinexgs.demo.synthetic import make_demo_scene

    return make_demo_scene(tmp_path_factory.mktemp("dist") / "scene", n_train=4, n_test=2, width=24, height=18,
                           n_points=200)


@pytest.fixture(scope="module")
def two_ranks(scene, tmp_path_factory):
    """A run trained by 2 ranks (one view each a step)."""
    run = tmp_path_factory.mktemp("two") / "run"
    res, seconds = torchrun(train_args(scene, run))
    assert res.returncode == 0, res.stdout + res.stderr
    assert "2 ranks (gloo), 2 views a step" in res.stdout
    return run


@pytest.fixture(scope="module")
def one_rank_two_views(scene, tmp_path_factory):
    """The same run on one rank taking both views of each step."""
    run = tmp_path_factory.mktemp("one") / "run"
    plain_run(scene, run, ["train.views_per_rank=2"])
    return run


def test_two_ranks_train_as_one_rank_with_two_views_a_step(two_ranks, one_rank_two_views):
    a, b = final_state(two_ranks), final_state(one_rank_two_views)
    assert (a["ranks"], a["views_per_step"], b["ranks"], b["views_per_step"]) == (2, 2, 1, 2)
    assert_same_training(a, b)
    # The evaluation, sharded over the ranks (each rendered one of the two test views), is the one-rank one.
    ma = json.loads((two_ranks / "metrics.json").read_text())
    mb = json.loads((one_rank_two_views / "metrics.json").read_text())
    assert ma.keys() == mb.keys()
    assert [r["view"] for r in ma["views"]] == [r["view"] for r in mb["views"]]
    for ra, rb in zip(ma["views"], mb["views"]):
        assert ra.keys() == rb.keys()
        for k in ra:
            assert ra[k] == (rb[k] if isinstance(rb[k], str) else pytest.approx(rb[k], rel=1e-5, abs=1e-6)), k
    assert sorted(p.name for p in (two_ranks / "renders" / "test").iterdir()) == \
        sorted(Path(r["view"]).stem + ".png" for r in ma["views"])
    # The benchmark's figures, with the same keys for one rank and two.
    ta, tb = ma["train"], mb["train"]
    assert ta.keys() == tb.keys()
    assert (ta["ranks"], ta["views_per_step"], tb["ranks"], tb["views_per_step"]) == (2, 2, 1, 2)
    assert len(ta["host_rss_gb_per_rank"]) == 2 and len(tb["host_rss_gb_per_rank"]) == 1
    assert ta["views_per_second"] > 0 and ta["time_to_first_step"] > 0
    # Rank 0 alone wrote the log: one record per step, no duplicates.
    steps = [r["step"] for r in map(json.loads, (two_ranks / "train_log.jsonl").read_text().splitlines())
             if "event" not in r]
    assert steps == list(range(1, 7))


def test_densification_decides_alike_on_every_rank(two_ranks):
    events = [r for r in map(json.loads, (two_ranks / "train_log.jsonl").read_text().splitlines()) if "event" in r]
    assert [e["step"] for e in events] == [4]
    assert "split" in events[0]["event"]
    # Compared (fingerprints of every rank's Gaussians gathered) before rank 0's were broadcast: the split
    # offsets' random draws and the counts were the same on both ranks.
    assert all(e["ranks_agree"] is True for e in events)
    metrics = json.loads((two_ranks / "metrics.json").read_text())
    assert metrics["train"]["ranks_in_sync"] is True  # every parameter, at the end
    assert metrics["train"]["gaussians"] == events[-1]["gaussians"] == len(final_state(two_ranks)["model"]["gaussians.means"])


def test_a_two_rank_checkpoint_resumes_on_one_rank_and_exports(two_ranks, one_rank_two_views, tmp_path, capsys):
    # 2 -> 1: resumed from step 3 on one rank taking both views of a step, it trains what 2 ranks trained.
    run = without_last_checkpoint(two_ranks, tmp_path / "resumed")
    plain_run(None, run, ["train.views_per_rank=2"], resume=True)
    state = final_state(run)
    assert (state["step"], state["ranks"], state["views_per_step"]) == (6, 1, 2)
    assert_same_training(state, final_state(one_rank_two_views))
    assert json.loads((run / "metrics.json").read_text())["train"]["ranks"] == 1
    # Export, eval and render read a multi-rank run as any other: one PLY of every Gaussian.
    from retinexgs.export.ply import read_ply

    code, out, err = run_cli(["export", "--run", two_ranks, "--out", tmp_path / "two.ply", "--device", "cpu",
                              "--quiet"], capsys)
    assert code == 0, out + err
    assert read_ply(tmp_path / "two.ply")["means"].shape[0] == len(final_state(two_ranks)["model"]["gaussians.means"])
    code, out, err = run_cli(["eval", "--run", run, "--device", "cpu"], capsys)
    assert code == 0, out + err


def test_a_one_rank_checkpoint_resumes_on_two_ranks(one_rank_two_views, two_ranks, tmp_path):
    # 1 -> 2, through `train --gpus 2 --device cpu` (it re-launches itself with torchrun).
    run = without_last_checkpoint(one_rank_two_views, tmp_path / "resumed")
    cmd = [sys.executable, "-m", "retinexgs", "train", "--out", run, "--resume", "--set", "train.views_per_rank=1",
           "--gpus", "2", "--device", "cpu", "--quiet"]
    res = subprocess.run(list(map(str, cmd)), env=_env(), capture_output=True, text=True, timeout=180, cwd=ROOT)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "2 ranks (gloo), 2 views a step" in res.stdout
    state = final_state(run)
    assert (state["step"], state["ranks"], state["views_per_step"]) == (6, 2, 2)
    assert_same_training(state, final_state(two_ranks))


def test_one_rank_under_torchrun_is_the_plain_run(scene, tmp_path):
    res, _ = torchrun(train_args(scene, tmp_path / "torchrun"), nproc=1)
    assert res.returncode == 0, res.stdout + res.stderr
    plain_run(scene, tmp_path / "plain")
    a, b = final_state(tmp_path / "torchrun"), final_state(tmp_path / "plain")
    assert (a["ranks"], a["views_per_step"]) == (1, 1)
    assert_same_training(a, b, exact=True)


@pytest.mark.parametrize("fault", ["die", "hang"])
def test_a_rank_that_dies_or_hangs_stops_the_others_with_a_clear_error(scene, tmp_path, fault):
    env = {"RETINEXGS_TEST_DIE_AT_STEP" if fault == "die" else "RETINEXGS_TEST_HANG_AT_STEP": "2",
           "RETINEXGS_DIST_TIMEOUT": "3"}
    res, seconds = torchrun(train_args(scene, tmp_path / "run"), extra_env=env, timeout=120)
    err = res.stderr
    assert res.returncode != 0
    assert f"rank 1 of 2 {'exits' if fault == 'die' else 'hangs'} at step 2" in err
    if fault == "hang":  # rank 0 waited for rank 1's gradients no longer than the timeout
        assert "rank 0 of 2: the gradient all-reduce of step 2 failed: no answer within 3 s" in err, err
    else:  # rank 0 saw the closed connection, torchrun stopped it first, or (a loaded machine) its timeout came
        assert ("rank 0 of 2: the gradient all-reduce of step 2 failed: another rank stopped" in err
                or "terminated (rank 0 of 2: torchrun stops every rank once one fails" in err
                or "rank 0 of 2: the gradient all-reduce of step 2 failed: no answer within 3 s" in err), err
        assert "exitcode  : 3" in err  # torchrun's summary names the rank that exited, and how
    assert str(ROOT / "retinexgs") not in err  # one paragraph per rank, no traceback of ours
    assert seconds < 90


def test_the_gpus_option(scene, tmp_path, capsys):
    assert strip_gpus(["train", "--gpus", "2", "--data", "s"]) == ["train", "--data", "s"]
    assert strip_gpus(["train", "--gpus=4", "--out", "o"]) == ["train", "--out", "o"]
    assert strip_gpus(["train", "--gpu", "4", "--set", "steps=3"]) == ["train", "--set", "steps=3"]
    code, _, err = run_cli(["train", "--data", scene, "--out", tmp_path / "x", "--gpus", "0"], capsys)
    assert code == 2 and "--gpus must be a number of GPUs >= 1" in err
    code, _, err = run_cli(["train", "--data", scene, "--out", tmp_path / "x", "--gpus", "2", "--device", "cuda:1"],
                           capsys)
    assert code == 2 and "the ranks use cuda:0..1" in err
    if not torch.cuda.is_available():
        code, _, err = run_cli(["train", "--data", scene, "--out", tmp_path / "x", "--gpus", "2"], capsys)
        assert code == 2 and "torch sees no CUDA GPU" in err and "--device cpu" in err
    else:
        n = torch.cuda.device_count() + 1
        code, _, err = run_cli(["train", "--data", scene, "--out", tmp_path / "x", "--gpus", str(n)], capsys)
        assert code == 2 and f"only {n - 1} GPU(s) are visible" in err
    assert not (tmp_path / "x").exists()


def test_learning_rates_scale_with_the_batch(scene, tmp_path, one_thread):
    from retinexgs.data import load_scene
    from retinexgs.run.config import load_config
    from retinexgs.train.trainer import Trainer

    assert lr_batch_factor("sqrt", 1) == lr_batch_factor("linear", 1) == 1.0
    assert (lr_batch_factor("sqrt", 4), lr_batch_factor("linear", 4), lr_batch_factor("none", 4)) == (2.0, 4.0, 1.0)
    s = load_scene(scene)

    def rates(*extra):
        cfg = load_config(["demo"], OVERRIDES + list(extra))
        tr = Trainer(cfg, s, tmp_path / "t", "cpu", progress=False, log=lambda m: None)
        tr.train_step(1, [tr.views[0], tr.views[1]] if tr.batch_size > 1 else tr.views[0])
        return {g["name"]: g["lr"] for g in tr.optimizer.param_groups}

    one = rates()
    for mode, factor in (("sqrt", 2.0), ("linear", 4.0), ("none", 1.0)):
        four = rates("train.views_per_rank=4", f"train.lr_batch_scaling={mode}")
        assert four.keys() == one.keys()
        for name in one:  # the position's schedule included (set at each step)
            assert four[name] == pytest.approx(one[name] * factor, rel=1e-12), (mode, name)


def test_adam_betas_follow_the_batch_and_a_resume_takes_its_own(scene, tmp_path, one_thread):
    from retinexgs.data import load_scene
    from retinexgs.run.config import load_config
    from retinexgs.train.distributed import adam_betas_for_batch
    from retinexgs.train.trainer import Trainer

    assert adam_betas_for_batch("power", 1) == adam_betas_for_batch("none", 4) == (0.9, 0.999)
    assert adam_betas_for_batch("power", 4) == pytest.approx((0.9 ** 4, 0.999 ** 4), rel=1e-15)
    with pytest.raises(ValueError, match="momentum_batch_scaling"):
        adam_betas_for_batch("sqrt", 2)
    s = load_scene(scene)

    def betas(run, resume, *extra):
        run.mkdir(exist_ok=True)
        cfg = load_config(["demo"], OVERRIDES + ["steps=2", "train.momentum_batch_scaling=power"] + list(extra))
        tr = Trainer(cfg, s, run, "cpu", resume=resume, progress=False, log=lambda m: None)
        if not resume:
            tr.train()
        return {tuple(g["betas"]) for g in tr.optimizer.param_groups}

    # Written with a batch of 4 (betas 0.9^4, 0.999^4), resumed with a batch of 1: torch's betas again.
    assert betas(tmp_path / "r", False, "train.views_per_rank=4") == {adam_betas_for_batch("power", 4)}
    assert betas(tmp_path / "r", True, "train.views_per_rank=1") == {(0.9, 0.999)}


def _sync_worker(rank, world, port, out):
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world),
                      LOCAL_RANK=str(rank))
    torch.set_num_threads(1)
    from retinexgs.train.distributed import init_from_env

    d, device = init_from_env("cpu")
    g = torch.Generator().manual_seed(rank)
    n = 5 + 2 * rank  # rank 1 decided differently: more Gaussians, other values
    model = GaussianModel.from_points(torch.rand(n, 3, generator=g), torch.rand(n, 3, generator=g), 1, 0.1)
    groups = [{"params": [getattr(model, name)], "name": name, "lr": 1e-2} for name in PARAM_NAMES]
    opt = torch.optim.Adam(groups)
    sum(p.square().sum() for p in model.parameters()).backward()
    opt.step()
    agreed = d.sync_gaussians(model, opt, step=1)
    moments = [opt.state[getattr(model, name)][k] for name in PARAM_NAMES for k in ("exp_avg", "exp_avg_sq")]
    after = d.agree([getattr(model, name) for name in PARAM_NAMES] + moments, "the test's tensors")
    if rank == 1:  # the same count, one value off: seen, then replaced
        with torch.no_grad():
            model.means[2, 1] += 1e-3
    again = [d.sync_gaussians(model, opt, step=s) for s in (2, 3)]
    Path(out, f"{rank}.json").write_text(json.dumps({"agreed": agreed, "after": after, "n": len(model),
                                                     "again": again}))
    d.close(True)


def test_rank_zeros_gaussians_replace_diverged_ones(tmp_path):
    """The safety net behind the identical decisions: after a density event the ranks compare their Gaussians
    (a difference is seen) and rank 0's parameters and Adam moments are broadcast, resizing a rank whose count
    differs."""
    import torch.multiprocessing as mp

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    mp.spawn(_sync_worker, args=(2, port, str(tmp_path)), nprocs=2, join=True)
    rows = [json.loads((tmp_path / f"{r}.json").read_text()) for r in range(2)]
    assert rows == [{"agreed": False, "after": True, "n": 5, "again": [False, True]}] * 2


def test_two_ranks_stream_their_views_as_they_preload_them(scene, two_ranks, tmp_path, capsys):
    """Views streamed from the shared view store (rank 0 writes it, the others wait and open it; each prefetches
    its own next views) train exactly as preloaded ones; a batch of several views on one rank is refused when the
    views stream (a streamed view lives one step on the device)."""
    run = tmp_path / "streamed"
    res, _ = torchrun(train_args(scene, run, ["train.stream_views=always",
                                              f"data.cache_dir={tmp_path / 'cache'}"]))
    assert res.returncode == 0, res.stdout + res.stderr
    assert "views: streamed" in res.stdout and res.stdout.count("writing the view store") == 1, res.stdout
    # Not bit for bit on the CPU's eager path: the packed targets are summed in another order (tests/test_view_store.py)
    assert_same_training(final_state(run), final_state(two_ranks))
    code, out, err = run_cli(train_args(scene, tmp_path / "refused", ["train.stream_views=always",
                                                                      "train.views_per_rank=2"]), capsys)
    assert code == 2 and "train.views_per_rank=2 needs the training views on the device" in err, err


def test_four_ranks_train_as_one_rank_with_four_views_a_step(scene, tmp_path):
    """Any rank count (issue 35 asks for 4 on the CPU): 4 gloo ranks, one view each, train as one rank taking the
    4 views of each step; the densification and the sharded evaluation (2 test views over 4 ranks) included."""
    four = tmp_path / "four"
    res, _ = torchrun(train_args(scene, four), nproc=4, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "4 ranks (gloo), 4 views a step" in res.stdout
    one = tmp_path / "one"
    plain_run(scene, one, ["train.views_per_rank=4"])
    a, b = final_state(four), final_state(one)
    assert (a["ranks"], a["views_per_step"], b["views_per_step"]) == (4, 4, 4)
    # Four summands are added in another order by the all-reduce than on one rank (float addition does not
    # associate), and Adam turns a few near-zero gradients' last bits into steps of the other sign: the same
    # decisions (every shape, the view order) and the bulk of every parameter alike, not every bit.
    assert a["step"] == b["step"] and a["order"] == b["order"]
    for k in a["model"]:
        x, y = a["model"][k].float(), b["model"][k].float()
        assert x.shape == y.shape, k
        rel = ((x - y).abs() / (y.abs() + 1e-6)).flatten()
        assert rel.median() <= 1e-4, (k, float(rel.median()))
    ma = json.loads((four / "metrics.json").read_text())
    mb = json.loads((one / "metrics.json").read_text())
    assert [r["view"] for r in ma["views"]] == [r["view"] for r in mb["views"]]
    assert ma["mean"]["psnr"] == pytest.approx(mb["mean"]["psnr"], abs=0.01)


# ---- several machines (issue 51): torchrun --nnodes, simulated on one host -----------------------------------------

def test_a_folder_a_rank_cannot_see_is_named_with_the_ranks_and_hosts(tmp_path):
    from retinexgs.train.distributed import shared_folder_problem

    assert shared_folder_problem(tmp_path, "the run folder", [(True, "a"), (True, "b")]) == ""
    msg = shared_folder_problem(tmp_path, "the run folder", [(True, "node-a"), (True, "node-a"), (False, "node-b"),
                                                             (False, "node-b")])
    assert msg.startswith(f"the run folder {tmp_path} is not shared by every rank: ranks 2, 3 (on node-b)")
    assert "(on node-a)" in msg and "--set data.cache_dir=DIR" in msg and "--out" in msg


def test_two_machines_of_one_rank_each_train_as_two_ranks_of_one_machine(scene, two_ranks, tmp_path):
    """Two torchrun launchers, --nnodes 2 --node_rank 0/1, one process each, meeting at a c10d rendezvous on
    this host: RANK differs from LOCAL_RANK (0 on both "machines"), which a one-machine run never shows. The run
    must be the two-rank run of one machine (both machines see one file system here, so the shared-folder check
    passes)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    run = tmp_path / "run"
    procs = []
    for node in (0, 1):
        cmd = [sys.executable, "-m", "torch.distributed.run", "--nnodes", "2", "--node_rank", str(node),
               "--nproc_per_node", "1", "--rdzv_backend", "c10d", "--rdzv_endpoint", f"127.0.0.1:{port}",
               "--rdzv_id", "retinexgs-test", "-m", "retinexgs", *map(str, train_args(scene, run))]
        procs.append(subprocess.Popen(cmd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                      text=True, cwd=ROOT))
    outs = []
    try:
        for p in procs:
            outs.append(p.communicate(timeout=240)[0])
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    assert all(p.returncode == 0 for p in procs), "\n".join(outs)
    assert "2 ranks (gloo), 2 views a step" in "\n".join(outs)
    assert_same_training(final_state(run), final_state(two_ranks))
    assert not list(run.glob(".rank0-*")), "rank 0's probe file is removed"
