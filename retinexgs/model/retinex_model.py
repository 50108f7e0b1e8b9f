"""The full RetinexGS model: reflectance Gaussians + illumination field + EnhancementNet, rendered in one pass.

Per view: reflectance colours (SH, albedo) and illumination (MLP on PE(x), PE(d)) of every Gaussian are
rasterized together as 6 channels, giving R̂ and L̂; the low-light reconstruction is R̂∘L̂ and the enhanced
output S_enh = clip(R̂∘L̂^g, 0, 1) with g predicted by the EnhancementNet from L̂ (one g per image by default).
The plain-3DGS baselines use the same Gaussians with 3 colour channels and no illumination or enhancement.
"""
from __future__ import annotations

from typing import Dict, Optional

import torch
from torch import Tensor, nn

from retinexgs.model.enhancement import EnhancementNet
from retinexgs.model.gaussians import GaussianModel
from retinexgs.model.illumination import IlluminationField
from retinexgs.render import Camera, rasterize_gaussians


class RetinexGSModel(nn.Module):
    """Gaussians (+ illumination field and EnhancementNet when ``decomposed``)."""

    def __init__(self, gaussians: GaussianModel, model_cfg: Dict, decomposed: bool = True) -> None:
        super().__init__()
        self.gaussians = gaussians
        self.decomposed = decomposed
        if decomposed:
            self.illumination = IlluminationField(**model_cfg["illumination"])
            enh = dict(model_cfg["enhancement"])
            enh["gamma_range"] = tuple(enh["gamma_range"])
            self.per_channel_gamma = bool(enh.pop("per_channel", False))
            self.enhancement = EnhancementNet(channels=3, **enh)

    def predict_gamma(self, L_bchw: Tensor) -> Tensor:
        """The EnhancementNet's gamma for L̂ [1,3,H,W]: one per image (the paper's single g, the default) or
        one per channel (``model.enhancement.per_channel``), as [1,C,1,1]."""
        g = self.enhancement(L_bchw)
        return g if self.per_channel_gamma else g.mean(dim=1, keepdim=True).expand_as(g)

    def render(self, camera: Camera, active_degree: int, exposure: Optional[float] = None,
               gamma: Optional[float] = None) -> Dict[str, Tensor]:
        """Render one view. Returns ``out`` (RenderOutput) and [H,W,3] maps: ``rgb`` (the model's output
        image: S_enh, or the plain render for baselines), and for RetinexGS ``R``, ``L``, ``S_rec``, ``gamma``.

        ``exposure`` scales the predicted gamma (< 1 brighter, > 1 darker); ``gamma`` replaces it.
        """
        g = self.gaussians
        center = camera.center.to(g.means)
        colors = g.colors(center, active_degree)
        if self.decomposed:
            illum = self.illumination(g.means, IlluminationField.view_dirs(g.means, center))
            colors = torch.cat([colors, illum.to(colors)], dim=-1)
        out = rasterize_gaussians(g.means, g.quats, g.scales, g.opacities, colors, camera)
        if not self.decomposed:
            return {"out": out, "rgb": out.image}
        R, L = out.image[..., :3], out.image[..., 3:6]
        L_bchw = L.permute(2, 0, 1).unsqueeze(0)
        g_pred = self.predict_gamma(L_bchw)
        if gamma is not None:
            g_pred = torch.full_like(g_pred, float(gamma))
        elif exposure is not None:
            g_pred = g_pred * float(exposure)
        L_enh = self.enhancement.enhance(L_bchw, g_pred)[0].permute(1, 2, 0)
        S_enh = (R * L_enh).clamp(0.0, 1.0)
        return {"out": out, "rgb": S_enh, "R": R, "L": L, "S_rec": R * L, "L_enh": L_enh,
                "gamma": g_pred.reshape(-1)}
