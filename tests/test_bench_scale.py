"""The large-scene benchmark (``python -m retinexgs.bench scale``, issue 34): the generator of big synthetic scenes
(torch twin of the demo's ray caster, files, cache by parameters), the memory estimate, the table's fallbacks for
keys a training does not record, and tiny end-to-end runs on the CPU (one rank; two gloo ranks where this build
has the distributed training)."""
import argparse
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from retinexgs.bench import scale
from retinexgs.data.load import load_scene
from retinexgs.demo.large import (PARAMS_FILE, ensure_large_scene, large_cameras, render_linear_torch,
                                  scene_params)
from retinexgs.demo.synthetic import demo_cameras, render_linear
from retinexgs.errors import UserError

ROOT = Path(__file__).resolve().parents[1]
QUICK = ["--views", "8", "--width", "64", "--height", "48", "--views-seen", "16", "--device", "cpu"]


def test_the_large_scene_renders_the_demo_scene_in_float32():
    """One caster (demo/raycast.py) serves both scenes: the large scene's float32 render of a demo camera is the
    demo's float64 image within float32 precision, and every pixel is lit or sky (finite, positive)."""
    cam = demo_cameras(5, 2, 40, 30, seed=3)[1]
    ref = render_linear(cam, 2)
    assert np.isfinite(ref).all() and (ref > 0).all()
    assert np.abs(render_linear_torch(cam, 2, "cpu", torch.float32).numpy() - ref).max() < 1e-4
    # the large scene's cameras see the scene from a band of heights and distances, not one circle
    cams = large_cameras(40, 4, 32, 24)
    heights = [c.center[1] for c in cams]
    assert max(heights) - min(heights) > 0.8 and sum(c.split == "test" for c in cams) == 4


def test_large_scene_files_cache_and_loading(tmp_path):
    params = scene_params(5, 2, 40, 30, seed=1, fmt="png", n_points=300)
    folder, summary = ensure_large_scene(tmp_path / "s", params)
    assert summary is not None and summary["views"] == 7
    names = sorted(p.name for p in (folder / "low").iterdir())
    assert names == sorted(p.name for p in (folder / "high").iterdir()) and len(names) == 7
    assert all(n.endswith(".png") for n in names)
    low = np.stack([np.asarray(Image.open(folder / "low" / n), np.float64) for n in names])
    high = np.stack([np.asarray(Image.open(folder / "high" / n), np.float64) for n in names])
    assert low.shape == (7, 30, 40, 3) and low.mean() / high.mean() < 0.2 and high.mean() > 50
    assert json.loads((folder / PARAMS_FILE).read_text())["params"] == params
    scene = load_scene(folder)
    assert len(scene.train) == 5 and len(scene.test) == 2
    assert all(v.paired_path is not None for v in scene.test)
    assert scale.scene_size(folder) == (5, 40, 30)
    # the same parameters: reused, nothing rewritten
    stamp = (folder / "low" / names[0]).stat().st_mtime_ns
    again, summary = ensure_large_scene(folder, params)
    assert summary is None and (again / "low" / names[0]).stat().st_mtime_ns == stamp
    # other parameters: that folder is made again
    _, summary = ensure_large_scene(folder, dict(params, seed=2))
    assert summary is not None
    assert not np.array_equal(np.asarray(Image.open(folder / "low" / names[0])), low[0].astype(np.uint8))
    # a folder it did not make is never deleted
    other = tmp_path / "mine"
    other.mkdir()
    (other / "keep.txt").write_text("x")
    with pytest.raises(UserError, match="not a scene generated"):
        ensure_large_scene(other, params)
    assert (other / "keep.txt").is_file()


def test_generation_in_a_process_of_its_own(tmp_path):
    """The GPU's path (a spawned process, so the benchmark holds no CUDA context), taken here on the CPU."""
    args = argparse.Namespace(scene=None, views=3, test_views=1, width=24, height=18, seed=0, format="jpg",
                              supersample=1, points=100, scenes_dir=tmp_path)
    folder, info = scale.make_scene(args, "cpu", separate_process=True)
    assert info["generated"] and not info["reused"] and info["generation"]["views"] == 4
    assert sorted(p.name for p in (folder / "low").iterdir()) == ["0000.jpg", "0001.jpg", "0002.jpg", "0003.jpg"]
    assert scale.make_scene(args, "cpu", separate_process=True)[1]["reused"]


def test_estimate_shows_that_1000_views_at_1080p_do_not_fit_preloaded():
    est = scale.estimate(1000, 1920, 1080, gpu_bytes=80 * scale.GB, host_bytes=128 * scale.GB)
    assert est["view_pixels"] == 1000 * 1920 * 1080
    assert est["gpu_after_setup"] == 28 * est["view_pixels"] and est["gpu_after_use"] == 44 * est["view_pixels"]
    assert est["fits_gpu"] is False and est["fits_host"] is True
    assert 900 < est["views_fitting_gpu"] < 1000
    text = scale.format_estimate(est)
    assert "does NOT fit" in text and "2,073,600,000 view-pixels" in text
    small = scale.estimate(300, 1920, 1080, gpu_bytes=80 * scale.GB)
    assert small["fits_gpu"] is True and small["fits_host"] is None


