"""Issue 53, first stage: ``render --format exr`` (scene-linear OpenEXR) and ``render --white-balance`` (an edit
of the trained scene's enhanced light before the shoulder and the sRGB curve), on tiny trained runs."""
import sys

import numpy as np
import pytest
import torch
from PIL import Image

from retinexgs.errors import UserError
from retinexgs.export.exr import read_exr, read_exr_header
from retinexgs.model.tone import highlight_shoulder, linear_to_srgb, srgb_to_linear
from retinexgs.model.white_balance import (grey_edge_gains, neutral_gains, parse_white_balance,
                                           temperature_matrix)
from retinexgs.run.folder import load_run
from retinexgs.run.render import active_sh_degree, encode_enhanced, render_function
from scenes import TINY_RUN, run_cli, tiny_trained_run


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return tiny_trained_run(tmp_path_factory.mktemp("wb"))[1]


@pytest.fixture(scope="module")
def loaded(run_dir):
    """(cfg, scene, model, degree, the first test view) of the tiny run, on the CPU."""
    cfg, scene, model, step = load_run(run_dir, "cpu")
    return cfg, scene, model, active_sh_degree(cfg, step), scene.test[0]


def cli(capsys, *args):
    return run_cli(["render", *args, "--device", "cpu", "--quiet"], capsys)


def png(path):
    return np.asarray(Image.open(path), dtype=np.float64)


def stem(view):
    return view.name.rsplit(".", 1)[0]


def test_exr_round_trip_equals_the_renderer_and_tones_to_the_png(run_dir, loaded, tmp_path, capsys):
    cfg, scene, model, degree, view = loaded
    code, _, err = cli(capsys, "--run", run_dir, "--out", tmp_path, "--format", "png,exr", "--maps", "enhanced,R,L")
    assert code == 0, err
    res = render_function(model, cfg, degree, linear=True)(view)
    exr = read_exr(tmp_path / "enhanced" / f"{stem(view)}.exr")
    # float32 in the file, float32 in the renderer: equal to the last bit
    assert exr.dtype == np.float32 and np.array_equal(exr, res["rgb_linear"].numpy())
    assert exr.max() > 0.05  # not a black image
    # the tone curve (shoulder + sRGB) on the file's values gives the PNG within 1/255
    toned = linear_to_srgb(highlight_shoulder(torch.from_numpy(exr), model.shoulder)).numpy() * 255
    assert np.abs(toned - png(tmp_path / "enhanced" / f"{stem(view)}.png")).max() <= 1.0
    assert float((encode_enhanced(model, cfg, res["rgb_linear"]) - res["rgb"]).abs().max()) < 1e-5
    # R̂ and L̂ decoded to linear light, on the documented scale
    R = read_exr(tmp_path / "R" / f"{stem(view)}.exr")
    assert np.abs(linear_to_srgb(torch.from_numpy(R)).numpy() - res["R"].clamp(0, 1).numpy()).max() < 1e-5
    L = read_exr(tmp_path / "L" / f"{stem(view)}.exr")
    expect = srgb_to_linear(res["L"]) / srgb_to_linear(model.illum_ref)  # 1.0 = the scene's full light
    assert np.allclose(L, expect.numpy(), rtol=1e-6, atol=1e-7)
    header = read_exr_header(tmp_path / "enhanced" / f"{stem(view)}.exr")
    assert np.allclose(header["chromaticities"], (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290), atol=1e-6)
    assert "as-trained" in header["retinexgs"] and "1.0 = the PNG's white" in header["retinexgs_values"]


def test_exr_without_the_optional_package_says_how_to_install(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "OpenEXR", None)  # import OpenEXR now raises ImportError
    code, _, err = cli(capsys, "--run", tmp_path / "no-such-run", "--format", "exr")
    assert code == 2 and 'pip install "retinexgs[hdr]"' in err and "needs OpenEXR" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_gains_of_one_are_as_trained_bit_for_bit(run_dir, loaded, tmp_path, capsys):
    cfg, scene, model, degree, view = loaded
    base = render_function(model, cfg, degree)(view)["rgb"]
    for balance in ([1.0, 1.0, 1.0], np.eye(3)):
        assert torch.equal(render_function(model, cfg, degree, balance=balance)(view)["rgb"], base)
    for spec in ("as-trained", "gains:1,1,1", "gains:2,2,2", "temp:6504"):
        code, _, err = cli(capsys, "--run", run_dir, "--out", tmp_path / spec.replace(":", "_"),
                           "--white-balance", spec)
        assert code == 0, err
    files = [tmp_path / d / "enhanced" / f"{stem(view)}.png" for d in ("as-trained", "gains_1,1,1", "gains_2,2,2",
                                                                         "temp_6504")]
    assert all(np.array_equal(png(files[0]), png(f)) for f in files[1:])


