"""train.resolution (issue 65): the coarse-to-fine schedule's values, the downscaled camera and maps, training on
it (preloaded and streamed views, the graphed loss path), and the default's bit-identical steps."""
import pytest
import torch

from retinexgs.data import load_scene
from retinexgs.demo.synthetic import make_demo_scene
from retinexgs.errors import UserError
from retinexgs.render.reference import project_reference, rasterize_gaussians_reference
from retinexgs.run.config import load_config
from retinexgs.train import losses
from retinexgs.train.resolution import ResolutionSchedule, downscale_camera, downscale_view, pool_map
from retinexgs.train.trainer import Trainer
from retinexgs.train.views import TrainView, unpack_edges, unpack_targets

from scenes import make_camera, random_gaussians

TINY = ["checkpoint.every=1000", "log.every=1", "log.tensorboard=false", "model.sh_degree=1",
        "model.max_init_points=300", "decomposer.method=lime", "eval.lpips=false", "density.start=1000"]


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    # 74x66: not a multiple of 4 (the crop) and 1/4 still >= 16 px a side
    return make_demo_scene(tmp_path_factory.mktemp("scene") / "demo", n_train=3, n_test=1, width=74, height=66,
                           n_points=300)


def trainer_for(scene_dir, run, overrides=(), emulate_graphs=False):
    cfg = load_config(["demo"], TINY + list(overrides))
    run.mkdir(parents=True, exist_ok=True)
    return Trainer(cfg, load_scene(scene_dir), run, "cpu", progress=False, log=lambda s: None,
                   emulate_graphs=emulate_graphs)


# ---- the schedule ------------------------------------------------------------------------------------------

def test_schedule_values_fractions_and_steps():
    cfg = load_config([], ["steps=100", "train.resolution=[[0.2, 4], [0.5, 2]]"])
    rs = ResolutionSchedule.from_config(cfg)
    assert rs.enabled
    assert [rs.downsample_at(s) for s in (1, 20, 21, 50, 51, 100)] == [4, 4, 2, 2, 1, 1]
    assert rs.describe() == "resolution: 1/4 until step 20, 1/2 until step 50, full size after"
    rs = ResolutionSchedule.from_config(load_config([], ["steps=100", "train.resolution=[[30, 3]]"]))
    assert [rs.downsample_at(s) for s in (1, 30, 31)] == [3, 3, 1]


def test_no_schedule_is_full_size_and_returns_the_view_itself():
    rs = ResolutionSchedule.from_config(load_config([], ["train.resolution=[]"]))
    assert not rs.enabled and rs.stages == []
    tv = TrainView(make_camera(), torch.rand(37, 45, 3))
    assert rs.view_at(tv, 0, 1) is tv


def test_views_below_the_pixel_threshold_train_at_full_size():
    rs = ResolutionSchedule([(10, 4), (20, 2)], 30, min_pixels=6_000_000)
    assert rs.on_schedule(4000, 3000) and rs.on_schedule(3000, 2000)  # 6 MP: on the schedule
    assert not rs.on_schedule(2999, 2000) and not rs.on_schedule(2000, 1500)
    assert not rs.on_schedule(1920, 1080) and not rs.on_schedule(640, 360)
    assert ResolutionSchedule([(10, 4)], 30).on_schedule(64, 48)  # 0: every view
    tv = TrainView(make_camera(45, 37), torch.rand(37, 45, 3))  # 1665 pixels: below a threshold of 1666
    assert ResolutionSchedule([(10, 2)], 30, min_pixels=1666).view_at(tv, 0, 1) is tv
    pooled = ResolutionSchedule([(10, 2)], 30, min_pixels=1665).view_at(tv, 0, 1)
    assert (pooled.camera.width, pooled.camera.height) == (22, 18)


def test_the_default_pools_12_megapixel_views_and_leaves_small_ones_at_full_size():
    cfg = load_config([], ["steps=10000"])
    big = ResolutionSchedule.from_config(cfg, [(4000, 3000)] * 2)
    assert big.enabled
    assert big.describe() == "resolution: 1/4 until step 8000, 1/2 until step 9500, full size after"
    small = ResolutionSchedule.from_config(cfg, [(640, 360), (500, 375), (2000, 1500)])
    assert not small.enabled
    assert small.describe() == ("resolution: full size throughout (every view below "
                                "train.resolution_min_pixels=6000000)")
    tv = TrainView(make_camera(45, 37), torch.rand(37, 45, 3))
    assert all(small.view_at(tv, 0, s) is tv for s in (1, 8001, 9501))
    mixed = ResolutionSchedule.from_config(cfg, [(2000, 1500), (4000, 3000)])
    assert mixed.describe() == ("resolution: full size or 1/4 until step 8000, full size or 1/2 until step 9500, "
                                "full size after (views below train.resolution_min_pixels=6000000 at full size)")


