"""The strategy protocol: what the trainer may ask of a densification strategy, and the registry that
``density.kind`` picks a strategy from.

A strategy owns the density schedule (when Gaussians are added, moved, pruned or reset), the per-Gaussian
statistics it decides on, and the only edits of the Gaussians' parameters and Adam moments (through
:mod:`retinexgs.strategy.ops`). The trainer calls it at fixed points of a step and never reads the density
schedule itself. A new strategy is one module: a :class:`Strategy` subclass decorated with :func:`register`.
"""
from __future__ import annotations

from typing import Callable, ClassVar, Dict, Optional, Tuple, Type

import torch
from torch import Tensor

from retinexgs.config.schema import Density
from retinexgs.model.gaussians import PARAM_NAMES, GaussianModel
from retinexgs.model.schedule import Schedule
from retinexgs.render import RenderOutput

STRATEGIES: Dict[str, Type["Strategy"]] = {}


def register(name: str) -> Callable[[Type["Strategy"]], Type["Strategy"]]:
    """Class decorator: make a strategy selectable as ``density.kind: NAME``."""
    def add(cls: Type["Strategy"]) -> Type["Strategy"]:
        cls.name = name
        STRATEGIES[name] = cls
        return cls
    return add


class Strategy:
    """The base of every strategy: the hooks the trainer calls, each a no-op here.

    Order within a step: render, loss (+ :meth:`extra_loss`), backward, :meth:`after_backward` per view, the
    optimiser step, :meth:`after_optimizer_step`; then, on several ranks and where :meth:`will_edit`,
    :meth:`reduce`; then :meth:`step`, the scheduled edits."""

    name: ClassVar[str] = ""
    #: the Gaussian parameters (optimiser group names) this strategy edits; the trainer keeps them one group each
    edits: ClassVar[Tuple[str, ...]] = PARAM_NAMES

    def __init__(self, cfg: "Density", scene_extent: float, schedule: Schedule, seed: int = 0) -> None:
        self.cfg = cfg
        self.schedule = schedule
        self.extent = float(scene_extent)
        self.seed = int(seed)

    # ---- schedule ----------------------------------------------------------------------------------------
    def edits_at(self, step: int) -> bool:
        """Whether :meth:`step` may change the Gaussians at ``step`` (the trainer checks finiteness before, and
        times these steps apart from the steady ones)."""
        return False

    def will_edit(self, step: int) -> bool:
        """Whether the ranks must :meth:`reduce` this strategy's statistics before :meth:`step` at ``step``."""
        return False

    # ---- hooks ---------------------------------------------------------------------------------------------
    def extra_loss(self, model: GaussianModel) -> Optional[Tensor]:
        """A regulariser this strategy adds to every step's loss (weighted, differentiable), or None."""
        return None

    def after_backward(self, out: RenderOutput, width: int, height: int) -> None:
        """One view's render after its backward (its 2D means' gradients are set)."""

    def after_optimizer_step(self, model: GaussianModel, optimizer: torch.optim.Optimizer, step: int) -> None:
        """After every optimiser step (constraints or perturbations of the updated parameters)."""

    def step(self, step: int, model: GaussianModel, optimizer: torch.optim.Optimizer, image_size: int) -> str:
        """The scheduled edits at ``step``; a short description of what was done ('' if nothing)."""
        return ""

    def reduce(self, all_reduce_sum: Callable[[Tensor], Tensor], all_reduce_max: Callable[[Tensor], Tensor],
               n: int, image_size: int, device: torch.device) -> int:
        """Several ranks, where :meth:`will_edit`: make every rank's statistics alike; returns the largest image
        side of the batch."""
        return image_size

    # ---- checkpoint ----------------------------------------------------------------------------------------
    def state_dict(self) -> Dict[str, object]:
        return {}

    def load_state_dict(self, state: Dict[str, object], device: torch.device) -> None:
        pass


def build_strategy(cfg: "Density", scene_extent: float, schedule: Schedule, seed: int = 0) -> Strategy:
    """The strategy ``cfg.kind`` names (the loader has checked the name against :data:`STRATEGIES`)."""
    return STRATEGIES[cfg.kind](cfg, scene_extent, schedule, seed)
