"""decomposer.redenoise_at: the views' 2D priors made again from the views re-denoised with the model's render as
the Wiener pilot (issue 64 item 1, retinexgs/train/redenoise.py)."""
import pytest
import torch

from retinexgs.data import load_scene
from retinexgs.demo.synthetic import make_demo_scene
from retinexgs.errors import UserError
from retinexgs.run.config import load_config
from retinexgs.train.redenoise import redenoise_steps
from retinexgs.train.trainer import Trainer

TINY = ["steps=6", "checkpoint.every=3", "log.every=1", "log.tensorboard=false", "model.sh_degree=1",
        "model.sh_degree_every=2", "model.max_init_points=300", "loss.enhance_from=4", "density.start=100",
        "decomposer.method=lime", "train.stream_views=never"]


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return make_demo_scene(tmp_path_factory.mktemp("scene") / "demo", n_train=4, n_test=2, width=64, height=48,
                           n_points=400)


def trainer_for(scene_dir, run, overrides=(), resume=False):
    cfg = load_config(["demo"], list(TINY) + list(overrides))
    run.mkdir(parents=True, exist_ok=True)
    return Trainer(cfg, load_scene(scene_dir), run, "cpu", resume=resume, progress=False, log=lambda s: None)


def priors(tr):
    return [(v.R.clone(), v.L.clone()) for v in tr.views]


def test_steps_resolve_fractions_and_drop_the_ends():
    cfg = load_config(["demo"], ["steps=100", "decomposer.redenoise_at=[0.5, 30, 0, 100, 0.3]"])
    assert redenoise_steps(cfg) == [30, 50]
    with pytest.raises(UserError, match="redenoise_at"):
        load_config(["demo"], ["decomposer.redenoise_at=[fast]"])


@pytest.mark.parametrize("chroma,source", [("pilot", "render"), ("denoiser", "render"), ("pilot", "views")])
def test_the_priors_are_replaced_at_the_step_and_training_goes_on(scene_dir, tmp_path, chroma, source):
    tr = trainer_for(scene_dir, tmp_path / "run", ["decomposer.redenoise_at=[3]",
                                                   f"decomposer.redenoise_chroma={chroma}",
                                                   f"decomposer.redenoise_source={source}"])
    before = priors(tr)
    tr.train(stop_after=2)
    assert all(torch.equal(R, v.R) for (R, _), v in zip(before, tr.views))  # not yet
    tr.train(stop_after=1)  # step 3: re-denoised after it
    after = priors(tr)
    assert all(not torch.equal(R0, R1) for (R0, _), (R1, _) in zip(before, after))
    assert all(R1.shape == R0.shape and L1.shape == L0.shape and torch.isfinite(R1).all() and torch.isfinite(L1).all()
               for (R0, L0), (R1, L1) in zip(before, after))
    assert all(v.packed is None or torch.equal(v.packed[..., 3:6], v.R) for v in tr.views)
    tr.train()
    assert tr.step == 6


def test_a_resumed_run_re_denoises_what_it_had_re_denoised(scene_dir, tmp_path):
    run = tmp_path / "run"
    tr = trainer_for(scene_dir, run, ["decomposer.redenoise_at=[2]"])
    tr.train(stop_after=3)  # re-denoised after step 2, checkpoint at 3
    again = trainer_for(scene_dir, run, ["decomposer.redenoise_at=[2]"], resume=True)
    fresh = priors(again)
    again.train(stop_after=1)
    assert all(not torch.equal(R0, v.R) for (R0, _), v in zip(fresh, again.views))
    off = trainer_for(scene_dir, run, [], resume=True)  # without the key nothing is re-denoised
    fresh = priors(off)
    off.train(stop_after=1)
    assert all(torch.equal(R0, v.R) for (R0, _), v in zip(fresh, off.views))


@pytest.mark.parametrize("overrides,match", [
    (["method=3dgs"], "method retinexgs"),
    (["decomposer.method=none"], "decomposer"),
    (["train.stream_views=always"], "streamed"),
])
def test_where_it_cannot_run_one_line_says_why(scene_dir, tmp_path, overrides, match):
    with pytest.raises(UserError, match=match):
        trainer_for(scene_dir, tmp_path / "run", ["decomposer.redenoise_at=[3]"] + overrides)


def test_the_chroma_choice_changes_the_priors(scene_dir, tmp_path):
    """``decomposer.redenoise_chroma``: the same run re-denoised with the render's chroma gains or with the single-view
    denoiser's chroma ends with other priors (the luma filtering alike)."""
    out = []
    for chroma in ("pilot", "denoiser"):
        tr = trainer_for(scene_dir, tmp_path / chroma, ["decomposer.redenoise_at=[2]",
                                                        f"decomposer.redenoise_chroma={chroma}"])
        tr.train(stop_after=2)
        out.append(priors(tr))
    assert any(not torch.equal(a[0], b[0]) for a, b in zip(*out))


def test_the_views_source_averages_the_neighbours_in(scene_dir, tmp_path, monkeypatch):
    """``decomposer.redenoise_source: views``: every view is averaged with its neighbours warped in, and the
    priors differ from the render's Wiener filter's."""
    import retinexgs.train.redenoise as rd
    from retinexgs.train.view_warp import neighbours

    calls = []
    real = rd.warp_average

    def spy(target, sources, *a, **k):
        calls.append((target.camera, [s.camera for s in sources]))
        avg, count = real(target, sources, *a, **k)
        assert avg.shape == target.light.shape and bool((count >= 1).all())
        return avg, count

    monkeypatch.setattr(rd, "warp_average", spy)
    out = {}
    for source in ("render", "views"):
        tr = trainer_for(scene_dir, tmp_path / source, ["decomposer.redenoise_at=[2]",
                                                        f"decomposer.redenoise_source={source}"])
        tr.train(stop_after=2)
        out[source] = priors(tr)
    cams = [v.camera for v in tr.views]
    assert [c for c, _ in calls] == cams  # once per view, the render source never warps
    # the sources: the others facing within 60° (the demo's 4 views are spread: views 0 and 1 see each other)
    assert [srcs for _, srcs in calls] == [[cams[j] for j in neighbours(cams, i, 16)] for i in range(len(cams))]
    assert calls[0][1] == [cams[1]] and calls[1][1] == [cams[0]]
    assert any(not torch.equal(a[0], b[0]) for a, b in zip(out["render"], out["views"]))
    with pytest.raises(UserError, match="redenoise_source"):
        load_config(["demo"], ["decomposer.redenoise_source=depth"])