def test_plan():
    assert scale.parse_gpus("1,2,4") == [1, 2, 4] and scale.parse_gpus("2, 2,1") == [2, 1]
    for bad in ("", "0,1", "a"):
        with pytest.raises(ValueError):
            scale.parse_gpus(bad)
    assert [scale.steps_for(2000, n) for n in (1, 2, 4)] == [2000, 1000, 500]
    assert scale.steps_for(10, 4) == 3 and scale.steps_for(16, 2, views_per_rank=2) == 4
    assert scale.train_command(Path("S"), Path("R"), 1, 16, "cpu", "default", [])[1:4] == ["-m", "retinexgs", "train"]
    cmd = scale.train_command(Path("S"), Path("R"), 4, 500, "cuda", "paper", ["a=1"])
    assert cmd[1:7] == ["-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "4", "-m"]
    assert cmd[-6:] == ["--set", "steps=500", "--config", "paper", "--set", "a=1"]


def test_table_from_todays_keys_and_from_the_distributed_ones():
    today = {"train": {"train_seconds": 100.0, "steps": 2000, "gaussians": 120000, "device": "NVIDIA H100",
                       "peak_gpu_memory_gb": 30.5}, "mean": {"psnr": 25.0, "ssim": 0.9}}
    one, notes1 = scale.summarize(1, today, 150.0, 12.0)
    assert one["views_per_second"] == pytest.approx(20.0) and one["steps_per_second"] == pytest.approx(20.0)
    assert {"views_fallback", "gpu_single", "rss_fallback", "first_missing", "ranks_missing"} <= set(notes1)
    dist = {"train": {"train_seconds": 52.0, "steps": 1000, "ranks": 2, "views_per_step": 2,
                      "views_per_second": 38.0, "time_to_first_step": 21.5,
                      "peak_gpu_memory_gb_per_rank": [10.0, 10.5], "host_rss_gb_per_rank": [6.0, 7.5],
                      "gaussians": 118000}, "mean": {"psnr": 24.9, "ssim": 0.9}}
    two, notes2 = scale.summarize(2, dist, 80.0, 99.0)
    assert notes2 == [] and two["host_rss_gb_max"] == 7.5 and two["views_seen"] == 2000
    missing, notes3 = scale.summarize(4, {"train": {}}, 30.0, None)
    rows = [dict(one, status="ok", notes=notes1), dict(two, status="ok", notes=notes2),
            dict(missing, status="ok", notes=notes3), {"gpus": 8, "planned_steps": 250, "status": "skipped: 4 GPU(s)"}]
    md = scale.table(rows)
    line = {r.split("|")[1].strip(): [c.strip() for c in r.split("|")[2:-1]] for r in md.splitlines()
            if r.startswith("| ")}
    assert line["speed-up (views/s over 1 GPU)"] == ["1.00×", "1.90×", "–", "–"]
    assert line["PSNR aligned to the truth's grey mean (GT-mean)"] == ["–", "–", "–", "–"]  # not in these metrics
    assert line["efficiency (speed-up / N)"] == ["100 %", "95 %", "–", "–"]
    assert line["peak GPU memory per rank (GB)"][1] == "10.50 (min 10.00)"
    assert line["time to first step (s)"][1] == "21.5" and line["time to first step (s)"][0].startswith("– (")
    steps = line["steps (views seen)"]
    assert steps[:2] == ["2000 (2000)", "1000 (2000)"] and steps[3] == "250 planned"
    assert line["PSNR / SSIM (test views)"][2].startswith("– (")
    assert "time to first step: not recorded" in md and "wait4" in md


def _bench(tmp_path, *args, timeout=600):
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "retinexgs.bench", "scale", *args, "--scenes-dir",
                           str(tmp_path / "scenes"), "--out", str(tmp_path / "out")],
                          capture_output=True, text=True, cwd=ROOT, env=env, timeout=timeout)


