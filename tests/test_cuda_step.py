"""The training step's graphed image losses (retinexgs/train/graphs.py) against the eager step: the same loss
values and gradients for every shipped config, before and after the enhancement losses switch on. The
CPU tests run the graphed path's plumbing eagerly (``emulate_graphs``); the CUDA tests capture real graphs
(skipped without a GPU)."""
from pathlib import Path

import pytest
import torch

from retinexgs.data import load_scene
from retinexgs.demo.synthetic import make_demo_scene
from retinexgs.model.tone import srgb_to_linear
from retinexgs.train import losses
from retinexgs.config import configs_dir
from retinexgs.run.config import load_config
from retinexgs.train.noise import sigma_limit
from retinexgs.train.trainer import Trainer
from retinexgs.train.losses import to_bchw
from retinexgs.train.views import pad_edges, unpack_edges, unpack_targets
from scenes import needs_cuda

TINY = ["steps=20", "log.every=1", "log.tensorboard=false", "model.sh_degree=1", "model.sh_degree_every=2",
        "model.max_init_points=300", "loss.enhance_from=3", "density.start=100", "checkpoint.every=100"]


def shipped_configs():
    """Every config file in configs/ (the demo aside: it is the default with a smaller model)."""
    root = configs_dir()
    return [p.stem for p in sorted(root.glob("*.yaml")) if p.stem not in ("default",)] + \
        [f"ablations/{p.stem}" for p in sorted((root / "ablations").glob("*.yaml"))] + ["default"]


def config_overrides(name):
    cfg = load_config([] if name == "default" else [name])
    sets = list(TINY)
    # LIME: the same code path as LR3M, much faster on tiny views; LR3M's own parameters (a config that tunes
    # them, e.g. ablations/lr3m_beta_0.15) keep LR3M, which LIME would refuse.
    if cfg.decomposer.method == "lr3m" and not cfg.decomposer.params:
        sets.append("decomposer.method=lime")
    return [] if name == "default" else [name], sets


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return make_demo_scene(tmp_path_factory.mktemp("scene") / "demo", n_train=3, n_test=1, width=48, height=36,
                           n_points=400)


def make_trainer(scene_dir, run: Path, name: str, device: str, emulate: bool = False, extra=()):
    files, sets = config_overrides(name)
    cfg = load_config(files, sets + list(extra))
    run.mkdir(parents=True, exist_ok=True)
    tr = Trainer(cfg, load_scene(scene_dir), run, device, progress=False, log=lambda s: None, emulate_graphs=emulate)
    with torch.no_grad():  # non-trivial SH and anisotropy so that every gradient path carries something
        g = torch.Generator().manual_seed(1)
        tr.model.gaussians.sh_rest.copy_(torch.randn(tr.model.gaussians.sh_rest.shape, generator=g) * 0.05)
        tr.model.gaussians.log_scales.add_(torch.randn(tr.model.gaussians.log_scales.shape, generator=g).to(
            tr.model.gaussians.log_scales) * 0.2)
    return tr


def step_gradients(tr: Trainer, view: int, step: int, graphed: bool):
    """(loss values, gradients of every parameter) of one step's loss on view ``view``, through the graphed or
    the eager path; no optimiser step."""
    tr.optimizer.zero_grad(set_to_none=True)
    tv = tr.views[view]
    res = tr.render_view(tv, step, graphed=graphed)
    if graphed:
        terms = tr.objective.backward_graphed(tr.graphs, res, tv, step, tr._log_graph_failures)
        assert terms is not None, tr.graphs.failures
    else:
        terms = tr.objective.loss(res, tv, step)
        terms["total"].backward()
    values = {k: float(v.detach()) for k, v in terms.items()}
    grads = {n: (None if p.grad is None else p.grad.detach().clone()) for n, p in tr.model.named_parameters()}
    grads["means2d"] = res["out"].means2d.grad.detach().clone()
    tr.optimizer.zero_grad(set_to_none=True)
    return values, grads


