"""The divergence watch: a loss term or parameter that becomes NaN/inf stops the run naming it and the step, with
the last good checkpoint intact. Each step's loss terms and parameter norms are written, without a host sync, into
one row of a float32 buffer on the device: two ops a step (a multi-tensor norm and one stack), no elementwise
bookkeeping, since training is launch-bound and every kernel launch costs host time. The rows are read back in one
sync on logging, checkpoint and density steps only (a sync stalls the GPU queue) and searched on the host."""
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
    """Watches ``model``'s parameters and each step's loss terms; ``run``: the run folder its messages name;
    ``rows``: the steps a buffer first holds between two checks (it doubles when full, which is rare: the buffers
    are kept from one check to the next)."""

    def __init__(self, model: nn.Module, run: Path, step: int, rows: int = 64) -> None:
        self.model, self.run = model, Path(run)
        self._rows = max(1, int(rows))
        # per key (term names, parameter names): a float32 (rows, terms + parameters) buffer on the device and
        # its rows as views (made once per buffer, so writing a row dispatches no indexing op)
        self._buffers: Dict[tuple, Tuple[Tensor, Tuple[Tensor, ...]]] = {}
        self._pending: Dict[tuple, List[int]] = {}  # per key since the last check: [first step, rows filled]
        # the last step's (term names, its buffer row: the terms come first)
        self._last_terms: Optional[Tuple[Tuple[str, ...], Tensor]] = None
        self.checked_through = step  # every step up to this one is known finite

    def watch(self, terms: Dict[str, Tensor], step: int) -> None:
        """Write this step's loss terms and the norms of the parameters (as updated by the previous step; a NaN
        or inf anywhere in a tensor makes its norm non-finite) into the next row of the key's device buffer,
        without a host sync; the next :meth:`check` reads the rows back. Two ops (training is launch-bound):
        the multi-tensor norm of the parameters and one stack written straight into the row (a buffer that is
        full is first copied into one twice its size: rare)."""
        params = list(self.model.named_parameters())
        key = (tuple(terms), tuple(name for name, _ in params))
        entry = self._pending.get(key)
        if entry is None:
            entry = self._pending[key] = [step, 0]
        with torch.no_grad():  # no autograd graph, and no detach op per tensor
            norms = torch._foreach_norm([p for _, p in params])
            values = [t if t.dtype == torch.float32 else t.float() for t in terms.values()] + \
                [n if n.dtype == torch.float32 else n.float() for n in norms]
            row = self._row(key, entry[1], len(values), values[0].device)
            torch.stack(values, out=row)
        entry[1] += 1
        self._last_terms = (key[0], row)

    def _row(self, key: tuple, index: int, width: int, device: torch.device) -> Tensor:
        """Row ``index`` of the key's buffer, growing the buffer (twice the rows, the filled ones copied) when
        it is too small."""
        held = self._buffers.get(key)
        if held is not None and index < len(held[1]) and held[0].device == device:
            return held[1][index]
        buffer = torch.empty((max(self._rows, 2 * len(held[1]) if held is not None else 0, index + 1), width),
                             dtype=torch.float32, device=device)
        if held is not None and index > 0:
            buffer[:index].copy_(held[0][:index])
        self._buffers[key] = (buffer, buffer.unbind(0))
        return self._buffers[key][1][index]

    def check(self, step: int) -> Dict[str, float]:
        """Raise :class:`TrainingDiverged` naming the first loss term or parameter that became non-finite at any
        step since the last check (and the step); returns the last step's loss values. One host sync for all
        of it (training is launch-bound: syncs stall the GPU queue), so the trainer runs it on logging,
        checkpoint and density steps only, and before writing a checkpoint: the last checkpoint on disk is
        always a good one. The first non-finite row of each column of the buffers is found on the host. In
        between a non-finite parameter does no harm: the renderer culls Gaussians with non-finite geometry, and
        NaN/inf never turn finite again under Adam."""
        params = list(self.model.named_parameters())
        pending = [(key, first, rows) for key, (first, rows) in self._pending.items() if rows > 0]
        with torch.no_grad():
            norms = torch._foreach_norm([p for _, p in params])  # as updated by this step
            names, last = self._last_terms if self._last_terms is not None else ((), None)
            parts = ([last[:len(names)]] if last is not None else []) + \
                [self._buffers[key][0][:rows].reshape(-1) for key, _, rows in pending] + \
                [torch.stack(norms).float()]
            flat = torch.cat(parts).tolist()
        values = dict(zip(names, flat[:len(names)]))
        pos = len(names)
        # (step, 0 for a loss term / 1 for a parameter, position, name): a step's loss comes before its update;
        # within a step the log's order decides (the terms before their total).
        bad: List[Tuple[int, int, int, str]] = []
        for (term_names, param_names), first, rows in pending:
            width = len(term_names) + len(param_names)
            block = flat[pos:pos + rows * width]  # row-major: one row per watched step
            pos += len(block)
            if math.isfinite(sum(block)):  # float32 values: a sum of finite ones cannot overflow a double
                continue
            for i, name in enumerate(term_names + param_names):
                r = next((r for r in range(rows) if not math.isfinite(block[r * width + i])), None)
                if r is None:
                    continue
                if i < len(term_names):
                    bad.append((first + r, 0, i, name))
                else:  # seen non-finite before the update of step first + r: made so by the one before
                    bad.append((first + r - 1, 1, i - len(term_names), name))
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
        self._pending.clear()  # the buffers are kept: the next steps overwrite their rows
        self.checked_through = step
        return values
