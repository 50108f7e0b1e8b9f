"""The pinhole camera the renderer takes."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import List

import torch


@dataclass(frozen=True)
class Camera:
    """A pinhole camera in the OpenCV convention (x right, y down, z forward).

    Attributes:
        viewmat: world-to-camera transform, a [4, 4] tensor (kept on the CPU: the kernels read it on the host).
        fx, fy, cx, cy: intrinsics in pixels; the centre of pixel (i, j) is at (i + 0.5, j + 0.5).
        width, height: image size in pixels.
        near, far: depth range; Gaussians whose centre lies outside it are culled.
    """

    viewmat: torch.Tensor
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    near: float = 0.01
    far: float = 1e10
    _flat: List[float] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        vm = self.viewmat
        if not isinstance(vm, torch.Tensor):
            vm = torch.as_tensor(vm, dtype=torch.float64)
        if tuple(vm.shape) != (4, 4):
            raise ValueError(f"camera viewmat must have shape (4, 4), got {tuple(vm.shape)}")
        vm = vm.detach().to("cpu", torch.float64)
        if not bool(torch.isfinite(vm).all()):
            raise ValueError("camera viewmat contains non-finite values")
        object.__setattr__(self, "viewmat", vm)
        object.__setattr__(self, "_flat", vm.reshape(-1).tolist())
        for name in ("fx", "fy", "cx", "cy", "near", "far"):
            value = getattr(self, name)
            if isinstance(value, torch.Tensor):
                value = float(value)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"camera {name} must be a finite number, got {value!r}")
            object.__setattr__(self, name, float(value))
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"camera fx and fy must be positive, got fx={self.fx}, fy={self.fy}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
                raise ValueError(f"camera {name} must be a positive integer, got {value!r}")
        if not 0 < self.near < self.far:
            raise ValueError(f"camera needs 0 < near < far, got near={self.near}, far={self.far}")

    @property
    def kernel_args(self) -> tuple:
        """(viewmat as 16 floats, fx, fy, cx, cy, width, height, near, far) for ``retinexgs._C``."""
        return (self._flat, self.fx, self.fy, self.cx, self.cy, self.width, self.height, self.near, self.far)

    @property
    def center(self) -> torch.Tensor:
        """Camera centre in world space, [3] float64."""
        R, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -R.T @ t

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by ``factor`` (pixel-centre convention preserved)."""
        return Camera(self.viewmat, self.fx * factor, self.fy * factor, self.cx * factor, self.cy * factor,
                      max(1, int(round(self.width * factor))), max(1, int(round(self.height * factor))),
                      self.near, self.far)
