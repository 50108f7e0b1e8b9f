"""MCMC densification (Kheradmand et al. 2024, "3D Gaussian Splatting as Markov Chain Monte Carlo"): the
Gaussians are samples of the scene, moved by noise and never cloned or pruned by heuristics.

- After every optimiser step each Gaussian's centre takes a random step shaped by its own covariance, large where
  it is nearly transparent and vanishing where it is opaque (the paper's stochastic-gradient Langevin term).
- On the density schedule, "dead" Gaussians (opacity at most ``min_opacity``) are relocated onto live ones drawn in
  proportion to their opacity, and ``growth`` more are added the same way up to ``cap_max``. A Gaussian that
  becomes N copies keeps the rendered look of the one it was (the paper's eq. 9): opacity 1 − (1 − o)^(1/N), its
  scale shrunk by o / Σᵢ Σₖ C(i−1, k) (−1)ᵏ oₙ^(k+1) / √(k+1).
- Opacity and scale regularisers (L1 on both) make unneeded Gaussians fade, to be relocated.
There are no opacity resets. Why a second strategy: issue 63 (and issue 64's floaters that fit one view's noise):
noise-driven exploration instead of gradient thresholds that a noisy capture's gradients trip.
"""
from __future__ import annotations

from typing import Dict, Optional, Tuple

import torch
from torch import Tensor

from retinexgs.config.schema import Density
from retinexgs.model.gaussians import GaussianModel
from retinexgs.model.schedule import Schedule
from retinexgs.render.rotation import quat_to_rotmat
from retinexgs.strategy.base import Strategy, register
from retinexgs.strategy.ops import cap_anisotropy, edit_gaussians, mask_indices

N_MAX = 51  # the most copies one Gaussian becomes in one event (the binomial sum's table)


def relocation(opacity: Tensor, scale: Tensor, copies: Tensor) -> Tuple[Tensor, Tensor]:
    """The opacity [K] and scales [K,3] of each of ``copies`` [K] (≥ 1) Gaussians that replace one Gaussian of
    ``opacity`` and ``scale`` so that together they render as it did (eq. 9). Computed in float64: the binomial sum
    alternates in sign."""
    n = copies.clamp(1, N_MAX).to(torch.float64)
    o = opacity.to(torch.float64).clamp(1e-8, 1.0 - 1e-8)
    o_new = 1.0 - (1.0 - o).pow(1.0 / n)
    k = torch.arange(N_MAX, dtype=torch.float64, device=o.device)              # k = 0..N_MAX-1
    i = torch.arange(1, N_MAX + 1, dtype=torch.float64, device=o.device)       # i = 1..N_MAX
    # C(i-1, k) through log-gamma; zero where k > i - 1.
    lg = torch.lgamma(i[:, None]) - torch.lgamma(k[None, :] + 1) - torch.lgamma(i[:, None] - k[None, :])
    binom = torch.where(k[None, :] <= i[:, None] - 1, lg.exp(), torch.zeros_like(lg))     # [I,K]
    coef = binom * (-1.0) ** k[None, :] / (k[None, :] + 1).sqrt()                        # [I,K]
    powers = o_new[:, None] ** (k[None, :] + 1)                                           # [M,K]
    inner = powers @ coef.T                                                               # [M,I]
    denom = (inner * (i[None, :] <= n[:, None])).sum(-1)                                  # Σ over i ≤ N
    factor = o / denom.clamp_min(1e-12)
    return o_new.to(opacity.dtype), scale * factor.to(scale.dtype)[:, None]


