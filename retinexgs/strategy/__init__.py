"""Densification strategies: the objects that decide when Gaussians are added, split, pruned or reset, and the one
place that edits the Gaussians' parameters together with their optimiser state (:mod:`retinexgs.strategy.ops`).

The trainer calls a strategy at four points of a step (gsplat's ``strategy/`` is the model):
``after_backward`` (gather per-Gaussian statistics from the render), ``after_optimizer_step`` (constraints on the
updated parameters), ``reduce`` (several ranks: the statistics summed so that every rank decides alike) and ``step``
(the scheduled edits). Its statistics travel in the checkpoint through ``state_dict``.
"""
from retinexgs.strategy.default import DefaultStrategy, noise_share
from retinexgs.strategy.ops import edit_gaussians, reset_opacity, resize_gaussians

__all__ = ["DefaultStrategy", "noise_share", "edit_gaussians", "resize_gaussians", "reset_opacity"]
