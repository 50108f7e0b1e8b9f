"""The fused per-Gaussian colour kernel (SH reflectance + illumination MLP) against the torch model code, and the
inference renderer against ``RetinexGSModel.render`` (CPU)."""
import math

import pytest
import torch

from retinexgs.model.gaussians import GaussianModel
from retinexgs.model.illumination import IlluminationField
from retinexgs.model.inference import (InferenceRenderer, camera_center, fused_colors_unsupported,
                                       fused_gaussian_colors, illumination_shape, pack_illumination)
from retinexgs.model.retinex_model import RetinexGSModel
from retinexgs.config.schema import Model
from retinexgs.render._backend import kernels
from scenes import make_camera

# (pos_freqs, dir_freqs, hidden, depth, dir_hidden): the default and the other register-resident widths, and
# runtime widths (odd sizes, no encoding octaves, a deep trunk).
SHAPES = [(10, 4, 64, 3, 32), (6, 2, 32, 2, 16), (0, 0, 24, 1, 8), (3, 5, 20, 4, 12), (2, 1, 7, 2, 5)]


def make_gaussians(n=300, sh_degree=3, dtype=torch.float64, seed=0):
    gen = torch.Generator().manual_seed(seed)
    pts = torch.randn(n, 3, generator=gen)
    g = GaussianModel.from_points(pts, torch.rand(n, 3, generator=gen), sh_degree=sh_degree)
    with torch.no_grad():
        g.sh_dc.normal_(0, 1, generator=gen)  # some colours go below 0 before the clamp
        g.sh_rest.normal_(0, 0.4, generator=gen)
        g.log_scales.sub_(1.0)
        g.opacity_logits.normal_(0, 2, generator=gen)
    return g.to(dtype)


def make_field(shape, dtype=torch.float64, bound=2.0, seed=1, view_dependent=True):
    torch.manual_seed(seed)
    pos_freqs, dir_freqs, hidden, depth, dir_hidden = shape
    f = IlluminationField(pos_freqs=pos_freqs, dir_freqs=dir_freqs, hidden=hidden, depth=depth,
                          dir_hidden=dir_hidden, bound=bound, view_dependent=view_dependent).to(dtype)
    with torch.no_grad():
        f.head[-1].weight.normal_(0, 0.5)  # a view-dependent field, not the near-constant initial one
    return f


def torch_colors(g, field, center, degree):
    c = torch.tensor(center, dtype=torch.float64)
    with torch.no_grad():
        out = g.colors(c, degree)
        if field is None:
            return out
        illum = field(g.means, IlluminationField.view_dirs(g.means, c.to(g.means)))
        return torch.cat([out, illum], dim=-1)


CENTER = [0.3, -0.2, 2.5]


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("shape", SHAPES)
def test_fused_colors_match_the_model_in_float64(degree, shape):
    g, f = make_gaussians(), make_field(shape)
    out = fused_gaussian_colors(g, CENTER, degree, f)
    ref = torch_colors(g, f, CENTER, degree)
    assert out.shape == (len(g), 6) and out.dtype == torch.float64
    assert (ref[:, :3] == 0).any()  # the clamp is exercised
    assert torch.allclose(out, ref, rtol=0, atol=1e-10), (out - ref).abs().max()


@pytest.mark.parametrize("degree", [0, 3])
@pytest.mark.parametrize("shape", SHAPES[:3])
def test_fused_colors_match_the_model_in_float32(degree, shape):
    g, f = make_gaussians(dtype=torch.float32), make_field(shape, torch.float32)
    out = fused_gaussian_colors(g, CENTER, degree, f)
    ref = torch_colors(g, f, CENTER, degree)
    assert out.dtype == torch.float32
    assert torch.allclose(out, ref, rtol=0, atol=1e-5), (out - ref).abs().max()


@pytest.mark.parametrize("bound", [1.7, 3.0])
def test_fused_colors_any_bound(bound):
    g, f = make_gaussians(), make_field(SHAPES[0], bound=bound)
    assert torch.allclose(fused_gaussian_colors(g, CENTER, 2, f), torch_colors(g, f, CENTER, 2), rtol=0, atol=1e-10)