def test_a_stage_pools_the_large_views_of_a_mixed_scene_and_hands_the_small_ones_on():
    rs = ResolutionSchedule([(10, 2)], 20, min_pixels=1000, sizes=[(45, 37), (20, 18)])
    big = TrainView(make_camera(45, 37), torch.rand(37, 45, 3))
    small = TrainView(make_camera(20, 18), torch.rand(18, 20, 3))
    pooled = rs.view_at(big, 0, 1)
    assert (pooled.camera.width, pooled.camera.height) == (22, 18) and rs.view_at(big, 0, 2) is pooled  # kept
    assert rs.view_at(small, 1, 1) is small  # 360 < 1000 pixels: full size
    assert rs.view_at(big, 0, 11) is big  # after the stage


def test_stages_that_train_no_step_are_dropped():
    """The default's fractions in a run of a few steps: 0.8 and 0.95 of 2 steps are both step 2."""
    rs = ResolutionSchedule.from_config(load_config([], ["steps=2"]))
    assert rs.stages == [(2, 4)] and [rs.downsample_at(s) for s in (1, 2, 3)] == [4, 4, 1]
    assert ResolutionSchedule([(0, 4), (5, 2), (5, 1)], 10).stages == [(5, 2)]


@pytest.mark.parametrize("value, words", [("[[0.5, 2], [0.2, 1]]", "must increase"),
                                          ("[[0.2, 2], [0.5, 4]]", "must not grow")])
def test_a_schedule_out_of_order_is_refused_in_one_line(value, words):
    with pytest.raises(UserError, match=words) as err:
        ResolutionSchedule.from_config(load_config([], ["steps=100", f"train.resolution={value}"]))
    assert "\n" not in str(err.value)


def test_a_downsample_that_leaves_too_few_pixels_is_refused():
    rs = ResolutionSchedule([(10, 4)], 100)
    tv = TrainView(make_camera(45, 37), torch.rand(37, 45, 3))
    with pytest.raises(UserError, match="below 16 px"):
        rs.view_at(tv, 0, 1)


# ---- the downscaled camera and maps -------------------------------------------------------------------------

def test_pooled_maps_are_exact_area_means_cropped_at_the_far_edges():
    g = torch.Generator().manual_seed(0)
    x = torch.randint(0, 256, (37, 45, 3), generator=g).float() / 256  # dyadic: the means are exact in float32
    for k in (2, 3, 4):
        H, W = 37 // k, 45 // k
        ref = x[:H * k, :W * k].reshape(H, k, W, k, 3).double().mean(dim=(1, 3)).float()
        got = pool_map(x, k)
        assert got.shape == (H, W, 3)
        if k in (2, 4):  # k² a power of two: the float32 mean is exact
            assert torch.equal(got, ref)
        else:
            torch.testing.assert_close(got, ref, rtol=0, atol=1e-6)


