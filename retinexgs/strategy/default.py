"""The default strategy: 3DGS's adaptive density control (Kerbl et al. 2023, §5.2): clone small and split large
Gaussians with large view-space gradients, prune transparent or oversized ones, periodically reset opacities;
``density.max_aniso`` caps needles after every optimiser step. Parameters and Adam moments change only through :mod:`retinexgs.strategy.ops`."""
from __future__ import annotations

import math
from typing import Callable, Dict, Optional

import torch
from torch import Tensor

from retinexgs.config.schema import Density
from retinexgs.model.gaussians import GaussianModel
from retinexgs.model.schedule import Schedule
from retinexgs.render import RenderOutput
from retinexgs.render.rotation import quat_to_rotmat
from retinexgs.render.screen_stats import screen_stats
from retinexgs.strategy.base import Strategy, register
from retinexgs.strategy.ops import cap_anisotropy, edit_gaussians, mask_indices, reset_opacity


# The per-Gaussian statistics summed over views (and over ranks before a densification), and the one kept as a
# running maximum.
SUMMED = ("grad_accum", "count")
MAXIMA = ("max_radius",)


@register("default")
class DefaultStrategy(Strategy):
    """Accumulates per-Gaussian screen-space gradient statistics and densifies, prunes and resets on schedule.
    ``cfg``: the config's ``density`` section."""

    def __init__(self, cfg: Density, scene_extent: float, schedule: Schedule, seed: int = 0) -> None:
        super().__init__(cfg, scene_extent, schedule, seed)  # schedule: when to densify and reset, in steps
        self.grad_accum: Optional[Tensor] = None  # Σ over views of the NDC gradient norm (3DGS's statistic)
        self.count: Optional[Tensor] = None       # views that saw each Gaussian
        self.max_radius: Optional[Tensor] = None

    def state_dict(self) -> Dict[str, Optional[Tensor]]:
        return {key: getattr(self, key) for key in SUMMED + MAXIMA}

    def load_state_dict(self, state: Dict[str, Optional[Tensor]], device: torch.device) -> None:
        for key in SUMMED + MAXIMA:
            value = state.get(key)
            # float32 and contiguous: the fused statistics kernel adds to them in place
            setattr(self, key, None if value is None else value.to(device, torch.float32).contiguous())

    def _ensure(self, n: int, device: torch.device) -> None:
        if self.grad_accum is None or self.grad_accum.shape[0] != n:
            for key in SUMMED + MAXIMA:
                setattr(self, key, torch.zeros(n, device=device, dtype=torch.float32))

    def after_backward(self, out: RenderOutput, width: int, height: int) -> None:
        """Add one view's statistics (call after backward, before the optimizer step): one fused kernel,
        no host sync (:func:`retinexgs.render.screen_stats.screen_stats`)."""
        grad = out.means2d.grad
        if grad is None:
            return
        self._ensure(grad.shape[0], grad.device)
        screen_stats(grad, out.radii, width, height, self.grad_accum, self.count, self.max_radius)

    def densification_statistic(self) -> Tensor:
        """[N] what the threshold is compared with: the mean NDC gradient norm over the views that saw each
        Gaussian (3DGS)."""
        return self.grad_accum / self.count.clamp_min(1)

    def step(self, step: int, model: GaussianModel, optimizer: torch.optim.Optimizer, image_size: int) -> str:
        """Run whatever the schedule asks for at ``step``; returns a short description ('' if nothing)."""
        did = ""
        if self.schedule.densify_at(step) and self.grad_accum is not None:
            did = self.densify_and_prune(step, model, optimizer, image_size)
        if self.schedule.reset_at(step):
            reset_opacity(model, optimizer)
            did += " opacity reset"
        return did.strip()

    def edits_at(self, step: int) -> bool:
        return self.schedule.densify_at(step) or self.schedule.reset_at(step)

    def after_optimizer_step(self, model: GaussianModel, optimizer: Optional[torch.optim.Optimizer] = None,
                             step: int = 0) -> None:
        """Cap every Gaussian's longest axis at ``max_aniso`` times its shortest (0: no cap). Why: a Gaussian far
        longer than wide is a needle, seen as a streak from any view off its axis, and where one or two training
        views see a region nothing stops it growing (the floaters of a view past the training views). The long
        axis is shortened, not the short one widened, so the cap never makes a Gaussian cover more than it did."""
        cap_anisotropy(model, float(self.cfg.max_aniso))

    def will_edit(self, step: int) -> bool:
        """Whether :meth:`step` densifies at ``step`` (the ranks must first :meth:`reduce` the statistics)."""
        return self.schedule.densify_at(step)

    def reduce(self, all_reduce_sum: Callable[[Tensor], Tensor], all_reduce_max: Callable[[Tensor], Tensor],
               n: int, image_size: int, device: torch.device) -> int:
        """Several ranks, before a densification: sum the per-Gaussian statistics over the ranks and take the
        maximum of the screen radii, so every rank decides alike; returns the largest image side of the batch
        (the screen-size prune's reference). ``all_reduce_*`` reduce one flat tensor in place and return it."""
        has = self.grad_accum is not None
        dev = self.grad_accum.device if has else None

        def flat(keys, extra: float) -> Tensor:
            parts = [getattr(self, k).float() if has and getattr(self, k) is not None else None for k in keys]
            device = dev if dev is not None else torch.device("cpu")
            parts = [p if p is not None else torch.zeros(n, device=device, dtype=torch.float32) for p in parts]
            return torch.cat(parts + [torch.tensor([extra], device=device)])

        sums = all_reduce_sum(flat(SUMMED, 1.0 if has else 0.0))
        maxima = all_reduce_max(flat(MAXIMA, float(image_size)))
        anyone, biggest = torch.stack([sums[-1], maxima[-1]]).tolist()  # one host read for both
        anyone = anyone > 0
        for keys, values in ((SUMMED, sums), (MAXIMA, maxima)):
            for i, key in enumerate(keys):
                setattr(self, key, values[i * n:(i + 1) * n] if anyone else None)
        return int(biggest)

    @torch.no_grad()
    def densify_and_prune(self, step: int, model: GaussianModel, optimizer: torch.optim.Optimizer,
                          image_size: int) -> str:
        """Clone, split and prune (3DGS) with two host reads in all (issue 65: every read stalls the GPU queue):
        the clone and split counts together, then the kept indices. Everything else is decided on the device."""
        c = self.cfg
        n = len(model)
        avg = self.densification_statistic()
        selected = avg >= c.grad_threshold
        room = max(0, int(c.max_gaussians) - n)
        if room < n:  # over budget only if more than ``room`` are selected: keep the largest gradients then
            capped = torch.zeros_like(selected)
            if room > 0:
                capped[avg.topk(room).indices] = True
            selected = torch.where(selected.sum() > room, capped, selected)
        scales = model.scales
        big = scales.max(-1).values > c.percent_dense * self.extent
        clone, split = selected & ~big, selected & big
        n_clone, n_split = torch.stack([clone.sum(), split.sum()]).tolist()  # host read 1
        params = model.tensors()
        clone_idx = mask_indices(clone, n_clone)
        new: Dict[str, Tensor] = {k: v.detach().index_select(0, clone_idx) for k, v in params.items()}
        # Split: two samples drawn from the Gaussian, each 1.6x smaller.
        idx = mask_indices(split, n_split).repeat(2)
        if n_split:
            R = quat_to_rotmat(params["quats"].detach()[idx])
            offs = (R @ (torch.randn(idx.numel(), 3, 1, device=R.device) * scales[idx].unsqueeze(-1))).squeeze(-1)
            split_new = {k: v.detach()[idx] for k, v in params.items()}
            split_new["means"] = split_new["means"] + offs
            split_new["log_scales"] = split_new["log_scales"] - math.log(1.6)
            new = {k: torch.cat([new[k], split_new[k]]) for k in new}
        n_new = n_clone + 2 * n_split
        edit_gaussians(model, optimizer, lambda name, t, is_state: torch.cat(
            [t, torch.zeros_like(new[name]) if is_state else new[name].to(t)]))
        # Prune: the split originals, transparent Gaussians, and (after the first reset) oversized ones.
        prune = torch.cat([split, torch.zeros(n_new, dtype=torch.bool, device=split.device)])
        prune |= model.opacities < c.prune_opacity
        if self.schedule.prune_large_at(step):
            radius = torch.cat([self.max_radius, torch.zeros(n_new, device=split.device, dtype=torch.float32)])
            prune |= radius > c.max_screen_fraction * image_size
            prune |= model.scales.max(-1).values > 0.1 * self.extent
        # Never prune everything: where all would go, the most opaque stays (decided on the device).
        opaque = model.opacities.argmax().unsqueeze(0)  # an index tensor, not a Python int (that is a read)
        prune.index_put_((opaque,), prune[opaque] & ~prune.all())
        keep = (~prune).nonzero().squeeze(-1)  # host read 2
        edit_gaussians(model, optimizer, lambda name, t, is_state: t.index_select(0, keep))
        for key in SUMMED + MAXIMA:  # the next interval starts afresh (_ensure: at the new Gaussian count)
            setattr(self, key, None)
        return f"densify +{n_clone} clone +{n_split} split -{n + n_new - keep.numel()} pruned"
