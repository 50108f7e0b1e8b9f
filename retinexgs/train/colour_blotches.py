"""How blotchy a set of photos' colour noise is: what ``decomposer.denoise: auto`` reads on photos (issue 64;
:meth:`retinexgs.data.capture.PhotoCapture.auto_denoise` holds the rule, :data:`retinexgs.data.capture.PHOTO_BLOTCH_MIN`
its threshold and why).

A photo is brightened as the enhancement's auto exposure does (the night is then seen at a working level), and the
noise σ of its two opponent chroma components is read on 4×4-pixel averages (Immerkær's estimate,
:func:`retinexgs.retinex.denoise.measured_sigma`). White pixel noise falls 4× in such averages, and the Gaussians'
footprints and the views' average remove it; colour noise correlated over several pixels (a night camera JPEG's:
demosaicing and the colour matrix act before the codec) stays, and trains into colour blotches
(experiments/notes/2026-11-29-photo-chroma-blotch.md).
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from retinexgs.retinex.denoise import YCC, measured_sigma
from retinexgs.train.sfm_preview import PROBE_PHOTOS, probed

# The opponent chroma the denoiser filters, (R − B)/√2 and (R − 2G + B)/√6 (orthonormal: white noise keeps its σ).
_CHROMA = YCC[1:].numpy().astype(np.float32)
BLOTCH_SCALE = 4  # pixels a side of the averages the colour blotches are read on
# A view whose shorter side has fewer pixels than this is not read (blotches 0): its 4×4 averages are too few and too
# coarse for the scene's texture to be told from noise (texture's share of the estimate grows as a photo shrinks:
# experiments/notes/2026-11-29-adam-one-launch.md §5; the ladder's JPEGs are 360-427 px, the demo's views 72).
BLOTCH_MIN_SIDE = 256


def bright_chroma_blotch(rgb: np.ndarray, downscale: float = 1.0) -> float:
    """The noise σ of the colour of the 4×4-pixel averages of ``rgb`` (a brightened photo, uint8 [H,W,3] or floats in
    [0, 1]) as training sees it ``downscale``× smaller: Immerkær's estimate on the averages of each opponent chroma
    component, their mean. White pixel noise falls 4× in such averages; colour noise correlated over several pixels
    (a night camera JPEG's blotches: the demosaicing and the colour matrix before the codec) stays. 0 for a view
    smaller than :data:`BLOTCH_MIN_SIDE` on its shorter side."""
    d = max(1, int(round(downscale)))
    if min(rgb.shape[:2]) < BLOTCH_MIN_SIDE * d:
        return 0.0
    x = rgb.astype(np.float32) / (255.0 if rgb.dtype == np.uint8 else 1.0)
    chroma = np.einsum("ij,hwj->ihw", _CHROMA, x)
    scale = BLOTCH_SCALE * d  # 4×4 pixels of the view d× smaller: 4d×4d of the file's
    # measured_sigma reports a pixel's σ (the averages' times the scale): divided back to the averages' own
    return float(np.mean([measured_sigma(torch.from_numpy(c).double(), scale) for c in chroma])) / scale


def previews_chroma_blotch(paths: Sequence[Path], downscale: float = 1.0, photos: int = PROBE_PHOTOS) -> float:
    """The median of :func:`bright_chroma_blotch` (at ``data.downscale``) over the brightened previews (the
    enhancement's auto exposure) of up to ``photos`` of the photos ``paths``, spread evenly: what
    ``decomposer.denoise: auto`` reads on photos (:meth:`retinexgs.data.capture.PhotoCapture.auto_denoise`)."""
    from retinexgs.data.enhance import auto_exposure
    from retinexgs.data.images import read_image

    chosen = probed(paths, photos)
    if not chosen:
        return 0.0
    return float(np.median([bright_chroma_blotch(auto_exposure(read_image(p)), downscale) for p in chosen]))
