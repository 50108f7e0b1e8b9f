"""Low-light / normal-light pairing of LOM-style folders (``low/`` inputs, ``high/`` references).

Files pair by name; a camera raw input (``low/NAME.dng``, docs/raw.md "Raw scenes") pairs by stem with the
normal-light photo of that stem (``high/NAME.png`` or ``.jpg``), the truth a raw capture is scored against."""
from __future__ import annotations

from pathlib import Path

from retinexgs.data.images import is_raw_file, list_images
from retinexgs.errors import UserError


def _key(p: Path, by_stem: bool) -> str:
    return p.stem if by_stem else p.name


def check_same_files(low: Path, high: Path) -> None:
    """Raise UserError naming the differing files when ``low`` and ``high`` hold different image names (by stem
    when ``low`` holds camera raw files)."""
    lows = list_images(low)
    by_stem = any(is_raw_file(p) for p in lows)
    a = {_key(p, by_stem) for p in lows}
    b = {_key(p, by_stem) for p in list_images(high)}
    if a == b:
        return
    only_low, only_high = sorted(a - b), sorted(b - a)

    def show(names):
        return ", ".join(names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "") or "none"

    what = "image files (raw files in low/ pair by name without extension)" if by_stem else "image files"
    raise UserError(f"{low} and {high} must hold the same {what}: only in {low.name}/: "
                    f"{show(only_low)}; only in {high.name}/: {show(only_high)}")


def high_partner(low_file: Path, high: Path) -> Path:
    """The file in ``high`` paired with ``low_file``: the same name, or for a camera raw input the one
    non-raw photo of the same stem (``high/NAME.dng`` when none; the caller reports it missing). UserError
    when several photos share the stem (which one is the truth would be a guess)."""
    same = Path(high) / Path(low_file).name
    if not is_raw_file(low_file) or same.is_file():
        return same
    stem = Path(low_file).stem
    found = [p for p in list_images(high) if p.stem == stem and not is_raw_file(p)]
    if len(found) > 1:
        raise UserError(f"{high} holds {len(found)} photos named {stem} ({', '.join(p.name for p in found)}) for the "
                        f"raw input {low_file}; keep one normal-light photo per view")
    return found[0] if found else same
