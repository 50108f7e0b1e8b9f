"""Low-light / normal-light pairing of LOM-style folders (``low/`` inputs, ``high/`` references)."""
from __future__ import annotations

from pathlib import Path

from retinexgs.data.images import list_images
from retinexgs.errors import UserError


def check_same_files(low: Path, high: Path) -> None:
    """Raise UserError naming the differing files when ``low`` and ``high`` hold different image names."""
    a = {p.name for p in list_images(low)}
    b = {p.name for p in list_images(high)}
    if a == b:
        return
    only_low, only_high = sorted(a - b), sorted(b - a)

    def show(names):
        return ", ".join(names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "") or "none"

    raise UserError(f"{low} and {high} must hold the same image files: only in {low.name}/: "
                    f"{show(only_low)}; only in {high.name}/: {show(only_high)}")
