"""train.crop_pixels (issue 65): full-resolution crops of large views. The crop camera renders the window of the
whole render, the crop's size and position, the density statistic and the screen-size prune measured against the
whole view, training and resuming on crops, and the config's one-line errors."""
import pytest
import torch

from retinexgs.data import load_scene
from retinexgs.errors import UserError
from retinexgs.model.schedule import build_schedule
from retinexgs.render import rasterize_gaussians
from retinexgs.run.config import load_config
from retinexgs.strategy import DefaultStrategy
from retinexgs.train import losses
from retinexgs.train.crop import CropPolicy, crop_camera, crop_size, crop_view
from retinexgs.train.resolution import MIN_SIDE, downscale_view
from retinexgs.train.trainer import Trainer
from retinexgs.train.views import TrainView, unpack_edges, unpack_targets

from scenes import make_camera, random_gaussians
from test_resolution_schedule import scene_dir, trainer_for  # noqa: F401  (the 74x66 demo scene fixture)


def _render(camera, gaussians, means=None):
    m, q, s, o, c = gaussians
    return rasterize_gaussians(m if means is None else means, q, s, o, c, camera, validate=False)


# ---- the crop camera ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("x0, y0, w, h", [(13, 7, 37, 29), (0, 0, 20, 17), (50, 37, 20, 17), (5, 21, 64, 33)])
def test_a_render_of_the_crop_camera_is_the_window_of_the_whole_render(x0, y0, w, h):
    cam = make_camera(70, 54, cx_shift=2.1)
    g = tuple(t.float() for t in random_gaussians(150, seed=3, spread=1.2))
    whole = _render(cam, g).image
    crop = _render(crop_camera(cam, x0, y0, w, h), g).image
    assert crop.shape == (h, w, 3)
    assert whole[y0:y0 + h, x0:x0 + w].abs().max() > 0.1  # the window shows Gaussians
    torch.testing.assert_close(crop, whole[y0:y0 + h, x0:x0 + w], rtol=0, atol=2e-6)


def test_the_crop_cameras_projection_matches_the_reference_and_its_gradients_hold():
    """The guard band is the whole frame's in the kernels (forward and backward) and the reference alike: a crop
    away from the principal point, with Gaussians inside it that the crop's own band would clamp."""
    from torch.autograd import gradcheck
    from retinexgs.render.functions import ProjectGaussians
    from retinexgs.render.reference import project_reference
    cam = make_camera(70, 54)
    crop = crop_camera(cam, 52, 38, 18, 16)  # the bottom-right corner: the principal point far outside
    assert crop.frame_box == (-52.0, -38.0, 18.0, 16.0)
    means, quats, scales, opac, _ = random_gaussians(40, seed=5, spread=1.2, scale_range=(-2.0, -1.2))
    got = ProjectGaussians.apply(means, quats, scales, opac, crop)[:4]
    want = project_reference(means, quats, scales, opac, crop)
    assert (got[3] > 0).any(dim=-1).sum() >= 3 and torch.equal(got[3], want[3])
    for a, b in zip(got[:3], want[:3]):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)
    whole = ProjectGaussians.apply(means, quats, scales, opac, cam)
    seen = (got[3] > 0).any(dim=-1)
    torch.testing.assert_close(got[2][seen], whole[2][seen], rtol=1e-12, atol=1e-12)  # the conics: the view's
    m, q, sc = (t[seen].clone().requires_grad_() for t in (means, quats, scales))
    assert gradcheck(lambda a, b, c: ProjectGaussians.apply(a, b, c, opac[seen], crop)[:3], (m, q, sc),
                     eps=1e-6, atol=1e-5, rtol=1e-4)