def test_gains_multiply_the_linear_light_before_the_curve_and_are_recorded(run_dir, loaded, tmp_path, capsys):
    cfg, scene, model, degree, view = loaded
    light = render_function(model, cfg, degree, linear=True)(view)["rgb_linear"]
    gains = torch.tensor([1.3, 1.0, 0.7])
    res = render_function(model, cfg, degree, balance=gains, linear=True)(view)
    assert torch.allclose(res["rgb_linear"], light * gains, rtol=1e-6, atol=0)
    assert torch.allclose(res["rgb"], encode_enhanced(model, cfg, light * gains), atol=1e-6)
    assert float(res["rgb"][..., 0].mean()) > float(render_function(model, cfg, degree)(view)["rgb"][..., 0].mean())
    # gains:2.6,2,1.4 is the same edit (divided by G), and the numbers used are recorded in the PNG
    code, _, err = cli(capsys, "--run", run_dir, "--out", tmp_path, "--white-balance", "gains:2.6,2,1.4")
    assert code == 0, err
    out = tmp_path / "enhanced" / f"{stem(view)}.png"
    assert np.abs(png(out) / 255 - res["rgb"].numpy()).max() <= 1 / 255 + 1e-6
    note = Image.open(out).text["retinexgs"]
    assert "gains:2.6,2,1.4" in note and "gains R,G,B = 1.3, 1, 0.7" in note


@pytest.mark.parametrize("balance", [torch.tensor([1.3, 1.0, 0.7]), torch.from_numpy(temperature_matrix(4000, 10))])
def test_the_renderer_balances_in_its_tone_kernel_as_the_torch_path_does(loaded, balance):
    """The fast path puts the balance into the exposure tone's one kernel (W·diag(k), no re-encoding in torch):
    the same frame as the torch path (model.render, then the balanced light encoded again), to float rounding."""
    cfg, scene, model, degree, view = loaded
    fast = render_function(model, cfg, degree, balance=balance)
    assert fast(view)["rgb"].shape[-1] == 3 and "rgb_linear" not in fast(view)  # no torch re-encoding was made
    slow = render_function(model, cfg, degree, balance=balance, fast=False)(view)["rgb"]
    got = fast(view)["rgb"]
    assert float((got - slow).abs().max()) < 2e-6
    plain = render_function(model, cfg, degree)(view)["rgb"]
    assert float((got - plain).abs().max()) > 1e-2  # the balance did something


def test_a_picked_neutral_turns_grey(run_dir, loaded, tmp_path, capsys):
    cfg, scene, model, degree, view = loaded
    res = render_function(model, cfg, degree, linear=True)(view)
    light, record = res["rgb_linear"], res["R"] * res["L"]
    ok = (light.amin(-1) > 0.02) & (record.amax(-1) < 0.99)
    chroma = light.amax(-1) / light.amin(-1).clamp_min(1e-6)
    y, x = np.unravel_index(int(torch.where(ok, chroma, torch.zeros_like(chroma)).argmax()), ok.shape)
    assert float(chroma[y, x]) > 1.05  # a coloured pixel, so the test can fail
    code, _, err = cli(capsys, "--run", run_dir, "--out", tmp_path, "--format", "exr",
                       "--white-balance", f"pick:{stem(view)},{x},{y}")
    assert code == 0, err
    picked = read_exr(tmp_path / "enhanced" / f"{stem(view)}.exr")[y, x]
    assert np.allclose(picked, picked[1], rtol=1e-5), picked
    assert abs(picked[1] - float(light[y, x, 1])) < 1e-6  # the green is kept


def test_temperature_is_monotone_warmer_is_redder():
    kelvins = [1000, 2000, 3000, 4000, 5000, 6504, 8000, 12000, 20000, 40000]
    whites = np.array([temperature_matrix(k) @ np.ones(3) for k in kelvins])  # what a neutral becomes
    assert np.allclose(whites[:, 1], 1.0)  # the green is kept
    assert np.all(np.diff(whites[:, 0]) > 0) and np.all(np.diff(whites[:, 2]) < 0)
    assert np.array_equal(temperature_matrix(6504), np.eye(3))
    magenta = temperature_matrix(6504, 40) @ np.ones(3)
    assert magenta[0] > 1 and magenta[2] > 1 and abs(magenta[1] - 1) < 1e-12


