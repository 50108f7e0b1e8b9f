"""The divergence watch: a loss term or parameter that becomes NaN/inf stops the run naming it and the step, with
the last good checkpoint intact. Recorded on the device every step without a host sync, read back on logging,
checkpoint and density steps only (training is launch-bound: a sync stalls the GPU queue)."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import torch
from torch import Tensor, nn

from retinexgs.errors import UserError


class TrainingDiverged(UserError):
    """A loss term or parameter became non-finite; the last good checkpoint is left intact."""


class DivergenceWatch:
    """Watches ``model``'s parameters and each step's loss terms; ``run``: the run folder its messages name."""

    def __init__(self, model: nn.Module, run: Path, step: int) -> None:
        self.model, self.run = model, Path(run)
        # per (term names, parameter names): [leading finite steps on the device, first step, steps]
        self._pending: Dict[tuple, list] = {}
        self._last_terms: Optional[Tuple[Tuple[str, ...], Tensor]] = None  # the last step's (names, values)
        self.checked_through = step  # every step up to this one is known finite

    def watch(self, terms: Dict[str, Tensor], step: int) -> None:
        """Record, on the device and without a host sync, for how many leading steps since the last check every
        loss term of this step and every parameter (as updated by the previous step) stayed finite; the next
        :meth:`check` reads it back. A few kernels: the multi-tensor norm of the parameters (a NaN or
        inf anywhere in a tensor makes its norm non-finite), one stack, five elementwise ops."""
        params = list(self.model.named_parameters())
        key = (tuple(terms), tuple(name for name, _ in params))
        norms = torch._foreach_norm([p.detach() for _, p in params])
        vec = torch.stack([t.detach().float() for t in terms.values()] + [n.float() for n in norms])
        entry = self._pending.get(key)
        if entry is None:  # [leading finite steps per value, first step, steps]
            entry = self._pending[key] = [torch.zeros(vec.shape[0], dtype=torch.int32, device=vec.device), step, 0]
        prefix = entry[0]
        # x - x is 0 exactly when x is finite (2 kernels; torch.isfinite is 4 of them).
        prefix.add_(vec.sub(vec).eq(0).logical_and_(prefix.eq(entry[2])))
        entry[2] += 1
        self._last_terms = (key[0], vec[:len(terms)])

    def check(self, step: int) -> Dict[str, float]:
        """Raise :class:`TrainingDiverged` naming the first loss term or parameter that became non-finite at any
        step since the last check (and the step); returns the last step's loss values. One host sync for all
        of it (training is launch-bound: syncs stall the GPU queue), so the trainer runs it on logging,
        checkpoint and density steps only, and before writing a checkpoint: the last checkpoint on disk is
        always a good one. In between a non-finite parameter does no harm: the renderer culls Gaussians with
        non-finite geometry, and NaN/inf never turn finite again under Adam."""
        params = list(self.model.named_parameters())
        norms = torch._foreach_norm([p.detach() for _, p in params])  # as updated by this step
        names, last = self._last_terms if self._last_terms is not None else ((), None)
        pending = list(self._pending.items())
        parts = ([last.float()] if last is not None else []) + [e[0].float() for _, e in pending] + \
            [torch.stack(norms).float()]
        flat = torch.cat(parts).tolist()
        values = dict(zip(names, flat[:len(names)]))
        pos = len(names)
        # (step, 0 for a loss term / 1 for a parameter, position, name): a step's loss comes before its update;
        # within a step the log's order decides (the terms before their total).
        bad: List[Tuple[int, int, int, str]] = []
        for (term_names, param_names), (_, first, steps) in pending:
            prefix = flat[pos:pos + len(term_names) + len(param_names)]
            pos += len(prefix)
            for i, (name, ok) in enumerate(zip(term_names, prefix)):
                if ok < steps:
                    bad.append((first + int(ok), 0, i, name))
            for i, (name, ok) in enumerate(zip(param_names, prefix[len(term_names):])):
                if ok < steps:  # seen non-finite before the update of step first + ok: made so by the one before
                    bad.append((first + int(ok) - 1, 1, i, name))
        for i, ((name, _), norm) in enumerate(zip(params, flat[pos:])):
            if not math.isfinite(norm):
                bad.append((step, 1, i, name))
        if bad:
            at, kind, _, name = min(bad)
            where = f"at step {at}; the last good checkpoint in {self.run / 'checkpoints'} is intact"
            if kind == 0:
                value = values.get(name) if at == step else None
                became = value if value is not None and not math.isfinite(value) else "non-finite"
                raise TrainingDiverged(f"loss term {name} became {became} {where} (lower the learning rates or "
                                       "resume from it)")
            label = (f"Gaussian parameter {name[len('gaussians.'):]}" if name.startswith("gaussians.")
                     else f"network parameter {name}")
            raise TrainingDiverged(f"{label} became non-finite {where}")
        self._pending.clear()
        self.checked_through = step
        return values