@pytest.mark.parametrize("k", [2, 3, 4])
def test_downscaled_camera_projects_into_the_pooled_pixel_of_the_full_size_projection(k):
    cam = make_camera(45, 37, cx_shift=1.3)
    small = downscale_camera(cam, k)
    assert (small.width, small.height) == (45 // k, 37 // k)
    means, quats, scales, opac, _ = random_gaussians(200, seed=1, spread=0.9)
    full = project_reference(means, quats, scales, opac, cam)[0]
    low = project_reference(means, quats, scales, opac, small)[0]
    inside = ((full[:, 0] >= 0) & (full[:, 0] < small.width * k) & (full[:, 1] >= 0)
              & (full[:, 1] < small.height * k))
    assert inside.sum() > 50
    centre = torch.floor(full[inside] / k) + 0.5  # the centre of the pooled pixel that holds the full projection
    assert (low[inside] - centre).abs().max() <= 0.5
    torch.testing.assert_close(low, full / k)


def test_a_render_at_the_downscaled_camera_matches_the_pooled_full_size_render():
    """The raster's own pixel convention: a small Gaussian's centroid in the low-resolution render is where it
    is in the pooled full-size render (within a tenth of a pooled pixel)."""
    k = 4
    cam = make_camera(70, 54, cx_shift=2.1)
    small = downscale_camera(cam, k)
    means = torch.tensor([[0.23, -0.11, 0.0]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    scales = torch.full((1, 3), 0.12, dtype=torch.float64)
    opac = torch.tensor([0.9], dtype=torch.float64)
    col = torch.ones(1, 1, dtype=torch.float64)

    def centroid(img):
        w = img[..., 0]
        ys, xs = torch.meshgrid(torch.arange(w.shape[0], dtype=w.dtype) + 0.5,
                                torch.arange(w.shape[1], dtype=w.dtype) + 0.5, indexing="ij")
        return torch.stack([(w * xs).sum() / w.sum(), (w * ys).sum() / w.sum()])

    hi = rasterize_gaussians_reference(means, quats, scales, opac, col, cam).image
    lo = rasterize_gaussians_reference(means, quats, scales, opac, col, small).image
    assert lo.shape[:2] == (54 // k, 70 // k)
    assert (centroid(lo) - centroid(pool_map(hi, k))).abs().max() < 0.1


def test_downscaled_view_pools_every_map_and_rebuilds_packed_targets_and_edges():
    g = torch.Generator().manual_seed(2)
    H, W, k = 37, 45, 2
    S, R, L = (torch.rand(H, W, c, generator=g) for c in (3, 3, 1))
    tv = TrainView(make_camera(W, H), S, R, L, target=S, center=torch.zeros(3))
    tv.pack(True, depth_edge=10.0)  # a view already packed (its maps are views of the packed tensor)
    small = downscale_view(tv, k)
    assert small.packed is None and small.edges is None and small.target is small.S
    for a, b in ((small.S, S), (small.R, R), (small.L, L)):
        assert torch.equal(a, pool_map(b, k))
    packed = small.pack(True, depth_edge=10.0)
    assert packed.shape == (H // k, W // k, 9)
    s2, r2, l2 = unpack_targets(packed, True, True)
    assert torch.equal(r2, pool_map(R, k)) and torch.equal(l2, pool_map(L, k))
    wx, wy = losses.edge_weights(pool_map(R, k).permute(2, 0, 1).unsqueeze(0), 10.0)
    ux, uy = unpack_edges(packed)
    assert torch.equal(ux, wx) and torch.equal(uy, wy)
    # a baseline's own target (the pre-enhancement baseline's) is pooled too
    pre = TrainView(make_camera(W, H), S, R, L, target=R * L)
    assert torch.equal(downscale_view(pre, k).target, pool_map(R * L, k))


# ---- training ---------------------------------------------------------------------------------------------

def _full_size_loss(tr, i=0):
    """View i's loss at full size, as at step 1 (before the enhancement losses switch on)."""
    with torch.no_grad():
        res = tr.render_view(tr.views[i], 1, graphed=False)
        return float(tr.objective.loss(res, tr.views[i], 1)["total"])


@pytest.mark.parametrize("stream", ["never", "always"])
def test_training_on_the_schedule_trains_at_each_stage_and_the_loss_falls(scene_dir, tmp_path, stream):
    tr = trainer_for(scene_dir, tmp_path / "run", ["steps=24", "train.resolution=[[0.25, 4], [0.5, 2]]",
                                                   "train.resolution_min_pixels=0", f"train.stream_views={stream}"],
                     emulate_graphs=True)
    sizes = []
    render = tr.render_view

    def spy(tv, step, graphed=True):
        sizes.append((step, tv.camera.width, tv.camera.height, tuple(tv.S.shape[:2])))
        return render(tv, step, graphed)

    before = [_full_size_loss(tr, i) for i in range(len(tr.views))]
    tr.render_view = spy
    tr.train()
    tr.render_view = render
    after = [_full_size_loss(tr, i) for i in range(len(tr.views))]
    by_step = {s: (w, h, shape) for s, w, h, shape in sizes if s >= 1}
    assert by_step[1] == (18, 16, (16, 18)) and by_step[6] == (18, 16, (16, 18))
    assert by_step[7] == (37, 33, (33, 37)) and by_step[12] == (37, 33, (33, 37))
    assert by_step[13] == (74, 66, (66, 74)) and by_step[24] == (74, 66, (66, 74))
    assert sum(after) < 0.99 * sum(before), (before, after)  # 24 steps: 0.981 (0.978 at full size throughout)
    if stream == "never":  # preloaded: the last stage's pooled views were freed when it ended
        assert tr.resolution._cache == {}


def test_the_default_trains_bit_identically_to_the_loop_without_a_schedule(scene_dir, tmp_path):
    """The default leaves every step of views below its pixel floor (these 74 x 66) as it was: the same parameters
    as a loop that hands the views on untouched."""
    def trained(name, overrides=(), plain_loop=False):  # each seeded and trained in turn (one global RNG)
        tr = trainer_for(scene_dir, tmp_path / name, ["steps=3", *overrides])
        if plain_loop:
            tr.resolution.view_at = lambda tv, i, step, cache=True: tv  # the loop before train.resolution
        tr.train()
        return tr

    a, b = trained("a"), trained("b", plain_loop=True)
    c = trained("c", ["train.resolution=[[1, 2]]", "train.resolution_min_pixels=0"])  # step 1 at 1/2
    pa, pb, pc = (dict(tr.model.named_parameters()) for tr in (a, b, c))
    assert pa.keys() == pb.keys()
    for name in pa:
        assert torch.equal(pa[name], pb[name]), name
    assert not torch.equal(pa["gaussians.means"], pc["gaussians.means"])  # the comparison sees a change


def test_streamed_coarse_stages_keep_their_pooled_views_where_they_fit(scene_dir, tmp_path):
    """Streamed views: a coarse stage whose pooled views fit train.views_on_device_gb fetches each full-size view
    once a stage, not every step; the training is bit-identical to pooling every step (budget 0)."""
    from retinexgs.train.streamed_views import StreamedViews

    def trained(name, budget):
        tr = trainer_for(scene_dir, tmp_path / name, ["steps=24", "train.resolution=[[0.25, 4], [0.5, 2]]",
                                                      "train.resolution_min_pixels=0", "train.stream_views=always",
                                                      f"train.views_on_device_gb={budget}"])
        fetched = []
        get = StreamedViews.get

        def counting(views, i, prefetch=True):
            fetched.append((tr.step, int(i)))
            return get(views, i, prefetch)

        with pytest.MonkeyPatch.context() as m:
            m.setattr(StreamedViews, "get", counting)
            tr.train()
        return tr, fetched

    kept, fetched_kept = trained("kept", 2)
    pooled, fetched_pooled = trained("pooled", 0)
    assert kept.streamed and pooled.streamed
    assert kept.resolution.keeps_streamed(4) and kept.resolution.keeps_streamed(2)
    assert not pooled.resolution.keeps_streamed(4)
    stage = lambda fetched, lo, hi: [i for s, i in fetched if lo <= s <= hi]  # noqa: E731
    for lo, hi in ((1, 6), (7, 12)):  # the coarse stages: each of the 3 views fetched once when kept
        assert sorted(stage(fetched_kept, lo, hi)) == sorted(set(stage(fetched_pooled, lo, hi)))
        assert len(stage(fetched_pooled, lo, hi)) == 6  # every step when not
    assert len(stage(fetched_kept, 13, 24)) == len(stage(fetched_pooled, 13, 24)) == 12  # full size: every step
    pk, pp = dict(kept.model.named_parameters()), dict(pooled.model.named_parameters())
    for name in pk:
        assert torch.equal(pk[name], pp[name]), name


def test_the_streamed_plan_counts_only_the_views_a_stage_pools():
    """A stage keeps its pooled views where they fit the budget; views below the threshold are streamed at full size
    and do not count. Without the views' sizes nothing is kept."""
    rs = ResolutionSchedule([(10, 4), (20, 2)], 30, min_pixels=1000, sizes=[(100, 100), (20, 20)])
    rs.plan_streamed(100, 25 * 25 * 100 / 1e9)  # exactly the large view at 1/4; the 20 x 20 one is not pooled
    assert rs.keeps_streamed(4) and not rs.keeps_streamed(2)
    bare = ResolutionSchedule([(10, 4)], 30)
    bare.plan_streamed(100, 1.0)
    assert not bare.keeps_streamed(4)
