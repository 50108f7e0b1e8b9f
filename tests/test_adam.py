"""GroupAdam (retinexgs/train/adam.py, csrc/include/rgs/adam.h): one kernel call for every parameter group, held to
torch.optim.Adam step by step; its state dict, a fused Adam's checkpoint read back, the density strategy's edits of
its moments, and the kernel's one-line errors."""
import copy

import pytest
import torch
from torch import nn

from retinexgs.render._backend import kernels
from retinexgs.strategy.ops import edit_gaussians
from retinexgs.train.adam import GroupAdam, adam_for


def _groups(dtype, seed=0):
    """Parameters of different sizes and shapes in three groups with their own rates (one group of two)."""
    g = torch.Generator().manual_seed(seed)
    shapes = [(70001, 3), (513, 16, 3), (64, 63), (64,), (5,)]
    params = [nn.Parameter(torch.randn(s, generator=g, dtype=dtype)) for s in shapes]
    return params, [{"params": params[:1], "lr": 1.6e-4, "name": "means"},
                    {"params": params[1:2], "lr": 2.5e-3, "name": "sh_dc"},
                    {"params": params[2:], "lr": 1e-3, "name": "mlp"}]


def _grads(params, step, skip=()):
    g = torch.Generator().manual_seed(100 + step)
    for i, p in enumerate(params):
        # a wide range of magnitudes (the eps matters for the smallest), a missing gradient for ``skip``
        grad = torch.randn(p.shape, generator=g, dtype=p.dtype) * 10.0 ** (i - 3)
        p.grad = None if i in skip else grad.to(p.device)


def _run(opt_cls, dtype, steps=6, skip_at=None, lr_change=None, **kw):
    params, groups = _groups(dtype)
    opt = opt_cls(groups, eps=1e-15, **kw)
    for step in range(steps):
        _grads(params, step, skip=(3,) if step == skip_at else ())
        if lr_change is not None and step == lr_change:
            opt.param_groups[0]["lr"] = 3e-5  # the means' decaying rate
        opt.step()
    return params, opt


_SPANS = [(0, 1), (1, 2), (2, 5)]  # _groups' parameters, group by group


def _mirror(params, groups):
    """Copies of ``params`` and the same groups over them: another optimiser's own tensors."""
    mirror = [nn.Parameter(p.detach().clone()) for p in params]
    return mirror, [{**g, "params": mirror[i:j]} for g, (i, j) in zip(groups, _SPANS)]


def _stepped(opt, params, n):
    """``opt`` after ``n`` steps on :func:`_grads`' gradients."""
    for step in range(n):
        _grads(params, step)
        opt.step()
    return opt


def _steps_alike(params, opt, mirror, other, steps, tol=1e-12):
    """The same gradients to both, a step of each, and the parameters equal afterwards (to ``tol``)."""
    for step in steps:
        _grads(params, step)
        _grads(mirror, step)
        opt.step()
        other.step()
    for a, b in zip(params, mirror):
        torch.testing.assert_close(a, b, rtol=tol, atol=tol)


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-6)])
def test_matches_torch_adam(dtype, tol):
    ours, opt = _run(GroupAdam, dtype, skip_at=2, lr_change=3)
    ref, ref_opt = _run(torch.optim.Adam, dtype, skip_at=2, lr_change=3, foreach=False)
    for a, b in zip(ours, ref):
        torch.testing.assert_close(a, b, rtol=tol, atol=tol)
    for pa, pb in zip(ours, ref):
        sa, sb = opt.state[pa], ref_opt.state[pb]
        assert float(sa["step"]) == float(sb["step"])  # the skipped parameter missed one step, in both
        torch.testing.assert_close(sa["exp_avg"], sb["exp_avg"], rtol=tol, atol=tol)
        torch.testing.assert_close(sa["exp_avg_sq"], sb["exp_avg_sq"], rtol=tol, atol=tol * 1e-3)
    assert float(opt.state[ours[3]]["step"]) == 5.0 and float(opt.state[ours[0]]["step"]) == 6.0


def test_moves_the_parameters():
    """Not a no-op: after the steps the parameters differ from their start by about the rates' size."""
    start, _ = _groups(torch.float64)
    ours, _ = _run(GroupAdam, torch.float64)
    moved = [(a - b).abs().max().item() for a, b in zip(ours, start)]
    assert all(m > 1e-5 for m in moved)


def test_state_dict_round_trip_and_resume():
    """Three steps, a state dict, a fresh optimiser loading it, three more: the same as six in one go."""
    params, groups = _groups(torch.float64)
    opt = _stepped(GroupAdam(groups, eps=1e-15), params, 3)
    clone, groups2 = _mirror(params, groups)
    opt2 = GroupAdam(groups2, eps=1e-15)
    opt2.load_state_dict(copy.deepcopy(opt.state_dict()))
    _steps_alike(params, opt, clone, opt2, range(3, 6), tol=0.0)  # the same optimiser: bit for bit