def test_grey_edge_recovers_a_known_cast():
    rng = np.random.default_rng(3)
    # a warm scene (a façade: its surfaces average to brown, not grey) whose surfaces vary by as much in each
    # channel, so its edges are achromatic: grey-world is pulled to its average colour, grey-edge is not
    images = []
    for _ in range(4):
        patches = np.array([0.5, 0.35, 0.2]) + rng.uniform(-0.15, 0.15, (32, 32, 3))
        images.append(patches.repeat(2, 0).repeat(2, 1))  # 64×64, flat 2×2 surfaces
    cast = np.array([1.25, 1.0, 0.8])
    gains = np.array(grey_edge_gains(torch.from_numpy(im * cast) for im in images))
    truth = np.array(grey_edge_gains(torch.from_numpy(im) for im in images)) / cast
    assert np.allclose(gains, truth, rtol=1e-9)  # equivariant: a cast divides the gains exactly
    assert np.allclose(gains * cast, 1.0, atol=0.03), gains * cast  # and the cast is recovered within 3 %
    world = np.mean([im.reshape(-1, 3).mean(0) for im in images], axis=0)
    assert abs(world[0] / world[1] - 1.0) > 0.06  # grey-world would be off by more on this scene


def test_auto_white_balance_on_a_tinted_scene_moves_the_render_towards_neutral(tmp_path, capsys):
    from retinexgs.demo.synthetic import make_demo_scene
    from retinexgs.train.runner import train_run

    torch.set_num_threads(1)
    scene = make_demo_scene(tmp_path / "scene", n_train=3, n_test=1, width=24, height=18, n_points=200,
                            color_cast=(1.5, 1.0, 0.65))
    train_run(scene, tmp_path / "run", ["demo"], list(TINY_RUN), "cpu", progress=False, log=lambda s: None)
    cfg, sc, model, step = load_run(tmp_path / "run", "cpu")
    degree = active_sh_degree(cfg, step)
    fn = render_function(model, cfg, degree, linear=True)
    before = np.mean([fn(v)["rgb_linear"].reshape(-1, 3).mean(0).numpy() for v in sc.train], axis=0)
    code, out, err = cli(capsys, "--run", tmp_path / "run", "--out", tmp_path / "auto", "--white-balance", "auto",
                         "--views", "train", "--format", "exr")
    assert code == 0, err
    after = np.mean([read_exr(tmp_path / "auto" / "enhanced" / f"{stem(v)}.exr").reshape(-1, 3).mean(0)
                     for v in sc.train], axis=0)
    spread = lambda c: float(np.log(c / c[1]).__abs__().max())  # noqa: E731 (distance from grey, in log ratio)
    assert spread(after) < 0.6 * spread(before), (before, after)
    assert "white balance auto: gains R,G,B" in read_exr_header(
        tmp_path / "auto" / "enhanced" / f"{stem(sc.train[0])}.exr")["retinexgs"]


@pytest.mark.parametrize("spec, says", [
    ("gains:-1,1,1", "three positive numbers"), ("gains:1,0,1", "three positive numbers"),
    ("gains:1,1", "three positive numbers"), ("gains:a,b,c", "must be numbers"),
    ("temp:500", "1000..40000"), ("temp:50000", "1000..40000"), ("temp:5000,300", "tint"),
    ("daylight", "unknown --white-balance"), ("pick:0001", "pick:VIEW,X,Y"),
])
def test_bad_white_balance_values_fail_before_the_run_loads(tmp_path, capsys, spec, says):
    code, _, err = cli(capsys, "--run", tmp_path / "no-such-run", "--white-balance", spec)
    assert code == 2 and says in err and "--white-balance" in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_bad_picks_and_formats_name_the_problem(run_dir, loaded, tmp_path, capsys):
    view = loaded[4]
    cases = [
        (["--white-balance", "pick:nope,1,1"], "no view named 'nope'"),
        (["--white-balance", f"pick:{stem(view)},{view.width},0"], "outside view"),
        (["--white-balance", f"pick:{stem(view)},0,-1"], "outside view"),
        (["--format", "exr", "--maps", "enhanced,depth"], "depth has no EXR form"),
        (["--format", "mp4,exr"], "cannot be combined"),
        (["--format", "tiff"], "unknown --format"),
    ]
    for args, says in cases:
        code, _, err = cli(capsys, "--run", run_dir, "--out", tmp_path / "x", *args)
        assert code == 2 and says in err, (args, err)
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()
    with pytest.raises(UserError, match="is black"):
        neutral_gains([0.2, 0.0, 0.1], "pick:v,1,1")
    assert parse_white_balance(None).kind == "as-trained"