@pytest.mark.parametrize("sh_degree", [0, 1, 3])
def test_reflectance_only_and_degree_capped(sh_degree):
    g = make_gaussians(sh_degree=sh_degree)
    out = fused_gaussian_colors(g, CENTER, 3, None)  # active degree 3 is capped at the model's
    assert out.shape == (len(g), 3)
    assert torch.allclose(out, torch_colors(g, None, CENTER, 3), rtol=0, atol=1e-12)


def test_a_gaussian_at_the_camera_centre_gets_finite_colours():
    g, f = make_gaussians(n=5), make_field(SHAPES[0])
    with torch.no_grad():
        g.means[2] = torch.tensor(CENTER, dtype=torch.float64)
    out = fused_gaussian_colors(g, CENTER, 3, f)
    ref = torch_colors(g, f, CENTER, 3)
    assert torch.isfinite(out).all()
    assert torch.allclose(out, ref, rtol=0, atol=1e-10)


def test_no_gaussians():
    g = GaussianModel.empty_like_state({k: v[:0] for k, v in make_gaussians(n=2).tensors().items()}, 3)
    f = make_field(SHAPES[0])
    assert fused_gaussian_colors(g, CENTER, 3, f).shape == (0, 6)
    assert fused_gaussian_colors(g, CENTER, 3, None).shape == (0, 3)


def test_thread_count_does_not_change_the_result():
    g, f = make_gaussians(n=1000), make_field(SHAPES[0])
    K = kernels()
    old = K.get_num_threads()
    try:
        K.set_num_threads(1)
        one = fused_gaussian_colors(g, CENTER, 3, f)
        K.set_num_threads(2)
        two = fused_gaussian_colors(g, CENTER, 3, f)
    finally:
        K.set_num_threads(0 if old == torch.get_num_threads() else old)
    assert torch.equal(one, two)


def test_camera_center_matches_the_camera():
    cam = make_camera(eye=(0.7, -1.3, -3.1), target=(0.2, 0.1, 0.4))
    assert torch.allclose(torch.tensor(camera_center(cam), dtype=torch.float64), cam.center, atol=1e-14)


# ---- bad input -------------------------------------------------------------------------------------------------
def _args(g, f, **over):
    args = dict(degree=2, means=g.means, sh_dc=g.sh_dc, sh_rest=g.sh_rest, center=CENTER,
                illum=list(illumination_shape(f)), bound=2.0, weights=pack_illumination(f))
    args.update(over)
    return args


@pytest.mark.parametrize("over, error, message", [
    (dict(degree=4), ValueError, "degree"),
    (dict(sh_dc="f32"), TypeError, "sh_dc must have dtype"),
    (dict(sh_dc="bad_shape"), ValueError, "sh_dc must have 3 dims"),
    (dict(sh_rest="few"), ValueError, "sh_rest has 3 bases"),
    (dict(center=[0.0, 1.0]), ValueError, "center must have 3"),
    (dict(center=[0.0, math.nan, 1.0]), ValueError, "center must be finite"),
    (dict(weights="short"), ValueError, "weights has shape"),
    (dict(weights="f32"), TypeError, "weights must have dtype"),
    (dict(weights=None), ValueError, "both the illumination shape and its weights"),
    (dict(illum=[10, 4, 64, 3]), ValueError, "illum must be"),
    (dict(illum=[10, 4, 200, 3, 32]), ValueError, "widths 1..128"),
    (dict(illum=[10, 4, 64, 0, 32]), ValueError, "depth"),
    (dict(illum=[-1, 4, 64, 3, 32]), ValueError, "pos_freqs"),
    (dict(bound=0.0), ValueError, "bound"),
])
def test_bad_inputs_raise_named_errors(over, error, message):
    g, f = make_gaussians(n=10), make_field(SHAPES[0])
    subs = {"f32": lambda name: getattr(g, name).float() if name != "weights" else pack_illumination(f).float(),
            "bad_shape": lambda name: g.sh_dc[:, 0],
            "few": lambda name: g.sh_rest[:, :3],
            "short": lambda name: pack_illumination(f)[:-4]}
    over = {k: (subs[v](k) if isinstance(v, str) and v in subs else v) for k, v in over.items()}
    with pytest.raises(error, match=message):
        kernels().gaussian_colors(**_args(g, f, **over))