def test_quick_cpu_run(tmp_path):
    r = _bench(tmp_path, *QUICK, "--gpus", "1")
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "generating 8 + 8 test views at 64x48" in r.stdout and "view-pixels" in r.stdout
    report = json.loads((tmp_path / "out" / "scale.json").read_text())
    assert report["decompose"]["mode"] == "once" and report["decompose"]["exit"] == 0
    (run,) = report["runs"]
    assert run["status"] == "ok" and run["steps"] == 16 and run["views_seen"] == 16 and run["ranks"] == 1
    assert run["views_per_second"] > 0 and run["host_rss_gb_max"] > 0.1 and 0 < run["psnr"] < 60
    md = (tmp_path / "out" / "scale.md").read_text()
    assert "| status | ok |" in md and "| speed-up (views/s over 1 GPU) | 1.00× |" in md
    assert "(2.0 passes over the training views)" in md and "A short run" not in md  # one rank count: no caveat
    # --reuse reads a finished run's row back instead of training it again (same --out, same command)
    r = _bench(tmp_path, *QUICK, "--gpus", "1", "--reuse")
    assert r.returncode == 0 and "reused the finished run" in r.stdout, r.stdout[-2000:] + r.stderr[-2000:]
    assert json.loads((tmp_path / "out" / "scale.json").read_text())["runs"] == [run]
    # the scene is reused; another command is trained even with --reuse; a run that fails makes the benchmark
    # fail, and says where its log is
    r = _bench(tmp_path, *QUICK, "--gpus", "1", "--decompose", "none", "--set", "loss.no_such_key=1", "--reuse")
    assert "reusing" in r.stdout and r.returncode == 1, r.stdout[-2000:]
    (run,) = json.loads((tmp_path / "out" / "scale.json").read_text())["runs"]
    assert run["status"].startswith("failed (exit") and "gpus1.log" in run["status"]
    assert not (tmp_path / "out" / "runs" / "gpus1.row.json").exists()  # the failed run left no row to reuse


@pytest.mark.skipif(importlib.util.find_spec("retinexgs.train.distributed") is None,
                    reason="no multi-GPU training in this build (retinexgs.train.distributed) for the 2-rank case")
def test_two_gloo_ranks_at_equal_views_seen(tmp_path):
    r = _bench(tmp_path, *QUICK, "--gpus", "1,2", "--decompose", "none")
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    one, two = json.loads((tmp_path / "out" / "scale.json").read_text())["runs"]
    assert one["status"] == two["status"] == "ok"
    assert two["ranks"] == 2 and two["steps"] == 8 and two["views_seen"] == one["views_seen"] == 16
    assert two["views_per_second"] > 0 and two["psnr"] is not None
    md = (tmp_path / "out" / "scale.md").read_text()
    assert "A short run (under 20 passes)" in md and "more --views-seen" in md  # 2 passes: PSNR says little


def test_seeds_aggregate_to_means_and_spread():
    runs = [dict(gpus=2, seed=s, status="ok", steps=8, views_per_step=2, views_seen=16, ranks=2, notes=[],
                 views_per_second=v, steps_per_second=v / 2, psnr=p, ssim=0.5, psnr_gt_mean=p + 3.0 + s,
                 peak_gpu_gb_per_rank=[1.0, g], gaussians=1000 * (s + 1),
                 views_per_second_after_first_step=v + 1, density_event_steps=4, density_event_overhead_seconds=0.5)
            for s, v, p, g in ((0, 10.0, 20.0, 2.0), (1, 14.0, 22.0, 3.0))]
    row = scale.aggregate(runs)
    assert row["status"] == "ok" and row["seeds"] == [0, 1]
    assert row["views_per_second"] == pytest.approx(12.0) and row["psnr"] == pytest.approx(21.0)
    assert row["psnr_std"] == pytest.approx(2 ** 0.5) and row["peak_gpu_gb_per_rank"] == [1.0, 3.0]
    failed = scale.aggregate(runs + [dict(gpus=2, seed=2, status="failed (exit 1, x.log)")])
    assert failed["status"].startswith("ok for 2 of 3 seeds; failed") and failed["psnr"] == pytest.approx(21.0)
    base = dict(runs[0], gpus=1, views_per_second_after_first_step=5.0)
    md = scale.table([dict(base, seeds=[0]), row])
    line = {r.split("|")[1].strip(): [c.strip() for c in r.split("|")[2:-1]] for r in md.splitlines()
            if r.startswith("| ")}
    assert line["views/s after step 1 (speed-up, efficiency)"] == ["5.00 (1.00×, 100 %)", "13.00 (2.60×, 130 %)"]
    assert line["PSNR / SSIM (test views)"][1] == "21.00 ± 1.41 / 0.500 ± 0.000"
    assert line["PSNR aligned to the truth's grey mean (GT-mean)"] == ["23.00", "24.50 ± 2.12"]
    assert line["density events: steps timed; seconds beyond plain steps"][1] == "4; 0.50 s"


def test_steady_timing_leaves_out_the_first_step_and_prices_the_events():
    from retinexgs.train.distributed import steady_timing
    # 101 steps of 2 views in 12 s: step 1 took 2 s, 10 event-timed steps 2 s, the 90 plain steps 8 s.
    out = steady_timing(2, 202, 12.0, {"first_step_seconds": 2.0, "event_seconds": 2.0, "event_steps": 10})
    assert out["views_per_second_after_first_step"] == pytest.approx(200 / 10.0)
    assert out["plain_step_seconds"] == pytest.approx(8.0 / 90, abs=1e-6)
    assert out["density_event_overhead_seconds"] == pytest.approx(2.0 - 10 * 8.0 / 90, abs=1e-3)
    assert steady_timing(2, 202, 12.0, None) == {} and steady_timing(1, 1, 1.0, {"first_step_seconds": 1.0}) == {}
