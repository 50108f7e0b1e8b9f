"""Issue 53, second stage: the white balance baked into ``export``'s PLY (as the exposure is) and in the viewer
(the frame callback without a server, and a real server through a websocket client), on a tiny trained run."""
import numpy as np
import plyfile
import pytest
import torch

from retinexgs.evaluate.metrics import psnr
from retinexgs.export.bake import enhanced_colour, to_normalized
from retinexgs.export.ply import read_background, read_ply
from retinexgs.model.white_balance import parse_white_balance
from retinexgs.render import rasterize_gaussians, spherical_harmonics
from retinexgs.run.folder import load_run
from retinexgs.run.render import active_sh_degree, render_function, view_camera, white_balance_of
from scenes import run_cli, tiny_trained_run

# Opaque Gaussians and an active SH degree of 1, as tests/test_export.py: what the baked PLY is meant for.
TINY = ["steps=4", "checkpoint.every=4", "log.tensorboard=false", "model.sh_degree=1", "model.sh_degree_every=2",
        "model.max_init_points=800", "model.init_opacity=0.95", "density.start=100", "decomposer.method=lime",
        "loss.enhance_from=2"]
GAINS = "gains:1.6,1,0.6"  # a strong cast: the balanced PLY must follow it, the unbalanced one cannot


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A tiny RetinexGS run (800 Gaussians, 40×30) and a tiny plain-3DGS baseline."""
    _, run, base = tiny_trained_run(tmp_path_factory.mktemp("wbx"), TINY, width=40, height=30, n_points=800,
                                    baseline_overrides=["steps=2", "method=3dgs"])
    return run, base


@pytest.fixture(scope="module")
def run_dir(runs):
    return runs[0]


@pytest.fixture(scope="module")
def loaded(run_dir):
    cfg, scene, model, step = load_run(run_dir, "cpu")
    return cfg, scene, model, active_sh_degree(cfg, step)


def export(capsys, run_dir, out, *args):
    return run_cli(["export", "--run", run_dir, "--out", out, *args, "--device", "cpu", "--quiet"], capsys)


def render_ply(params, camera, degree, background):
    """A PLY's Gaussians (in the run's frame) drawn as a standard 3DGS viewer draws them."""
    coeffs = torch.cat([params["sh_dc"], params["sh_rest"]], dim=1)
    colors = (spherical_harmonics(degree, params["means"] - camera.center.float(), coeffs) + 0.5).clamp_min(0.0)
    return rasterize_gaussians(params["means"], params["quats"], params["log_scales"].exp(),
                               torch.sigmoid(params["opacity_logits"]), colors, camera, background=background).image


# ---------------------------------------------------------------------------------------------------- export


def test_export_gains_of_one_bake_bit_for_bit_as_without(run_dir, loaded, tmp_path, capsys):
    cfg, scene, model, degree = loaded
    plain, ones = tmp_path / "plain.ply", tmp_path / "ones.ply"
    assert export(capsys, run_dir, plain)[0] == 0
    code, _, err = export(capsys, run_dir, ones, "--white-balance", "gains:2,2,2")
    assert code == 0, err
    a, b = read_ply(plain), read_ply(ones)
    for name in a:
        assert torch.equal(a[name], b[name]), name
    assert torch.equal(read_background(plain), read_background(ones))
    # and the colour the bake fits is the model's own tone map, bit for bit (the code path before the balance)
    g = torch.Generator().manual_seed(0)
    R, L = torch.rand(50, 7, 3, generator=g), torch.rand(50, 7, 3, generator=g) * 0.3
    gamma = torch.tensor([0.6, 0.7, 0.8])
    assert torch.equal(enhanced_colour(model, R, L, gamma), model.tone_map(R, L, gamma)[0])
    assert torch.equal(enhanced_colour(model, R, L, gamma, torch.ones(3)), model.tone_map(R, L, gamma)[0])


def test_export_bakes_the_balanced_colours_the_renderer_shows(run_dir, loaded, tmp_path, capsys):
    """The balanced PLY, drawn as a viewer draws it, against ``render --white-balance``'s frames of the same
    gains: as close as the unbalanced PLY is to the unbalanced render (test_export: ≥ 33 dB), and far from the
    unbalanced render (the gains reached the colours)."""
    cfg, scene, model, degree = loaded
    out = tmp_path / "warm.ply"
    code, _, err = export(capsys, run_dir, out, "--white-balance", GAINS)
    assert code == 0, err
    params = to_normalized(read_ply(out), scene.normalization)
    background = read_background(out)
    balance = white_balance_of(parse_white_balance(GAINS), model, cfg, scene, degree)
    balanced = render_function(model, cfg, degree, balance=balance, fast=False)
    plain = render_function(model, cfg, degree, fast=False)
    near, far, ratio = [], [], []
    for view in scene.train + scene.test:
        cam = view_camera(view)
        img = render_ply(params, cam, 1, background).clamp(0, 1)
        want = balanced(view)["rgb"]
        near.append(psnr(img, want))
        far.append(psnr(img, plain(view)["rgb"]))
        ratio.append((img[..., 0].mean() / img[..., 2].mean()).item())
    assert min(near) >= 33.0, near
    assert max(far) < min(near) - 5.0, (near, far)
    # the background recorded for a viewer is the balanced one too: redder than blue as the gains are
    plain_out = tmp_path / "plain.ply"
    assert export(capsys, run_dir, plain_out)[0] == 0
    bg0, bg1 = read_background(plain_out), background
    assert float(bg1[0] / bg1[2]) > float(bg0[0] / bg0[2])


def test_export_records_the_white_balance_beside_the_exposure(run_dir, tmp_path, capsys):
    out = tmp_path / "t.ply"
    code, outtext, err = run_cli(["export", "--run", run_dir, "--out", out, "--white-balance", "temp:4000,10",
                                  "--exposure", "0.8", "--device", "cpu", "--quiet"], capsys)
    assert code == 0, err
    assert "white balance temp:4000,10: matrix" in outtext  # said on the console as render says it
    colour = [c for c in plyfile.PlyData.read(str(out)).comments if c.startswith("colour: ")]
    assert len(colour) == 1
    text = colour[0]
    assert "W*k*lin(R*L)" in text and "k = lin(L_ref)^(-1/g)" in text  # W beside the exposure's gain
    assert "W = white balance temp:4000,10: matrix (linear Rec.709, rows R,G,B) = " in text
    plain = tmp_path / "p.ply"
    assert export(capsys, run_dir, plain)[0] == 0
    text = [c for c in plyfile.PlyData.read(str(plain)).comments if c.startswith("colour: ")][0]
    assert "W*" not in text and "white balance as-trained: none (as trained)" in text


@pytest.mark.parametrize("args, message", [
    (["--white-balance", "sepia"], "unknown --white-balance 'sepia'; choose from as-trained, auto"),
    (["--white-balance", "gains:1,0,1"], "gains must be three positive numbers"),
    (["--white-balance", "gains:1,nan,1"], "must be finite numbers"),
    (["--white-balance", "temp:500"], "the temperature must lie in 1000..40000 K"),
    (["--white-balance", "temp:5000,300"], "the tint must lie in -100..100"),
    (["--white-balance", "pick:nosuchview,1,1"], "the scene has no view named 'nosuchview'"),
    (["--white-balance", "pick:0000,999,1"], "lies outside view 0000"),
    (["--white-balance", GAINS, "--reflectance-only"], "--reflectance-only exports R̂"),
])
def test_export_bad_white_balance_is_one_line_and_writes_nothing(run_dir, tmp_path, capsys, args, message):
    out = tmp_path / "x.ply"
    code, _, err = export(capsys, run_dir, out, *args)
    assert code == 2 and message in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_export_white_balance_on_a_baseline_is_refused(runs, tmp_path, capsys):
    out = tmp_path / "b.ply"
    code, _, err = export(capsys, runs[1], out, "--white-balance", "auto")
    assert code == 2 and "needs a RetinexGS run" in err and "method=3dgs" in err
    assert len(err.strip().splitlines()) == 1 and not out.exists()
    assert export(capsys, runs[1], out, "--white-balance", "as-trained")[0] == 0  # the default stays accepted


# ---------------------------------------------------------------------------------------------------- viewer


@pytest.fixture(scope="module")
def frames(loaded):
    from retinexgs.viewer.frame import FrameRenderer
    cfg, scene, model, degree = loaded
    return FrameRenderer(model, cfg, degree, scene.train)


def viewer_cam(scene, i=0):
    from retinexgs.viewer.camera import camera_to_viewer
    return camera_to_viewer(view_camera(scene.train[i]))


@pytest.mark.parametrize("form, exposure", [(GAINS, 1.0), ("temp:4000,10", 0.7), ("auto", 1.0)])
def test_view_white_balance_frame_is_what_render_writes(loaded, frames, form, exposure):
    from retinexgs.evaluate.evaluate import to_uint8
    from retinexgs.viewer.camera import viewer_to_camera
    from retinexgs.viewer.frame import FrameSettings
    cfg, scene, model, degree = loaded
    vcam = viewer_cam(scene)
    got = frames.render(vcam, FrameSettings(exposure=exposure, white_balance=form))
    assert form in frames.balance_text  # the numbers used, for the panel
    balance = white_balance_of(parse_white_balance(form), model, cfg, scene, degree, exposure)
    assert balance is not None
    want = render_function(model, cfg, degree, exposure=exposure, balance=balance)(viewer_to_camera(vcam))["rgb"]
    assert np.array_equal(got, to_uint8(want))
    plain = frames.render(vcam, FrameSettings(exposure=exposure))
    assert np.abs(got.astype(int) - plain.astype(int)).max() >= 10  # the control changed the colour
    # the other maps are the scene's, not the edit's
    for m in ("R", "L", "low", "depth"):
        assert np.array_equal(frames.render(vcam, FrameSettings(map=m, white_balance=form)),
                              frames.render(vcam, FrameSettings(map=m)))


def test_view_as_trained_forms_are_bit_for_bit_the_plain_frame(loaded, frames):
    from retinexgs.viewer.frame import FrameSettings
    vcam = viewer_cam(loaded[1], 1)
    plain = frames.render(vcam, FrameSettings())
    for form in ("as-trained", "gains:1,1,1", "gains:3,3,3", "temp:6504"):
        assert np.array_equal(frames.render(vcam, FrameSettings(white_balance=form)), plain), form


@pytest.mark.parametrize("form, message", [("gains:1,0,1", "gains must be three positive numbers"),
                                           ("gains:nan,1,1", "finite"),
                                           ("temp:500", "temperature must lie in 1000..40000"),
                                           ("sepia", "unknown --white-balance"),
                                           ("pick:0000,3,3", "eyedropper")])
def test_view_bad_white_balance_is_refused_as_a_bad_exposure_is(loaded, frames, form, message):
    from retinexgs.viewer.frame import FrameSettings
    with pytest.raises(ValueError, match="exposure must be a positive"):  # the exposure's refusal, for comparison
        frames.render(viewer_cam(loaded[1]), FrameSettings(exposure=0.0))
    with pytest.raises(ValueError, match=message):
        frames.render(viewer_cam(loaded[1]), FrameSettings(white_balance=form))


def test_view_shoulder_switch_clips_at_white_when_off(loaded, frames):
    from retinexgs.evaluate.evaluate import to_uint8
    from retinexgs.model.tone import linear_to_srgb
    from retinexgs.viewer.camera import viewer_to_camera
    from retinexgs.viewer.frame import FrameSettings
    cfg, scene, model, degree = loaded
    assert frames.has_shoulder and model.shoulder < 1.0
    vcam = viewer_cam(scene)
    bright = 0.25  # four times the light: highlights past the knee
    on = frames.render(vcam, FrameSettings(exposure=bright))
    off = frames.render(vcam, FrameSettings(exposure=bright, shoulder=False))
    res = render_function(model, cfg, degree, exposure=bright, linear=True)(viewer_to_camera(vcam))
    assert np.array_equal(on, to_uint8(res["rgb"]))
    assert np.array_equal(off, to_uint8(linear_to_srgb(res["rgb_linear"])))
    assert (off.astype(int) - on.astype(int)).max() >= 10 and (off >= on).all()  # the clip is brighter
    # with a balance: the balanced light clipped
    form_off = frames.render(vcam, FrameSettings(exposure=bright, shoulder=False, white_balance=GAINS))
    balance = white_balance_of(parse_white_balance(GAINS), model, cfg, scene, degree, bright)
    res = render_function(model, cfg, degree, exposure=bright, balance=balance, linear=True)(viewer_to_camera(vcam))
    assert np.array_equal(form_off, to_uint8(linear_to_srgb(res["rgb_linear"])))


def test_view_eyedropper_makes_the_picked_pixel_grey(loaded, frames):
    from retinexgs.viewer.camera import viewer_to_camera
    from retinexgs.viewer.frame import FrameSettings
    cfg, scene, model, degree = loaded
    vcam = viewer_cam(scene)
    settings = FrameSettings(exposure=0.8)
    gains = frames.pick_neutral(vcam, settings, 0.5, 0.5)
    assert gains[1] == 1.0 and abs(gains[0] - 1.0) + abs(gains[2] - 1.0) > 1e-3
    cam = viewer_to_camera(vcam)
    x, y = int(0.5 * cam.width), int(0.5 * cam.height)
    form = "gains:" + ",".join(repr(float(g)) for g in gains)
    balance = white_balance_of(parse_white_balance(form), model, cfg, scene, degree, 0.8)
    light = render_function(model, cfg, degree, exposure=0.8, balance=balance, linear=True)(cam)["rgb_linear"][y, x]
    assert torch.allclose(light, light[1].expand(3), rtol=1e-4), light  # grey
    with pytest.raises(ValueError, match="finite"):
        frames.pick_neutral(vcam, settings, float("nan"), 0.5)


def test_neutral_at_refuses_a_clipped_or_black_pixel():
    from retinexgs.errors import UserError
    from retinexgs.run.render import neutral_at
    res = {"R": torch.full((2, 2, 3), 0.5), "L": torch.full((2, 2, 3), 0.5),
           "rgb_linear": torch.tensor([0.2, 0.4, 0.1]).expand(2, 2, 3)}
    assert np.allclose(neutral_at(res, 1, 0, "pick"), [2.0, 1.0, 4.0])
    clipped = dict(res, L=torch.full((2, 2, 3), 2.0))
    with pytest.raises(UserError, match="clipped"):
        neutral_at(clipped, 1, 0, "pick")
    black = dict(res, rgb_linear=torch.zeros(2, 2, 3))
    with pytest.raises(UserError, match="black"):
        neutral_at(black, 1, 0, "pick")


def test_view_server_white_balance_controls_and_eyedropper(run_dir, loaded):
    """A real server and a websocket client: the white-balance controls change the frame as FrameRenderer does
    for the same form, typed values out of range are clamped, and the eyedropper's click sets the gains."""
    import time

    viser = pytest.importorskip("viser")
    msgpack = pytest.importorskip("msgspec.msgpack")
    from websockets.sync.client import connect

    from polling import wait_until
    from retinexgs.viewer.camera import ViewerCamera
    from retinexgs.viewer.frame import FrameSettings
    from retinexgs.viewer.server import view_run

    logs = []
    camera = dict(type="ViewerCameraMessage", wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, -3.0), fov=1.0,
                  near=0.01, far=100.0, image_height=24, image_width=32, look_at=(0.0, 0.0, 0.0),
                  up_direction=(0.0, -1.0, 0.0))
    viewer = view_run(run_dir, port=0, device="cpu", log=logs.append, block=False)
    try:
        with connect(viewer.url.replace("http", "ws"), subprotocols=[f"viser-v{viser.__version__}"],
                     open_timeout=10) as ws:
            ws.send(msgpack.encode(camera))
            assert wait_until(lambda: viewer.frames >= 1 and viewer._clients, 30), logs
            state = next(iter(viewer._clients.values()))

            def update(handle, value):
                frames = viewer.frames
                ws.send(msgpack.encode(dict(type="GuiUpdateMessage", uuid=handle._impl.uuid,
                                            updates={"value": value})))
                assert wait_until(lambda: viewer.frames > frames, 30), logs

            def frame_of(settings):
                cam = state.client.camera  # what the server rendered from
                vc = ViewerCamera(tuple(cam.wxyz), tuple(cam.position), float(cam.fov), int(cam.image_width),
                                  int(cam.image_height))
                return viewer.renderer.render(vc, settings)

            # The first frame may come from the camera before the client's own reached the server: wait for the
            # frame of the client's camera, as the checks below do.
            assert wait_until(lambda: viewer.last_frame is not None and np.array_equal(
                viewer.last_frame, frame_of(FrameSettings(scale=state.settings().scale))), 10), logs
            plain = viewer.last_frame.copy()
            update(state.gains, (1.6, 1.0, 0.6))
            update(state.wb_mode, "gains (or a picked neutral)")
            assert wait_until(lambda: state.settings().white_balance == "gains:1.6,1.0,0.6", 10)
            assert wait_until(lambda: np.array_equal(viewer.last_frame, frame_of(state.settings())), 10)
            assert np.abs(viewer.last_frame.astype(int) - plain.astype(int)).max() >= 10
            assert "gains:1.6,1.0,0.6" in state.wb_note.value
            # a temperature typed out of the slider's range is clamped, as the exposure's is
            update(state.kelvin, 100000.0)
            update(state.wb_mode, "temperature / tint")
            assert state.settings().white_balance.startswith("temp:15000.0,")
            assert wait_until(lambda: np.array_equal(viewer.last_frame, frame_of(state.settings())), 10)
            # the eyedropper: the button arms it, the next click on the canvas picks
            update(state.wb_mode, "as trained")
            ws.send(msgpack.encode(dict(type="GuiUpdateMessage", uuid=state.pick._impl.uuid,
                                        updates={"value": True})))
            assert wait_until(lambda: state._picking, 10), logs
            ws.send(msgpack.encode(dict(type="ScenePointerMessage", event_type="click", ray_origin=(0.0, 0.0, -3.0),
                                        ray_direction=(0.0, 0.0, 1.0), screen_pos=((0.5, 0.5),), modifier=None)))
            assert wait_until(lambda: state.settings().white_balance.startswith("gains:"), 30), (
                logs, state.wb_note.value)
            assert not state._picking and state.gains.value != (1.6, 1.0, 0.6)
            settings = replace_settings(state.settings(), white_balance="as-trained")
            cam = state.client.camera
            vc = ViewerCamera(tuple(cam.wxyz), tuple(cam.position), float(cam.fov), int(cam.image_width),
                              int(cam.image_height))
            expect = viewer.renderer.pick_neutral(vc, settings, 0.5, 0.5)
            assert np.allclose(state.gains.value, expect, rtol=1e-6)
            # the shoulder switch reaches the frame
            update(state.shoulder, False)
            assert state.settings().shoulder is False
            assert wait_until(lambda: np.array_equal(viewer.last_frame, frame_of(state.settings())), 10)
            assert not any("failed" in m for m in logs), logs
    finally:
        start = time.time()
        viewer.stop()
        assert time.time() - start < 10


def replace_settings(settings, **change):
    from dataclasses import replace
    return replace(settings, **change)
