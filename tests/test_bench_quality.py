"""The quality benchmark's bookkeeping (seeds, the mean ± std table, contact sheets) and the 2D proxy's pieces,
on fabricated run folders: no training."""
import json
import math

import numpy as np
import pytest
import torch
from PIL import Image

from retinexgs.bench import quality
from retinexgs.train.benchmarks import proxy
from retinexgs.run.config import load_config
from retinexgs.errors import UserError


def test_parse_seeds():
    assert quality.parse_seeds("3") == [0, 1, 2]
    assert quality.parse_seeds("0,") == [0]
    assert quality.parse_seeds("1,2") == [1, 2]
    with pytest.raises(ValueError):
        quality.parse_seeds("0")


def _fake_run(job, psnr, ssim, width=8, height=6, panels=5, aligned=None):
    job.run.mkdir(parents=True, exist_ok=True)
    views = []
    for k, name in enumerate(("a", "b")):
        img = np.zeros((height, width * panels, 3), np.uint8)
        for p in range(panels):
            img[:, p * width:(p + 1) * width] = 40 * p + k
        (job.run / "renders" / "test").mkdir(parents=True, exist_ok=True)
        Image.fromarray(img).save(job.run / "renders" / "test" / f"{name}.png")
        views.append({"view": f"{name}.jpg"})
    mean = {"psnr": psnr, "ssim": ssim, "low_psnr": 7.0, "low_ssim": 0.2}
    if aligned is not None:
        mean.update(psnr_gt_mean=aligned[0], ssim_gt_mean=aligned[1])
    job.metrics_path.write_text(json.dumps({
        "mean": mean, "views": views,
        "panels": " | ".join(["x"] * panels), "train": {"train_seconds": 10.0}}))


def test_table_mean_and_sample_std_over_seeds_and_scenes(tmp_path):
    scenes = [tmp_path / "s1", tmp_path / "s2"]
    jobs = quality.plan(scenes, ["default", "ablations/baseline_pre"], [0, 1], tmp_path / "runs")
    values = {("s1", "default"): [20.0, 22.0], ("s2", "default"): [24.0, 26.0],
              ("s1", "ablations/baseline_pre"): [18.0, 18.0], ("s2", "ablations/baseline_pre"): [19.0, 19.0]}
    for j in jobs:
        _fake_run(j, values[(j.scene.name, j.config)][j.seed], 0.5 + 0.1 * j.seed,
                  panels=5 if j.config == "default" else 3)
    md = quality.table(jobs, ["default", "ablations/baseline_pre"])
    row = next(line for line in md.splitlines() if line.startswith("| `default`"))
    assert f"21.00 ± {math.sqrt(2):.2f}" in row and "25.00 ± 1.41" in row
    # the mean column: each seed's mean over scenes (22, 24) -> 23 ± 1.41
    assert row.rstrip(" |").endswith(f"23.00 ± {math.sqrt(2):.2f} / 0.550 ± 0.071")
    assert "| low input | 7.00 / 0.200 | 7.00 / 0.200 |" in md
    sheet = quality.contact_sheet(jobs, ["default", "ablations/baseline_pre"], "s1", tmp_path / "sheet.png")
    img = np.asarray(Image.open(sheet))
    assert img.shape[1] == 8 * 4  # low | default | baseline | truth
    top = 14  # the label strip
    # columns: low input (panel 0), each config's output (panel 1), the truth (last panel) — view "a" is row 0
    assert img[top + 2, 1, 0] == 0 and img[top + 2, 8 + 1, 0] == 40 and img[top + 2, 24 + 1, 0] == 80


def test_contact_sheets_written_at_once_by_two_benches_sharing_runs(tmp_path):
    """Two benches with one --runs folder write the same sheet at the same time (a device call did): each write
    has a temporary name of its own, so neither fails and the sheet is whole."""
    from concurrent.futures import ThreadPoolExecutor
    jobs = quality.plan([tmp_path / "s1"], ["default"], [0], tmp_path / "runs")
    for j in jobs:
        _fake_run(j, 20.0, 0.5)
    out = tmp_path / "sheet.png"
    with ThreadPoolExecutor(8) as pool:
        paths = list(pool.map(lambda _: quality.contact_sheet(jobs, ["default"], "s1", out), range(16)))
    assert paths == [out] * 16
    assert np.asarray(Image.open(out)).shape[1] == 8 * 3  # low | default | truth
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".tmp-")] == []


