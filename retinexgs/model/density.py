"""Adaptive density control (3DGS §5.2): clone small and split large Gaussians with large view-space gradients,
prune transparent or oversized ones, and periodically reset opacities. Edits the Adam state in place."""
from __future__ import annotations

import math
from typing import Callable, Dict, Optional

import torch
from torch import Tensor, nn

from retinexgs.model.gaussians import PARAM_NAMES, GaussianModel
from retinexgs.render import RenderOutput
from retinexgs.render.reference import quat_to_rotmat
from retinexgs.model.schedule import Schedule


def _edit_params(model: GaussianModel, optimizer: torch.optim.Optimizer,
                 edit: Callable[[str, Tensor, bool], Tensor]) -> None:
    """Replace every Gaussian parameter by ``edit(name, tensor, is_state)``, and its Adam moments likewise."""
    for group in optimizer.param_groups:
        name = group.get("name")
        if name not in PARAM_NAMES:
            continue
        old = group["params"][0]
        new = nn.Parameter(edit(name, old.detach(), False).contiguous())
        state = optimizer.state.pop(old, None)
        if state:
            for key in ("exp_avg", "exp_avg_sq"):
                state[key] = edit(name, state[key], True).contiguous()
            optimizer.state[new] = state
        group["params"][0] = new
        setattr(model, name, new)


