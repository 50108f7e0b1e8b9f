"""Argument checks of the public rendering API: clear ``TypeError``/``ValueError`` naming the argument."""
from __future__ import annotations

from typing import List, Optional, Sequence, Tuple, Union

import torch
from torch import Tensor

from retinexgs.render.camera import Camera


def check_tensor(value, name: str, shape: Sequence[Optional[int]], like: Optional[Tensor] = None) -> Tensor:
    """Check that ``value`` is a float32/float64 tensor of ``shape`` (None = any size), matching ``like``."""
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if value.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"{name} must be float32 or float64, got {value.dtype}")
    if like is not None and value.dtype != like.dtype:
        raise TypeError(f"{name} has dtype {value.dtype} but means has {like.dtype}; use one dtype")
    if like is not None and value.device != like.device:
        raise ValueError(f"{name} is on {value.device} but means is on {like.device}; use one device")
    if value.dim() != len(shape) or any(s is not None and value.shape[i] != s for i, s in enumerate(shape)):
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name} must have shape {want}, got {tuple(value.shape)}")
    if value.device.type not in ("cpu", "cuda"):
        raise ValueError(f"{name} is on {value.device}; only cpu and cuda tensors are supported")
    return value


def finite_flag(named: Sequence) -> Optional[Tensor]:
    """A 0-dim bool tensor, on the tensors' device, that is True when every tensor of the ``(name, tensor)`` pairs
    is finite; None when there is nothing to check. Nothing waits for it: read it with :func:`raise_if_not_finite`
    where the caller synchronises anyway. (The renderer does not use it: its projection checks as it reads.)"""
    tensors = [t for _, t in named if t is not None and t.numel()]
    if not tensors:
        return None
    with torch.no_grad():
        # A NaN or inf makes a tensor's norm non-finite; the multi-tensor norm is one kernel for all of them.
        return torch.isfinite(torch.stack(torch._foreach_norm([t.detach() for t in tensors]))).all()


def raise_if_not_finite(flag: Union[Tensor, bool, None], named: Sequence) -> None:
    """Raise a ValueError naming the first of ``(name, tensor)`` pairs holding a NaN or an infinity, when ``flag``
    (True: all finite, e.g. from :func:`finite_flag` on the same pairs) says one does."""
    if flag is None or bool(flag):
        return
    for name, t in named:
        if t is not None and not bool(torch.isfinite(t.detach()).all()):
            bad = int((~torch.isfinite(t.detach())).sum())
            raise ValueError(f"{name} contains non-finite values (NaN or inf) in {bad} of {t.numel()} entries; "
                             "the renderer needs finite inputs")


def check_finite(named: Sequence) -> None:
    """Raise a ValueError naming the first of ``(name, tensor)`` pairs holding a NaN or an infinity.

    One reduction and one host sync for all of them (the kernels would otherwise cull such Gaussians
    silently, or let a NaN colour through to the image)."""
    raise_if_not_finite(finite_flag(named), named)


def check_gaussians(means, quats, scales, opacities, colors, camera, background=None, finite: bool = True) -> None:
    """Validate one render call's inputs; raises TypeError/ValueError naming the offending argument.

    Every tensor must be finite (a NaN or inf is a ValueError; ``finite=False`` leaves that check to the caller,
    e.g. the projection's own check in :func:`~retinexgs.render.rasterize_gaussians`). A zero quaternion is allowed and means the identity rotation (it gets
    a zero gradient); opacities outside [0, 1] are allowed (alpha is clamped to 0.99, a non-positive opacity
    culls the Gaussian)."""
    check_tensor(means, "means", (None, 3))
    n = means.shape[0]
    if n == 0:
        raise ValueError("means is empty: there are no Gaussians to render (N = 0)")
    check_tensor(quats, "quats", (n, 4), means)
    check_tensor(scales, "scales", (n, 3), means)
    check_tensor(opacities, "opacities", (n,), means)
    check_tensor(colors, "colors", (n, None), means)
    if colors.shape[1] < 1:
        raise ValueError("colors must have at least one channel, got shape " f"{tuple(colors.shape)}")
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a retinexgs.render.Camera, got {type(camera).__name__}")
    if background is not None:
        check_tensor(background, "background", (colors.shape[1],), means)
    if finite:
        check_finite(gaussian_tensors(means, quats, scales, opacities, colors, background))


def gaussian_tensors(means, quats, scales, opacities, colors, background=None) -> List[Tuple[str, Optional[Tensor]]]:
    """The ``(name, tensor)`` pairs that :func:`check_gaussians` checks for finiteness, in its order."""
    return [("means", means), ("quats", quats), ("scales", scales), ("opacities", opacities), ("colors", colors),
            ("background", background)]
