"""A scene as its files declare it: what readers (transforms JSON, COLMAP, SfM) hand to
:func:`retinexgs.data.load_scene` before images are processed and the world is normalised: views with their
original (possibly distorted) cameras and world-frame poses. (Not "raw": that word is camera RAW's,
:mod:`retinexgs.data.camera_raw`.)"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

import numpy as np

from retinexgs.data.camera import Intrinsics


@dataclass
class DeclaredView:
    """A view as its files declare it: source image, camera as declared, camera-to-world (OpenCV axes, world frame)."""

    name: str
    image: Path
    camera: Intrinsics
    c2w: np.ndarray
    paired: Optional[Path] = None


@dataclass
class DeclaredScene:
    """A reader's output: views per split, and world-frame points (None when the input has none)."""

    root: Path
    reader: str
    train: List[DeclaredView]
    test: List[DeclaredView] = field(default_factory=list)
    val: List[DeclaredView] = field(default_factory=list)
    points: Optional[np.ndarray] = None  # [P,3] float64
    colors: Optional[np.ndarray] = None  # [P,3] uint8
    points_source: str = "colmap"