def test_reads_a_fused_adam_checkpoint():
    """A checkpoint written by torch's Adam (fused on the GPU: flags set, device step tensors) loads; its step counts
    come to the host and the run goes on as torch's Adam would."""
    params, groups = _groups(torch.float64)
    ref = _stepped(torch.optim.Adam(groups, eps=1e-15, foreach=False), params, 2)
    saved = copy.deepcopy(ref.state_dict())
    for group in saved["param_groups"]:
        group["fused"] = True  # as a GPU run saved it
    ours = GroupAdam(groups, eps=1e-15)
    ours.load_state_dict(saved)
    assert all(not g["fused"] and not g["foreach"] for g in ours.param_groups)
    assert all(type(s["step"]) is float and s["step"] == 2.0 for s in ours.state.values())
    mirror, mirror_groups = _mirror(params, groups)
    ref2 = torch.optim.Adam(mirror_groups, eps=1e-15, foreach=False)
    ref2.load_state_dict(ref.state_dict())
    _steps_alike(params, ours, mirror, ref2, [2])


def test_strategy_edit_follows():
    """edit_gaussians (the density strategy's one way to change the Gaussians) replaces a parameter and its moments;
    the next step updates the new tensor from the edited moments."""
    model = nn.Module()
    model.means = nn.Parameter(torch.randn(10, 3, dtype=torch.float64))
    opt = GroupAdam([{"params": [model.means], "lr": 1e-2, "name": "means"}], eps=1e-15)
    model.means.grad = torch.ones_like(model.means)
    opt.step()
    edit_gaussians(model, opt, lambda name, t, is_state: torch.cat([t, t[:2] * 0 if is_state else t[:2]]))
    assert model.means.shape == (12, 3) and opt.param_groups[0]["params"][0] is model.means
    m_before = opt.state[model.means]["exp_avg"].clone()
    model.means.grad = torch.ones_like(model.means)
    opt.step()
    m = opt.state[model.means]["exp_avg"]
    torch.testing.assert_close(m[:10], 0.9 * m_before[:10] + 0.1)
    torch.testing.assert_close(m[10:], torch.full((2, 3), 0.1, dtype=torch.float64))


def test_refuses_what_it_lacks():
    """Refused with one line, and before anything changes: the group before the refused one is not stepped."""
    p, q = nn.Parameter(torch.randn(4)), nn.Parameter(torch.randn(4))
    opt = GroupAdam([{"params": [p]}, {"params": [q]}])
    opt.param_groups[1]["weight_decay"] = 0.1
    p.grad, q.grad = torch.ones(4), torch.ones(4)
    before = p.detach().clone()
    with pytest.raises(ValueError, match="weight decay"):
        opt.step()
    assert torch.equal(p.detach(), before) and len(opt.state[p]) == 0


def test_kernel_errors_are_one_line():
    k = kernels()
    p, g = torch.zeros(4), torch.zeros(4)
    with pytest.raises(ValueError, match="one grad"):
        k.adam_step([p], [], [p.clone()], [p.clone()], [0.9], [0.999], [1e-8], [1e-3], [1.0])
    with pytest.raises(ValueError, match="elements"):
        k.adam_step([p], [torch.zeros(5)], [p.clone()], [p.clone()], [0.9], [0.999], [1e-8], [1e-3], [1.0])
    with pytest.raises(TypeError, match="dtype"):
        k.adam_step([p], [g.double()], [p.clone()], [p.clone()], [0.9], [0.999], [1e-8], [1e-3], [1.0])
    with pytest.raises(ValueError, match="contiguous"):
        k.adam_step([torch.zeros(4, 2).t()], [torch.zeros(2, 4)], [torch.zeros(2, 4)], [torch.zeros(2, 4)],
                    [0.9], [0.999], [1e-8], [1e-3], [1.0])
    with pytest.raises(ValueError, match="bc2_sqrt"):
        k.adam_step([p], [g], [p.clone()], [p.clone()], [0.9], [0.999], [1e-8], [1e-3], [0.0])
    k.adam_step([], [], [], [], [], [], [], [], [])  # nothing to do: no error


def test_state_dict_reads_back_into_torch_adam():
    """GroupAdam's state dict (host numbers for the step counts) loads into torch's Adam (the CPU's, e.g. a GPU run
    resumed on a CPU), which turns them into tensors, and both go on alike."""
    params, groups = _groups(torch.float64)
    ours = _stepped(GroupAdam(groups, eps=1e-15), params, 2)
    mirror, mirror_groups = _mirror(params, groups)
    ref = torch.optim.Adam(mirror_groups, eps=1e-15, foreach=False)
    ref.load_state_dict(copy.deepcopy(ours.state_dict()))
    assert all(torch.is_tensor(s["step"]) and float(s["step"]) == 2.0 for s in ref.state.values())
    _steps_alike(params, ours, mirror, ref, [2])


def test_adam_for_picks_by_device():
    params, groups = _groups(torch.float32)
    assert type(adam_for(torch.device("cpu"), groups, 1e-15)) is torch.optim.Adam
    assert type(adam_for(torch.device("cuda"), groups, 1e-15)) is GroupAdam  # built on the CPU: no launch here
