"""Which training views saw each Gaussian, and the prune of those only one view constrains (issue 64 item 3,
``density.prune_single_view``).

On a noisy night capture a Gaussian that one training view alone sees can fit that view's noise (colour speckle in
the test views), since no second view contradicts it. A Gaussian is *seen* by a view where that view's render gave
it a screen footprint (``RenderOutput.visible``, the test the default strategy counts views with). Per Gaussian
this module keeps, on the device and without a host read in the steady step:

- ``last_view``: the last training view that saw it (-1: none yet);
- ``multi``: whether two distinct views saw it. For view v: ``multi |= seen & (last_view >= 0) & (last_view != v)``,
  then ``last_view = v`` where seen. Exact: a sequence of views with two distinct entries has a consecutive pair that
  differs;
- ``hits``: how many times it was seen (``fresh``: the hits of this rank since the ranks last agreed).

The evidence rule: a Gaussian seen only by one view is pruned once it has ``min_hits`` hits, the fewest for which a
Gaussian that two views saw equally often would land every hit on one view with probability 2 * 0.5^h below
:data:`FALSE_PRUNE` (1 %: h >= 8). The statistics are never reset, only carried through every index edit (a clone,
a split child or an MCMC copy inherits the statistics of the Gaussian it copies: it covers the same place, so the
views that saw that one are the evidence about it, and starting unseen would let a floater escape the rule by
being densified). Because the evidence only grows, the events "all of the first h hits on one view" are nested, so
deciding at every density step prunes a two-view Gaussian with probability at most the first decision's, < 1 %.
The decisions: at every density step (the default: with the densification, no clone or split of a Gaussian about to
go; MCMC: such a Gaussian is relocated like a dead one) and once more at ``density.last_event`` where that comes after
the densification window (Gaussians the window's last steps made get their evidence, and the run has the remaining
steps to recover).
"""
from __future__ import annotations

import math
from typing import Callable, Dict, Optional

import torch
from torch import Tensor

from retinexgs.config.schema import Density
from retinexgs.model.schedule import Schedule, at_step

#: The chance, at most, that a Gaussian two training views saw equally often is pruned as seen by one. 1 %: a wrong
#: prune is cheap (densification regrows what the views need while its window is open), a kept floater is not.
FALSE_PRUNE = 0.01
KEYS = ("last_view", "multi", "hits", "fresh")  # the checkpoint's names, with the prefix STATE_PREFIX
STATE_PREFIX = "views_"


def min_hits(false_prune: float = FALSE_PRUNE) -> int:
    """The fewest hits h for which 2 * 0.5^h < ``false_prune`` (8 for 1 %)."""
    return int(math.floor(math.log2(2.0 / false_prune))) + 1


