"""The depth prior (``loss.w_depth``, ``losses.depth_smoothness_loss``): its value against a loop over pixels,
what it ignores (scale, uncovered pixels, differences across the guide's edges), float64 gradients, and its
place in the training step (logged, in the total, off at 0 and for the 3DGS baselines)."""
import pytest
import torch

from retinexgs.train import losses
from retinexgs.run.config import load_config
from test_train import scene_dir, trainer_for  # noqa: F401  (the fixture)


def random_maps(h=6, w=7, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    alpha = torch.rand(1, 1, h, w, generator=g, dtype=dtype)
    depth = alpha * (1.0 + torch.rand(1, 1, h, w, generator=g, dtype=dtype) * 3)  # Σwz = α · (expected depth)
    guide = torch.rand(1, 3, h, w, generator=g, dtype=dtype)
    return depth, alpha, guide


def loop_reference(depth, alpha, guide, edge, min_alpha=0.5):
    _, _, h, w = depth.shape
    I = guide[0].mean(0)
    cov = [[bool(alpha[0, 0, i, j] >= min_alpha) for j in range(w)] for i in range(h)]
    disp = {(i, j): float(alpha[0, 0, i, j] / depth[0, 0, i, j]) for i in range(h) for j in range(w) if cov[i][j]}
    mean = sum(disp.values()) / len(disp)
    total = 0.0
    for di, dj in ((0, 1), (1, 0)):
        s, n = 0.0, 0
        for i in range(h - di):
            for j in range(w - dj):
                if cov[i][j] and cov[i + di][j + dj]:
                    wgt = torch.exp(-edge * (I[i + di, j + dj] - I[i, j]).abs())
                    s += float(wgt) * abs(disp[(i + di, j + dj)] - disp[(i, j)]) / mean
                    n += 1
        total += s / max(n, 1)
    return total


@pytest.mark.parametrize("edge", [0.0, 10.0])
def test_value_matches_a_loop_over_pixels(edge):
    depth, alpha, guide = random_maps()
    assert (alpha >= 0.5).any() and (alpha < 0.5).any()  # both kinds of pixel are in the test
    wx, wy = losses.edge_weights(guide, edge)
    got = float(losses.depth_smoothness_loss(depth, alpha, wx, wy))
    assert got == pytest.approx(loop_reference(depth, alpha, guide, edge), rel=1e-10)


def test_flat_disparity_costs_nothing_and_scale_does_not_matter():
    depth, alpha, guide = random_maps()
    wx, wy = losses.edge_weights(guide, 10.0)
    flat = alpha * 2.5  # every covered pixel at depth 2.5
    assert float(losses.depth_smoothness_loss(flat, alpha, wx, wy)) == pytest.approx(0.0, abs=1e-12)
    base = losses.depth_smoothness_loss(depth, alpha, wx, wy)
    assert float(base) > 0
    assert float(losses.depth_smoothness_loss(depth * 7.3, alpha, wx, wy)) == pytest.approx(float(base), rel=1e-12)


def test_uncovered_pixels_are_ignored():
    depth, alpha, guide = random_maps()
    wx, wy = losses.edge_weights(guide, 10.0)
    other = torch.where(alpha < 0.5, depth * 5 + 1, depth)
    assert not torch.equal(other, depth)
    assert float(losses.depth_smoothness_loss(other, alpha, wx, wy)) == pytest.approx(
        float(losses.depth_smoothness_loss(depth, alpha, wx, wy)), rel=1e-12)


def test_a_step_along_an_edge_of_the_guide_costs_less_than_one_across_flat_guide():
    h, w = 8, 8
    alpha = torch.ones(1, 1, h, w, dtype=torch.float64)
    depth = torch.ones_like(alpha)
    depth[..., 4:] = 3.0  # a depth step between columns 3 and 4
    at_edge = torch.zeros(1, 3, h, w, dtype=torch.float64)
    at_edge[..., 4:] = 0.5  # the guide steps at the same place
    elsewhere = torch.zeros_like(at_edge)
    elsewhere[..., 2:] = 0.5  # the guide steps two columns away
    cost = [float(losses.depth_smoothness_loss(depth, alpha, *losses.edge_weights(gd, 10.0)))
            for gd in (at_edge, elsewhere)]
    assert cost[0] < 0.01 * cost[1]


def test_float64_gradients_match_finite_differences():
    """The mean disparity is a detached scale (the term only measures shape), so the finite differences are taken
    at that fixed scale; every pixel covered (the coverage mask is a step)."""
    depth, alpha, guide = random_maps(5, 6, seed=3)
    a0 = alpha * 0.5 + 0.5
    d0 = a0 * (1.0 + torch.rand(a0.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(4)))
    wx, wy = losses.edge_weights(guide, 10.0)
    d = d0.clone().requires_grad_(True)
    a = a0.clone().requires_grad_(True)
    losses.depth_smoothness_loss(d, a, wx, wy).backward()
    scale = float((a0 / d0).mean())

    def at_fixed_scale(dd, aa):
        disp = aa / dd / scale
        return float((disp[..., :, 1:] - disp[..., :, :-1]).abs().mul(wx).mean() +
                     (disp[..., 1:, :] - disp[..., :-1, :]).abs().mul(wy).mean())

    eps = 1e-6
    for idx in [(0, 0, 0, 0), (0, 0, 2, 3), (0, 0, 4, 5)]:
        for which, grad in ((0, d.grad), (1, a.grad)):
            plus, minus = [d0.clone(), a0.clone()], [d0.clone(), a0.clone()]
            plus[which][idx] += eps
            minus[which][idx] -= eps
            fd = (at_fixed_scale(*plus) - at_fixed_scale(*minus)) / (2 * eps)
            assert float(grad[idx]) == pytest.approx(fd, rel=1e-5, abs=1e-9)


def test_the_training_step_logs_and_adds_the_prior(scene_dir, tmp_path):  # noqa: F811
    tr = trainer_for(scene_dir, tmp_path / "on", ["loss.w_depth=2.0"])
    assert tr.depth_prior
    tv = tr.views[0]
    res = tr.render_view(tv, 0)
    assert res["out"].depth is not None
    terms = tr.objective.loss(res, tv, 0)
    assert list(terms).index("depth") == list(terms).index("sh") + 1
    others = sum(getattr(tr.cfg.loss, w) * terms[k] for k, w in (("sup_r", "w_r"), ("sup_l", "w_l"),
                                                                 ("sup_rec", "w_s"), ("tv", "w_tv"), ("sh", "w_sh")))
    assert float(terms["total"].detach()) == pytest.approx(float((others + 2.0 * terms["depth"]).detach()), rel=1e-6)
    tr.optimizer.zero_grad(set_to_none=True)
    tr.objective.depth_loss(tr.render_view(tv, 0), tv).backward()  # the prior alone reaches the Gaussians' positions
    assert tr.model.gaussians.means.grad.abs().sum() > 0


@pytest.mark.parametrize("overrides, method", [(["loss.w_depth=0"], "retinexgs"), (["loss.w_depth=1"], "pre")])
def test_off_at_zero_and_for_the_baselines(scene_dir, tmp_path, overrides, method):  # noqa: F811
    tr = trainer_for(scene_dir, tmp_path / "off", overrides, method=method)
    assert not tr.depth_prior
    tv = tr.views[0]
    res = tr.render_view(tv, 0)
    assert res["out"].depth is None
    assert "depth" not in tr.objective.loss(res, tv, 0)


def test_a_negative_weight_is_refused():
    with pytest.raises(Exception, match="w_depth"):
        load_config([], ["loss.w_depth=-1"])


def test_a_render_without_depth_is_refused_by_name(scene_dir, tmp_path):  # noqa: F811
    tr = trainer_for(scene_dir, tmp_path / "run", ["loss.w_depth=0.3"])
    res = tr.model.render(tr.views[0].camera, 0)  # depth not asked for
    with pytest.raises(ValueError, match="depth=True"):
        tr.objective.loss(res, tr.views[0], 0)