def test_a_crop_view_slices_every_map_and_rebuilds_packed_targets_and_edges():
    gen = torch.Generator().manual_seed(2)
    H, W = 40, 52
    S, R, L = (torch.rand(H, W, c, generator=gen) for c in (3, 3, 1))
    tv = TrainView(make_camera(W, H), S, R, L, target=S, center=torch.zeros(3))
    tv.pack(True, depth_edge=10.0)  # already packed: its maps are views of the packed tensor
    c = crop_view(tv, 9, 5, 30, 23)
    assert c.packed is None and c.edges is None and c.target is c.S and c.center is tv.center
    assert c.size == (W, H) and c.pixel_share == pytest.approx(30 * 23 / (W * H))
    for a, b in ((c.S, S), (c.R, R), (c.L, L)):
        assert torch.equal(a, b[5:28, 9:39])
    s2, r2, l2 = unpack_targets(c.pack(True, depth_edge=10.0), True, True)
    assert torch.equal(r2, R[5:28, 9:39]) and torch.equal(l2, L[5:28, 9:39])
    wx, wy = losses.edge_weights(R.permute(2, 0, 1).unsqueeze(0), 10.0)  # the whole view's, sliced
    ux, uy = unpack_edges(c.packed)
    assert torch.equal(ux, wx[..., 5:28, 9:38]) and torch.equal(uy, wy[..., 5:27, 9:39])
    pre = TrainView(make_camera(W, H), S, R, L, target=R * L)  # a baseline's own target is sliced too
    assert torch.equal(crop_view(pre, 9, 5, 30, 23).target, (R * L)[5:28, 9:39])


# ---- sizes and positions --------------------------------------------------------------------------------------

@pytest.mark.parametrize("W, H, P", [(4000, 3000, 1048576), (3000, 4000, 1048576), (640, 360, 50000),
                                     (74, 66, 1200), (101, 103, 10000), (4000, 3000, 12000000)])
def test_crop_sizes_keep_the_aspect_and_stay_within_the_pixels(W, H, P):
    w, h = crop_size(W, H, P)
    assert w * h <= P and w <= W and h <= H and min(w, h) >= MIN_SIDE
    assert abs(w / h - W / H) <= (W / H) * (1 / h + 1 / w) + 1e-9  # the aspect, to a pixel a side
    assert (w + 1) * (h + 1) > P  # not needlessly small


def test_a_view_at_or_below_the_pixels_is_the_view_itself():
    tv = TrainView(make_camera(45, 37), torch.rand(37, 45, 3))
    assert CropPolicy(45 * 37, seed=0).view_at(tv, 0, 1) is tv
    assert CropPolicy(0, seed=0).view_at(tv, 0, 1) is tv  # off
    small = CropPolicy(45 * 37 - 1, seed=0).view_at(tv, 0, 1)
    assert small is not tv and small.camera.width * small.camera.height < 45 * 37


def test_positions_are_seeded_by_run_step_and_view_and_cover_every_position():
    W, H = 60, 44
    w, h = crop_size(W, H, 1500)
    a, b, other = CropPolicy(1500, seed=7), CropPolicy(1500, seed=7), CropPolicy(1500, seed=8)
    corners = [a.corner(W, H, w, h, s, v) for s in range(1, 1001) for v in (0, 3)]
    assert corners == [b.corner(W, H, w, h, s, v) for s in range(1, 1001) for v in (0, 3)]
    assert sum(c != other.corner(W, H, w, h, s, v) for c, (s, v) in
               zip(corners, [(s, v) for s in range(1, 1001) for v in (0, 3)])) > 1900
    assert a.corner(W, H, w, h, 5, 0) != a.corner(W, H, w, h, 5, 3)  # another view, another crop
    xs, ys = {x for x, _ in corners}, {y for _, y in corners}
    assert xs == set(range(W - w + 1)) and ys == set(range(H - h + 1))  # corners included


# ---- the statistics ---------------------------------------------------------------------------------------------

def _statistic(strategy_cfg, camera, tv, gaussians, width, height, share):
    """The default strategy's densification statistic after one backward of the mean over the pixels of the
    render's channels (a per-pixel error of 1 everywhere, the same in any window)."""
    s = DefaultStrategy(strategy_cfg.density, 1.0, build_schedule(strategy_cfg))
    means = gaussians[0].clone().requires_grad_(True)
    out = _render(camera, gaussians, means)
    out.image.mean().backward()
    s.after_backward(out, width, height, share)
    return s.densification_statistic()


