"""Adam with one kernel launch for every parameter group (``csrc/include/rgs/adam.h``, CPU and CUDA).

torch's fused Adam launches once per parameter group, and its multi-tensor kernel gives each 64k-element chunk one
block: the Gaussians' 57k-row tensors get a handful of blocks each, so on fox-dark its 8 launches take ~44 µs
apiece, ~0.35 ms of a ~4.7 ms step (issue 65, experiments/notes/2026-11-29-adam-one-launch.md). :class:`GroupAdam`
is ``torch.optim.Adam`` itself (the same state, state dict, checkpoints and parameter groups: the density strategy
edits its moments as before) with a :meth:`~GroupAdam.step` that updates every tensor in one launch, one thread per
element. Its algorithm is Adam's without weight decay or AMSGrad, as the trainer uses it; the tests hold it to
``torch.optim.Adam``.
"""
from __future__ import annotations

import math
from typing import Dict, Iterable, List

import torch
from torch import Tensor

from retinexgs.render._backend import kernels


class GroupAdam(torch.optim.Adam):
    """``torch.optim.Adam(params, lr, betas, eps)`` whose step is one :func:`retinexgs._C.adam_step` call.

    Each parameter's step count is a Python float in its state (torch's Adam keeps a tensor; its ``__setstate__``
    turns a number back into one, so either optimiser reads the other's state dict), so the bias corrections are host
    numbers passed to the kernel: a step reads nothing back from the device, and costs no tensor operation on the
    host (a 0-d CPU tensor's ``+= 1`` and ``float()`` were most of the step's Python time). Weight
    decay, AMSGrad, maximize and sparse or complex gradients are refused (ValueError), as the kernel has none."""

    def __init__(self, params: Iterable, lr: float = 1e-3, betas=(0.9, 0.999), eps: float = 1e-8) -> None:
        super().__init__(params, lr=lr, betas=betas, eps=eps, foreach=False, fused=False)

    def load_state_dict(self, state_dict: Dict) -> None:
        """torch's, then the step counts as host numbers (a checkpoint of torch's fused Adam keeps them on the device:
        read once here, not at every step) and the groups' fused/foreach flags cleared."""
        super().load_state_dict(state_dict)
        for group in self.param_groups:
            group["fused"], group["foreach"], group["capturable"] = False, False, False
        for state in self.state.values():
            if "step" in state:
                state["step"] = float(state["step"])

    @torch.no_grad()
    def step(self, closure=None):
        """One Adam step of every parameter with a gradient (those without are left as they are, their step count
        too, as torch does)."""
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        # Everything refused before anything changes: a refusal leaves no group half stepped.
        for group in self.param_groups:
            if group["weight_decay"] or group["amsgrad"] or group["maximize"]:
                raise ValueError("GroupAdam has no weight decay, AMSGrad or maximize: use torch.optim.Adam")
            if any(p.grad is not None and (p.grad.is_sparse or p.is_complex()) for p in group["params"]):
                raise ValueError("GroupAdam takes dense real gradients only")
        batches: Dict[tuple, List[list]] = {}
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            lr = float(group["lr"])
            for p in group["params"]:
                if p.grad is None:
                    continue
                state = self.state[p]
                if len(state) == 0:
                    state["step"] = 0.0
                    state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                    state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                t = state["step"] = float(state["step"]) + 1.0
                grad = p.grad if p.grad.is_contiguous() else p.grad.contiguous()
                row = batches.setdefault((p.device, p.dtype), [[] for _ in range(9)])
                for column, value in zip(row, (p, grad, state["exp_avg"], state["exp_avg_sq"], float(beta1),
                                               float(beta2), float(group["eps"]), lr / (1.0 - beta1 ** t),
                                               math.sqrt(1.0 - beta2 ** t))):
                    column.append(value)
        for columns in batches.values():
            kernels().adam_step(*columns)
        return loss


def adam_for(device: torch.device, groups: List[dict], eps: float) -> torch.optim.Optimizer:
    """The trainer's Adam: :class:`GroupAdam` on the GPU (one launch a step), torch's on the CPU (its vectorised
    loop is as fast there, and CPU training stays exactly as it was)."""
    if device.type == "cuda":
        return GroupAdam(groups, eps=eps)
    return torch.optim.Adam(groups, eps=eps)
