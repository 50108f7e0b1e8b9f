"""Training on a tiny generated scene: parameter updates, the loss schedule, checkpoints/resume, the demo
pipeline end to end, and the bad-input cases of issue 6."""
import json
import shutil

import numpy as np
import pytest
import torch

from retinexgs.data import load_scene
from retinexgs.demo.synthetic import make_demo_scene
from retinexgs.errors import UserError
from retinexgs.run.config import load_config
from retinexgs.evaluate.evaluate import eval_run
from retinexgs.run.folder import load_run
from retinexgs.train.runner import train_run
from retinexgs.model.retinex_model import RetinexGSModel
from retinexgs.train.trainer import Trainer, TrainingDiverged

TINY = ["steps=6", "checkpoint.every=3", "log.every=1", "log.tensorboard=false", "model.sh_degree=1",
        "model.sh_degree_every=2", "model.max_init_points=300", "loss.enhance_from=4", "density.start=1",
        "density.every=2", "density.stop=5", "decomposer.method=lime"]


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return make_demo_scene(tmp_path_factory.mktemp("scene") / "demo", n_train=4, n_test=2, width=40, height=30,
                           n_points=400)


def trainer_for(scene_dir, run, overrides=(), method="retinexgs"):
    cfg = load_config(["demo"], list(TINY) + [f"method={method}"] + list(overrides))
    scene = load_scene(scene_dir)
    run.mkdir(parents=True, exist_ok=True)
    return Trainer(cfg, scene, run, "cpu", progress=False, log=lambda s: None)


def test_one_step_changes_every_parameter_group(scene_dir, tmp_path):
    tr = trainer_for(scene_dir, tmp_path / "run", ["loss.enhance_from=1", "density.start=100",
                                                   "model.sh_degree_every=1", "loss.enhance_trains_scene=true"])
    with torch.no_grad():  # anisotropic Gaussians (rotation matters) and non-zero higher-order SH
        tr.model.gaussians.log_scales.add_(torch.randn_like(tr.model.gaussians.log_scales) * 0.3)
        tr.model.gaussians.sh_rest.normal_(0, 0.05)
    before = {n: p.detach().clone() for n, p in tr.model.named_parameters()}
    tr.step = 2
    tr.train_step(2, tr.views[0])
    changed = {n for n, p in tr.model.named_parameters() if not torch.equal(p.detach(), before[n])}
    groups = {"gaussians.means", "gaussians.quats", "gaussians.log_scales", "gaussians.opacity_logits",
              "gaussians.sh_dc", "gaussians.sh_rest"}
    assert groups <= changed, groups - changed
    assert any(n.startswith("illumination.") for n in changed)
    assert any(n.startswith("enhancement.") for n in changed)


def test_enhancement_loss_trains_only_the_enhancement_net_by_default(scene_dir, tmp_path):
    tr = trainer_for(scene_dir, tmp_path / "run", ["loss.enhance_from=1"])
    res = tr.model.render(tr.views[0].camera, 0, depth=tr.depth_prior)
    terms = tr.objective.loss(res, tr.views[0], step=5)
    enh = tr.cfg.loss.w_exp * terms["exp"]
    enh.backward()
    assert tr.model.gaussians.means.grad is None or float(tr.model.gaussians.means.grad.abs().sum()) == 0
    assert any(float(p.grad.abs().sum()) > 0 for p in tr.model.enhancement.parameters() if p.grad is not None)


def test_enhancement_losses_switch_on_at_enhance_from(scene_dir, tmp_path):
    tr = trainer_for(scene_dir, tmp_path / "run")
    res = tr.model.render(tr.views[0].camera, 0, depth=tr.depth_prior)
    before = tr.objective.loss(res, tr.views[0], step=3)
    after = tr.objective.loss(res, tr.views[0], step=4)
    assert not {"spa", "exp", "col"} & set(before)
    assert {"spa", "exp", "col"} <= set(after)
    extra = tr.cfg.loss.w_spa * after["spa"] + tr.cfg.loss.w_exp * after["exp"] \
        + tr.cfg.loss.w_col * after["col"]
    torch.testing.assert_close(after["total"], before["total"] + extra)