def assert_same(eager, graphed, rtol, atol_frac):
    ev, eg = eager
    gv, gg = graphed
    assert list(ev) == list(gv), (list(ev), list(gv))  # the log's key order too
    for k in ev:
        assert gv[k] == pytest.approx(ev[k], rel=rtol, abs=1e-7), k
    assert eg.keys() == gg.keys()
    for k in eg:
        a, b = eg[k], gg[k]
        assert (a is None) == (b is None), f"{k}: a gradient on one path only"
        if a is None:
            continue
        scale = float(a.abs().max())
        assert torch.allclose(b, a, rtol=rtol, atol=atol_frac * scale + 1e-30), \
            f"{k}: max diff {float((a - b).abs().max())} of max {scale}"


def check_config(scene_dir, tmp_path, name, device, emulate):
    tr = make_trainer(scene_dir, tmp_path / name.replace("/", "_"), name, device, emulate=emulate)
    assert tr.graphs is not None
    before, after = 1, tr.schedule.enhance_from + 1
    assert not tr.schedule.enhance_at(before) and tr.schedule.enhance_at(after)
    for step in (before, after):
        for view in (0, 1, 0):  # a second view: the static inputs are refilled; then the first again
            eager = step_gradients(tr, view, step, graphed=False)
            graphed = step_gradients(tr, view, step, graphed=True)
            assert_same(eager, graphed, rtol=1e-4, atol_frac=1e-5)
            if tr.decomposed and tr.schedule.enhance_at(step):
                assert any(graphed[1][n] is not None for n in graphed[1] if n.startswith("enhancement."))
    return tr


# ---- CPU: the graphed path's plumbing, run eagerly --------------------------------------------------------------

@pytest.mark.parametrize("name", ["default", "paper", "ablations/no_priors", "ablations/baseline_3dgs",
                                  "ablations/baseline_pre", "ablations/no_sh", "ablations/tone_illumination",
                                  "ablations/exp_on_illumination", "ablations/scene_gamma",
                                  "ablations/rec_exposed", "ablations/rec_photo",
                                  "ablations/depth_smooth", "ablations/no_depth", "ablations/background_black"])
def test_graphed_path_matches_eager_on_cpu(scene_dir, tmp_path, name, one_thread):
    tr = check_config(scene_dir, tmp_path, name, "cpu", emulate=True)
    assert len(tr.graphs) == 0  # nothing captured on the CPU


def _force_fused(monkeypatch) -> list:
    """The fused supervision pass on the CPU (what the GPU runs: retinexgs/train/fused_loss.py, with the CPU
    kernel); returns the list its calls are counted in."""
    from retinexgs.model.tones import fused_curve
    from retinexgs.train import fused_loss
    monkeypatch.setattr(fused_curve, "runs_fused", lambda x: True)
    calls = []
    real = fused_loss.supervision_terms
    monkeypatch.setattr(fused_loss, "supervision_terms", lambda *a, **k: calls.append(1) or real(*a, **k))
    return calls


@pytest.mark.parametrize("name", shipped_configs())
def test_fused_supervision_matches_eager_on_cpu(scene_dir, tmp_path, name, one_thread, monkeypatch):
    """Every shipped config's graphed loss with the fused supervision pass where it applies, against the eager
    torch step: the same terms, in the log's order, and every parameter's gradient."""
    _force_fused(monkeypatch)
    check_config(scene_dir, tmp_path, name, "cpu", emulate=True)


@pytest.mark.parametrize("name,fuses", [("default", True), ("ablations/no_depth", True),
                                        ("ablations/no_priors", False), ("ablations/baseline_3dgs", False)])
