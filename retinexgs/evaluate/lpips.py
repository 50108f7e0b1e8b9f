"""LPIPS (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual Metric"), AlexNet
backbone with the v0.1 linear heads, in plain torch: no ``lpips`` package, no torchvision, nothing downloaded.

The network, as the reference implementation defines it:

1. inputs in [0, 1] mapped to [-1, 1], then the scaling layer ``(x - shift) / scale`` per RGB channel;
2. AlexNet's ``features``: conv 11x11 stride 4 pad 2 (64) · ReLU · max-pool 3/2 · conv 5x5 pad 2 (192) · ReLU ·
   max-pool 3/2 · conv 3x3 pad 1 (384) · ReLU · conv 3x3 pad 1 (256) · ReLU · conv 3x3 pad 1 (256) · ReLU; the five
   ReLU outputs are the features;
3. each feature map unit-normalised over its channels at every position (``f / (‖f‖ + 1e-10)``);
4. per layer the squared difference of the two images' normalised features, weighted by the layer's linear head
   (a 1x1 convolution to one channel, no bias) and averaged over the positions; the five layers summed.

The weights (``weights/lpips_alex.npz``, float32, torch layout) are torchvision's AlexNet and the LPIPS v0.1 heads,
converted once by ``experiments/lpips_convert.py``; their licences are in ``weights/THIRD_PARTY.md``.
Lower is more similar; 0 for identical images.
"""
from __future__ import annotations

import threading
from pathlib import Path
from typing import Dict, List, Optional, Tuple, Union

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["WEIGHTS", "MIN_SIZE", "LpipsAlex", "lpips_model", "lpips_distance", "weights_available"]

WEIGHTS = Path(__file__).resolve().parent / "weights" / "lpips_alex.npz"
# The reference's scaling layer (for inputs in [-1, 1]).
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
# (stride, padding) of AlexNet's five convolutions; a 3x3 stride-2 max-pool follows the first two ReLUs.
CONV_GEOMETRY = ((4, 2), (1, 2), (1, 1), (1, 1), (1, 1))
POOL_AFTER = (0, 1)
EPS = 1e-10
# The smallest side the network takes: the second max-pool needs a 3x3 window (31 -> 7 -> 3 -> 1).
MIN_SIZE = 31
# Values this far outside [0, 1] are rounding (a float32 render, a resample), not another range such as [0, 255].
RANGE_SLACK = 1e-3


def weights_available(path: Optional[Path] = None) -> Tuple[bool, str]:
    """Whether the weights file (default :data:`WEIGHTS`, shipped) is there (a broken install may lack it); the
    reason when not."""
    path = WEIGHTS if path is None else path
    if not Path(path).is_file():
        return False, f"the LPIPS weights file {path} is missing (reinstall retinexgs)"
    return True, ""


