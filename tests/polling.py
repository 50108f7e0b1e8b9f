"""Bounded polling for the tests that talk to a live server or browser."""
import time
from typing import Callable


def wait_until(cond: Callable[[], bool], seconds: float = 30.0, step: float = 0.05) -> bool:
    """True as soon as ``cond()`` is, False after ``seconds`` (the tests assert on it: nothing hangs)."""
    end = time.time() + seconds
    while time.time() < end:
        if cond():
            return True
        time.sleep(step)
    return False