def test_pack_rejects_mismatched_layers():
    f = make_field(SHAPES[0])
    shape = illumination_shape(f)
    layers = [m for m in list(f.trunk) + list(f.head) if isinstance(m, torch.nn.Linear)]
    with pytest.raises(ValueError, match="expected 5 weights"):
        kernels().pack_illum_weights([m.weight for m in layers[:-1]], [m.bias for m in layers[:-1]], *shape)
    with pytest.raises(ValueError, match=r"weights\[0\] has shape"):
        kernels().pack_illum_weights([m.weight.t() if i == 0 else m.weight for i, m in enumerate(layers)],
                                     [m.bias for m in layers], *shape)


def test_wide_fields_are_reported_unsupported():
    wide = IlluminationField(hidden=160, dir_hidden=32)
    assert "exceed" in fused_colors_unsupported(wide)
    assert fused_colors_unsupported(make_field(SHAPES[0])) is None
    with pytest.raises(ValueError, match="cannot evaluate"):
        pack_illumination(wide)


# ---- the inference renderer ------------------------------------------------------------------------------------
MODEL_CFG = {"sh_degree": 3, "sh_degree_every": 0.1, "init_opacity": 0.1, "max_init_points": 100000,
             "near_fraction": 0.0, "near_in_training": True,
             "illumination": {"pos_freqs": 10, "dir_freqs": 4, "hidden": 64, "depth": 3, "dir_hidden": 32,
                              "init_value": 0.1, "view_dependent": True},
             "enhancement": {"gamma_range": [0.1, 1.0], "init_gamma": 0.45, "per_view": True,
                             "ref_quantile": 1.0, "raw": {"shoulder": None}}}


def make_model(decomposed=True, illumination=None, n=400, dtype=torch.float32,
               tone="illumination", background="black", shoulder=1.0):
    enh = dict(MODEL_CFG["enhancement"], tone=tone, shoulder=shoulder)
    if tone == "exposure":  # the default's range and start
        enh.update(gamma_range=[0.25, 2.0], init_gamma=1.0)
    cfg = Model.model_validate(dict(MODEL_CFG, illumination=dict(MODEL_CFG["illumination"], **(illumination or {})),
                                    enhancement=enh, background=background))  # the typed section the model takes
    g = make_gaussians(n=n, dtype=torch.float64)
    with torch.no_grad():
        g.means.mul_(0.6)
    model = RetinexGSModel(g, cfg, decomposed).to(dtype)
    if decomposed:
        torch.manual_seed(3)
        with torch.no_grad():
            model.illumination.head[-1].weight.normal_(0, 0.5)
            model.enhancement.out.weight.normal_(0, 0.5)  # content-dependent gamma
            model.illum_ref.fill_(0.4)
    if model.has_background:
        with torch.no_grad():
            model.background.copy_(torch.linspace(0.2, 0.7, model.background.numel()))
    return model.eval()


CAM = make_camera(width=40, height=30, eye=(0.3, -0.2, -3.0))


@pytest.mark.parametrize("exposure, gamma", [(None, None), (0.7, None), (None, 0.5), (1.3, 0.8)])
@pytest.mark.parametrize("tone, shoulder", [("illumination", 1.0), ("exposure", 1.0), ("exposure", 0.5)])
def test_renderer_equals_model_render(exposure, gamma, tone, shoulder):
    model = make_model(tone=tone, shoulder=shoulder)
    r = InferenceRenderer(model, 3, fused=True)
    assert r.fused
    res = r.render(CAM, exposure, gamma)
    with torch.no_grad():
        ref = model.render(CAM, 3, exposure=exposure, gamma=gamma)
    assert res["rgb"].shape == (30, 40, 3)
    assert ref["rgb"].std() > 0.01  # not a blank frame
    for key in ("rgb", "R", "L", "S_rec", "gamma"):
        assert torch.allclose(res[key], ref[key], rtol=0, atol=1e-6), (key, (res[key] - ref[key]).abs().max())
    if shoulder < 1 and gamma == 0.5:  # the bright setting has highlights: the shoulder must show in them
        model.shoulder = 1.0
        with torch.no_grad():
            clipped = model.render(CAM, 3, exposure=exposure, gamma=gamma)["rgb"]
        assert float((clipped - res["rgb"]).max()) > 0.005 and bool((res["rgb"] <= clipped + 1e-6).all())