def test_fused_supervision_is_taken_where_it_applies(scene_dir, tmp_path, name, fuses, one_thread, monkeypatch):
    calls = _force_fused(monkeypatch)
    tr = make_trainer(scene_dir, tmp_path / name.replace("/", "_"), name, "cpu", emulate=True)
    step_gradients(tr, 0, 1, graphed=True)
    assert bool(calls) == fuses


def test_graphed_training_loop_matches_eager_on_cpu(scene_dir, tmp_path, one_thread):
    """The whole loop (checks every few steps, densification, the enhancement switch, the SH degree growing)
    through the graphed path's plumbing ends where the eager loop ends, to accumulation-order noise."""
    sets = ["steps=40", "log.every=5", "model.sh_degree_every=0.25", "loss.enhance_from=10", "density.start=5",
            "density.every=8", "density.stop=30"]
    runs = {}
    for emulate in (False, True):
        tr = make_trainer(scene_dir, tmp_path / f"loop{emulate}", "default", "cpu", emulate=emulate, extra=sets)
        runs[emulate] = (tr.train(), len(tr.model.gaussians))
    (eager, n_eager), (graphed, n_graphed) = runs[False], runs[True]
    assert abs(n_eager - n_graphed) <= max(2, 0.01 * n_eager), (n_eager, n_graphed)
    assert eager.keys() == graphed.keys()
    for k in eager:
        if k not in ("seconds", "total_seconds"):  # timings
            assert graphed[k] == pytest.approx(eager[k], rel=1e-3, abs=1e-7), k


@pytest.mark.parametrize("name", ["default", "ablations/tone_illumination",
                                  "ablations/rec_exposed", "ablations/rec_photo",
                                  "ablations/no_depth", "ablations/noise_blind", "ablations/noise_share_10"])
def test_eager_loss_is_the_papers_sum(scene_dir, tmp_path, one_thread, name):
    """Trainer.loss (the reference of the graphed path) against the loss functions composed by hand:
    L_sup + w_tv·L_TV + w_sh·L_SH + L_enhance on the detached R̂, L̂ (the default; L_exp on the image, or on
    the enhanced light for the previous default), + w_depth·(depth prior) where it is on."""
    tr = make_trainer(scene_dir, tmp_path / "ref", name, "cpu")
    c = tr.cfg.loss
    assert tr.depth_prior == (name != "ablations/no_depth")
    tv = tr.views[1]
    res = tr.model.render(tv.camera, 1, depth=tr.depth_prior)
    terms = tr.objective.loss(res, tv, step=10)
    R_hat, L_hat, S = to_bchw(res["R"]), to_bchw(res["L"]), to_bchw(tv.S)
    # the reconstruction term's options: the g = 1 exposure is 1 / lin(L_ref)
    gain = 1.0 / srgb_to_linear(tr.model.illum_ref) if c.rec_domain != "photo" else None
    if gain is not None and c.rec_noise_floor:  # capped at the photos' noise floor (train/noise.py)
        gain = min(float(gain), tr.noise.capture_noise.gain_cap(sigma_limit(c.rec_noise_share)))
    sup, _ = losses.supervision_loss(R_hat, L_hat, to_bchw(tv.R), to_bchw(tv.L), S, c.w_r, c.w_l, c.w_s,
                                     c.lambda_ssim, gain, c.rec_domain == "exposed")
    out = tr.model.enhance(res["R"].detach(), res["L"].detach())
    E = losses.exposure_target(c, tr.model.tone, res["R"] * res["L"], tr.model.shoulder)
    enh, _ = losses.enhancement_loss(to_bchw(out["rgb"]), S, c.w_spa, c.w_exp, c.w_col, E,
                                     illumination=to_bchw(out["L_enh"]) if c.exp_on == "illumination" else None,
                                     exp_patch=c.exp_patch,
                                     exp_form=c.exp_form, spa_form=c.spa_form,
                                     scale_invariant=c.enhance_scale_invariant)
    want = sup + c.w_tv * losses.tv_loss(R_hat) + c.w_sh * losses.sh_sparsity_loss(
        tr.model.gaussians.sh_rest, c.sh_reduction) + enh
    if tr.depth_prior:
        out = res["out"]
        want = want + c.w_depth * losses.depth_smoothness_loss(
            to_bchw(out.depth), to_bchw(out.alpha), *losses.edge_weights(to_bchw(tv.R), c.depth_edge))
    assert float(terms["total"].detach()) == pytest.approx(float(want.detach()), rel=1e-6)
    depth = ["depth"] if tr.depth_prior else []
    assert list(terms) == ["sup_r", "sup_l", "sup_rec", "tv", "sh"] + depth + ["spa", "exp", "col", "exp_E", "total"]