def test_aligned_table_reads_the_gt_mean_figures_and_skips_older_runs(tmp_path):
    scenes = [tmp_path / "s1", tmp_path / "s2"]
    jobs = quality.plan(scenes, ["default"], [0, 1], tmp_path / "runs")
    for j in jobs:  # seed 1 of s2 was evaluated before the GT-mean keys existed
        old = j.scene.name == "s2" and j.seed == 1
        _fake_run(j, 20.0, 0.5, aligned=None if old else (30.0 + j.seed + (2 if j.scene.name == "s2" else 0), 0.9))
    md = quality.table(jobs, ["default"], aligned=True)
    row = next(line for line in md.splitlines() if line.startswith("| `default`"))
    assert "(n=1/2)" in row and f"30.50 ± {math.sqrt(0.5):.2f} / 0.900 ± 0.000" in row and "| 32.00 / 0.900 |" in row
    assert row.rstrip(" |").endswith("31.00 / 0.900")  # the mean over scenes: seed 0 only has both
    assert "low input" not in md and "GT-mean" in md
    plain = next(line for line in quality.table(jobs, ["default"]).splitlines() if line.startswith("| `default`"))
    assert "20.00 ± 0.00 / 0.500 ± 0.000" in plain and "(n=2)" in plain


def test_texture_split_and_proxy_gamma():
    torch.manual_seed(0)
    tex = 0.2 + 0.6 * torch.rand(32, 32, 1)
    flat = torch.full((32, 32, 1), 0.5)
    assert proxy.texture_split(flat.expand(32, 32, 3), tex) == pytest.approx(1.0)
    assert proxy.texture_split(tex.expand(32, 32, 3), flat) == pytest.approx(0.0, abs=1e-9)
    # With the previous default's loss (whole-image exposure of the light, L_col off) a uniform light
    # v/ref = 0.25 gets the gamma whose light is E = 0.6 on average: g = log 0.6 / log 0.25 ≈ 0.37 (L_spa is
    # scale-invariant: 0).
    R = torch.full((32, 32, 3), 0.7)
    g = proxy.proxy_gamma(R, torch.full((32, 32, 1), 0.1), R * 0.1, 0.4, load_config(["ablations/tone_illumination"]))
    assert g == pytest.approx(math.log(0.6) / math.log(0.25), abs=0.006)
    # The default (a gain in linear light, the image metered at 0.5): srgb(k·lin(0.07)) = 0.5 with
    # k = lin(0.4)^(-1/g), i.e. g = -log lin(0.4) / log(lin(0.5) / lin(0.07)) ≈ 0.568, on the 0.01 grid.
    lin = lambda v: ((v + 0.055) / 1.055) ** 2.4  # noqa: E731  (sRGB decoding above 0.04045)
    g = proxy.proxy_gamma(R, torch.full((32, 32, 1), 0.1), R * 0.1, 0.4, load_config([]))
    assert g == pytest.approx(-math.log(lin(0.4)) / math.log(lin(0.5) / lin(0.07)), abs=0.011)
    # The default's highlight cap, as in training: a frame whose tenth is 10x brighter than the rest would blow
    # that tenth out at mean 0.5; metered with the cap the gamma is larger (a shorter exposure) than the averaging
    # meter's alone (ablations/meter_average).
    R = torch.full((32, 32, 3), 0.05)
    R[:4] = 0.5
    L, S = torch.full((32, 32, 1), 0.4), R * 0.4
    capped = proxy.proxy_gamma(R, L, S, 0.4, load_config([]))
    average = proxy.proxy_gamma(R, L, S, 0.4, load_config(["ablations/meter_average"]))
    assert capped > average + 0.05, (capped, average)


