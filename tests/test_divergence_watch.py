"""The divergence watch on its own (issue 65): which loss term or parameter went non-finite, and at which step,
between two checks; and how few ops one watched step dispatches (training is launch-bound on the GPU)."""
import pytest
import torch
from torch import nn
from torch.utils._python_dispatch import TorchDispatchMode

from retinexgs.train.divergence import DivergenceWatch, TrainingDiverged


class Tiny(nn.Module):
    """Gaussian parameters (``gaussians.*``) beside a small network (``net.*``): ~20 parameter tensors."""

    def __init__(self) -> None:
        super().__init__()
        self.gaussians = nn.Module()
        self.gaussians.means = nn.Parameter(torch.randn(8, 3))
        self.gaussians.opacities = nn.Parameter(torch.zeros(8, 1))
        self.net = nn.Sequential(*[nn.Linear(3, 3) for _ in range(9)])


def terms_of(model: nn.Module, step: int, bad: str = "", names=("rgb", "tv", "total")) -> dict:
    """Loss terms that depend on the parameters (as a real step's do); ``bad`` is made NaN."""
    base = model.net(model.gaussians.means).square().mean() + model.gaussians.opacities.mean()
    out = {name: base * (i + 1) + step for i, name in enumerate(names)}
    if bad:
        out[bad] = out[bad] * float("nan")
    return out


def run_steps(watch: DivergenceWatch, model: nn.Module, steps, bad_term=None, bad_param=None, names=None):
    """Watch each step, then write a NaN into ``bad_param`` = (step, tensor) after that step's watch, as the
    optimiser's update would."""
    for step in steps:
        kwargs = {"names": names(step)} if names else {}
        watch.watch(terms_of(model, step, bad_term[1] if bad_term and bad_term[0] == step else "", **kwargs),
                    step)
        if bad_param and bad_param[0] == step:
            with torch.no_grad():
                bad_param[1].view(-1)[0] = float("nan")


def diverged(watch: DivergenceWatch, step: int) -> str:
    with pytest.raises(TrainingDiverged) as err:
        watch.check(step)
    return str(err.value)


@pytest.mark.parametrize("k", [1, 4, 10])
def test_a_nan_term_between_checks_is_named_with_its_step(tmp_path, k):
    model = Tiny()
    watch = DivergenceWatch(model, tmp_path, 0)
    run_steps(watch, model, range(1, 11), bad_term=(k, "tv"))
    became = "nan" if k == 10 else "non-finite"  # the value itself only when it is the checked step's
    assert diverged(watch, 10) == (f"loss term tv became {became} at step {k}; the last good checkpoint in "
                                   f"{tmp_path / 'checkpoints'} is intact (lower the learning rates or resume "
                                   "from it)")


@pytest.mark.parametrize("k", [1, 5, 9, 10])
def test_a_nan_parameter_written_after_a_steps_watch_is_named_at_that_step(tmp_path, k):
    # Pinned against the watch before issue 65: the norm seen at step k + 1's watch was made by step k's update
    # (and after the last step's watch, the check's own norms name the checked step).
    model = Tiny()
    watch = DivergenceWatch(model, tmp_path, 0)
    run_steps(watch, model, range(1, 11), bad_param=(k, model.net[3].weight))
    assert diverged(watch, 10) == (f"network parameter net.3.weight became non-finite at step {k}; the last good "
                                   f"checkpoint in {tmp_path / 'checkpoints'} is intact")


def test_a_steps_loss_comes_before_its_update_and_the_first_step_wins(tmp_path):
    model = Tiny()
    watch = DivergenceWatch(model, tmp_path, 0)
    # means NaN after step 6's update; the loss terms of step 7 on see it too (rgb first in the log's order)
    run_steps(watch, model, range(1, 9), bad_param=(6, model.gaussians.means))
    assert diverged(watch, 8).startswith("Gaussian parameter means became non-finite at step 6; ")
    model = Tiny()
    watch = DivergenceWatch(model, tmp_path, 0)
    run_steps(watch, model, range(1, 9), bad_term=(6, "tv"), bad_param=(6, model.gaussians.means))
    assert diverged(watch, 8).startswith("loss term tv became non-finite at step 6; ")