def test_baselines_keep_a_black_background():
    """The 3DGS baselines stay as published: model.background "mean" is RetinexGS's only."""
    model = make_model(decomposed=False, background="mean", n=50)
    assert not model.has_background and "background" not in model.state_dict()


@pytest.mark.parametrize("fused", [True, False])
def test_background_fills_uncovered_pixels_in_both_renderers(fused):
    """model.background "mean": pixels no Gaussian covers show the background channels (R̂, L̂), partly
    covered ones blend into it, and the frame renderer composites it as model.render does."""
    decomposed = True
    model = make_model(decomposed=decomposed, background="mean", dtype=torch.float64)
    cam = make_camera(width=40, height=30, eye=(0.3, -0.2, -9.0))  # the Gaussians fill the middle of the frame
    with torch.no_grad():
        ref = model.render(cam, 3)
        model.has_background = False  # the same model composited over black
        plain = model.render(cam, 3)
        model.has_background = True
    T = 1.0 - ref["out"].alpha
    assert float(T.max()) > 0.99 and float(T.min()) < 0.01  # the camera sees both empty space and Gaussians
    channels = ref["out"].image
    assert torch.allclose(channels, plain["out"].image + T * model.background, rtol=0, atol=1e-12)
    empty = T[..., 0] > 1 - 1e-9
    assert torch.allclose(channels[empty], model.background.expand(int(empty.sum()), -1), atol=1e-9)
    res = InferenceRenderer(model, 3, fused=fused).render(cam)
    for key in ("rgb", "R", "L") if decomposed else ("rgb",):
        assert torch.allclose(res[key], ref[key], rtol=0, atol=1e-10), key


def test_renderer_float64_and_torch_fallback():
    model = make_model(dtype=torch.float64)
    with torch.no_grad():
        ref = model.render(CAM, 2, exposure=0.8)["rgb"]
    for fused in (True, False):
        r = InferenceRenderer(model, 2, fused=fused)
        assert r.fused == fused
        assert torch.allclose(r.render(CAM, 0.8)["rgb"], ref, rtol=0, atol=1e-10)


def test_renderer_defaults_to_torch_colours_on_the_cpu():
    model = make_model(n=50)
    r = InferenceRenderer(model, 3)
    assert not r.fused and "CPU" in r.fallback_reason
    with torch.no_grad():
        ref = model.render(CAM, 3, exposure=0.9)["rgb"]
    assert torch.allclose(r.render(CAM, 0.9)["rgb"], ref, rtol=0, atol=1e-6)


def test_renderer_falls_back_for_wide_fields():
    model = make_model(illumination={"hidden": 160}, n=100)
    r = InferenceRenderer(model, 1, fused=True)
    assert not r.fused and "exceed" in r.fallback_reason
    with torch.no_grad():
        ref = model.render(CAM, 1)["rgb"]
    assert torch.allclose(r.render(CAM)["rgb"], ref, rtol=0, atol=1e-6)


def test_renderer_baseline():
    model = make_model(decomposed=False)
    res = InferenceRenderer(model, 3, fused=True).render(CAM, exposure=0.5)  # baselines ignore exposure, as render does
    with torch.no_grad():
        ref = model.render(CAM, 3)["rgb"]
    assert res["rgb"].shape == (30, 40, 3)
    assert torch.allclose(res["rgb"], ref, rtol=0, atol=1e-6)


def test_renderer_follows_model_changes():
    model = make_model()
    r, snapshot = InferenceRenderer(model, 3, fused=True, live=True), InferenceRenderer(model, 3, fused=True)
    before = r.render(CAM)["rgb"].clone()
    assert torch.equal(snapshot.render(CAM)["rgb"], before)
    with torch.no_grad():
        model.illumination.head[-1].bias.add_(0.5)  # in place: the version counter moves
        model.gaussians.opacity_logits.mul_(0.5)
    assert torch.equal(snapshot.render(CAM)["rgb"], before)  # not live: a snapshot until refresh()
    snapshot.refresh()
    after = r.render(CAM)["rgb"]
    assert torch.equal(snapshot.render(CAM)["rgb"], after)
    with torch.no_grad():
        ref = model.render(CAM, 3)["rgb"]
    assert (after - before).abs().max() > 1e-3
    assert torch.allclose(after, ref, rtol=0, atol=1e-6)
    # Densification replaces the parameters: fewer Gaussians.
    g = model.gaussians
    keep = torch.arange(len(g)) % 2 == 0
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        setattr(g, name, torch.nn.Parameter(getattr(g, name).detach()[keep].clone()))
    with torch.no_grad():
        ref = model.render(CAM, 3)["rgb"]
    for renderer in (r, snapshot):  # replaced parameters are noticed without live
        assert torch.allclose(renderer.render(CAM)["rgb"], ref, rtol=0, atol=1e-6)