def test_edge_weights_travel_with_the_packed_targets():
    g = torch.Generator().manual_seed(0)
    wx, wy = torch.rand(1, 1, 5, 6, generator=g), torch.rand(1, 1, 4, 7, generator=g)
    packed = torch.cat([torch.rand(5, 7, 7, generator=g), pad_edges(wx, wy)], dim=-1)
    ux, uy = unpack_edges(packed)
    assert torch.equal(ux, wx) and torch.equal(uy, wy)
    S, R, L = unpack_targets(packed, True, edges=True)
    assert torch.equal(torch.cat([S, R, L], -1), packed[..., :7])
    S, R, L = unpack_targets(packed[..., 4:], True, edges=True)  # S alone (no priors) and the edges
    assert R is None and L is None and torch.equal(S, packed[..., 4:7])


@pytest.mark.parametrize("name", ["default", "ablations/no_priors", "ablations/no_depth"])
def test_depth_prior_runs_inside_the_loss_graph(scene_dir, tmp_path, name, one_thread):
    """The depth prior's term is one of the graphed loss's terms (not eager beside it), fed by two more input
    channels; its edge weights are packed once per view, and the view's maps stay views of the packed tensor."""
    tr = make_trainer(scene_dir, tmp_path / "g", name, "cpu", emulate=True)
    tv = tr.views[0]
    res = tr.render_view(tv, 1)
    C = res["out"].image.shape[-1]
    assert tr.objective.graph_input(res).shape[-1] == C + (2 if tr.depth_prior else 0)
    result = tr.graphs.run(tr.objective.graph_input(res), tv.pack(True, tr.cfg.loss.depth_edge if tr.depth_prior
                                                        else None), False)
    assert ("depth" in result.names) == tr.depth_prior
    assert result.grad_image.shape[-1] == C + (2 if tr.depth_prior else 0)
    assert tv.S.data_ptr() == tv.packed.data_ptr()
    if tr.depth_prior:
        assert all(torch.equal(a, b) for a, b in zip(unpack_edges(tv.packed), tv.edges))


def test_graphs_are_off_on_the_cpu_and_by_the_switch(scene_dir, tmp_path):
    assert make_trainer(scene_dir, tmp_path / "a", "default", "cpu").graphs is None
    off = make_trainer(scene_dir, tmp_path / "b", "default", "cpu", emulate=True, extra=["train.cuda_graphs=false"])
    assert off.graphs is None