def test_more_steps_than_a_buffer_first_holds_are_attributed_exactly(tmp_path):
    model = Tiny()
    watch = DivergenceWatch(model, tmp_path, 0)
    run_steps(watch, model, range(1, 201))  # > 64 rows: the buffer grows (twice)
    values = watch.check(200)
    assert values == pytest.approx({k: float(v.detach()) for k, v in terms_of(model, 200).items()})
    assert watch.checked_through == 200
    run_steps(watch, model, range(201, 501), bad_term=(377, "rgb"), bad_param=(450, model.net[0].bias))
    assert diverged(watch, 500).startswith("loss term rgb became non-finite at step 377; ")
    model = Tiny()
    watch = DivergenceWatch(model, tmp_path, 0)
    run_steps(watch, model, range(1, 301), bad_param=(299, model.net[8].bias))
    assert diverged(watch, 300).startswith("network parameter net.8.bias became non-finite at step 299; ")


def test_term_names_that_change_between_checks_are_kept_apart(tmp_path):
    model = Tiny()
    watch = DivergenceWatch(model, tmp_path, 0)

    def names(step):  # a term joins the log from step 4 on (two keys in one interval)
        return ("rgb", "total") if step < 4 else ("rgb", "enhance", "total")

    run_steps(watch, model, range(1, 8), names=names)
    assert set(watch.check(7)) == {"rgb", "enhance", "total"}
    run_steps(watch, model, range(8, 12), names=lambda s: ("rgb", "total"))  # back to the first key
    assert set(watch.check(11)) == {"rgb", "total"}
    run_steps(watch, model, range(12, 20), bad_term=(16, "enhance"), names=lambda s: names(s - 10))
    assert diverged(watch, 19).startswith("loss term enhance became non-finite at step 16; ")
    model = Tiny()
    watch = DivergenceWatch(model, tmp_path, 0)
    run_steps(watch, model, range(1, 3), bad_term=(2, "total"), names=lambda s: ("total",))
    run_steps(watch, model, range(3, 6), bad_term=(4, "rgb"), names=lambda s: ("rgb", "total"))
    assert diverged(watch, 5).startswith("loss term total became non-finite at step 2; ")


def test_terms_of_other_dtypes_are_watched(tmp_path):
    model = Tiny()
    watch = DivergenceWatch(model, tmp_path, 0)
    for step in range(1, 4):
        watch.watch({"rgb": torch.tensor(0.5, dtype=torch.float64), "tv": torch.tensor(0.25, dtype=torch.float16),
                     "total": torch.tensor(float("inf") if step == 2 else 1.0, dtype=torch.bfloat16)}, step)
    assert diverged(watch, 3).startswith("loss term total became non-finite at step 2; ")
    watch = DivergenceWatch(model, tmp_path, 0)
    watch.watch({"rgb": torch.tensor(0.5, dtype=torch.float64), "tv": torch.tensor(0.25, dtype=torch.float16)}, 1)
    assert watch.check(1) == {"rgb": 0.5, "tv": 0.25}


class CountOps(TorchDispatchMode):
    """Counts the aten ops dispatched while it is active."""

    def __init__(self) -> None:
        super().__init__()
        self.ops = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops.append(str(func))
        return func(*args, **(kwargs or {}))


def test_one_watched_step_dispatches_at_most_three_ops(tmp_path):
    model = Tiny()
    watch = DivergenceWatch(model, tmp_path, 0)
    terms = terms_of(model, 1)
    watch.watch(terms, 1)  # the buffer is made at the first step
    with CountOps() as counted:
        watch.watch(terms, 2)
    # the multi-tensor norm and one stack into the buffer's row (2 on the CPU: no detach, no indexing op)
    assert len(counted.ops) <= 3, counted.ops
    assert any("_foreach_norm" in op for op in counted.ops) and any("stack" in op for op in counted.ops)
    assert watch.check(2) == pytest.approx({k: float(v.detach()) for k, v in terms.items()})  # the counted step's