def test_a_cut_off_run_resumes_from_its_checkpoint_and_its_time_is_left_out(tmp_path, monkeypatch):
    """run_job: a run folder with a checkpoint but no metrics (cut off by a time limit) continues with
    ``train --resume``; one without a checkpoint starts again; the resumed run's partial train time is not
    averaged into the table."""
    from retinexgs.run.checkpoint import latest_checkpoint

    jobs = quality.plan([tmp_path / "s1"], ["default"], [0, 1], tmp_path / "runs")
    calls = []

    def fake_run(cmd, stdout, stderr):
        calls.append(cmd)
        run = __import__("pathlib").Path(cmd[cmd.index("--out") + 1])
        run.mkdir(parents=True, exist_ok=True)
        _fake_run(next(j for j in jobs if j.run == run), 20.0, 0.5)
        return type("Done", (), {"returncode": 0})()

    monkeypatch.setattr(quality.subprocess, "run", fake_run)
    cut, fresh = jobs
    (cut.run / "checkpoints").mkdir(parents=True)
    torch.save({"step": 2000}, cut.run / "checkpoints" / "step_002000.pt")
    assert latest_checkpoint(cut.run) is not None, "the fixture's checkpoint name must be one the trainer lists"
    fresh.run.mkdir(parents=True)
    (fresh.run / "stale.txt").write_text("cut off before its first checkpoint")
    assert quality.run_job(cut, "cpu", None, []).endswith("(resumed)")
    assert "--resume" in calls[0] and "--data" not in calls[0] and (cut.run / quality.RESUMED).is_file()
    assert not quality.run_job(fresh, "cpu", None, []).endswith("(resumed)")
    assert "--resume" not in calls[1] and not (fresh.run / "stale.txt").exists()
    assert quality.run_job(fresh, "cpu", None, []).startswith("reused") and len(calls) == 2
    row = next(line for line in quality.table(jobs, ["default"]).splitlines() if line.startswith("| `default`"))
    assert "(10 s)" in row  # both runs report 10 s; only the fresh one counts, and its mean is 10 s
    (fresh.run / quality.RESUMED).write_text("")
    row = next(line for line in quality.table(jobs, ["default"]).splitlines() if line.startswith("| `default`"))
    assert " s)" not in row  # no run trained in one go: no time shown
    # the mean Gaussian count, where the runs report it
    for j, n in zip(jobs, (1000, 3000)):
        m = json.loads(j.metrics_path.read_text())
        m["train"]["gaussians"] = n
        j.metrics_path.write_text(json.dumps(m))
    row = next(line for line in quality.table(jobs, ["default"]).splitlines() if line.startswith("| `default`"))
    assert "(2k Gaussians)" in row


def test_noise_ladder_darkens_each_level_once_and_names_the_columns(tmp_path, monkeypatch, capsys):
    """--noise-ladder: one dark scene per ladder level (reused on a second call), the runs' columns SCENE@LEVEL."""
    from retinexgs.data.sensor import NOISE_LADDER
    from retinexgs.demo.synthetic import make_demo_scene

    src = make_demo_scene(tmp_path / "fox", n_train=2, n_test=1, width=32, height=24, n_points=100)
    trained = []
    monkeypatch.setattr(quality, "run_job", lambda job, *a: trained.append(job) or f"{job.run}: skipped")
    assert quality.main(["--scenes", str(src), "--noise-ladder", "--runs", str(tmp_path / "runs"), "--seeds", "0,",
                         "--jobs", "1"]) in (0, 1)
    levels = [label for label, _, _ in NOISE_LADDER]
    assert sorted(j.scene.name for j in trained) == sorted(f"fox@{label}" for label in levels)
    made = {p.name: (p / "sensor.json").stat().st_mtime_ns for p in (tmp_path / "runs" / "ladder").iterdir()}
    assert sorted(made) == sorted(f"fox@{label}" for label in levels)
    quality.main(["--scenes", str(src), "--noise-ladder", "--runs", str(tmp_path / "runs"), "--seeds", "0,",
                  "--no-train"])
    assert {p.name: (p / "sensor.json").stat().st_mtime_ns for p in (tmp_path / "runs" / "ladder").iterdir()} == made
    assert quality.main(["--scenes", str(tmp_path / "runs"), "--noise-ladder", "--runs", str(tmp_path / "r2")]) == 2
    assert "has no high/ folder" in capsys.readouterr().err


def test_raw_ladder_makes_a_raw_and_a_jpeg_column_per_level_once_and_spreads_runs_over_gpus(tmp_path, monkeypatch,
                                                                                              capsys):
    """--raw-ladder: per level SCENE@LEVEL-raw (DNGs) and SCENE@LEVEL-jpeg (the camera's JPEGs of the same mosaics),
    reused on a second call; --gpus hands each run one GPU; an unknown level is one line."""
    from retinexgs.demo.synthetic import make_demo_scene

    src = make_demo_scene(tmp_path / "fox", n_train=2, n_test=1, width=32, height=24, n_points=100)
    trained = []
    monkeypatch.setattr(quality, "run_job", lambda job, device, steps, extra, gpu=None:
                        trained.append((job, device, gpu)) or f"{job.run}: skipped")
    args = ["--scenes", str(src), "--raw-ladder", "1500e,1000e", "--runs", str(tmp_path / "runs"), "--seeds", "0,1",
            "--jobs", "1", "--gpus", "2,3"]
    assert quality.main(args) in (0, 1)
    names = sorted({j.scene.name for j, _, _ in trained})
    assert names == ["fox@1000e-jpeg", "fox@1000e-raw", "fox@1500e-jpeg", "fox@1500e-raw"]
    assert {g for _, _, g in trained} <= {2, 3} and {d for _, d, _ in trained} == {"cuda"}
    ladder = tmp_path / "runs" / "ladder"
    assert sorted(p.name for p in ladder.iterdir()) == names  # no half-made temporary folder left
    assert all(p.suffix == ".dng" for p in (ladder / "fox@1000e-raw" / "low").iterdir())
    made = {p.name: (p / "sensor.json").stat().st_mtime_ns for p in ladder.iterdir()}
    quality.main([*args[:6], "--no-train"])
    assert {p.name: (p / "sensor.json").stat().st_mtime_ns for p in ladder.iterdir()} == made
    capsys.readouterr()
    assert quality.main(["--scenes", str(src), "--raw-ladder", "900e", "--runs", str(tmp_path / "r2")]) == 2
    assert "unknown ladder level '900e'" in capsys.readouterr().err
    assert quality.parse_gpus("") == [] and quality.parse_gpus("3") == [0, 1, 2] and quality.parse_gpus("1,3") == [1, 3]