def test_the_loss_log_carries_the_exposure_meters_target(scene_dir, tmp_path):
    """``exp_E`` (logged, not summed) is L_exp's target: 0.5, or the highlight meter's capped mean."""
    from retinexgs.train import losses
    from retinexgs.train.trainer import enhancement_objective

    tr = trainer_for(scene_dir, tmp_path / "run")
    c = tr.cfg.loss
    H, W = 30, 40
    R, L = torch.full((H, W, 3), 0.5), torch.full((H, W, 3), 0.02)  # the rendered light is RGB
    R[: H // 5], L[: H // 5] = 1.0, 0.4  # a fifth of the frame 40x brighter: metered to 0.5 it would blow out
    S_b = (R * L).permute(2, 0, 1).unsqueeze(0)
    total, terms = enhancement_objective(tr.model, c, R, L, S_b)
    want = losses.exposure_target(c, tr.model.tone, R * L, tr.model.shoulder)
    assert float(terms["exp_E"]) == pytest.approx(float(want)) and float(terms["exp_E"]) < c.exposure_E - 0.05
    parts = c.w_spa * terms["spa"] + c.w_exp * terms["exp"] + c.w_col * terms["col"]
    assert float(total.detach()) == pytest.approx(float(parts.detach()))  # exp_E is not part of the sum
    _, plain = enhancement_objective(tr.model, c.model_copy(update={"exp_highlight_share": 0.0}), R, L, S_b)
    assert float(plain["exp_E"]) == c.exposure_E
    res = tr.model.render(tr.views[0].camera, 0, depth=tr.depth_prior)
    assert "exp_E" in tr.objective.loss(res, tr.views[0], step=4) and "exp_E" not in tr.objective.loss(res, tr.views[0], step=3)


def test_checkpoint_resume_gives_the_same_parameters(scene_dir, tmp_path):
    run = tmp_path / "run"
    tr = trainer_for(scene_dir, run)
    tr.train(stop_after=3)
    saved = {k: v.clone() for k, v in tr.model.state_dict().items()}
    resumed = Trainer(tr.cfg, tr.scene, run, "cpu", resume=True, progress=False, log=lambda s: None)
    assert resumed.step == 3
    for k, v in resumed.model.state_dict().items():
        assert torch.equal(v, saved[k]), k
    # Training on from the checkpoint matches training straight through.
    resumed.train()
    straight = trainer_for(scene_dir, tmp_path / "straight")
    straight.train()
    for k, v in straight.model.state_dict().items():
        torch.testing.assert_close(resumed.model.state_dict()[k], v, rtol=1e-4, atol=1e-5, msg=k)


def test_train_run_end_to_end_and_eval(scene_dir, tmp_path):
    run = tmp_path / "run"
    metrics = train_run(scene_dir, run, ["demo"], TINY, "cpu", progress=False, log=lambda s: None)
    assert (run / "config.yaml").is_file() and (run / "metrics.json").is_file()
    assert len(list((run / "renders" / "test").glob("*.png"))) == 2
    assert metrics["mean"]["psnr"] > 0 and 0 < metrics["mean"]["ssim"] <= 1
    # the GT-mean figures beside the plain ones, per view and in the mean
    for row in metrics["views"]:
        assert row["psnr_gt_mean"] > 0 and 0 < row["ssim_gt_mean"] <= 1
    assert metrics["mean"]["psnr_gt_mean"] == pytest.approx(np.mean([r["psnr_gt_mean"] for r in metrics["views"]]))
    # the colour error split: the light alone, and the tone's own cost on the truth (both ≥ 0, in every view)
    assert all(r["delta_e_linear"] >= 0 and r["delta_e_tone_floor"] >= 0 for r in metrics["views"])
    assert json.loads((run / "metrics.json").read_text())["mean"]["psnr"] == pytest.approx(metrics["mean"]["psnr"])
    again = eval_run(run, "cpu", log=lambda s: None)
    assert again["mean"]["psnr"] == pytest.approx(metrics["mean"]["psnr"], abs=1e-6)
    assert again["mean"]["delta_e_linear"] == pytest.approx(metrics["mean"]["delta_e_linear"], abs=1e-6)
    cfg, scene, model, step = load_run(run, "cpu")
    assert step == 6 and len(model.gaussians) > 0


@pytest.mark.parametrize("method", ["3dgs", "pre", "post"])
def test_baselines_run(scene_dir, tmp_path, method):
    metrics = train_run(scene_dir, tmp_path / method, ["demo"], TINY + [f"method={method}"], "cpu",
                        progress=False, log=lambda s: None)
    assert metrics["mean"]["psnr"] > 0


def test_existing_run_folder_is_refused(scene_dir, tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "mine.txt").write_text("keep me")
    with pytest.raises(UserError, match="already exists"):
        train_run(scene_dir, run, ["demo"], TINY, "cpu", progress=False, log=lambda s: None)
    assert (run / "mine.txt").read_text() == "keep me"


def test_scene_without_test_views_trains_and_says_why(scene_dir, tmp_path):
    scene = tmp_path / "notest"
    shutil.copytree(scene_dir, scene)
    (scene / "transforms_test.json").unlink()
    split = scene / "split.json"
    if split.exists():
        data = json.loads(split.read_text())
        data["test"] = []
        split.write_text(json.dumps(data))
    logs = []
    metrics = train_run(scene, tmp_path / "run", ["demo"], TINY, "cpu", progress=False, log=logs.append)
    assert metrics is None
    assert any("evaluation skipped" in line for line in logs)
    assert "skipped" in json.loads((tmp_path / "run" / "metrics.json").read_text())


def test_nan_loss_stops_with_the_term_and_step(scene_dir, tmp_path, monkeypatch):
    run = tmp_path / "run"
    tr = trainer_for(scene_dir, run)
    tr.train(stop_after=3)  # checkpoint at step 3
    good = sorted((run / "checkpoints").glob("*.pt"))
    real_loss = tr.objective.loss

    def poisoned(res, tv, step):
        terms = real_loss(res, tv, step)
        terms["tv"] = terms["tv"] * float("nan")
        terms["total"] = terms["total"] + terms["tv"]
        return terms

    monkeypatch.setattr(tr.objective, "loss", poisoned)
    with pytest.raises(TrainingDiverged, match=r"tv .* step 4"):
        tr.train()
    assert sorted((run / "checkpoints").glob("*.pt")) == good
    assert Trainer(tr.cfg, tr.scene, run, "cpu", resume=True, progress=False, log=lambda s: None).step == 3


def test_bad_config_values_are_named(tmp_path):
    with pytest.raises(UserError, match="unknown config key"):
        load_config(overrides=["loss.w_typo=1"])
    with pytest.raises(UserError, match="method"):
        load_config(overrides=["method=magic"])
    bad = tmp_path / "bad.yaml"
    bad.write_text("loss: [1, 2\n")
    with pytest.raises(UserError, match="bad.yaml"):
        load_config([str(bad)])


def test_cli_resume_needs_no_data_and_train_without_data_is_refused(scene_dir, tmp_path, capsys):
    from retinexgs.cli import main
    from retinexgs.run.checkpoint import latest_checkpoint

    run = tmp_path / "run"
    sets = [a for s in TINY + ["steps=3"] for a in ("--set", s)]
    assert main(["train", "--data", str(scene_dir), "--out", str(run), "--config", "demo", "--quiet",
                 "--device", "cpu", *sets]) == 0
    assert latest_checkpoint(run).name.endswith("3.pt") or "000003" in latest_checkpoint(run).name
    assert main(["train", "--out", str(run), "--resume", "--set", "steps=6", "--quiet", "--device", "cpu"]) == 0
    assert "000006" in latest_checkpoint(run).name or latest_checkpoint(run).name.endswith("6.pt")
    assert main(["train", "--out", str(tmp_path / "other"), "--quiet"]) == 2
    assert "--data SCENE is required" in capsys.readouterr().err
    assert not (tmp_path / "other").exists()


def test_enhancement_normalises_by_the_scene_illumination_level(scene_dir, tmp_path):
    """L_ref is the median over training views of a quantile of the prior L (default: its maximum), saved with
    the model, and the output is clip(R̂ ∘ (L̂/L_ref)^g, 0, 1) (clip(R̂^g ∘ (L̂/L_ref)^g, 0, 1) with tone "signal"):
    a gamma of 1 gives back R̂ where L̂ = L_ref. (Tone "exposure", the default, has its own tests: test_tone.py.)"""
    tr = trainer_for(scene_dir, tmp_path / "run", ["model.enhancement.tone=illumination"])
    per_view = torch.stack([tv.L.reshape(-1).max() for tv in tr.views])
    ref = float(tr.model.illum_ref)
    assert ref == pytest.approx(float(per_view.median()), rel=1e-6)
    p99 = trainer_for(scene_dir, tmp_path / "run99", ["model.enhancement.tone=illumination",
                                                      "model.enhancement.ref_quantile=0.99"])
    per_view = torch.stack([tv.L.reshape(-1).quantile(0.99) for tv in p99.views])
    assert float(p99.model.illum_ref) == pytest.approx(float(per_view.median()), rel=2e-2)
    assert float(p99.model.illum_ref) < ref
    paper = trainer_for(scene_dir, tmp_path / "run_paper", ["model.enhancement.tone=illumination",
                                                            "model.enhancement.ref_quantile=null",
                                                            "loss.rec_domain=photo"])  # no L_ref to expose by
    assert float(paper.model.illum_ref) == 1.0  # the paper's L_enh = L̂^g
    assert 0.0 < ref < 1.0 and "illum_ref" in tr.model.state_dict()
    R = torch.rand(5, 7, 3)
    L = torch.full((5, 7, 3), ref)
    assert torch.allclose(tr.model.enhance(R, L, gamma=1.0)["rgb"], R.clamp(0, 1), atol=1e-6)
    half = tr.model.enhance(R, L * 0.25, gamma=0.5)["rgb"]
    assert tr.model.tone.name == "illumination"
    assert torch.allclose(half, (R * 0.5).clamp(0, 1), atol=1e-5)
    # Tone "signal": the gamma acts on R̂ too, (R̂ · L̂/L_ref)^g.
    sig = trainer_for(scene_dir, tmp_path / "run_signal", ["model.enhancement.tone=signal"])
    sig.model.illum_ref.fill_(ref)
    half = sig.model.enhance(R, L * 0.25, gamma=0.5)["rgb"]
    assert torch.allclose(half, (R.clamp_min(1e-3) ** 0.5 * 0.5).clamp(0, 1), atol=1e-5)
    # With a gamma tone exposure scales the predicted gamma: < 1 brighter.
    Ld = L * 0.2
    bright, base = tr.model.enhance(R, Ld, exposure=0.5)["rgb"], tr.model.enhance(R, Ld)["rgb"]
    assert float(bright.detach().mean()) > float(base.detach().mean())


def test_exposure_on_the_illumination_sets_the_gamma_the_image_level_does_not(scene_dir, tmp_path):
    """The default meters L_exp on the whole enhanced image S_enh (a camera's averaging meter);
    ``exp_on: illumination`` on the enhanced light L_enh; the paper's placement on 16×16 patches of S_enh. Each
    term must match the loss functions on the corresponding maps."""
    from retinexgs.train import losses
    tr = trainer_for(scene_dir, tmp_path / "run", ["loss.enhance_from=1"])
    res = tr.model.render(tr.views[0].camera, 0, depth=tr.depth_prior)
    out = tr.model.enhance(res["R"].detach(), res["L"].detach())
    terms = tr.objective.loss(res, tr.views[0], step=5)
    c = tr.cfg.loss
    assert c.exp_on == "image" and c.exp_patch == 0 and c.exposure_E == 0.5
    want = float(out["rgb"].detach().mean() - c.exposure_E) ** 2
    assert float(terms["exp"].detach()) == pytest.approx(want, rel=1e-4)
    light = trainer_for(scene_dir, tmp_path / "run1", ["loss.enhance_from=1", "loss.exp_on=illumination"])
    res1 = light.model.render(light.views[0].camera, 0, depth=light.depth_prior)
    out1 = light.model.enhance(res1["R"].detach(), res1["L"].detach())
    want = float(out1["L_enh"].detach().mean() - c.exposure_E) ** 2
    assert float(light.objective.loss(res1, light.views[0], step=5)["exp"].detach()) == pytest.approx(want, rel=1e-4)
    img = trainer_for(scene_dir, tmp_path / "run2", ["loss.enhance_from=1", "loss.exp_on=image",
                                                  "loss.exp_patch=8"])
    res2 = img.model.render(img.views[0].camera, 0, depth=img.depth_prior)
    out2 = img.model.enhance(res2["R"].detach(), res2["L"].detach())
    t2 = img.objective.loss(res2, img.views[0], step=5)
    bchw = out2["rgb"].permute(2, 0, 1)[None]
    assert float(t2["exp"].detach()) == pytest.approx(float(losses.exposure_loss(bchw.detach(), c.exposure_E, 8)),
                                                rel=1e-4)


def test_paper_config_runs_end_to_end(scene_dir, tmp_path):
    """configs/paper.yaml (the paper as written: L_enhance end to end, L_SH summed, no L_ref) trains."""
    cfg = load_config(["paper", "demo"], list(TINY) + ["loss.enhance_from=2", "loss.enhance_trains_scene=true",
                                                       "loss.sh_reduction=sum", "model.enhancement.ref_quantile=null"])
    tr = Trainer(cfg, load_scene(scene_dir), tmp_path / "run", "cpu", progress=False, log=lambda s: None)
    (tmp_path / "run").mkdir(exist_ok=True)
    values = tr.train()
    assert {"spa", "exp", "col", "sh"} <= set(values) and all(map(lambda v: v == v, values.values()))
    paper = load_config(["paper"])
    assert paper.loss.sh_reduction == "sum" and paper.loss.enhance_trains_scene is True
    assert paper.loss.exp_on == "image" and paper.model.enhancement.ref_quantile is None


def test_mean_background_comes_from_the_priors_and_travels_with_the_run(scene_dir, tmp_path):
    """model.background "mean": the trainer sets it to the training views' mean R and L priors, the checkpoint
    carries it, and a re-evaluation from the run folder renders with it (the same scores)."""
    run = tmp_path / "run"
    metrics = train_run(scene_dir, run, ["demo"], TINY + ["steps=2"], "cpu", progress=False, log=lambda s: None)
    cfg, scene, model, step = load_run(run, "cpu")
    assert cfg.model.background == "mean" and model.has_background
    from retinexgs.retinex.cache import load_or_compute, scene_cache_root
    dcfg = cfg.decomposer
    priors = load_or_compute([v.image_path for v in scene.train], dcfg.method, dict(dcfg.params) or None,
                             cache_dir=scene_cache_root(scene.root, cfg.data.cache_dir), device="cpu",
                             progress=False)
    R = torch.stack([r.reshape(-1, 3).float().mean(0) for r, _ in priors]).mean(0)
    L = torch.stack([l.float().mean() for _, l in priors]).mean()
    torch.testing.assert_close(model.background, torch.cat([R, L.expand(3)]), rtol=1e-5, atol=1e-6)
    assert float(model.background.min()) > 0.01  # not black
    again = eval_run(run, "cpu", log=lambda s: None)
    assert again["mean"]["psnr"] == pytest.approx(metrics["mean"]["psnr"], abs=1e-6)
    # Over black (the default before it): no background buffer, so older checkpoints keep their keys.
    black = RetinexGSModel(model.gaussians, load_config(["ablations/background_black"]).model)
    assert not black.has_background and "background" not in black.state_dict()
