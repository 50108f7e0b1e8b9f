"""Issue 63 item 3: the capture as a data-layer object (retinexgs/data/capture.py) and the raw-only keys grouped under
``raw`` sections (run format 2, with the 1 -> 2 migration).

Fixtures: a tiny demo scene turned into a raw scene (DNGs) and its camera JPEGs by ``darken --raw``; never the
shared data."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch
import yaml

from retinexgs.config import FORMAT
from retinexgs.data.capture import PHOTO, PHOTO_BLOTCH_MIN, RAW, Capture, PhotoCapture, RawCapture, capture_of_files
from retinexgs.demo.synthetic import make_demo_scene
from retinexgs.run.config import load_config
from scenes import TINY_RUN, run_cli

ROOT = Path(__file__).resolve().parents[1]

# what callers asked of the scene's rawness before the capture object (issue 63's list), now asked of the capture
QUESTIONS = ("name", "unclipped", "as_photo", "encode_target", "knee", "spa_input", "r_prior_luma", "linear_mode",
             "noise", "noise_downscale", "auto_denoise", "preview_denoise", "jpeg_codec")


@pytest.fixture(scope="module")
def night(tmp_path_factory):
    base = tmp_path_factory.mktemp("capture")
    src = make_demo_scene(base / "src", n_train=3, n_test=1, width=48, height=36, n_points=200)
    from retinexgs.cli import main
    assert main(["darken", "--data", str(src), "--out", str(base / "night"), "--raw", "--quiet"]) == 0
    return base / "night"


def _train(scene, out, capsys, *extra):
    sets = [a for s in (*TINY_RUN, *extra) for a in ("--set", s)]
    return run_cli(["train", "--data", scene, "--out", out, "--config", "demo", *sets, "--device", "cpu", "--quiet"],
                   capsys)


def test_the_two_capture_kinds_answer_alike_what_callers_ask():
    for kind in (PhotoCapture, RawCapture):
        for q in QUESTIONS:  # every question answered by the kind itself, none left to the base
            assert q in vars(kind) or q in vars(Capture) and not callable(getattr(Capture, q)), (kind, q)
    assert (PHOTO.name, RAW.name) == ("photo", "raw") and (PHOTO.unclipped, RAW.unclipped) == (False, True)
    cfg = load_config()
    t = torch.tensor([-0.2, 0.3, 1.4])
    assert torch.equal(PHOTO.as_photo(t), t) and torch.equal(RAW.as_photo(t), torch.tensor([0.0, 0.3, 1.0]))
    assert torch.equal(PHOTO.encode_target(t), t) and torch.equal(RAW.encode_target(t), t.half().float())
    assert PHOTO.knee(cfg.model.enhancement) == cfg.model.enhancement.shoulder == 0.5
    assert RAW.knee(cfg.model.enhancement) == cfg.model.enhancement.raw.shoulder == 1.0
    assert torch.equal(PHOTO.spa_input(t, cfg.loss), t) and torch.equal(RAW.spa_input(t, cfg.loss), RAW.as_photo(t))
    extended = load_config(["ablations/spa_raw_extended"]).loss
    assert torch.equal(RAW.spa_input(t, extended), t)
    assert PHOTO.linear_mode(cfg.loss) is None and RAW.linear_mode(cfg.loss) == "noise"
    # the R prior: a raw scene's on R̂'s chroma alone (its key), a photo's the paper's whatever the raw key says
    paper = load_config(["ablations/raw_r_prior_luma"]).loss
    assert (PHOTO.r_prior_luma(cfg.loss), RAW.r_prior_luma(cfg.loss), RAW.r_prior_luma(paper)) == (1.0, 0.0, 1.0)
    # views binned by data.downscale: the binned key (the paper's κ 1 by default), photos the paper's regardless
    assert (RAW.r_prior_luma(cfg.loss, 2.0), RAW.r_prior_luma(cfg.loss, 1.0), PHOTO.r_prior_luma(cfg.loss, 2.0)) == \
        (1.0, 0.0, 1.0)
    odd = load_config([], ["loss.raw.r_prior_luma_binned=0.25"]).loss
    assert (RAW.r_prior_luma(odd, 1.5), RAW.r_prior_luma(odd, 1.0)) == (0.25, 0.0)
    assert RAW.linear_mode(load_config(["ablations/raw_photo"]).loss) is None  # raw compared as the photo shown
    assert (PHOTO.auto_denoise(), RAW.auto_denoise()) == ("none", "chroma")
    # photos: the denoiser where their colour noise is blotchy (measured only when asked); raw: always
    assert PHOTO.auto_denoise(lambda: 2 * PHOTO_BLOTCH_MIN) == "chroma"
    assert PHOTO.auto_denoise(lambda: PHOTO_BLOTCH_MIN / 2) == "none"
    assert RAW.auto_denoise(lambda: PHOTO_BLOTCH_MIN / 2) == "chroma"
    assert PHOTO.preview_denoise(cfg.decomposer) is False and RAW.preview_denoise(cfg.decomposer) is True
    assert RAW.preview_denoise(load_config(["paper"]).decomposer) is False
    assert (PHOTO.noise_downscale(2.0), RAW.noise_downscale(2.0)) == (1.0, 2.0)
    # the photo path's noise is measured by the caller's function (train/noise.py lies above data/)
    assert PHOTO.noise([Path("a.jpg")]) is None and PHOTO.noise([Path("a.jpg")], lambda p: ("measured", p)) == \
        ("measured", [Path("a.jpg")])
    assert capture_of_files([Path("a.DNG"), Path("b.crw")]) is RAW
    assert capture_of_files([Path("a.dng"), Path("b.jpg")]) is PHOTO and capture_of_files([]) is PHOTO


def test_a_raw_scene_s_capture_is_raw_and_a_jpeg_scene_s_photo(night, tmp_path):
    from retinexgs.data import load_scene
    raw, jpeg = load_scene(night / "raw"), load_scene(night / "jpeg")
    assert isinstance(raw.capture, RawCapture) and raw.raw and raw.train[0].capture is RAW
    assert isinstance(jpeg.capture, PhotoCapture) and not jpeg.raw
    dngs = [v.user_path for v in raw.train]
    noise = raw.capture.noise(dngs)  # the DNG NoiseProfile darken wrote, never PIL's view of the file
    assert noise is not None and noise.source == "profile" and len(noise.a) == 3
    assert raw.capture.jpeg_codec(dngs[0]) is None
    import numpy as np
    from PIL import Image
    jpg = tmp_path / "view.jpg"  # a photo capture's JPEG: its codec is simulated for the noise fit
    Image.fromarray((np.random.default_rng(0).random((16, 16, 3)) * 255).astype(np.uint8)).save(jpg, quality=80)
    assert jpeg.capture.jpeg_codec(jpg) is not None and RAW.jpeg_codec(jpg) is None
    target = raw.train[0].load_target()
    assert target.min() < 0 and torch.equal(target, target.half().float())  # unclipped, float16-rounded


def _as_format_1(run: Path) -> None:
    """Rewrite a run folder as format 1 wrote it: the raw keys under their old names (with values unlike today's
    defaults, but loss.rec_raw_model_error at its default: format 3 deleted it, and drops it silently there), in
    config.yaml and in the checkpoints."""
    old = {"decomposer": {"raw_denoise": False}, "model": {"enhancement": {"shoulder_raw": 0.7}},
           "loss": {"rec_raw": "relative", "rec_raw_model_error": 0.0, "rec_raw_unit": "sigma",
                    "rec_raw_prior_snr": 1.5, "spa_raw": "extended"}}

    def back(recorded: dict) -> dict:  # plain data as written, not a Config
        del recorded["decomposer"]["raw"], recorded["model"]["enhancement"]["raw"], recorded["loss"]["raw"]
        recorded["decomposer"].update(old["decomposer"])
        recorded["model"]["enhancement"].update(old["model"]["enhancement"])
        recorded["loss"].update(old["loss"])
        return recorded

    data = yaml.safe_load((run / "config.yaml").read_text())
    assert data["format"] == FORMAT
    data = back(data)
    data["format"] = 1
    (run / "config.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    for ckpt in (run / "checkpoints").rglob("*.pt"):
        state = torch.load(ckpt, map_location="cpu", weights_only=False)
        state["format"] = 1
        state["config"] = back(state["config"])
        torch.save(state, ckpt)


def test_training_gives_the_reflectance_prior_the_captures_share_of_luma(night, tmp_path, capsys, monkeypatch):
    """The objective asks the capture for κ (loss.raw.r_prior_luma): 0 on the raw scene, the paper's 1 on the
    photos it was darkened from, 1 on the raw scene with ablations/raw_r_prior_luma, and on its views binned by
    data.downscale loss.raw.r_prior_luma_binned (1, or 0 when set so)."""
    from retinexgs.train import losses
    seen = []
    real = losses.supervision_loss

    def spy(*args, **kwargs):
        seen.append(args[12] if len(args) > 12 else kwargs.get("r_luma", 1.0))
        return real(*args, **kwargs)

    monkeypatch.setattr(losses, "supervision_loss", spy)
    seen_runs = []
    for scene, extra, want in ((night / "raw", [], 0.0), (night.parent / "src", [], 1.0),
                               (night / "raw", ["--config", "ablations/raw_r_prior_luma"], 1.0),
                               (night / "raw", ["--set", "data.downscale=2"], 1.0),
                               (night / "raw", ["--set", "data.downscale=2", "--set", "loss.raw.r_prior_luma_binned=0"],
                                0.0)):
        seen.clear()
        sets = [a for s in TINY_RUN for a in ("--set", s)]
        code, _, err = run_cli(["train", "--data", scene, "--out", tmp_path / f"run{len(seen_runs)}", "--config",
                                "demo", *extra, *sets, "--device", "cpu", "--quiet"], capsys)
        assert code == 0, err
        assert seen and set(seen) == {want}, (scene, extra, seen)
        seen_runs.append(scene)


def test_a_format_1_run_with_the_old_raw_keys_reads_them_in_their_new_places_and_trains_on(night, tmp_path, capsys):
    from retinexgs.run.folder import load_run, read_run_config
    run = tmp_path / "run"
    code, _, err = _train(night / "raw", run, capsys)
    assert code == 0, err
    _as_format_1(run)
    lines = []
    cfg, _ = read_run_config(run, lines.append)
    assert (cfg.decomposer.raw.preview_denoise, cfg.model.enhancement.raw.shoulder) == (False, 0.7)
    r = cfg.loss.raw
    assert (r.mode, r.unit, r.prior_snr, r.spa) == ("relative", "sigma", 1.5, "extended")
    assert not hasattr(r, "model_error")  # format 3 dropped it (its default)
    # moved, not filled; only the keys formats 5 and 6 added (back() took the whole raw section) predate the run
    assert len(lines) == 1 and "predates config keys loss.raw.r_prior_luma, loss.raw.r_prior_luma_binned:" in lines[0]
    assert r.r_prior_luma == r.r_prior_luma_binned == 1.0  # the paper's prior, as the run was trained
    assert load_run(run, "cpu")[2].shoulder == 0.7  # the raw scene's knee, read from its old key
    code, out, err = run_cli(["eval", "--run", run, "--device", "cpu"], capsys)
    assert code == 0, err
    code, out, err = run_cli(["train", "--out", run, "--resume", "--set", "steps=5", "--device", "cpu", "--quiet"],
                             capsys)
    assert code == 0, err
    written = yaml.safe_load((run / "config.yaml").read_text())  # rewritten in today's format
    assert written["format"] == FORMAT and written["loss"]["raw"]["mode"] == "relative"
    assert written["model"]["enhancement"]["raw"]["shoulder"] == 0.7 and "rec_raw" not in written["loss"]


def test_a_run_folder_of_a_newer_format_is_refused_in_one_line(night, tmp_path, capsys):
    from retinexgs.run.checkpoint import save_checkpoint
    from retinexgs.run.folder import write_run_config
    run = tmp_path / "run"
    run.mkdir()
    write_run_config(run, load_config(), night / "raw")
    data = yaml.safe_load((run / "config.yaml").read_text())
    data["format"] = FORMAT + 1
    (run / "config.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    save_checkpoint(run, 1, {"step": 1, "model": {}})
    code, out, err = run_cli(["eval", "--run", run, "--device", "cpu"], capsys)
    assert code == 2, (code, out, err)
    assert f"is in run format {FORMAT + 1}, newer than this retinexgs reads (format {FORMAT})" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err


def test_raw_checks_outside_data_live_in_at_most_two_files():
    """Issue 63's done-when: callers ask the capture. The two left: the decomposition cache keys a file's priors by
    its own preview recipe (a raw file or its float copy: retinex/cache.py), and ``noise`` picks a mixed folder's
    raw files for their report (commands/sensor.py)."""
    pattern = re.compile(r"\bis_raw_file\b|\bholds_unclipped\b|\bis_raw_path\b|\.is_raw\b|\bscene\.raw\b|"
                         r"RAW_EXTENSIONS")
    found = sorted(str(p.relative_to(ROOT)) for p in (ROOT / "retinexgs").rglob("*.py")
                   if "data" not in p.relative_to(ROOT / "retinexgs").parts[:1] and pattern.search(p.read_text()))
    found = [f for f in found if f != "retinexgs/formats.py"]  # the list of extensions itself, checked nowhere
    assert found == ["retinexgs/commands/sensor.py", "retinexgs/retinex/cache.py"], found


@pytest.mark.parametrize("overrides,says", [
    ([], "supervises R̂'s colour only (loss.raw.r_prior_luma)"),
    (["data.downscale=2"], "supervises R̂'s colour and brightness (loss.raw.r_prior_luma_binned: the views are binned)"),
    (["loss.raw.r_prior_luma=0.3"], "supervises R̂'s colour and 0.3 of its brightness (loss.raw.r_prior_luma)"),
])
def test_a_raw_run_says_what_its_reflectance_prior_supervises(night, tmp_path, overrides, says):
    from retinexgs.data import load_scene
    from retinexgs.train.trainer import Trainer
    cfg = load_config(["demo"], list(TINY_RUN) + overrides)
    lines = []
    Trainer(cfg, load_scene(night / "raw", downscale=cfg.data.downscale), tmp_path / "run", "cpu", progress=False,
            log=lines.append)
    assert [ln for ln in lines if ln.startswith("raw scene:") and says in ln], lines