@pytest.mark.parametrize("tone, shoulder", [("illumination", 1.0), ("signal", 1.0), ("exposure", 1.0),
                                             ("exposure", 0.5)])
def test_enhance_graph_body_equals_model_enhance(tone, shoulder):
    """The maths the frame graph captures on CUDA (exposure and the fixed gamma as device tensors, the switch
    by torch.where), run eagerly on the CPU against RetinexGSModel.enhance for every setting."""
    from retinexgs.model.inference import _EnhanceGraph
    from retinexgs.model.tone import log_lin_ref
    model = make_model(tone=tone, dtype=torch.float64, shoulder=shoulder)
    g = torch.Generator().manual_seed(5)
    image = torch.cat([torch.rand(12, 9, 3, generator=g), torch.rand(12, 9, 3, generator=g) * 0.3], -1).double()
    body = _EnhanceGraph.__new__(_EnhanceGraph)  # its state without the capture (CUDA only)
    body.model, body.image, body.size = model, image, 12 * 9 * 3
    body.log_ref = log_lin_ref(model.illum_ref, image)
    body.balanced = False
    for exposure, gamma in [(None, None), (0.5, None), (2.0, None), (None, 0.7)]:
        body.exposure = torch.tensor(1.0 if exposure is None else exposure, dtype=torch.float64)
        body.fixed = torch.tensor(1.0 if gamma is None else gamma, dtype=torch.float64)
        body.use_fixed = torch.tensor(gamma is not None)
        with torch.no_grad():
            out = body._body()
            ref = model.enhance(image[..., :3], image[..., 3:], exposure, gamma)
        torch.testing.assert_close(out[:body.size].view(12, 9, 3), ref["rgb"], rtol=0, atol=1e-12)
        torch.testing.assert_close(out[body.size:], ref["gamma"], rtol=0, atol=1e-12)
    if tone != "exposure":
        return
    # a balanced graph's body (issue 53): the balance inside the tone kernel, as the torch path applies it
    from retinexgs.model.tone import exposure_gain, highlight_shoulder, linear_to_srgb, srgb_to_linear, white_balance
    body.balanced = True
    body.balance = torch.tensor([[0.87, -0.19, -0.04], [0.01, 1.01, -0.01], [0.02, 0.07, 1.75]], dtype=torch.float64)
    body.exposure, body.use_fixed = torch.tensor(0.5, dtype=torch.float64), torch.tensor(False)
    with torch.no_grad():
        out = body._body()
        g = model.enhance(image[..., :3], image[..., 3:], 0.5)["gamma"]
        light = white_balance(exposure_gain(model.illum_ref, g) * srgb_to_linear(image[..., :3] * image[..., 3:]),
                              body.balance)
    torch.testing.assert_close(out[:body.size].view(12, 9, 3), linear_to_srgb(highlight_shoulder(light, shoulder)),
                               rtol=0, atol=1e-12)


def test_renderer_without_tile_culling_renders_the_same_frame():
    from retinexgs.model.inference import InferenceRenderer
    from scenes import make_camera
    model = make_model(n=600, tone="exposure")
    cam = make_camera(width=48, height=36, eye=(0.3, -0.2, -3.0))
    culled, unculled = InferenceRenderer(model, 3), InferenceRenderer(model, 3)
    culled.cull_tiles, unculled.cull_tiles = True, False
    a, b = culled.render(cam), unculled.render(cam)
    assert a["rgb"].std() > 0.01 and torch.equal(a["rgb"], b["rgb"]) and torch.equal(a["L"], b["L"])