class ViewsSeen:
    """The per-Gaussian view statistics of one strategy and their prune decision (see the module). ``enabled``
    False (``density.prune_single_view`` off): every method is a no-op, nothing is allocated or saved."""

    def __init__(self, cfg: Density, schedule: Schedule) -> None:
        self.enabled = bool(cfg.prune_single_view)
        self.min_hits = min_hits()
        self.schedule = schedule
        last = at_step(cfg.last_event, schedule.steps)
        # The final decision: at last_event where it comes after the densification window (within the run).
        self.final_step = last if schedule.densify_stop < last <= schedule.steps else None
        self.last_view: Optional[Tensor] = None  # [N] int64
        self.multi: Optional[Tensor] = None      # [N] bool
        self.hits: Optional[Tensor] = None       # [N] int64, agreed over the ranks at the last decision
        self.fresh: Optional[Tensor] = None      # [N] int64, this rank's hits since then

    # ---- schedule ------------------------------------------------------------------------------------------
    def decides_at(self, step: int) -> bool:
        """Whether ``step`` decides (a density step or the final decision), where enabled."""
        return self.enabled and (self.schedule.densify_at(step) or step == self.final_step)

    def final_at(self, step: int) -> bool:
        """Whether ``step`` is the final decision (no densification happens there)."""
        return self.enabled and step == self.final_step and not self.schedule.densify_at(step)

    # ---- statistics ------------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return 0 if self.last_view is None else int(self.last_view.shape[0])

    def reset(self, n: int, device: torch.device) -> None:
        """``n`` Gaussians none has seen."""
        self.last_view = torch.full((n,), -1, dtype=torch.long, device=device)
        self.multi = torch.zeros(n, dtype=torch.bool, device=device)
        self.hits = torch.zeros(n, dtype=torch.long, device=device)
        self.fresh = torch.zeros(n, dtype=torch.long, device=device)

    def ensure(self, n: int, device: torch.device) -> None:
        """Statistics for ``n`` Gaussians. A count that differs from the statistics' (a rank resized to rank 0's
        Gaussians by the broadcast, a checkpoint written without them) restarts them unseen: evidence lost, never
        misattributed."""
        if self.last_view is None or self.last_view.shape[0] != n:
            self.reset(n, device)

    @torch.no_grad()
    def add(self, visible: Tensor, view: int) -> None:
        """Training view ``view`` (its index in the training set; < 0: unknown, not counted) saw the Gaussians
        where ``visible`` [N] bool. Device ops only, no host read."""
        if not self.enabled or view < 0:
            return
        self.ensure(visible.shape[0], visible.device)
        self.multi |= visible & (self.last_view >= 0) & (self.last_view != view)
        self.last_view.masked_fill_(visible, view)
        self.fresh += visible

    def fold(self) -> None:
        """One rank: its fresh hits join the agreed ones (several ranks: :meth:`reduce` does this)."""
        if self.hits is not None:
            self.hits += self.fresh
            self.fresh.zero_()

    def reduce(self, all_reduce_sum: Callable[[Tensor], Tensor], all_reduce_max: Callable[[Tensor], Tensor],
               n: int, device: torch.device) -> None:
        """Several ranks, before a decision: make every rank's statistics the union of all ranks' views. hits:
        the agreed count (alike on every rank; max) plus the sum of the fresh ones; multi: OR (max); last_view:
        the largest; and two ranks whose lone views differ make the Gaussian multi-view (the smallest seen view,
        as the max of its negation, against the largest)."""
        if not self.enabled or n == 0:
            return
        self.ensure(n, device)
        seen = self.last_view >= 0
        big = torch.iinfo(torch.long).max
        maxima = all_reduce_max(torch.cat([self.multi.long(), self.last_view,
                                           torch.where(seen, -self.last_view, -big), self.hits]))
        fresh = all_reduce_sum(self.fresh.clone())
        multi, hi, neg_lo, hits = maxima.split(n)
        self.multi = multi.bool() | ((hi >= 0) & (-neg_lo != hi))
        self.last_view = hi.clone()
        self.hits = hits + fresh
        self.fresh = torch.zeros_like(self.hits)

    def single_view(self, n: int, device: torch.device) -> Tensor:
        """[n] bool: seen by one view only, with at least ``min_hits`` hits (after :meth:`fold`): the Gaussians
        the rule prunes. All False where disabled."""
        if not self.enabled:
            return torch.zeros(n, dtype=torch.bool, device=device)
        self.ensure(n, device)
        self.fold()
        return ~self.multi & (self.hits >= self.min_hits)

    def gather(self, rows: Tensor) -> None:
        """Follow an index edit: new Gaussian i takes the statistics of old Gaussian ``rows[i]`` (called by
        :func:`retinexgs.strategy.ops.edit_gaussians`)."""
        if self.last_view is None:
            return
        rows = rows.to(self.last_view.device)
        for key in KEYS:
            setattr(self, key, getattr(self, key).index_select(0, rows))

    # ---- checkpoint ----------------------------------------------------------------------------------------
    def state_dict(self) -> Dict[str, Tensor]:
        """The statistics (this rank's fresh hits folded in), under ``views_*``; {} where disabled or empty."""
        if not self.enabled or self.last_view is None:
            return {}
        return {STATE_PREFIX + "last_view": self.last_view, STATE_PREFIX + "multi": self.multi,
                STATE_PREFIX + "hits": self.hits + self.fresh}

    def load_state_dict(self, state: Dict[str, object], device: torch.device) -> None:
        """Restore :meth:`state_dict`; a state without them (an older checkpoint, or one written with the key
        off) starts every Gaussian unseen."""
        last = state.get(STATE_PREFIX + "last_view")
        if not isinstance(last, Tensor):
            self.last_view = self.multi = self.hits = self.fresh = None
            return
        self.last_view = last.to(device, torch.long)
        self.multi = state[STATE_PREFIX + "multi"].to(device, torch.bool)
        self.hits = state[STATE_PREFIX + "hits"].to(device, torch.long)
        self.fresh = torch.zeros_like(self.hits)
