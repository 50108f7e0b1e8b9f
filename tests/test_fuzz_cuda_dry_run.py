"""``scripts/fuzz_cuda.py`` (CUDA vs CPU over the shared fuzz corpus) imports and builds its cases without a
GPU: its ``--dry-run`` renders 5 corpus cases on the CPU and checks the invariants."""
import importlib.util
from pathlib import Path

SCRIPT = Path(__file__).resolve().parent.parent / "scripts" / "fuzz_cuda.py"


def load_script():
    spec = importlib.util.spec_from_file_location("fuzz_cuda_script", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_dry_run_on_five_cases(one_thread):
    fuzz_cuda = load_script()
    lines = []
    assert fuzz_cuda.run(5, seed=0, dry_run=True, out=lines.append) == 0
    assert lines[-1].startswith("fuzz_cuda [dry run (CPU only)]: 5 cases, 0 failing"), lines
    assert "edge cases hit" in lines[-1]


def test_cases_are_float32_and_reach_64_channels():
    fuzz_cuda = load_script()
    recipes = [fuzz_cuda.make_recipe(fuzz_cuda.case_seed(0, i)) for i in range(300)]
    assert {r["dtype"] for r in recipes} == {"float32"}
    channels = {len(r["gaussians"][0]["color"]) + bool(r["render_depth"]) for r in recipes}
    assert max(channels) == fuzz_cuda.MAX_CUDA_CHANNELS and min(channels) == 1
    for r in recipes:  # every Gaussian and the background share the channel count
        C = len(r["gaussians"][0]["color"])
        assert all(len(g["color"]) == C for g in r["gaussians"])
        assert r["background"] is None or len(r["background"]) == C
