"""IlluminationField and EnhancementNet: shapes, ranges, initial values, gradients, a tiny fit."""
import math

import pytest
import torch

from retinexgs.model.enhancement import EnhancementNet, area_pool
from retinexgs.model.illumination import IlluminationField, encoded_dim, positional_encoding
from retinexgs.model.tone import tone_map
from retinexgs.train.losses import exposure_loss


pytestmark = pytest.mark.usefixtures("one_thread")


def test_positional_encoding_layout_and_values():
    x = torch.tensor([[0.25, -0.5, 1.0]], dtype=torch.float64)
    e = positional_encoding(x, 2)
    assert e.shape == (1, encoded_dim(3, 2)) == (1, 15)
    assert torch.equal(e[0, :3], x[0])
    # sines: freq π for the 3 coords, then 2π; cosines likewise.
    vals = (0.25, -0.5, 1.0)
    want_sin = [math.sin(f * math.pi * v) for f in (1, 2) for v in vals]
    want_cos = [math.cos(f * math.pi * v) for f in (1, 2) for v in vals]
    assert torch.allclose(e[0, 3:9], torch.tensor(want_sin, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(e[0, 9:], torch.tensor(want_cos, dtype=torch.float64), atol=1e-12)
    assert positional_encoding(x, 0).shape == (1, 3)
    assert positional_encoding(x, 3, include_input=False).shape == (1, 18)


def test_illumination_field_shape_range_init():
    torch.manual_seed(0)
    f = IlluminationField()
    xyz = torch.rand(500, 3) * 3 - 1.5
    d = torch.randn(500, 3) * 5  # not unit: normalised inside
    out = f(xyz, d)
    assert out.shape == (500, 3)
    assert (out > 0).all() and (out < 1).all()
    assert torch.allclose(out, torch.full_like(out, 0.1), atol=0.01)  # starts near init_value
    assert torch.allclose(f(xyz, d), f(xyz, d / 7.0))  # direction length does not matter
    with pytest.raises(ValueError):
        f(xyz, d[:10])


def test_illumination_field_gradients_and_fit():
    torch.manual_seed(0)
    f = IlluminationField(hidden=32, depth=2)
    xyz = torch.rand(256, 3) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(256, 3), dim=-1)
    # Smooth dark target in the decomposer's range (0.02–0.3), RGB-dependent.
    target = 0.02 + 0.28 * torch.sigmoid(torch.stack([xyz[:, 0] * 2, xyz[:, 1] * 2, -xyz[:, 2] * 2], -1))
    opt = torch.optim.Adam(f.parameters(), lr=5e-3)
    first = None
    for _ in range(150):
        loss = (f(xyz, d) - target).abs().mean()
        if first is None:
            loss.backward()
            assert all(torch.isfinite(p.grad).all() for p in f.parameters())
            assert all(p.grad.abs().sum() > 0 for p in f.parameters())
            opt.zero_grad()
            first = float(loss.detach())
            continue
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(loss.detach()) < 0.3 * first


def test_illumination_view_dirs():
    xyz = torch.tensor([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    d = IlluminationField.view_dirs(xyz, torch.zeros(3))
    assert torch.allclose(d, torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))


def light(net, L, g):
    """The paper's enhanced light L_enh = max(L, eps)^g, as the model computes it (tone "illumination", L_ref 1)."""
    return tone_map(torch.ones_like(L), L, torch.tensor(1.0), g, "illumination", net.eps)[1]


@pytest.mark.parametrize("shape", [(1, 3, 37, 53), (2, 3, 300, 200), (1, 3, 4, 4)])
def test_enhancement_shapes_range_init(shape):
    torch.manual_seed(0)
    net = EnhancementNet()
    L = 0.02 + 0.28 * torch.rand(*shape)
    g = net(L)
    assert g.shape == (shape[0], 3, 1, 1)
    assert torch.allclose(g, torch.full_like(g, 0.4), atol=1e-6)  # initial gamma for any input
    enh = light(net, L, g)
    assert enh.shape == L.shape
    assert (enh >= L).all() and (enh <= 1).all()  # g <= 1 lifts illumination in (0,1)


def test_enhancement_range_bounds_and_enhance_eps():
    net = EnhancementNet(gamma_range=(0.2, 0.8), init_gamma=0.5)
    with torch.no_grad():
        net.out.bias.fill_(100.0)
    assert torch.allclose(net(torch.rand(1, 3, 16, 16)), torch.tensor(0.8))
    with torch.no_grad():
        net.out.bias.fill_(-100.0)
    assert torch.allclose(net(torch.rand(1, 3, 16, 16)), torch.tensor(0.2))
    L = torch.zeros(1, 3, 2, 2, requires_grad=True)
    out = light(net, L, torch.tensor(0.5))
    assert torch.allclose(out, torch.full_like(out, math.sqrt(net.eps)))
    with pytest.raises(ValueError):
        net(torch.rand(3, 16, 16))
    with pytest.raises(ValueError):
        EnhancementNet(gamma_range=(0.1, 1.0), init_gamma=1.0)


def test_enhancement_learns_content_adaptive_gamma():
    """Trained only with the exposure loss, a dark map gets a smaller gamma than a brighter one."""
    torch.manual_seed(0)
    net = EnhancementNet(widths=(8, 16, 16))
    dark = 0.03 + 0.02 * torch.rand(1, 3, 32, 32)
    bright = 0.25 + 0.05 * torch.rand(1, 3, 32, 32)
    batch = torch.cat([dark, bright])
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    g0 = net(batch).detach()
    for step in range(120):
        g = net(batch)
        loss = exposure_loss(light(net, batch, g), E=0.6, patch=8)
        opt.zero_grad()
        loss.backward()
        if step == 0:
            assert all(torch.isfinite(p.grad).all() for p in net.parameters())
        opt.step()
    g = net(batch).detach()
    # Ideal gammas: log(0.6)/log(0.04) ≈ 0.16 and log(0.6)/log(0.275) ≈ 0.39.
    assert g[0].mean() < g[1].mean() - 0.1
    assert float(loss.detach()) < float(exposure_loss(light(net, batch, g0), E=0.6, patch=8))


def test_enhancement_per_scene_gamma_is_one_learned_constant():
    """per_view=False: the same g for every input (the output bias through the range), learned by its loss; only
    that bias is a used parameter, and it starts at init_gamma like the per-view net."""
    net = EnhancementNet(init_gamma=0.45, per_view=False)
    a, b = torch.rand(2, 3, 20, 30) * 0.1, torch.rand(1, 3, 7, 9)
    ga, gb = net(a), net(b)
    assert ga.shape == (2, 3, 1, 1) and torch.allclose(ga, torch.full_like(ga, 0.45), atol=1e-6)
    assert torch.equal(ga[0], gb[0]) and torch.equal(ga[0], ga[1])
    assert net.used_parameters() == [net.out.bias]
    assert len(EnhancementNet().used_parameters()) == len(list(EnhancementNet().parameters()))
    opt = torch.optim.Adam(net.used_parameters(), lr=0.05)
    L = torch.rand(1, 3, 16, 16) * 0.3 + 0.05
    for _ in range(200):  # exposure alone: the constant moves to the g that brings the mean to E
        loss = exposure_loss(light(net, L, net(L)), E=0.6, patch=0)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(light(net, L, net(L)).mean().detach()) == pytest.approx(0.6, abs=0.01)
    assert all(p.grad is None for p in net.features.parameters())


@pytest.mark.parametrize("shape,size", [((1, 3, 360, 640), (72, 128)), ((2, 3, 12, 8), (3, 2)),
                                        ((1, 3, 375, 500), (96, 128)), ((1, 1, 10, 10), (10, 10))])
@pytest.mark.parametrize("channels_last", [False, True])
def test_area_pool_is_adaptive_avg_pool(shape, size, channels_last):
    """The exact-multiple shortcut (a reduction over a view) and the fallback give adaptive_avg_pool2d's windows, on a
    contiguous input and on the render's channels-last view, values and gradients."""
    torch.manual_seed(0)
    base = torch.rand(shape[0], shape[2], shape[3], shape[1], dtype=torch.float64) if channels_last else \
        torch.rand(shape, dtype=torch.float64)
    x = (base.permute(0, 3, 1, 2) if channels_last else base).requires_grad_(True)
    got = area_pool(x, size)
    ref = torch.nn.functional.adaptive_avg_pool2d(x, size)
    assert got.shape == ref.shape
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)
    w = torch.rand_like(ref)
    g_got, = torch.autograd.grad((got * w).sum(), x)
    g_ref, = torch.autograd.grad((ref * w).sum(), x)
    torch.testing.assert_close(g_got, g_ref, rtol=1e-12, atol=1e-12)
