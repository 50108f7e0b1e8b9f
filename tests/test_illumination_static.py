"""The illumination field without its direction input (``model.illumination.view_dependent: false``): L̂ depends on
position alone, stays so through training, and the fused colour kernel (on the CPU, and on CUDA where there is a
GPU) gives the torch field's values for any camera."""
import pytest
import torch
import torch.nn.functional as F

from retinexgs.model.gaussians import GaussianModel
from retinexgs.model.illumination import positional_encoding
from retinexgs.model.inference import fused_gaussian_colors
from retinexgs.model.retinex_model import RetinexGSModel
from retinexgs.render import has_cuda
from retinexgs.run.config import load_config
from test_fused_colors import SHAPES, make_field, make_gaussians, torch_colors


def field(view_dependent, shape=SHAPES[0]):
    return make_field(shape, view_dependent=view_dependent)  # float64, far from the near-constant initial field


def two_views(n=200, seed=0):
    gen = torch.Generator().manual_seed(seed)
    xyz = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    return xyz, torch.randn(n, 3, generator=gen, dtype=torch.float64), torch.randn(n, 3, generator=gen,
                                                                                   dtype=torch.float64)


@pytest.mark.parametrize("shape", SHAPES)
def test_static_field_ignores_the_direction(shape):
    xyz, d1, d2 = two_views()
    f = field(False, shape)
    with torch.no_grad():
        assert torch.equal(f(xyz, d1), f(xyz, d2))
        g = field(True, shape)  # the same seed with its direction: the check above can fail
        assert (g(xyz, d1) - g(xyz, d2)).abs().max() > 1e-4


def test_view_dependent_field_is_the_sequential_mlp():
    """The forward written out layer by layer equals the head as a module (the layout the kernel packs)."""
    xyz, d1, _ = two_views()
    f = field(True)
    with torch.no_grad():
        h = torch.cat([f.trunk(positional_encoding(xyz / f.bound, f.pos_freqs)),
                       positional_encoding(F.normalize(d1, dim=-1), f.dir_freqs)], dim=-1)
        assert torch.allclose(f(xyz, d1), torch.sigmoid(f.head(h)), rtol=0, atol=1e-14)


def test_training_keeps_the_direction_columns_at_zero():
    """Adam steps on a loss that would use the direction leave its columns exactly zero, and the field static."""
    xyz, d1, d2 = two_views()
    f = field(False)
    hidden = f.trunk[0].out_features
    opt = torch.optim.Adam(f.parameters(), lr=1e-2)
    target = torch.rand(len(xyz), 3, dtype=torch.float64)
    for i in range(5):
        opt.zero_grad()
        dirs = d1 if i % 2 else d2
        loss = (f(xyz, dirs) - target * dirs[:, :1].sigmoid()).square().mean()  # a view-dependent target
        loss.backward()
        assert f.head[0].weight.grad[:, hidden:].abs().max() == 0
        opt.step()
    assert f.head[0].weight[:, hidden:].abs().max() == 0
    assert f.head[0].weight[:, :hidden].abs().max() > 0
    with torch.no_grad():
        assert torch.equal(f(xyz, d1), f(xyz, d2))


@pytest.mark.parametrize("shape", SHAPES[:3])
def test_fused_kernel_gives_the_static_field(shape):
    """Even with non-zero raw direction columns (an edited or foreign state), the kernel evaluates what the torch
    forward does: the packed weights are the masked ones."""
    g, f = make_gaussians(), field(False, shape)
    hidden = f.trunk[0].out_features
    with torch.no_grad():
        f.head[0].weight[:, hidden:].normal_(0, 1.0)
    outs = []
    for center in ([0.3, -0.2, 2.5], [-1.5, 0.7, -2.0]):
        out = fused_gaussian_colors(g, center, 2, f)
        assert torch.allclose(out, torch_colors(g, f, center, 2), rtol=0, atol=1e-10)
        outs.append(out[:, 3:])
    assert torch.allclose(outs[0], outs[1], rtol=0, atol=1e-12)


@pytest.mark.skipif(not (torch.cuda.is_available() and has_cuda()), reason="needs a CUDA GPU and the CUDA kernels")
def test_cuda_fused_kernel_gives_the_static_field():
    g, f = make_gaussians(n=700), field(False)
    hidden = f.trunk[0].out_features
    with torch.no_grad():
        f.head[0].weight[:, hidden:].normal_(0, 1.0)
    center = [0.3, -0.2, 2.5]
    ref = torch_colors(g, f, center, 3)  # before .cuda(), which moves the modules in place
    gpu = fused_gaussian_colors(g.cuda(), center, 3, f.cuda()).cpu()
    assert torch.allclose(gpu, ref, rtol=0, atol=1e-10), (gpu - ref).abs().max()


def test_config_reaches_the_model_and_old_checkpoints_load():
    """The ablation's key builds a static field; the mask is not in the state, so a checkpoint written before the
    key existed (same tensors) loads into either kind of field."""
    cfg = load_config(["ablations/illum_static"])
    g = GaussianModel.from_points(torch.randn(50, 3), torch.rand(50, 3), sh_degree=3)
    model = RetinexGSModel(g, cfg.model)
    assert model.illumination.view_dependent is False
    assert load_config([]).model.illumination.view_dependent is True
    assert load_config(["paper"]).model.illumination.view_dependent is True
    state = field(True).state_dict()
    assert not any("head_mask" in k for k in state)
    static = field(False)
    static.load_state_dict(state)  # strict
    xyz, d1, d2 = two_views()
    with torch.no_grad():
        assert torch.equal(static(xyz, d1), static(xyz, d2))
