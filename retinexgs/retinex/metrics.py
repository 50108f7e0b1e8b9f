"""Image quality metrics in torch: PSNR and SSIM (Wang et al. 2004).

SSIM uses an 11×11 Gaussian window with σ = 1.5, C1 = (0.01·range)², C2 = (0.03·range)², computed per
channel on the 'valid' region (no padding) and averaged — the standard reference definition.
Images are channels-last [H,W,C] or [B,H,W,C] floats; the result is one value per image.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F


def _to_bchw(x: torch.Tensor) -> torch.Tensor:
    if x.dim() == 3:
        x = x.unsqueeze(0)
    if x.dim() != 4:
        raise ValueError(f"expected [H,W,C] or [B,H,W,C], got shape {tuple(x.shape)}")
    return x.permute(0, 3, 1, 2).to(torch.float64)


def psnr(x: torch.Tensor, y: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB: 10·log10(range² / MSE). [H,W,C] -> scalar, [B,H,W,C] -> [B]."""
    if x.shape != y.shape:
        raise ValueError(f"shape mismatch {tuple(x.shape)} vs {tuple(y.shape)}")
    a, b = _to_bchw(x), _to_bchw(y)
    mse = ((a - b) ** 2).flatten(1).mean(1).clamp_min(1e-20)
    out = (10.0 * torch.log10(data_range ** 2 / mse)).float()
    return out[0] if x.dim() == 3 else out


def _gauss_window(size: int, sigma: float, device: torch.device) -> torch.Tensor:
    t = torch.arange(size, device=device, dtype=torch.float64) - (size - 1) / 2.0
    g = torch.exp(-0.5 * (t / sigma) ** 2)
    return g / g.sum()


def ssim(x: torch.Tensor, y: torch.Tensor, data_range: float = 1.0, window: int = 11,
         sigma: float = 1.5) -> torch.Tensor:
    """Structural similarity. [H,W,C] -> scalar, [B,H,W,C] -> [B]."""
    if x.shape != y.shape:
        raise ValueError(f"shape mismatch {tuple(x.shape)} vs {tuple(y.shape)}")
    a, b = _to_bchw(x), _to_bchw(y)
    if min(a.shape[-2:]) < window:
        raise ValueError(f"images must be at least {window}x{window} for SSIM")
    c = a.shape[1]
    g = _gauss_window(window, sigma, a.device)
    kh = g.view(1, 1, 1, -1).expand(c, 1, 1, -1)
    kv = g.view(1, 1, -1, 1).expand(c, 1, -1, 1)

    def blur(v: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.conv2d(v, kh, groups=c), kv, groups=c)

    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    mu_a, mu_b = blur(a), blur(b)
    saa = blur(a * a) - mu_a ** 2
    sbb = blur(b * b) - mu_b ** 2
    sab = blur(a * b) - mu_a * mu_b
    num = (2 * mu_a * mu_b + c1) * (2 * sab + c2)
    den = (mu_a ** 2 + mu_b ** 2 + c1) * (saa + sbb + c2)
    out = (num / den).flatten(1).mean(1).float()
    return out[0] if x.dim() == 3 else out