def test_black_table_reads_the_black_lift_and_skips_older_runs(tmp_path):
    scenes = [tmp_path / "s1"]
    jobs = quality.plan(scenes, ["default", "ablations/noise_blind"], [0, 1, 2], tmp_path / "runs")
    for j in jobs:
        _fake_run(j, 20.0, 0.5)
        if j.config == "ablations/noise_blind" and j.seed == 2:
            continue  # evaluated before the key existed: left out of the mean
        m = json.loads(j.metrics_path.read_text())
        m["mean"].update(black_lift=0.01 * (j.seed + 1) * (4.0 if j.config == "default" else 1.0), low_black_lift=-0.002)
        j.metrics_path.write_text(json.dumps(m))
    md = quality.black_table(jobs, ["default", "ablations/noise_blind"])
    assert "| low input | -0.0020 |" in md
    assert "| `default` | 0.0800 ± 0.0400 |" in md
    assert f"| `ablations/noise_blind` | 0.0150 ± {0.01 * math.sqrt(0.5):.4f} |" in md
    assert "Black lift" in md


def test_colour_table_reads_the_colour_error_and_skips_older_runs(tmp_path):
    scenes = [tmp_path / "s1", tmp_path / "s2"]
    jobs = quality.plan(scenes, ["default", "ablations/baseline_pre"], [0, 1], tmp_path / "runs")
    for j in jobs:
        _fake_run(j, 20.0, 0.5)
        if j.scene.name == "s2" and j.config == "ablations/baseline_pre":
            continue  # evaluated before the key existed
        m = json.loads(j.metrics_path.read_text())
        m["mean"].update(delta_e_gt_mean=2.0 + j.seed + (3.0 if j.config == "default" else 0.0),
                         low_delta_e_gt_mean=9.5)
        j.metrics_path.write_text(json.dumps(m))
    md = quality.colour_table(jobs, ["default", "ablations/baseline_pre"])
    assert "| low input | 9.50 | 9.50 |" in md
    assert "Colour error" in md
    assert f"| `default` | 5.50 ± {math.sqrt(0.5):.2f} | 5.50 ± {math.sqrt(0.5):.2f} |" in md
    assert f"| `ablations/baseline_pre` | 2.50 ± {math.sqrt(0.5):.2f} | – |" in md


def test_linear_colour_table_splits_the_colour_error(tmp_path):
    jobs = quality.plan([tmp_path / "s1"], ["default"], [0, 1], tmp_path / "runs")
    for j in jobs:
        _fake_run(j, 20.0, 0.5)
        m = json.loads(j.metrics_path.read_text())
        m["mean"].update(delta_e_linear=0.5 + j.seed, delta_e_tone_floor=2.25)
        j.metrics_path.write_text(json.dumps(m))
    md = quality.linear_colour_table(jobs, ["default"])
    light, floor = md.split("The tone's own cost")[0], md.split("luminance, and of the truth in linear light.")[1]
    assert f"| `default` | 1.00 ± {math.sqrt(0.5):.2f} |" in light and "light alone" in light
    assert "| `default` | 2.25 ± 0.00 |" in floor


