"""Densification strategies: the objects that decide when Gaussians are added, moved, pruned or reset, and the one
place that edits the Gaussians' parameters together with their optimiser state (:mod:`retinexgs.strategy.ops`).

The protocol (:class:`retinexgs.strategy.base.Strategy`, gsplat's ``strategy/`` is the model): the trainer calls
``extra_loss`` (a regulariser added to the step's loss), ``after_backward`` (per-Gaussian statistics from the
render), ``after_optimizer_step`` (constraints or perturbations of the updated parameters), ``reduce`` (several
ranks: the statistics summed so that every rank decides alike) and ``step`` (the scheduled edits); ``edits_at``
answers for the density schedule, which the strategy owns. ``density.kind`` picks the class from
:data:`STRATEGIES`: ``default`` (3DGS's adaptive density control) or ``mcmc`` (3DGS as MCMC). Statistics travel in
the checkpoint through ``state_dict``.
"""
from retinexgs.strategy.base import STRATEGIES, Strategy, build_strategy, register
from retinexgs.strategy.default import DefaultStrategy
from retinexgs.strategy.mcmc import MCMCStrategy, relocation
from retinexgs.strategy.ops import edit_gaussians, reset_opacity, resize_gaussians

__all__ = ["STRATEGIES", "Strategy", "build_strategy", "register", "DefaultStrategy", "MCMCStrategy",
           "relocation", "edit_gaussians", "resize_gaussians", "reset_opacity"]
