"""Ctrl-C and SIGTERM during training: finish the step, write a checkpoint, then stop (issue 50).

A signal that lands mid-step would leave parameters and Adam moments half-updated, so the handler only notes it;
the loop looks after every step, saves, and raises as the signal would have. A second signal stops at once (the
user insists, or the save hangs), through the handler that was there before.
"""
from __future__ import annotations

import signal
import threading
from typing import Optional

from retinexgs.errors import Terminated


class DeferredStop:
    """Context manager: while active (in the main thread), SIGINT and SIGTERM set :attr:`signum` instead of
    raising; :meth:`raise_now` raises what the signal would have (KeyboardInterrupt, or Terminated for SIGTERM)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.signum: Optional[int] = None
        self._previous: dict = {}

    def _note(self, signum, frame) -> None:
        if self.signum is not None:  # the second signal: stop now, as before
            self._restore()
            self.raise_now(signum)
        self.signum = signum

    def __enter__(self) -> "DeferredStop":
        if threading.current_thread() is threading.main_thread():
            for s in self.SIGNALS:
                self._previous[s] = signal.signal(s, self._note)
        return self

    def _restore(self) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        self._previous = {}

    def __exit__(self, *exc) -> None:
        self._restore()

    @property
    def requested(self) -> bool:
        return self.signum is not None

    def raise_now(self, signum: Optional[int] = None) -> None:
        """Raise the exception the noted signal stands for."""
        if (signum if signum is not None else self.signum) == signal.SIGTERM:
            raise Terminated()
        raise KeyboardInterrupt()