@register("mcmc")
class MCMCStrategy(Strategy):
    """Relocation and growth by opacity-weighted sampling, Langevin noise on the centres, L1 regularisers
    (``density.mcmc``: cap_max, growth, min_opacity, noise_lr, opacity_reg, scale_reg)."""

    def __init__(self, cfg: "Density", scene_extent: float, schedule: Schedule, seed: int = 0) -> None:
        super().__init__(cfg, scene_extent, schedule, seed)
        self.generator: Optional[torch.Generator] = None
        self._saved_rng: Optional[Tensor] = None

    def _rng(self, device: torch.device) -> torch.Generator:
        # Its own stream, seeded alike on every rank (the ranks' Gaussians must move alike between broadcasts).
        if self.generator is None or self.generator.device != device:
            self.generator = torch.Generator(device=device)
            self.generator.manual_seed(9_176_011 * (self.seed + 1))
            if self._saved_rng is not None:
                self.generator.set_state(self._saved_rng)
        return self.generator

    def edits_at(self, step: int) -> bool:
        return self.schedule.densify_at(step)

    def extra_loss(self, model: GaussianModel) -> Optional[Tensor]:
        m = self.cfg.mcmc
        if not (m.opacity_reg or m.scale_reg) or len(model) == 0:
            return None
        return m.opacity_reg * model.opacities.mean() + m.scale_reg * model.scales.mean()

    @torch.no_grad()
    def after_optimizer_step(self, model: GaussianModel, optimizer: torch.optim.Optimizer, step: int) -> None:
        cap_anisotropy(model, float(self.cfg.max_aniso))
        if len(model) == 0 or not self.cfg.mcmc.noise_lr:
            return
        lr = next(g["lr"] for g in optimizer.param_groups if g.get("name") == "means")
        o = model.opacities
        # ~1 for a nearly transparent Gaussian (o well under min_opacity), ~0 once it is opaque.
        gate = torch.sigmoid(-100.0 * (o - self.cfg.mcmc.min_opacity))
        R = quat_to_rotmat(model.quats)
        s2 = model.scales.square()
        eps = torch.randn(model.means.shape, device=o.device, dtype=o.dtype, generator=self._rng(o.device))
        # Σ·ε = R·diag(s²)·Rᵀ·ε
        step_ = (R @ (s2[:, :, None] * (R.transpose(-1, -2) @ eps[:, :, None]))).squeeze(-1)
        model.means.add_(step_ * (gate * (lr * self.cfg.mcmc.noise_lr))[:, None])

    def step(self, step: int, model: GaussianModel, optimizer: torch.optim.Optimizer, image_size: int) -> str:
        if not self.schedule.densify_at(step) or len(model) == 0:
            return ""
        moved = self._relocate(model, optimizer)
        added = self._grow(model, optimizer)
        return f"mcmc: {moved} relocated, +{added} added"

    # ---- the moves -------------------------------------------------------------------------------------------
    def _sample(self, weights: Tensor, k: int) -> Tensor:
        return torch.multinomial(weights.float().clamp_min(0) + 1e-12, k, replacement=True,
                                 generator=self._rng(weights.device))

    @torch.no_grad()
    def _split(self, model: GaussianModel, optimizer: torch.optim.Optimizer, sources: Tensor,
               targets: Optional[Tensor]) -> None:
        """Turn each Gaussian in ``sources`` (with repeats) into its share of copies: its own opacity and scale
        per eq. 9, then copied onto ``targets`` (dead slots) or appended (None). Adam's moments restart on all."""
        n = len(model)
        # bincount, but without its host reads of the sources' range (two syncs on CUDA); 1-D scatter_add_ is
        # deterministic.
        counts = torch.zeros(n, dtype=torch.long, device=sources.device).scatter_add_(0, sources,
                                                                                      torch.ones_like(sources))
        o_new, s_new = relocation(model.opacities[sources], model.scales[sources], counts[sources] + 1)
        o_new = o_new.clamp(self.cfg.mcmc.min_opacity, 1.0 - 1e-6)
        changed = {"opacity_logits": torch.logit(o_new)[:, None].to(model.opacity_logits.dtype),
                   "log_scales": s_new.clamp_min(1e-12).log().to(model.log_scales.dtype)}
        fresh = sources if targets is None else torch.cat([sources, targets])

        def edit(name: str, t: Tensor, is_state: bool) -> Tensor:
            t = t.clone()
            if is_state:
                t[fresh] = 0
            elif name in changed:
                t[sources] = changed[name].reshape(t[sources].shape)
            if targets is not None:
                t[targets] = t[sources]
                return t
            return torch.cat([t, torch.zeros_like(t[sources]) if is_state else t[sources]])

        edit_gaussians(model, optimizer, edit)

    def _relocate(self, model: GaussianModel, optimizer: torch.optim.Optimizer) -> int:
        o = model.opacities.reshape(-1)
        dead = o <= self.cfg.mcmc.min_opacity
        n_dead = int(dead.sum())  # the one host read of a relocation: the index sets follow from it
        if n_dead == 0 or n_dead == o.numel():
            return 0
        alive = mask_indices(~dead, o.numel() - n_dead)
        sources = alive[self._sample(o[alive], n_dead)]
        self._split(model, optimizer, sources, mask_indices(dead, n_dead))
        return n_dead

    def _grow(self, model: GaussianModel, optimizer: torch.optim.Optimizer) -> int:
        n = len(model)
        target = min(int(self.cfg.mcmc.cap_max), int(n * (1.0 + self.cfg.mcmc.growth)))
        k = max(0, target - n)
        if k == 0:
            return 0
        self._split(model, optimizer, self._sample(model.opacities.reshape(-1), k), None)
        return k

    # ---- checkpoint ----------------------------------------------------------------------------------------
    def state_dict(self) -> Dict[str, object]:
        return {"rng": self.generator.get_state() if self.generator is not None else self._saved_rng}

    def load_state_dict(self, state: Dict[str, object], device: torch.device) -> None:
        rng = state.get("rng")
        self._saved_rng = rng if isinstance(rng, Tensor) else None
        self.generator = None