def check_prior_late(scene_dir, tmp_path, device, emulate):
    """loss.prior_late_views: a graph captured before loss.prior_late_from, replayed after it, reads the priors'
    new weights (the same values and gradients as the eager step), and the sum loses exactly that share of the
    priors' terms: n0 a quarter of the scene's views a point, × 1/4."""
    n = load_scene(scene_dir).views_per_point()
    assert n is not None and n >= 1
    tr = make_trainer(scene_dir, tmp_path / "late", "default", device, emulate=emulate,
                      extra=[f"loss.prior_late_views={n / 4}", "loss.prior_late_from=8"])
    assert tr.objective.prior_late_scale == pytest.approx(0.25)
    early, late = 4, 8  # both with the enhancement on and at SH degree 1: the same render
    assert not tr.schedule.prior_late_at(early) and tr.schedule.prior_late_at(late)
    runs = {}
    for step in (early, late, early):
        eager = step_gradients(tr, 0, step, graphed=False)
        graphed = step_gradients(tr, 0, step, graphed=True)
        assert_same(eager, graphed, rtol=1e-4, atol_frac=1e-5)
        runs[step] = eager[0]
    c = tr.cfg.loss
    e, la = runs[early], runs[late]
    assert la["sup_r"] == pytest.approx(e["sup_r"]) and la["sup_l"] == pytest.approx(e["sup_l"])
    drop = 0.75 * (c.w_r * e["sup_r"] + c.w_l * e["sup_l"])
    assert drop > 1e-4 and la["total"] == pytest.approx(e["total"] - drop, rel=1e-5, abs=1e-7)
    return tr


def test_late_prior_scale_is_n0_over_the_views_a_point():
    from retinexgs.train.objective import late_prior_scale
    assert late_prior_scale(9, 36.0) == pytest.approx(0.25)
    assert late_prior_scale(9, 9.0) == 1.0 and late_prior_scale(9, 4.0) == 1.0  # few views: the full weights
    assert late_prior_scale(0, 36.0) == 1.0 and late_prior_scale(9, None) == 1.0  # off; no SfM points


def test_prior_late_scale_reaches_the_graphed_loss_on_cpu(scene_dir, tmp_path, one_thread):
    check_prior_late(scene_dir, tmp_path, "cpu", emulate=True)


# ---- CUDA: captured graphs ----------------------------------------------------------------------------------------

@needs_cuda
@pytest.mark.parametrize("name", shipped_configs())
def test_cuda_graphed_losses_match_eager(scene_dir, tmp_path, name):
    tr = check_config(scene_dir, tmp_path, name, "cuda", emulate=False)
    assert not tr.graphs.failures, tr.graphs.failures
    assert len(tr.graphs) == 1  # one image size; the graph without the enhancement is freed once it is on
    assert not tr.channel_graphs.failures, tr.channel_graphs.failures
    assert tr.channel_graphs.captures >= 1
    centers = [tv.camera.center.to(tv.center) for tv in tr.views]
    assert all(torch.equal(tv.center, c) for tv, c in zip(tr.views, centers)), "a view's cached centre changed"


@needs_cuda
def test_cuda_prior_late_scale_reaches_the_captured_graph(scene_dir, tmp_path):
    tr = check_prior_late(scene_dir, tmp_path, "cuda", emulate=False)
    assert not tr.graphs.failures and len(tr.graphs) == 1  # one capture, replayed across the phase change


@needs_cuda
def test_cuda_graphed_training_matches_eager_training(scene_dir, tmp_path):
    """A few whole steps (a densification and the enhancement switch included) with and without graphs: the
    same loss values and Gaussian counts up to float32 accumulation-order noise (Adam's normalisation can turn
    a last-bit difference of a tiny gradient into a visible step, and a Gaussian at the densification
    threshold may go either way)."""
    extra = ["density.start=5", "density.every=6", "density.stop=9", "loss.enhance_from=4"]
    runs = {}
    for graphs in (True, False):
        tr = make_trainer(scene_dir, tmp_path / f"g{graphs}", "default", "cuda",
                          extra=extra + [f"train.cuda_graphs={str(graphs).lower()}"])
        torch.manual_seed(0)
        logs = [tr.train_step(step, tr.views[step % len(tr.views)]) for step in range(1, 11)]
        runs[graphs] = (logs, len(tr.model.gaussians))
        assert (tr.graphs is not None) == graphs
    (lg, ng), (le, ne) = runs[True], runs[False]
    assert abs(ng - ne) <= max(2, 0.01 * ne), (ng, ne)
    for step, (a, b) in enumerate(zip(lg, le), start=1):
        assert a.keys() == b.keys()
        for k in a:
            if k != "event":
                assert a[k] == pytest.approx(b[k], rel=1e-4 if step == 1 else 2e-2, abs=1e-6), (step, k)


