"""L_enhance of the default configuration as two kernels (retinexgs/train/fused_enhance.py, rgs/enhance_loss.h): the
terms and their gradient in the tone's gain against the torch composition they replace (float64 to rounding, finite
differences), the objective's terms and the EnhancementNet's gradients unchanged, and where it does not apply."""
import pytest
import torch

from retinexgs.model.tones import fused_curve
from retinexgs.model.tones.fused_curve import tone_curve_reference
from retinexgs.render._backend import kernels
from retinexgs.train import fused_enhance, losses
from retinexgs.train.fused_enhance import enhance_loss
from retinexgs.train.losses import to_bchw


def scene(H, W, dtype=torch.float64, seed=0):
    """R̂∘L̂-like values (dark, some past white and below the sRGB knee) and a view."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand((H, W, 3), generator=g, dtype=dtype) ** 3 * 0.6
    x[::5, ::3] *= 0.02  # the curve's linear segment
    x[1::7, ::4] += 0.7  # past the shoulder's knee at k of a few
    s = torch.rand((H, W, 3), generator=g, dtype=dtype) * 0.1
    return x, s


def reference(x, s, k, E, knee, exp_l1, scale_invariant):
    """The torch composition (losses.enhancement_loss's three terms on the exposure tone's image)."""
    enh = to_bchw(tone_curve_reference(x, k, knee))
    orig = to_bchw(s)
    spa = losses.spatial_consistency_loss(enh, orig, form="zero_dce", scale_invariant=scale_invariant)
    exp = losses.exposure_loss(enh, E, 0, "l1" if exp_l1 else "l2")
    col = losses.color_constancy_loss(enh, "paper", scale_invariant=scale_invariant)
    return torch.stack([spa, exp, col])


@pytest.mark.parametrize("H,W", [(20, 28), (22, 31), (4, 4), (9, 5)])
@pytest.mark.parametrize("scale_invariant", [True, False])
@pytest.mark.parametrize("exp_l1,knee", [(False, 0.5), (True, 1.0), (False, 1.0)])
def test_terms_and_gain_gradient_match_the_torch_composition(H, W, scale_invariant, exp_l1, knee):
    x, s = scene(H, W)
    k0 = torch.tensor([3.0, 4.5, 6.0], dtype=torch.float64)
    E = torch.tensor([0.45], dtype=torch.float64)
    k = k0.clone().requires_grad_(True)
    want = reference(x, s, k, float(E), knee, exp_l1, scale_invariant)
    kf = k0.clone().requires_grad_(True)
    got = enhance_loss(x, s, kf, E, knee, exp_l1, scale_invariant)
    torch.testing.assert_close(got.detach(), want.detach(), rtol=1e-10, atol=1e-13)
    for t in range(3):  # each term's gradient in k, through autograd of the reference and the kernel's Jacobian
        gw, = torch.autograd.grad(want[t], k, retain_graph=True)
        gg, = torch.autograd.grad(got[t], kf, retain_graph=True)
        torch.testing.assert_close(gg, gw, rtol=1e-9, atol=1e-12)


def test_gain_gradient_by_finite_differences():
    x, s = scene(13, 18)
    E = torch.tensor([0.4], dtype=torch.float64)
    w = torch.tensor([0.1, 1.0, 0.5], dtype=torch.float64)
    k = torch.tensor([2.0, 3.0, 2.5], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda kk: (enhance_loss(x, s, kk, E, 0.5) * w).sum(), (k,), eps=1e-6,
                                    atol=1e-8, rtol=1e-6)


def test_float32_agrees_with_float64():
    x, s = scene(36, 64)
    k = torch.tensor([3.0, 4.0, 5.0], dtype=torch.float64)
    E = torch.tensor([0.5], dtype=torch.float64)
    f64 = kernels().enhance_loss(x, s, k, E, 4, 0.5, 0, 0, False, True)
    f32 = kernels().enhance_loss(x.float(), s.float(), k.float(), E.float(), 4, 0.5, 0, 0, False, True)
    torch.testing.assert_close(f32.double(), f64, rtol=2e-4, atol=1e-7)


def test_the_kernels_refuse_bad_shapes_in_one_line():
    x, s = scene(8, 8)
    k, E = torch.ones(3, dtype=torch.float64), torch.zeros(1, dtype=torch.float64)
    with pytest.raises(ValueError, match="enhance_loss needs 1 <= pool <= H, W"):
        kernels().enhance_loss(x[:3], s[:3], k, E, 4, 1.0, 0, 0, False, True)
    with pytest.raises(ValueError, match="s has shape"):
        kernels().enhance_loss(x, s[:4], k, E, 4, 1.0, 0, 0, False, True)
    with pytest.raises(ValueError, match="x must have shape"):
        kernels().enhance_loss(x[..., :2], s, k, E, 4, 1.0, 0, 0, False, True)


# ---- the objective's path ------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def trainer(tmp_path_factory):
    from retinexgs.data import load_scene
    from retinexgs.demo.synthetic import make_demo_scene
    from retinexgs.run.config import load_config
    from retinexgs.train.trainer import Trainer
    root = tmp_path_factory.mktemp("fe")
    scene_dir = make_demo_scene(root / "demo", n_train=3, n_test=1, width=44, height=30, n_points=300)
    cfg = load_config(["demo"], ["steps=4", "log.tensorboard=false", "model.max_init_points=300",
                                 "decomposer.method=lime"])
    return Trainer(cfg, load_scene(scene_dir), root / "run", "cpu", progress=False, log=lambda s: None)


def objective_grads(tr, fused, monkeypatch):
    from retinexgs.train.objective import enhancement_objective
    monkeypatch.setattr(fused_curve, "runs_fused", lambda x: fused)
    tv = tr.views[0]
    with torch.no_grad():
        res = tr.model.render(tv.camera, 0, depth=tr.depth_prior)
    assert fused_enhance.applies(tr.model, tr.cfg.loss, res["R"]) == fused  # the path under test is taken
    tr.model.enhancement.zero_grad(set_to_none=True)
    total, terms = enhancement_objective(tr.model, tr.cfg.loss, res["R"], res["L"], to_bchw(tv.S))
    total.backward()
    grads = {n: p.grad.clone() for n, p in tr.model.enhancement.named_parameters() if p.grad is not None}
    return total.detach(), {k: v.detach() for k, v in terms.items()}, grads


def test_the_objective_gives_the_torch_paths_terms_and_net_gradients(trainer, monkeypatch):
    with torch.no_grad():  # a net that answers its input (its output layer starts at zero weights)
        trainer.model.enhancement.out.weight.normal_(0, 0.3)
    assert fused_enhance.applies(trainer.model, trainer.cfg.loss, torch.zeros(8, 8, 3, device="cpu")) is False
    total_t, terms_t, grads_t = objective_grads(trainer, False, monkeypatch)
    total_f, terms_f, grads_f = objective_grads(trainer, True, monkeypatch)
    assert list(terms_f) == list(terms_t) == ["spa", "exp", "col", "exp_E"]
    torch.testing.assert_close(total_f, total_t, rtol=1e-5, atol=1e-7)
    for name in terms_t:
        torch.testing.assert_close(terms_f[name], terms_t[name], rtol=1e-4, atol=1e-7)
    assert set(grads_f) == set(grads_t) and grads_t
    for name in grads_t:
        scale = float(grads_t[name].abs().max())
        torch.testing.assert_close(grads_f[name], grads_t[name], rtol=1e-3, atol=1e-4 * scale + 1e-12)


@pytest.mark.parametrize("change", ["loss.exp_patch=16", "loss.exp_on=illumination", "loss.spa_form=paper",
                                    "loss.enhance_trains_scene=true", "model.enhancement.tone=illumination"])
def test_other_configurations_take_the_torch_path(change, monkeypatch):
    from retinexgs.model.tones import get_tone
    from retinexgs.run.config import load_config
    monkeypatch.setattr(fused_curve, "runs_fused", lambda x: True)
    cfg = load_config(overrides=[change])

    class Model:
        tone = get_tone(cfg.model.enhancement.tone)

    R = torch.zeros(8, 8, 3)
    assert not fused_enhance.applies(Model(), cfg.loss, R)
    Model.tone = get_tone(load_config().model.enhancement.tone)
    assert fused_enhance.applies(Model(), load_config().loss, R)
    assert not fused_enhance.applies(Model(), load_config().loss, R[:3])  # smaller than a region
    assert fused_enhance.applies(Model(), load_config().loss, torch.zeros(360, 640, 3))  # fox-dark's
    assert fused_enhance.applies(Model(), load_config().loss, torch.zeros(1500, 2000, 3))  # no bound on the size
