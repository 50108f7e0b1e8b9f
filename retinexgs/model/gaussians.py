"""The reflectance field: 3D Gaussians whose SH colours are the scene's albedo (RetinexGS §II.C)."""
from __future__ import annotations

import math
from typing import Dict

import torch
from torch import Tensor, nn

from retinexgs.render import spherical_harmonics

SH_C0 = 0.28209479177387814
PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")


def rgb_to_sh_dc(rgb: Tensor) -> Tensor:
    """The degree-0 coefficient whose colour (SH + 0.5) is ``rgb``."""
    return (rgb - 0.5) / SH_C0


def sh_colors(means: Tensor, sh_dc: Tensor, sh_rest: Tensor, center: Tensor, degree: int) -> Tensor:
    """[N,3] colour max(SH(dir) + 0.5, 0) of degree ``degree`` seen from ``center`` (a function of the tensors,
    so that the trainer can capture it in a CUDA graph)."""
    coeffs = torch.cat([sh_dc, sh_rest], dim=1)
    return torch.clamp_min(spherical_harmonics(degree, means - center.to(means), coeffs) + 0.5, 0.0)


def knn_mean_distance(points: Tensor, k: int = 3, chunk: int = 2048) -> Tensor:
    """Mean distance of each point to its k nearest neighbours ([P]), computed in chunks."""
    out = torch.empty(points.shape[0], dtype=points.dtype, device=points.device)
    k = min(k, max(points.shape[0] - 1, 1))
    for s in range(0, points.shape[0], chunk):
        d = torch.cdist(points[s:s + chunk], points)
        out[s:s + chunk] = d.topk(k + 1, largest=False).values[:, 1:].mean(-1)
    return out


class GaussianModel(nn.Module):
    """N Gaussians: means [N,3], quats [N,4], log-scales [N,3], opacity logits [N], SH [N,1,3] + [N,K-1,3].

    Activations: scales = exp(log_scales), opacities = sigmoid(logits), colour = max(SH(dir) + 0.5, 0).
    """

    def __init__(self, params: Dict[str, Tensor], sh_degree: int) -> None:
        super().__init__()
        self.sh_degree = int(sh_degree)
        for name in PARAM_NAMES:
            setattr(self, name, nn.Parameter(params[name].contiguous()))

    @classmethod
    def from_points(cls, points: Tensor, colors: Tensor, sh_degree: int = 3, init_opacity: float = 0.1,
                    brighten: bool = True) -> "GaussianModel":
        """Isotropic Gaussians at ``points`` [P,3] sized by the neighbour distance; colours [P,3] in [0,1].

        With ``brighten`` the (dark) point colours are rescaled to a mean of 0.5, a better start for an albedo.
        """
        points, colors = points.float(), colors.float().clamp(0, 1)
        if points.shape[0] == 0:
            raise ValueError("the scene has no initial points")
        if brighten and colors.mean() > 1e-6:
            colors = (colors * (0.5 / colors.mean())).clamp(0, 1)
        n = points.shape[0]
        dist = knn_mean_distance(points).clamp_min(1e-7)
        k = (sh_degree + 1) ** 2
        params = {
            "means": points.clone(),
            "quats": torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1),
            "log_scales": torch.log(dist).unsqueeze(-1).repeat(1, 3),
            "opacity_logits": torch.full((n,), math.log(init_opacity / (1 - init_opacity))),
            "sh_dc": rgb_to_sh_dc(colors).unsqueeze(1),
            "sh_rest": torch.zeros(n, k - 1, 3),
        }
        return cls(params, sh_degree)

    @classmethod
    def empty_like_state(cls, state: Dict[str, Tensor], sh_degree: int) -> "GaussianModel":
        """A model shaped like a saved state dict (its N may differ from any fresh model's)."""
        return cls({name: torch.zeros_like(state[name]) for name in PARAM_NAMES}, sh_degree)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def scales(self) -> Tensor:
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> Tensor:
        return torch.sigmoid(self.opacity_logits)

    def colors(self, camera_center: Tensor, active_degree: int) -> Tensor:
        """[N,3] view-dependent colour seen from ``camera_center`` with SH up to ``active_degree``."""
        return sh_colors(self.means, self.sh_dc, self.sh_rest, camera_center, min(active_degree, self.sh_degree))

    def tensors(self) -> Dict[str, Tensor]:
        """The parameters by name."""
        return {name: getattr(self, name) for name in PARAM_NAMES}
