"""The strategy protocol (retinexgs/strategy/base.py) and the MCMC strategy (retinexgs/strategy/mcmc.py):
``density.kind`` picks the class; MCMC's relocation keeps the look of the Gaussian it splits (eq. 9), leaves no dead
Gaussian behind, grows by ``growth`` up to ``cap_max``, restarts the moved Gaussians' Adam moments, and trains and
resumes through the trainer like the default."""
import math

import pytest
import torch

from retinexgs.errors import UserError
from retinexgs.model.gaussians import GaussianModel
from retinexgs.model.schedule import build_schedule
from retinexgs.run.config import load_config
from retinexgs.strategy import STRATEGIES, DefaultStrategy, MCMCStrategy, Strategy, build_strategy, relocation
from retinexgs.train.trainer import Trainer
from test_train import scene_dir, trainer_for  # noqa: F401  (the fixture)


def test_density_kind_picks_the_registered_class_and_refuses_unknown_names():
    assert {"default", "mcmc"} <= set(STRATEGIES)
    for kind, cls in (("default", DefaultStrategy), ("mcmc", MCMCStrategy)):
        cfg = load_config([], [f"density.kind={kind}"])
        s = build_strategy(cfg.density, 1.0, build_schedule(cfg))
        assert type(s) is cls and isinstance(s, Strategy)
    with pytest.raises(UserError, match="density.kind must be one of"):
        load_config([], ["density.kind=nope"])


@pytest.mark.parametrize("opacity", [0.05, 0.4, 0.9, 0.995])
@pytest.mark.parametrize("n", [1, 2, 3, 7, 30])
def test_relocation_keeps_the_composite_opacity_and_its_integral(opacity, n):
    # N copies alpha-composited at one place: 1 - (1 - o' g)^N. Its peak must be o, and its integral along an axis
    # o·σ·√(2π), the original's (the paper's eq. 9 is exactly this condition).
    o = torch.tensor([opacity], dtype=torch.float64)
    s = torch.tensor([[0.7, 1.3, 0.2]], dtype=torch.float64)
    o_new, s_new = relocation(o, s, torch.tensor([n]))
    assert 1 - (1 - float(o_new)) ** n == pytest.approx(opacity, rel=1e-9)
    for axis in range(3):
        x = torch.linspace(-12, 12, 40001, dtype=torch.float64) * float(s[0, axis])
        g = torch.exp(-0.5 * (x / float(s_new[0, axis])) ** 2)
        composite = 1 - (1 - float(o_new) * g) ** n
        integral = torch.trapezoid(composite, x)
        assert float(integral) == pytest.approx(opacity * float(s[0, axis]) * math.sqrt(2 * math.pi), rel=1e-6)
    if n == 1:
        assert torch.allclose(o_new, o) and torch.allclose(s_new, s)


def _mcmc(overrides=()):
    cfg = load_config([], ["density.kind=mcmc", "steps=100", "density.start=10", "density.every=10",
                           "density.stop=50", *overrides])
    return cfg, build_strategy(cfg.density, 1.0, build_schedule(cfg), seed=0)


def _model_and_adam(n=50, dead=(3, 7, 8)):
    torch.manual_seed(0)
    g = GaussianModel.from_points(torch.randn(n, 3), torch.rand(n, 3), sh_degree=1, init_opacity=0.5)
    with torch.no_grad():
        g.opacity_logits.copy_(torch.logit(torch.rand(n) * 0.8 + 0.1))
        g.opacity_logits[list(dead)] = torch.logit(torch.tensor(0.001))
    opt = torch.optim.Adam([{"params": [p], "name": name, "lr": 1e-3} for name, p in g.tensors().items()])
    g.means.sum().add(g.opacities.sum()).add(g.log_scales.sum()).backward()
    opt.step()
    return g, opt


