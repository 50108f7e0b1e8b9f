"""``density.max_aniso``: no Gaussian's longest axis exceeds that multiple of its shortest after an optimiser step;
the long axis is shortened, the short one and every Gaussian within the cap are left as they are."""
import math

import pytest
import torch

from retinexgs.errors import UserError
from retinexgs.strategy import DefaultStrategy
from retinexgs.model.gaussians import GaussianModel
from retinexgs.run.config import load_config
from retinexgs.model.schedule import build_schedule
from test_train import scene_dir, trainer_for  # noqa: F401  (the fixture)


def gaussians_with_scales(log_scales):
    g = GaussianModel.from_points(torch.randn(len(log_scales), 3), torch.rand(len(log_scales), 3), sh_degree=0)
    with torch.no_grad():
        g.log_scales.copy_(torch.as_tensor(log_scales, dtype=g.log_scales.dtype))
    return g


def controller(max_aniso):
    cfg = load_config([], [f"density.max_aniso={max_aniso}"])
    return DefaultStrategy(cfg.density, 1.0, build_schedule(cfg))


def test_the_cap_shortens_only_the_long_axes_of_needles():
    r = 10.0
    ls = [[0.0, 0.0, 0.0],                     # a sphere
          [0.0, math.log(5.0), -0.5],          # within the cap (ratio 5·e^0.5)
          [-3.0, -1.0, 1.0],                   # a needle: ratio e^4 > 10 on one axis, e^2 < 10 on the other
          [-2.0, 1.0, 2.0]]                    # two axes over the cap
    g = gaussians_with_scales(ls)
    before = g.log_scales.detach().clone()
    controller(r).after_optimizer_step(g, None, 0)
    after = g.log_scales.detach()
    assert torch.equal(after[:2], before[:2])
    assert torch.equal(after.amin(-1), before.amin(-1))  # the short axis is kept
    ratio = (after.amax(-1) - after.amin(-1)).exp()
    assert (ratio <= r * (1 + 1e-5)).all(), ratio
    assert torch.allclose(after[2], torch.tensor([-3.0, -1.0, -3.0 + math.log(r)]))
    assert torch.allclose(after[3], torch.tensor([-2.0, -2.0 + math.log(r), -2.0 + math.log(r)]))


def test_zero_is_no_cap():
    g = gaussians_with_scales([[-5.0, 0.0, 5.0], [1.0, -4.0, 0.0]])
    before = g.log_scales.detach().clone()
    controller(0).after_optimizer_step(g, None, 0)
    assert torch.equal(g.log_scales.detach(), before)


@pytest.mark.parametrize("bad", ["0.5", "-1"])
def test_a_ratio_below_one_is_refused_by_name(bad):
    with pytest.raises(UserError, match="max_aniso"):
        load_config([], [f"density.max_aniso={bad}"])


def test_training_keeps_every_gaussian_within_the_cap(scene_dir, tmp_path):  # noqa: F811
    tr = trainer_for(scene_dir, tmp_path / "run", ["density.max_aniso=4"])
    with torch.no_grad():  # start far outside the cap
        tr.model.gaussians.log_scales.add_(torch.randn_like(tr.model.gaussians.log_scales) * 2.0)
    ls = tr.model.gaussians.log_scales.detach()
    assert ((ls.amax(-1) - ls.amin(-1)).exp() > 4.5).any()
    for step in range(3):
        tr.step = step
        tr.train_step(step, tr.views[step % len(tr.views)])
    ls = tr.model.gaussians.log_scales.detach()
    assert ((ls.amax(-1) - ls.amin(-1)).exp() <= 4 * (1 + 1e-5)).all()
