"""``retinexgs train --view``: serve the model while it trains.

The trainer's steps and the viewer's frames take turns through a :class:`StepGate`: a frame never sees a
model half way through an optimiser step or a densification. With no browser connected nothing renders and
the trainer only takes an uncontended lock per step (well under 1 % of a step)."""
from __future__ import annotations

import contextlib
import threading
import time
from typing import Callable, Iterator

from retinexgs.viewer.frame import FrameRenderer
from retinexgs.viewer.server import RunViewer, snap_cameras


class StepGate:
    """A lock shared by training steps and frames; a step yields briefly when a frame is waiting, so that a
    busy trainer does not starve the viewer (Python locks are not fair)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._waiting = 0

    def wrap(self, step_fn: Callable) -> Callable:
        """``step_fn`` run under the gate."""
        def locked(*args, **kwargs):
            with self._lock:
                out = step_fn(*args, **kwargs)
            if self._waiting:
                time.sleep(0.001)  # let the waiting frame take the lock between two steps
            return out
        return locked

    @contextlib.contextmanager
    def frame(self) -> Iterator[None]:
        """Hold the gate for one frame."""
        self._waiting += 1
        try:
            with self._lock:
                yield
        finally:
            self._waiting -= 1


def start_live_viewer(trainer, scene, host: str, port: int, log: Callable[[str], None] = print) -> RunViewer:
    """Serve ``trainer``'s model (rendered at its current SH degree) at ``host:port``; its ``train_step`` is
    wrapped by the gate. Stop the returned viewer when training ends."""
    gate = StepGate()
    trainer.train_step = gate.wrap(trainer.train_step)
    renderer = FrameRenderer(trainer.model, trainer.cfg, lambda: trainer.active_degree(trainer.step), scene.train,
                             guard=gate.frame)
    on_gpu = trainer.model.gaussians.means.is_cuda
    viewer = RunViewer(renderer, snap_cameras(scene), host, port, default_scale=1.0 if on_gpu else 0.5, log=log)
    log(f"retinexgs train --view: the live scene at {viewer.url}{viewer.port_note()} (stops when training ends; "
        "afterwards use retinexgs view --run RUN)")
    return viewer


def live_viewer(host: str, port: int) -> Callable:
    """``train_run``'s ``on_trainer`` hook for ``train --view``: serve the trainer's model at ``host:port``; returns
    the function that stops the server when training ends."""
    return lambda trainer, scene, log: start_live_viewer(trainer, scene, host, port, log).stop
