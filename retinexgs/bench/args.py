"""Argument types the benchmark command lines share."""
from __future__ import annotations

import argparse
from typing import Callable, Tuple


def image_size(form: str, example: str, minimum: int = 8) -> Callable[[str], Tuple[int, int]]:
    """An argparse ``type`` for an image size written as two integers joined by 'x', returned in the order written
    (``form`` names it for the message, e.g. "HxW" or "WxH"; ``example`` shows one); anything else, or a side
    below ``minimum``, is argparse's one-line error."""
    def parse(text: str) -> Tuple[int, int]:
        try:
            a, b = (int(v) for v in text.lower().split("x"))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {form}, e.g. {example}, got {text!r}") from None
        if a < minimum or b < minimum:
            raise argparse.ArgumentTypeError(f"a size of at least {minimum}x{minimum} is needed, got {text!r}")
        return a, b
    return parse