@needs_cuda
@pytest.mark.parametrize("late", [False, True])
def test_cuda_step_has_no_host_sync_outside_checks(scene_dir, tmp_path, late):
    """torch's sync debug mode raises on a synchronising call: a non-check step may only read binning's pair
    count, which the extension reads itself (not through torch), so torch sees no sync at all. ``late``: the
    priors' weights change phase inside the quiet steps (loss.prior_late_views, from step 8)."""
    n = load_scene(scene_dir).views_per_point()
    extra = [f"loss.prior_late_views={n / 4}", "loss.prior_late_from=8"] if late else []
    tr = make_trainer(scene_dir, tmp_path / "sync", "default", "cuda", extra=extra)
    for step in range(1, 6):  # capture both graphs first (capture itself may sync)
        tr.train_step(step, tr.views[step % len(tr.views)], check=True)
    # Density and opacity-reset steps check by design (TINY's 20-step schedule resets opacities at step 6).
    quiet = [s for s in range(6, 20) if not (tr.schedule.densify_at(s) or tr.schedule.reset_at(s))][:3]
    for step in range(6, quiet[0]):
        tr.train_step(step, tr.views[step % len(tr.views)], check=True)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for step in quiet:
            tr.train_step(step, tr.views[step % len(tr.views)], check=False)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert len(quiet) == 3 and quiet == list(range(quiet[0], quiet[0] + 3))  # consecutive: no step skipped
    assert tr.check_finite(quiet[-1])["total"] > 0
    if late:  # the phase changed inside the quiet steps, and the late weights are in force
        assert not tr.schedule.prior_late_at(quiet[0]) and tr.schedule.prior_late_at(quiet[-1])
        assert float(tr.objective._sup_w[0]) == pytest.approx(0.25 * tr.cfg.loss.w_r)


@needs_cuda
def test_channel_graphs_recapture_leanly_after_a_densification_and_skip_short_spans(scene_dir, tmp_path):
    """The Gaussians' channel graphs are captured where they will be replayed at least MIN_REPLAYS times; after a
    densification they are re-captured without warm-up or cache flushes (capture_lean) and still give the eager
    path's values and gradients; a span shorter than MIN_REPLAYS runs eagerly, capturing nothing."""
    tr = make_trainer(scene_dir, tmp_path / "cg", "default", "cuda",
                      extra=["steps=1000", "density.start=2", "density.every=20", "density.stop=500",
                             "model.sh_degree_every=1000"])
    cg = tr.channel_graphs
    assert tr.schedule.steps_unchanged(1) == 20 >= cg.MIN_REPLAYS
    assert_same(step_gradients(tr, 0, 1, graphed=False), step_gradients(tr, 0, 1, graphed=True), 1e-4, 1e-5)
    assert cg.captures == 1 and not cg.failures
    n0 = len(tr.model.gaussians)
    for step in range(1, 21):  # the densification of step 20 makes new Gaussian tensors
        tr.train_step(step, tr.views[step % len(tr.views)], check=True)
    assert tr.schedule.densify_at(20) and len(tr.model.gaussians) != n0
    assert_same(step_gradients(tr, 1, 21, graphed=False), step_gradients(tr, 1, 21, graphed=True), 1e-4, 1e-5)
    assert cg.captures == 2 and cg.deferred == 0 and not cg.failures
    cg._key = None  # as if the Gaussians had just changed, 3 steps before the next densification
    g = tr.model.gaussians
    assert cg.run(tr.active_degree(37), tr.views[0].center, replays=tr.schedule.steps_unchanged(37)) is None
    assert cg.deferred == 1 and cg.captures == 2 and g is tr.model.gaussians