def load_weights(path: Optional[Path] = None) -> Dict[str, np.ndarray]:
    """The arrays of the weights file (default :data:`WEIGHTS`): ``conv{k}.weight/bias`` and ``lin{k}.weight`` for
    k = 0..4."""
    with np.load(WEIGHTS if path is None else path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


class LpipsAlex:
    """LPIPS-AlexNet on one device in one float dtype; use :func:`lpips_model` for the cached instance."""

    def __init__(self, arrays: Dict[str, np.ndarray], device: Union[str, torch.device] = "cpu",
                 dtype: torch.dtype = torch.float32) -> None:
        as_t = lambda a: torch.as_tensor(np.asarray(a)).to(device=device, dtype=dtype)  # noqa: E731
        self.device, self.dtype = torch.device(device), dtype
        self.convs = [(as_t(arrays[f"conv{k}.weight"]), as_t(arrays[f"conv{k}.bias"])) for k in range(5)]
        self.heads = [as_t(arrays[f"lin{k}.weight"]).reshape(1, -1, 1, 1) for k in range(5)]
        self.shift = torch.tensor(SHIFT, dtype=dtype, device=device).reshape(1, 3, 1, 1)
        self.scale = torch.tensor(SCALE, dtype=dtype, device=device).reshape(1, 3, 1, 1)

    def features(self, x: torch.Tensor) -> List[torch.Tensor]:
        """The five unit-normalised feature maps of [B,3,H,W] images in [0, 1]."""
        h = ((x * 2 - 1) - self.shift) / self.scale
        out = []
        for k, ((w, b), (stride, pad)) in enumerate(zip(self.convs, CONV_GEOMETRY)):
            h = F.relu(F.conv2d(h, w, b, stride=stride, padding=pad))
            out.append(h / (h.square().sum(1, keepdim=True).sqrt() + EPS))
            if k in POOL_AFTER:
                h = F.max_pool2d(h, 3, 2)
        return out

    def distance(self, fx: List[torch.Tensor], fy: List[torch.Tensor]) -> torch.Tensor:
        """LPIPS [B] from two images' :meth:`features` (``fy`` may have batch 1, compared with every ``fx``)."""
        return sum(((a - b).square() * head).sum(1).mean((-2, -1)) for a, b, head in zip(fx, fy, self.heads))

    def __call__(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """LPIPS [B] of [B,3,H,W] images in [0, 1] on this model's device and dtype (``y`` may have batch 1)."""
        # Both in one pass: half the launches, and an image equal to the reference gets bit-equal features (a
        # separate pass may pick another convolution algorithm and differ in the last bits), so LPIPS exactly 0.
        f = self.features(torch.cat([x, y]))
        n = x.shape[0]
        return self.distance([t[:n] for t in f], [t[n:] for t in f])


# One model per (device, dtype), built on first use: loading and copying 2.5 M weights every view would cost more
# than the metric itself. Never dropped (10 MB per device).
_MODELS: Dict[Tuple[str, torch.dtype], LpipsAlex] = {}
_LOCK = threading.Lock()


def lpips_model(device: Union[str, torch.device] = "cpu", dtype: torch.dtype = torch.float32) -> LpipsAlex:
    """The cached :class:`LpipsAlex` for ``device`` and ``dtype``."""
    dev = torch.device(device)
    if dev.type == "cuda" and dev.index is None:
        dev = torch.device("cuda", torch.cuda.current_device())
    key = (str(dev), dtype)
    with _LOCK:
        model = _MODELS.get(key)
        if model is None:
            model = _MODELS[key] = LpipsAlex(load_weights(), dev, dtype)
    return model


def _check(x: torch.Tensor, y: torch.Tensor) -> None:
    for name, t in (("x", x), ("y", y)):
        if not isinstance(t, torch.Tensor):
            raise ValueError(f"LPIPS: {name} must be a torch tensor, got {type(t).__name__}")
        if t.dim() != 4 or t.shape[1] != 3:
            raise ValueError(f"LPIPS needs [B,3,H,W] RGB images, got {name} of shape {tuple(t.shape)}")
        if not t.is_floating_point():
            raise ValueError(f"LPIPS needs float images in [0, 1], got {name} of dtype {t.dtype}")
    if x.shape[-2:] != y.shape[-2:] or y.shape[0] not in (1, x.shape[0]):
        raise ValueError(f"LPIPS: shape mismatch {tuple(x.shape)} vs {tuple(y.shape)}")
    if min(x.shape[-2:]) < MIN_SIZE:
        raise ValueError(f"LPIPS needs images of at least {MIN_SIZE}x{MIN_SIZE} pixels, got {tuple(x.shape[-2:])}")
    if x.shape[0] == 0:
        raise ValueError("LPIPS: empty batch")
    for name, t in (("x", x), ("y", y)):
        lo, hi = (float(v) for v in torch.aminmax(t))  # NaN propagates into both
        if not (lo >= -RANGE_SLACK and hi <= 1 + RANGE_SLACK):
            raise ValueError(f"LPIPS needs images in [0, 1], got {name} in [{lo:.4g}, {hi:.4g}]")


def _no_tf32(device: torch.device):
    """cuDNN's convolutions in full float32: TF32, on by default for them on recent GPUs, moved LPIPS by 3e-5 on an
    H200 (full float32 there: 3e-8 from the CPU's figures); a no-op elsewhere."""
    if device.type != "cuda":
        return torch.no_grad()  # any context manager; the caller is in no_grad already
    c = torch.backends.cudnn
    return c.flags(enabled=c.enabled, benchmark=c.benchmark, deterministic=c.deterministic, allow_tf32=False)


@torch.no_grad()
def lpips_distance(x: torch.Tensor, y: torch.Tensor, device: Optional[Union[str, torch.device]] = None) -> torch.Tensor:
    """LPIPS-AlexNet of [B,3,H,W] RGB images in [0, 1], any H, W ≥ :data:`MIN_SIZE`; a [B] tensor on ``x``'s device.

    ``y`` may have batch 1 (one reference for B images: its features are computed once). Computed on ``device``
    (default ``x``'s), in float64 for float64 inputs and float32 otherwise. Raises a one-line ValueError on a bad
    shape, dtype or range (including NaN)."""
    _check(x, y)
    dev = torch.device(device) if device is not None else x.device
    dtype = torch.float64 if x.dtype == torch.float64 and y.dtype == torch.float64 else torch.float32
    model = lpips_model(dev, dtype)
    with _no_tf32(model.device):
        d = model(x.detach().to(model.device, dtype), y.detach().to(model.device, dtype))
    return d.to(x.device)