def test_raw_ladder_800e_rung_has_its_stated_noise_and_bit_depth(tmp_path):
    """--raw-ladder 800e: 12-bit DNGs whose noise, measured on flat patches, is the rung's Poisson-Gaussian model:
    variance of x = (DN - black)/(white - black) = x/800 + (6/800)^2 (+ the rounding to whole DN)."""
    from retinexgs.data.camera_raw import normalised_mosaic, read_raw

    assert "800e" in [label for label, _, _ in quality.NOISE_LADDER]
    src = tmp_path / "flat"
    (src / "high").mkdir(parents=True)
    levels = (0.0, 0.35, 0.55, 0.75, 0.95)  # sRGB grey of each band; 0 holds read noise only
    band = 32
    img = np.concatenate([np.full((192, band, 3), v) for v in levels], axis=1)
    Image.fromarray(np.round(img * 255).astype(np.uint8)).save(src / "high" / "0000.png")
    out = quality.raw_ladder_scenes([src], tmp_path / "ladder", exposure=0.5, levels=["800e"])
    assert [p.name for p in out] == ["flat@800e-raw", "flat@800e-jpeg"]
    photo = read_raw(out[0] / "low" / "0000.dng")
    assert photo.white_level == 2 ** 12 - 1
    x = normalised_mosaic(photo).astype(np.float64)
    means, variances = [], []
    for b in range(len(levels)):
        for i in range(2):
            for j in range(2):
                patch = x[i::2, b * band + 2 + j:(b + 1) * band - 2:2]  # away from the band's edges (demosaic-free)
                means.append(patch.mean())
                variances.append(patch.var(ddof=1))
    a, b0 = np.polyfit(means, variances, 1)
    span = photo.white_level - float(photo.black_level.mean())
    assert a == pytest.approx(1 / 800, rel=0.12), (a, means, variances)
    assert b0 == pytest.approx((6 / 800) ** 2 + 1 / (12 * span ** 2), rel=0.25), b0
    assert max(means) > 0.1  # the bright bands are well above the read noise: the slope is measured


def test_raw_ladder_makes_a_level_drawn_by_older_random_streams_again(tmp_path):
    """A raw ladder level darkened before the per-view random streams (its sensor.json has no ``rng``; the same
    model and bit depth, other noise) is made again rather than reused, so every machine's level holds the same
    captures; one that records today's streams is reused."""
    import json

    from PIL import Image

    src = tmp_path / "flat"
    (src / "high").mkdir(parents=True)
    Image.fromarray(np.full((24, 32, 3), 128, dtype=np.uint8)).save(src / "high" / "0000.png")
    ladder = tmp_path / "ladder"
    out = quality.raw_ladder_scenes([src], ladder, exposure=0.5, levels=["1000e"])
    records = [p / "sensor.json" for p in out]
    made = [r.stat().st_mtime_ns for r in records]
    assert quality.raw_ladder_scenes([src], ladder, exposure=0.5, levels=["1000e"]) == out
    assert [r.stat().st_mtime_ns for r in records] == made  # today's streams: reused
    for r in records:  # as the single-stream darken wrote it
        data = json.loads(r.read_text())
        del data["rng"]
        r.write_text(json.dumps(data))
    quality.raw_ladder_scenes([src], ladder, exposure=0.5, levels=["1000e"])
    assert all("rng" in json.loads(r.read_text()) for r in records)  # made again, by today's streams


def test_ladder_paths_pick_the_raw_or_the_jpeg_column(tmp_path, monkeypatch, capsys):
    """--ladder-paths raw (or jpeg) trains one of each capture's two folders; anything else is one line."""
    made = [tmp_path / "ladder" / "s@1000e-raw", tmp_path / "ladder" / "s@1000e-jpeg"]
    monkeypatch.setattr(quality, "raw_ladder_scenes", lambda *a, **k: list(made))
    planned = []
    monkeypatch.setattr(quality, "plan", lambda scenes, *a, **k: planned.append(list(scenes)) or [])
    src = tmp_path / "s"
    src.mkdir()
    for paths, want in (("raw", made[:1]), ("jpeg", made[1:]), ("raw,jpeg", made)):
        planned.clear()
        quality.main(["--scenes", str(src), "--raw-ladder", "1000e", "--ladder-paths", paths, "--no-train",
                      "--runs", str(tmp_path / "runs")])
        assert planned == [want], paths
    assert quality.ladder_paths("jpeg,raw") == ["jpeg", "raw"]
    for bad in ("dng", "", "raw,tiff"):
        with pytest.raises(UserError, match="--ladder-paths must be raw, jpeg or raw,jpeg"):
            quality.ladder_paths(bad)
    capsys.readouterr()
    assert quality.main(["--scenes", str(src), "--raw-ladder", "1000e", "--ladder-paths", "nef", "--no-train"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--ladder-paths must be" in err[0]
