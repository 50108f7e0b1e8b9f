"""The one module that edits the Gaussians' parameters and their Adam moments (densification, pruning, opacity
reset, the ranks' resize before a broadcast). Every edit replaces the parameter tensor and moves its optimiser state
to the new one, so Adam's moments always match the Gaussians they belong to."""
from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor, nn

from retinexgs.model.gaussians import PARAM_NAMES, GaussianModel


def edit_gaussians(model: nn.Module, optimizer: torch.optim.Optimizer,
                   edit: Callable[[str, Tensor, bool], Tensor]) -> None:
    """Replace every Gaussian parameter by ``edit(name, tensor, is_state)`` and its Adam moments likewise
    (``is_state`` True for ``exp_avg`` / ``exp_avg_sq``); the optimiser's state follows the new tensors."""
    for group in optimizer.param_groups:
        name = group.get("name")
        if name not in PARAM_NAMES:
            continue
        old = group["params"][0]
        new = nn.Parameter(edit(name, old.detach(), False).contiguous())
        state = optimizer.state.pop(old, None)
        if state:
            for key in ("exp_avg", "exp_avg_sq"):
                if key in state:
                    state[key] = edit(name, state[key], True).contiguous()
            optimizer.state[new] = state
        group["params"][0] = new
        setattr(model, name, new)


def mask_indices(mask: Tensor, count: int) -> Tensor:
    """The indices [count] where the 1-D ``mask`` is True, ascending (what ``mask.nonzero().squeeze(-1)`` gives),
    given their ``count`` read beforehand (e.g. with other counts in one ``.tolist()``). Why: ``nonzero`` or a
    mask index must read the count from the device, one host sync each; this is a stable partition instead,
    every size known on the host."""
    n = mask.shape[0]
    order = torch.arange(n, device=mask.device)
    before = torch.cumsum(mask, 0) - mask.long()  # Trues before each position
    # True i goes to its rank among the Trues, False i after all of them (count + its rank among the Falses).
    dest = torch.where(mask, before, count + order - before)
    out = torch.empty_like(order)
    out[dest] = order  # an integer index (a permutation): no read on the host
    return out[:count]


def resize_gaussians(model: nn.Module, optimizer: torch.optim.Optimizer, n: int) -> None:
    """Give every Gaussian parameter and moment ``n`` rows of zeros (a rank about to receive rank 0's Gaussians)."""
    edit_gaussians(model, optimizer, lambda name, t, is_state: t.new_zeros((n,) + tuple(t.shape[1:])))


@torch.no_grad()
def reset_opacity(model: GaussianModel, optimizer: torch.optim.Optimizer, ceiling: float = 0.01) -> None:
    """Clamp every opacity to at most ``ceiling`` (3DGS: 0.01) and clear its Adam moments."""
    target = torch.logit(torch.clamp(model.opacities, max=ceiling))

    def edit(name: str, t: Tensor, is_state: bool) -> Tensor:
        if name != "opacity_logits":
            return t
        return torch.zeros_like(t) if is_state else target.to(t)

    edit_gaussians(model, optimizer, edit)


@torch.no_grad()
def cap_anisotropy(model: GaussianModel, ratio: float) -> None:
    """Shorten every Gaussian's longest axis to at most ``ratio`` times its shortest, in place on the parameter
    (Adam's moments stay: the edit is a projection onto the allowed set, not a new Gaussian)."""
    if ratio <= 0 or len(model) == 0:
        return
    ls = model.log_scales
    torch.minimum(ls, ls.amin(dim=-1, keepdim=True) + math.log(ratio), out=ls)