def test_mcmc_relocates_the_dead_grows_and_restarts_their_moments():
    cfg, s = _mcmc(["density.mcmc.growth=0.1"])
    g, opt = _model_and_adam()
    before = {k: v.detach().clone() for k, v in g.tensors().items()}
    assert not s.edits_at(15) and s.step(15, g, opt, 64) == ""
    assert s.edits_at(20)
    note = s.step(20, g, opt, 64)
    assert note == "mcmc: 3 relocated, +5 added"
    assert len(g) == 55
    assert bool((g.opacities >= cfg.density.mcmc.min_opacity - 1e-7).all())
    # A relocated slot is a copy of a live Gaussian: its SH and rotation are some live Gaussian's.
    for i in (3, 7, 8):
        match = (before["sh_dc"] == g.sh_dc.detach()[i]).all(-1).all(-1)
        assert bool(match.any()) and not bool(match[[3, 7, 8]].any())
    # Untouched Gaussians kept parameters and moments; the moved ones' moments restart at zero.
    for group in opt.param_groups:
        p = group["params"][0]
        assert p is getattr(g, group["name"])
        st = opt.state[p]
        if group["name"] not in ("means", "opacity_logits", "log_scales"):
            assert not st  # no gradient reached it: no moments to move
            continue
        assert st["exp_avg"].shape == p.shape
        assert bool((st["exp_avg"][[3, 7, 8]] == 0).all()) and bool((st["exp_avg"][50:] == 0).all())
    changed = (g.opacity_logits.detach()[:50] != before["opacity_logits"]).nonzero().squeeze(-1).tolist()
    untouched = [i for i in range(50) if i not in changed]
    assert untouched and torch.equal(g.means.detach()[untouched], before["means"][untouched])


def test_mcmc_stops_growing_at_the_cap_and_noise_moves_only_the_transparent():
    _, s = _mcmc(["density.mcmc.cap_max=52", "density.mcmc.min_opacity=0.005"])
    g, opt = _model_and_adam(dead=())
    s.step(20, g, opt, 64)
    assert len(g) == 52
    with torch.no_grad():
        g.opacity_logits[:] = torch.logit(torch.tensor(0.9))
        g.opacity_logits[0] = torch.logit(torch.tensor(1e-4))
    means = g.means.detach().clone()
    s.after_optimizer_step(g, opt, 21)
    moved = (g.means.detach() - means).norm(dim=-1)
    assert float(moved[0]) > 0 and float(moved[1:].max()) < 1e-12 * max(1.0, float(moved[0]))


def test_mcmc_adds_its_regulariser_to_the_loss(scene_dir, tmp_path):
    tr = trainer_for(scene_dir, tmp_path / "run", ["density.kind=mcmc"])
    res = tr.render_view(tr.views[0], 1, graphed=False)
    terms = tr.objective.loss(res, tr.views[0], 1)
    g = tr.model.gaussians
    expected = 0.01 * g.opacities.mean() + 0.01 * g.scales.mean()
    assert float(terms["density"]) == pytest.approx(float(expected.detach()), rel=1e-6)
    default = trainer_for(scene_dir, tmp_path / "run2")
    assert "density" not in default.objective.loss(default.render_view(default.views[0], 1, graphed=False),
                                         default.views[0], 1)


def test_mcmc_trains_and_resumes_through_the_trainer(scene_dir, tmp_path):
    run = tmp_path / "run"
    tr = trainer_for(scene_dir, run, ["density.kind=mcmc", "density.mcmc.min_opacity=0.3"])
    n0 = len(tr.model.gaussians)
    tr.train(stop_after=3)
    assert len(tr.model.gaussians) > n0  # the density steps 2 (and 4) grew it
    resumed = Trainer(tr.cfg, tr.scene, run, "cpu", resume=True, progress=False, log=lambda s: None)
    resumed.train()
    straight = trainer_for(scene_dir, tmp_path / "straight", ["density.kind=mcmc", "density.mcmc.min_opacity=0.3"])
    straight.train()
    for k, v in straight.model.state_dict().items():
        torch.testing.assert_close(resumed.model.state_dict()[k], v, rtol=1e-4, atol=1e-5, msg=k)
