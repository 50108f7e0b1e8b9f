"""model.illumination.leak: the illumination MLP's hidden layers leaky. With ReLU, an input that switches every
unit of the head off gets sigmoid(last bias), whatever it is, and no gradient reaches the weights that could move
it; leaky units keep both. Leaky fields render through torch (the fused kernel implements ReLU)."""
import pytest
import torch

from retinexgs.model.gaussians import GaussianModel
from retinexgs.model.illumination import IlluminationField
from retinexgs.model.inference import InferenceRenderer, fused_colors_unsupported
from retinexgs.model.retinex_model import RetinexGSModel
from retinexgs.render import Camera
from retinexgs.run.config import load_config


def dead_head_field(leak):
    """A small field whose head's units are all off for every input (their biases far below any input's sum)."""
    torch.manual_seed(0)
    f = IlluminationField(pos_freqs=2, dir_freqs=1, hidden=8, depth=1, dir_hidden=4, leak=leak)
    with torch.no_grad():
        f.head[0].weight.uniform_(-0.1, 0.1)
        f.head[0].bias.fill_(-100.0)
        f.head[-1].weight.uniform_(-1.0, 1.0)
    return f


def test_relu_field_with_a_dead_head_sits_at_the_bias_floor_and_a_leaky_one_does_not():
    xyz, dirs = torch.randn(50, 3) * 0.5, torch.randn(50, 3)
    relu, leaky = dead_head_field(0.0), dead_head_field(0.05)
    out = relu(xyz, dirs)
    floor = torch.sigmoid(relu.head[-1].bias).expand_as(out)
    torch.testing.assert_close(out, floor)  # every input: the shared floor
    out.sum().backward()
    assert relu.head[0].weight.grad.abs().max() == 0  # nothing that could take it lower learns
    out_l = leaky(xyz, dirs)
    assert (out_l - out_l.mean(0)).abs().max() > 1e-3  # leaky: the inputs still tell apart
    out_l.sum().backward()
    assert leaky.head[0].weight.grad.abs().max() > 0


def test_the_forward_is_the_sequential_mlp_with_leaky_units():
    f = IlluminationField(pos_freqs=3, dir_freqs=2, hidden=16, depth=2, dir_hidden=8, leak=0.1)
    assert all(m.negative_slope == 0.1 for m in f.modules() if isinstance(m, torch.nn.LeakyReLU))
    xyz, dirs = torch.randn(20, 3), torch.randn(20, 3)
    from retinexgs.model.illumination import positional_encoding
    feat = f.trunk(positional_encoding(xyz / f.bound, f.pos_freqs))
    d = torch.nn.functional.normalize(dirs, dim=-1)
    ref = torch.sigmoid(f.head(torch.cat([feat, positional_encoding(d, f.dir_freqs)], dim=-1)))
    torch.testing.assert_close(f(xyz, dirs), ref)
    with pytest.raises(ValueError):
        IlluminationField(leak=1.0)


def test_a_leaky_model_renders_through_torch_and_the_renderer_agrees():
    cfg = load_config(["ablations/illum_leaky"], overrides=["model.sh_degree=0", "model.near_fraction=0"])
    assert cfg.model.illumination.leak == 0.01 and load_config().model.illumination.leak == 0.0
    g = torch.Generator().manual_seed(2)
    pts = torch.cat([(torch.rand(200, 2, generator=g) - 0.5) * 2, torch.full((200, 1), 2.0)], dim=-1)
    model = RetinexGSModel(GaussianModel.from_points(pts, torch.rand(200, 3, generator=g), 0, 0.8), cfg.model).eval()
    assert "leak" in fused_colors_unsupported(model.illumination)
    cam = Camera(torch.eye(4, dtype=torch.float64), 30.0, 30.0, 16.0, 12.0, 32, 24)
    renderer = InferenceRenderer(model, 0, fused=True)  # asked for the kernel: declined, with the reason
    assert not renderer.fused and "leak" in renderer.fallback_reason
    with torch.no_grad():
        ref, fast = model.render(cam, 0), renderer.render(cam)
    torch.testing.assert_close(fast["L"], ref["L"], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(fast["rgb"], ref["rgb"], rtol=1e-4, atol=1e-4)
