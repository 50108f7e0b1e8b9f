"""The decomposer interface, input validation, the method registry and the cache key.

A decomposer maps a low-light photo ``S`` ([H,W,3] float in [0,1]) to a reflectance ``R`` ([H,W,3], in
[0,1]) and an illumination ``L`` ([H,W,1], in the scale of ``S``) with ``S ≈ R∘L``. Every decomposer is
deterministic: the same input on the same device gives bit-identical outputs.
"""
from __future__ import annotations

import dataclasses
import hashlib
import importlib
import json
from typing import Any, Callable, Dict, Tuple

import torch

# Bump when an algorithm changes its output for the same parameters: it is part of every cache key,
# so caches written by older code are recomputed instead of trusted.
ALGORITHM_VERSION = 1

# Values outside [0, 1] by more than this are an error; smaller excursions (resampling, float16) are clipped.
RANGE_TOLERANCE = 1e-3

# method name -> "module:Class" (imported on first use so ``import retinexgs.retinex`` stays light).
_REGISTRY: Dict[str, str] = {
    "lr3m": "retinexgs.retinex.lr3m:LR3M",
    "lime": "retinexgs.retinex.lime:LIME",
}


def available_methods() -> Tuple[str, ...]:
    """Names accepted by :func:`get_decomposer`, default first."""
    return tuple(_REGISTRY)


def validate_image(image: Any) -> torch.Tensor:
    """Check a photo for decomposition and return it as float32 [B,H,W,3] clipped to [0,1].

    Accepts [H,W,3] or [B,H,W,3] floating tensors. Raises ``TypeError`` for a non-tensor or a
    non-floating dtype and ``ValueError`` for a wrong shape, too small a size, NaN/inf, values outside
    [0,1] by more than ``RANGE_TOLERANCE``, or an all-zero image.
    """
    if not isinstance(image, torch.Tensor):
        raise TypeError(f"image must be a torch.Tensor [H,W,3] with values in [0,1], got {type(image).__name__}")
    if not image.is_floating_point():
        raise TypeError(
            f"image must be a floating-point tensor with values in [0,1], got dtype {image.dtype} "
            "(convert 8-bit images with image.float() / 255)")
    if image.dim() not in (3, 4) or image.shape[-1] != 3:
        raise ValueError(f"image must have shape [H,W,3] or [B,H,W,3] (3 colour channels, channels last), "
                         f"got shape {tuple(image.shape)}")
    x = image.unsqueeze(0) if image.dim() == 3 else image
    if x.shape[0] == 0 or x.shape[1] < 8 or x.shape[2] < 8:
        raise ValueError(f"image must be at least 8x8 pixels, got shape {tuple(image.shape)}")
    x = x.float()
    if not torch.isfinite(x).all():
        raise ValueError("image contains NaN or infinite values")
    lo, hi = float(x.min()), float(x.max())
    if lo < -RANGE_TOLERANCE or hi > 1.0 + RANGE_TOLERANCE:
        raise ValueError(f"image values must lie in [0,1], found range [{lo:.4g}, {hi:.4g}] "
                         "(8-bit data must be divided by 255)")
    peak = x.flatten(1).amax(dim=1)
    if bool((peak <= 0).any()):
        bad = int(torch.nonzero(peak <= 0)[0])
        raise ValueError(f"image {bad} of the batch is all zero (black): there is nothing to decompose")
    return x.clamp(0.0, 1.0).contiguous()


def params_to_dict(params: Any) -> Dict[str, Any]:
    """A JSON-friendly dict of a parameter dataclass (or of a plain mapping)."""
    if dataclasses.is_dataclass(params):
        return dataclasses.asdict(params)
    return dict(params or {})


def cache_key(method: str, params: Any) -> str:
    """Stable short hash of method + parameters + algorithm version (hex, 12 characters).

    Floats are written with ``repr`` by ``json``, so the key only changes when a value really changes.
    Fields a params class lists in ``KEY_OMIT_AT_DEFAULT`` are left out at those values (fields added
    later: the caches written before them keep their key).
    """
    values = params_to_dict(params)
    for name, default in getattr(type(params), "KEY_OMIT_AT_DEFAULT", {}).items():  # added after caches existed
        if name in values and values[name] == default:
            del values[name]
    blob = json.dumps({"method": method, "params": values, "version": ALGORITHM_VERSION},
                      sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()[:12]


class Decomposer:
    """Base class: subclasses set ``name`` and ``Params`` and implement :meth:`_decompose_batch`."""

    name: str = ""
    Params: type = object

    def __init__(self, params: Any = None, **overrides: Any) -> None:
        if params is None:
            params = self.Params()
        elif not isinstance(params, self.Params):
            raise TypeError(f"{self.name} expects {self.Params.__name__}, got {type(params).__name__}")
        if overrides:
            params = dataclasses.replace(params, **overrides)
        self.params = params

    def cache_key(self) -> str:
        """Hash of this method and its parameters (see :func:`cache_key`)."""
        return cache_key(self.name, self.params)

    @torch.no_grad()
    def decompose(self, image: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """Split ``image`` ([H,W,3] or [B,H,W,3], float in [0,1]) into (R, L).

        Returns R with the input's leading shape and 3 channels, L with 1 channel, both float32 on the
        input's device.
        """
        single = isinstance(image, torch.Tensor) and image.dim() == 3
        x = validate_image(image)
        r, l = self._decompose_batch(x.permute(0, 3, 1, 2).contiguous())
        r = r.permute(0, 2, 3, 1).contiguous()
        l = l.permute(0, 2, 3, 1).contiguous()
        return (r[0], l[0]) if single else (r, l)

    __call__ = decompose

    def _decompose_batch(self, s: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """[B,3,H,W] float32 in [0,1] -> (R [B,3,H,W], L [B,1,H,W])."""
        raise NotImplementedError


def get_decomposer(name: str = "lr3m", params: Any = None, **overrides: Any) -> Decomposer:
    """Build a decomposer by name (``lr3m`` or ``lime``), with a params dataclass and/or field overrides.

    Raises ``ValueError`` for an unknown name or parameter.
    """
    key = (name or "").lower()
    if key not in _REGISTRY:
        raise ValueError(f"unknown decomposition method {name!r}; choose one of {', '.join(_REGISTRY)}")
    module_name, cls_name = _REGISTRY[key].split(":")
    cls: Callable[..., Decomposer] = getattr(importlib.import_module(module_name), cls_name)
    if isinstance(params, dict):
        overrides = {**params, **overrides}
        params = None
    elif params is not None and not isinstance(params, cls.Params):  # type: ignore[attr-defined]
        raise TypeError(f"{key} expects {cls.Params.__name__}, got {type(params).__name__}")  # type: ignore[attr-defined]
    try:
        return cls(params, **overrides)
    except TypeError as exc:  # dataclasses.replace on an unknown field
        raise ValueError(f"bad parameter for method {key!r}: {exc}") from None


def enhance_for_viewing(r: torch.Tensor, l: torch.Tensor, gamma: float = 2.2) -> torch.Tensor:
    """The viewable enhancement S' = R∘(L / max L)^{1/γ} (LR3M's display rule), clipped to [0,1].

    Works on [...,H,W,C] channels-last tensors; the max is taken per image.
    """
    if l.dim() == 3:
        peak = l.amax().clamp_min(1e-6)
    else:
        peak = l.flatten(1).amax(dim=1).clamp_min(1e-6).view(-1, 1, 1, 1)
    return (r * (l / peak).clamp(0, 1) ** (1.0 / gamma)).clamp(0.0, 1.0)