def test_the_density_statistic_of_a_crop_step_is_the_whole_view_steps():
    cfg = load_config([], [])
    cam = make_camera(96, 80)
    # Small Gaussians near the centre: every one of them lies wholly inside the centred crop.
    g = tuple(t.float() for t in random_gaussians(12, seed=4, spread=0.25, scale_range=(-4.0, -3.5),
                                                  opacity_range=(0.5, 0.9)))
    tv = TrainView(cam, torch.zeros(80, 96, 3))
    w, h = crop_size(96, 80, 2000)
    crop = crop_view(tv, (96 - w) // 2, (80 - h) // 2, w, h)
    whole = _statistic(cfg, cam, tv, g, 96, 80, 1.0)
    assert (whole > 0).sum() >= 10
    got = _statistic(cfg, crop.camera, crop, g, *crop.size, crop.pixel_share)
    torch.testing.assert_close(got, whole, rtol=1e-4, atol=1e-9)
    naive = _statistic(cfg, crop.camera, crop, g, crop.camera.width, crop.camera.height, 1.0)
    ratio = (naive[whole > 0] / whole[whole > 0]).median()
    assert ratio == pytest.approx((96 * 80 / (w * h)) ** 0.5, rel=0.05)  # what the fix removes: ~2 here


# ---- training ---------------------------------------------------------------------------------------------------

def _crop_trainer(scene_dir, run, extra=(), log=None, emulate_graphs=False):
    cfg = load_config(["demo"], ["checkpoint.every=3", "log.every=1", "log.tensorboard=false", "model.sh_degree=1",
                                 "model.max_init_points=300", "decomposer.method=lime", "eval.lpips=false",
                                 "train.crop_pixels=1200", *extra])
    run.mkdir(parents=True, exist_ok=True)
    return Trainer(cfg, load_scene(scene_dir), run, "cpu", progress=False, log=log or (lambda s: None),
                   emulate_graphs=emulate_graphs)


def _spy(tr):
    """Record each step's crop (camera) and what the strategy is handed."""
    seen = {"render": [], "after_backward": [], "step": []}
    render, after, step = tr.render_view, tr.strategy.after_backward, tr.strategy.step

    def render_spy(tv, s, graphed=True):
        seen["render"].append((s, tv.camera.width, tv.camera.height, tv.camera.cx, tv.camera.cy,
                               tuple(tv.S.shape[:2])))
        return render(tv, s, graphed)

    def after_spy(out, width, height, pixel_share=1.0):
        seen["after_backward"].append((width, height, pixel_share))
        return after(out, width, height, pixel_share)

    def step_spy(s, model, optimizer, image_size):
        seen["step"].append(image_size)
        return step(s, model, optimizer, image_size)

    tr.render_view, tr.strategy.after_backward, tr.strategy.step = render_spy, after_spy, step_spy
    return seen


def test_training_on_crops_completes_logs_them_and_hands_the_strategy_the_whole_view(scene_dir, tmp_path):
    lines = []
    tr = _crop_trainer(scene_dir, tmp_path / "run", ["steps=6"], log=lines.append)
    seen = _spy(tr)
    tr.train()
    assert any("train.crop_pixels" in line for line in lines)
    w, h = crop_size(74, 66, 1200)  # 36x32
    steps = [r for r in seen["render"] if r[0] >= 1]
    assert len(steps) == 6 and all(r[1:3] == (w, h) and r[5] == (h, w) for r in steps)
    assert len({(r[3], r[4]) for r in steps}) > 1  # the crops move
    assert seen["after_backward"] == [(74, 66, w * h / (74 * 66))] * 6
    assert seen["step"] == [74] * 6  # the screen-size prune's reference: the whole view's side
    assert all(torch.isfinite(p).all() for p in tr.model.parameters())


def test_streamed_views_are_cropped_after_their_fetch_as_preloaded_ones_are(scene_dir, tmp_path):
    """A streamed view is fetched whole and cropped on the device: the same crops and the same training as
    preloaded views, through the graphed loss path (emulated on the CPU)."""
    runs = {}
    for stream in ("never", "always"):
        tr = _crop_trainer(scene_dir, tmp_path / stream, ["steps=4", f"train.stream_views={stream}"],
                           emulate_graphs=True)
        seen = _spy(tr)
        tr.train()
        assert tr.streamed == (stream == "always")
        runs[stream] = (seen["render"], dict(tr.model.named_parameters()))
    assert runs["never"][0] == runs["always"][0]
    assert all(r[1:3] == crop_size(74, 66, 1200) for r in runs["always"][0] if r[0] >= 1)
    for name, p in runs["never"][1].items():
        assert torch.equal(p, runs["always"][1][name]), name


def test_the_screen_size_prune_measures_radii_against_the_whole_view():
    """The trainer hands the strategy the whole view's side (the test above); a radius of 30 px is kept against a
    200 px view (0.2 · 200 = 40) and would be pruned against a 60 px crop's side (12)."""
    from retinexgs.model.gaussians import GaussianModel
    cfg = load_config([], ["density.max_screen_fraction=0.2"])
    s = DefaultStrategy(cfg.density, 1e6, build_schedule(cfg))  # a huge extent: no world-size prune
    step = next(i for i in range(1, 10**6) if s.schedule.densify_at(i) and s.schedule.prune_large_at(i))

    def kept(image_size):
        model = GaussianModel.from_points(torch.tensor([[0.0, 0, 0], [1.0, 0, 0]]), torch.full((2, 3), 0.5), 0, 0.9)
        opt = torch.optim.Adam([{"params": [p], "name": n, "lr": 1e-3} for n, p in model.tensors().items()])
        s._ensure(2, torch.device("cpu"))
        s.max_radius = torch.tensor([30.0, 5.0])  # pixels at the view's scale (a crop's are the view's)
        s.densify_and_prune(step, model, opt, image_size)
        return len(model)

    assert kept(200) == 2
    assert kept(60) == 1


def test_a_resumed_run_trains_on_the_same_crops_as_a_straight_one(scene_dir, tmp_path):
    straight = _crop_trainer(scene_dir, tmp_path / "straight", ["steps=6"])
    seen_straight = _spy(straight)
    straight.train()
    run = tmp_path / "run"
    first = _crop_trainer(scene_dir, run, ["steps=6"])
    first.train(stop_after=3)
    resumed = Trainer(first.cfg, first.scene, run, "cpu", resume=True, progress=False, log=lambda s: None)
    assert resumed.step == 3
    seen = _spy(resumed)
    resumed.train()
    crops = lambda rows: [r for r in rows if r[0] >= 4]  # noqa: E731
    assert crops(seen["render"]) == crops(seen_straight["render"])
    for k, v in straight.model.state_dict().items():
        torch.testing.assert_close(resumed.model.state_dict()[k], v, rtol=1e-4, atol=1e-5, msg=k)
    other = _crop_trainer(scene_dir, tmp_path / "other", ["steps=6", "seed=1"])
    assert [other.crop.corner(74, 66, 36, 32, s, 0) for s in range(1, 7)] != \
        [straight.crop.corner(74, 66, 36, 32, s, 0) for s in range(1, 7)]


def test_crops_follow_the_resolution_schedules_pooled_view():
    tv = TrainView(make_camera(120, 100), torch.rand(100, 120, 3))
    policy = CropPolicy(2000, seed=0)
    pooled = downscale_view(tv, 2)  # 60x50 = 3000 px > 2000: cropped, measured against the pooled view
    c = policy.view_at(pooled, 0, 1)
    assert c.size == (60, 50) and (c.camera.width, c.camera.height) == crop_size(60, 50, 2000)
    assert policy.view_at(downscale_view(tv, 4), 0, 1).camera.width == 30  # 30x25 = 750 px: whole


# ---- config errors ----------------------------------------------------------------------------------------------

def test_a_negative_crop_is_refused_in_one_line():
    with pytest.raises(UserError, match="crop_pixels") as err:
        load_config([], ["train.crop_pixels=-5"])
    assert "\n" not in str(err.value)


def test_a_crop_below_the_smallest_side_is_refused_before_training_in_one_line(scene_dir, tmp_path):
    with pytest.raises(UserError, match=r"train.crop_pixels: 200 pixels crop training view 0 \(74x66\) to 14x13") as err:
        _crop_trainer(scene_dir, tmp_path / "run", ["steps=3", "train.crop_pixels=200"])
    assert "\n" not in str(err.value) and "below 16 px" in str(err.value)
    with pytest.raises(UserError, match=r"to 36x32, below 40 px"):  # a patched L_exp needs a whole patch
        _crop_trainer(scene_dir, tmp_path / "run3", ["steps=3", "loss.exp_patch=40"])


def test_views_that_train_whole_are_not_checked_against_the_smallest_side():
    # crops off, or a view with no more pixels than a crop: trained whole, so a view below 16 px a side is fine
    # (the downscaled 16x12 views of tests/test_bad_inputs_data_export.py failed here before)
    for sets in ([], ["train.crop_pixels=1000"]):
        policy = CropPolicy.from_config(load_config([], sets), [(16, 12), (12, 10)], [1, 2])
        assert not policy.crops(16, 12)
    with pytest.raises(UserError, match=r"train.crop_pixels: 100 pixels crop training view 0 \(16x12\)"):
        CropPolicy.from_config(load_config([], ["train.crop_pixels=100"]), [(16, 12)])
