"""2D Retinex decomposition: a low-light photo S -> reflectance R and illumination L (S ≈ R∘L).

Methods: ``lr3m`` (default; low-rank regularised, denoises R) and ``lime`` (fast baseline).

    >>> from retinexgs.retinex import decompose, get_decomposer
    >>> r, l = decompose(image)                  # image [H,W,3] float in [0,1]
    >>> d = get_decomposer("lime", gamma=0.8); r, l = d(image)

Per-scene results are cached on disk by :func:`retinexgs.retinex.cache.load_or_compute`, re-exported here.
Importing this package imports torch and the cache module; the decomposers' solvers are built on first use.
"""
from __future__ import annotations

from typing import Any, Tuple

from retinexgs.retinex.base import (Decomposer, available_methods, cache_key, enhance_for_viewing,
                                    get_decomposer, validate_image)
from retinexgs.retinex.cache import load_or_compute

__all__ = ["decompose", "get_decomposer", "available_methods", "cache_key", "enhance_for_viewing",
           "validate_image", "Decomposer", "load_or_compute"]


def decompose(image: Any, method: str = "lr3m", **params: Any) -> Tuple[Any, Any]:
    """Decompose ``image`` ([H,W,3] or [B,H,W,3] float tensor in [0,1]) into (R, L) with ``method``.

    R has 3 channels in [0,1]; L has 1 channel in the scale of the image. Runs on the image's device.
    """
    return get_decomposer(method, **params).decompose(image)
