"""The training schedule in absolute steps, resolved from the config for the run's length.

A schedule key (``density.start/stop/every/reset_opacity_every/last_event``, ``loss.enhance_from``,
``loss.prior_late_from``, ``model.sh_degree_every``) is either a decimal 0..1, a fraction of ``steps`` (the
default: the schedule follows the run length, ``--set steps=3000`` compresses it), or an integer, an absolute step
number. At ``steps: 10000`` the default fractions give exactly the steps the schedule was tuned with (densify
500..5000 every 100, opacity reset at 3000, enhancement losses from 3000, SH degree +1 every 1000).

No density event (densify, prune, opacity reset) happens after ``density.stop`` or ``density.last_event``: a
reset or a densification needs the rest of the run to recover from it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Union

from retinexgs.config.schema import Config
from retinexgs.errors import UserError

Point = Union[int, float]


def at_step(value: Point, steps: int) -> int:
    """A schedule point in steps: an integer as is, a decimal as that fraction of ``steps`` (rounded half up)."""
    if isinstance(value, float):
        return int(math.floor(value * steps + 0.5))
    return int(value)


def interval(value: Point, steps: int) -> int:
    """An interval in steps (at least 1); 0 stays 0 (= never)."""
    if value == 0:
        return 0
    return max(1, at_step(value, steps))


@dataclass(frozen=True)
class Schedule:
    """Every scheduled event of a run, in steps (1-based: ``step`` is the step just trained)."""

    steps: int
    densify_start: int      # densify at steps in (start, stop] that are multiples of densify_every
    densify_stop: int       # already capped at last_event
    densify_every: int
    reset_every: int        # opacity reset at multiples of this up to densify_stop; 0 = never
    enhance_from: int
    prior_late_from: int    # the priors' weights scaled by loss.prior_late_views from here on
    sh_degree: int
    sh_degree_every: int

    def densify_at(self, step: int) -> bool:
        return self.densify_start < step <= self.densify_stop and step % self.densify_every == 0

    def reset_at(self, step: int) -> bool:
        return bool(self.reset_every) and step % self.reset_every == 0 and step <= self.densify_stop

    def prune_large_at(self, step: int) -> bool:
        """Oversized Gaussians are pruned only after the first opacity reset (3DGS)."""
        return bool(self.reset_every) and step > self.reset_every

    def enhance_at(self, step: int) -> bool:
        return step >= self.enhance_from

    def prior_late_at(self, step: int) -> bool:
        """Whether the priors' weights are at their late scale at ``step``."""
        return step >= self.prior_late_from

    def sh_degree_at(self, step: int) -> int:
        return min(self.sh_degree, step // self.sh_degree_every)

    def steps_unchanged(self, step: int) -> int:
        """How many steps from ``step`` on (itself included) render the Gaussians and the SH degree of ``step``:
        up to the next densification (after its step's update, so that step still counts), the next SH degree
        increase (not counted) or the end of the run. What a CUDA graph of them would be replayed for."""
        end = self.steps
        if self.densify_stop > self.densify_start and self.densify_every > 0:
            nxt = max(-(-step // self.densify_every), self.densify_start // self.densify_every + 1) * self.densify_every
            if nxt <= self.densify_stop:
                end = min(end, nxt)
        if self.sh_degree_at(step) < self.sh_degree:
            end = min(end, (step // self.sh_degree_every + 1) * self.sh_degree_every - 1)
        return max(1, end - step + 1)

    def resets(self) -> List[int]:
        if not self.reset_every:
            return []
        return list(range(self.reset_every, self.densify_stop + 1, self.reset_every))

    def describe(self) -> str:
        """One line for the log."""
        dens = (f"densify steps {self.densify_start + 1}..{self.densify_stop} every {self.densify_every}"
                if self.densify_stop > self.densify_start else "no densification")
        resets = self.resets()
        enhance = (f"from step {self.enhance_from}" if self.enhance_from <= self.steps else
                   f"from step {self.enhance_from}, after the last step (not in this run)")
        return (f"schedule for {self.steps} steps: {dens}; opacity reset at "
                f"{', '.join(map(str, resets)) if resets else 'no step'}; enhancement losses {enhance}; "
                f"SH degree +1 every {self.sh_degree_every} steps")


def build_schedule(cfg: Config) -> Schedule:
    """The schedule of ``cfg`` (validated by the schema) for its ``steps``."""
    steps = int(cfg.steps)
    d = cfg.density
    start = at_step(d.start, steps)
    stop = min(at_step(d.stop, steps), at_step(d.last_event, steps))
    return Schedule(steps=steps, densify_start=start, densify_stop=stop, densify_every=interval(d.every, steps),
                    reset_every=interval(d.reset_opacity_every, steps),
                    enhance_from=at_step(cfg.loss.enhance_from, steps),
                    prior_late_from=at_step(cfg.loss.prior_late_from, steps),
                    sh_degree=int(cfg.model.sh_degree),
                    sh_degree_every=max(1, interval(cfg.model.sh_degree_every, steps)))


def check_schedule(cfg: Config) -> Schedule:
    """Refuse a schedule that cannot fit the run: a densification window that ends before it starts."""
    steps = int(cfg.steps)
    d = cfg.density
    start, stop = at_step(d.start, steps), at_step(d.stop, steps)
    if start < steps and stop <= start:
        raise UserError(f"density.stop={d.stop!r} (step {stop}) must come after density.start={d.start!r} "
                        f"(step {start}) in a run of {steps} steps; decimals are fractions of steps, integers "
                        "are steps")
    return build_schedule(cfg)