class DensityController:
    """Accumulates per-Gaussian screen-space gradient statistics and densifies/prunes on schedule."""

    def __init__(self, cfg: Dict, scene_extent: float, schedule: Schedule) -> None:
        self.cfg = cfg
        self.schedule = schedule  # when to densify and reset, in steps (retinexgs.model.schedule)
        self.extent = float(scene_extent)
        self.grad_accum: Optional[Tensor] = None
        self.count: Optional[Tensor] = None
        self.max_radius: Optional[Tensor] = None
        self._ndc_scale: Optional[tuple] = None  # ((width, height, device, dtype), [2] tensor)

    def state_dict(self) -> Dict[str, Optional[Tensor]]:
        return {"grad_accum": self.grad_accum, "count": self.count, "max_radius": self.max_radius}

    def load_state_dict(self, state: Dict[str, Optional[Tensor]], device: torch.device) -> None:
        for key in ("grad_accum", "count", "max_radius"):
            value = state.get(key)
            setattr(self, key, None if value is None else value.to(device))

    def _ensure(self, n: int, device: torch.device) -> None:
        if self.grad_accum is None or self.grad_accum.shape[0] != n:
            self.grad_accum = torch.zeros(n, device=device)
            self.count = torch.zeros(n, device=device)
            self.max_radius = torch.zeros(n, device=device)

    def update(self, out: RenderOutput, width: int, height: int) -> None:
        """Add one view's statistics (call after backward, before the optimizer step)."""
        grad = out.means2d.grad
        if grad is None:
            return
        self._ensure(grad.shape[0], grad.device)
        visible = out.visible
        # Pixel gradients -> NDC gradients (the unit 3DGS's threshold is defined in); the scale is cached on the
        # device (a tensor built from numbers every step is a host->device copy).
        key = (width, height, grad.device, grad.dtype)
        if self._ndc_scale is None or self._ndc_scale[0] != key:
            self._ndc_scale = (key, torch.tensor([width / 2.0, height / 2.0], device=grad.device, dtype=grad.dtype))
        ndc = grad.detach() * self._ndc_scale[1]
        # Masked arithmetic, not boolean indexing: indexing would sync with the GPU every step.
        self.grad_accum += torch.where(visible, ndc.norm(dim=-1).float(), 0.0)
        self.count += visible
        # A culled Gaussian has radii (0, 0), so its max radius is 0 and leaves the running maximum as it is.
        torch.maximum(self.max_radius, out.radii.amax(dim=-1), out=self.max_radius)

    def step(self, step: int, model: GaussianModel, optimizer: torch.optim.Optimizer, image_size: int) -> str:
        """Run whatever the schedule asks for at ``step``; returns a short description ('' if nothing)."""
        did = ""
        if self.schedule.densify_at(step) and self.grad_accum is not None:
            did = self.densify_and_prune(step, model, optimizer, image_size)
        if self.schedule.reset_at(step):
            self.reset_opacity(model, optimizer)
            did += " opacity reset"
        return did.strip()

    @torch.no_grad()
    def limit_anisotropy(self, model: GaussianModel) -> None:
        """Cap every Gaussian's longest axis at ``max_aniso`` times its shortest (0: no cap); call after each
        optimiser step. Why: a Gaussian far longer than wide is a needle, seen as a streak from any view off its
        axis, and where one or two training views see a region nothing stops it growing (the floaters of a view
        past the training views). The long axis is shortened, not the short one widened, so the cap never makes a
        Gaussian cover more than it did. In place on the parameter: Adam's moments stay as they are."""
        r = float(self.cfg["max_aniso"])
        if r <= 0 or len(model) == 0:
            return
        ls = model.log_scales
        torch.minimum(ls, ls.amin(dim=-1, keepdim=True) + math.log(r), out=ls)

    @torch.no_grad()
    def densify_and_prune(self, step: int, model: GaussianModel, optimizer: torch.optim.Optimizer,
                          image_size: int) -> str:
        c = self.cfg
        n = len(model)
        avg = self.grad_accum / self.count.clamp_min(1)
        selected = avg >= c["grad_threshold"]
        room = max(0, int(c["max_gaussians"]) - n)
        if int(selected.sum()) > room:  # keep the largest gradients within the budget
            keep = avg.topk(room).indices if room > 0 else avg.new_zeros(0, dtype=torch.long)
            selected = torch.zeros_like(selected)
            selected[keep] = True
        scales = model.scales
        big = scales.max(-1).values > c["percent_dense"] * self.extent
        clone, split = selected & ~big, selected & big
        params = model.tensors()
        new: Dict[str, Tensor] = {k: v.detach()[clone] for k, v in params.items()}
        # Split: two samples drawn from the Gaussian, each 1.6x smaller.
        idx = split.nonzero().squeeze(-1).repeat(2)
        if idx.numel():
            R = quat_to_rotmat(params["quats"].detach()[idx])
            offs = (R @ (torch.randn(idx.numel(), 3, 1, device=R.device) * scales[idx].unsqueeze(-1))).squeeze(-1)
            split_new = {k: v.detach()[idx] for k, v in params.items()}
            split_new["means"] = split_new["means"] + offs
            split_new["log_scales"] = split_new["log_scales"] - math.log(1.6)
            new = {k: torch.cat([new[k], split_new[k]]) for k in new}
        n_new = new["means"].shape[0]
        _edit_params(model, optimizer, lambda name, t, is_state: torch.cat(
            [t, torch.zeros_like(new[name]) if is_state else new[name].to(t)]))
        # Prune: the split originals, transparent Gaussians, and (after the first reset) oversized ones.
        prune = torch.cat([split, torch.zeros(n_new, dtype=torch.bool, device=split.device)])
        prune |= model.opacities < c["prune_opacity"]
        if self.schedule.prune_large_at(step):
            radius = torch.cat([self.max_radius, torch.zeros(n_new, device=split.device)])
            prune |= radius > c["max_screen_fraction"] * image_size
            prune |= model.scales.max(-1).values > 0.1 * self.extent
        if bool(prune.all()):  # never prune everything
            prune[model.opacities.argmax()] = False
        keep = ~prune
        _edit_params(model, optimizer, lambda name, t, is_state: t[keep])
        self.grad_accum = None
        return f"densify +{int(clone.sum())} clone +{int(split.sum())} split -{int(prune.sum())} pruned"

    @torch.no_grad()
    def reset_opacity(self, model: GaussianModel, optimizer: torch.optim.Optimizer) -> None:
        """Clamp every opacity to at most 0.01 (3DGS) and clear its Adam moments."""
        target = torch.logit(torch.clamp(model.opacities, max=0.01))

        def edit(name: str, t: Tensor, is_state: bool) -> Tensor:
            if name != "opacity_logits":
                return t
            return torch.zeros_like(t) if is_state else target.to(t)

        _edit_params(model, optimizer, edit)
