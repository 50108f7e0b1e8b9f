"""Would a chroma prior on R̂ where the 2D priors say nothing clean the night colour blotches? (issue 64 item 2)

On a raw night capture R̂ is a field of colour blotches while L̂ carries the scene's structure (the CPU proxy's render
of fox-dark at 1000 e⁻, test view 0021). The R prior is weighed by what the views resolve (``loss.raw.prior_snr``:
conf ∈ [0, 1]), so where the light is near the noise floor (the dark fox, its plaque) nothing constrains R̂'s colour
but the noisy reconstruction. This adds, only there, a prior that R̂'s chroma is smooth unless L̂ has an edge: with
weight w_r (the R prior's own, so that R̂'s chroma is held by the prior where conf = 1 and by this where conf = 0)

    L_cs = mean((1 − conf) · |chroma(R̂) − GF_L̂(chroma(R̂))|),

GF a guided filter (He et al.) of R̂'s chroma guided by L̂'s luma over its mean, radius ``--radius``, ε ``--eps``,
taken as a fixed target (detached). It patches :func:`retinexgs.train.losses.supervision_loss` (the eager path the
CPU trains with) and then runs ``retinexgs ARGS``:

    python experiments/chroma_prior_proxy.py [--radius 8] [--eps 0.01] -- train --data CAPTURE --out RUN \\
        --device cpu --set seed=0 --set steps=3000 --set data.downscale=2
"""
from __future__ import annotations

import argparse
import sys

import torch
import torch.nn.functional as F

from retinexgs.train import losses


def box(x: torch.Tensor, r: int) -> torch.Tensor:
    """The mean over the (2r+1)² window, the border's window cut to the image."""
    return F.avg_pool2d(x, 2 * r + 1, 1, r, count_include_pad=False)


def guided_filter(guide: torch.Tensor, p: torch.Tensor, r: int, eps: float) -> torch.Tensor:
    """He et al.'s guided filter of ``p`` [B,C,H,W] by the one-channel ``guide`` [B,1,H,W]."""
    mean_i, mean_p = box(guide, r), box(p, r)
    a = (box(guide * p, r) - mean_i * mean_p) / (box(guide * guide, r) - mean_i * mean_i + eps)
    b = mean_p - a * mean_i
    return box(a, r) * guide + box(b, r)


def patch(radius: int, eps: float) -> None:
    original = losses.supervision_loss

    def supervision_loss(R_hat, L_hat, R, L, S, w_r=0.5, *args, **kwargs):
        total, terms = original(R_hat, L_hat, R, L, S, w_r, *args, **kwargs)
        linear = kwargs.get("linear", args[5] if len(args) > 5 else None)
        if linear is None or linear.prior_snr <= 0:
            return total, terms
        conf = losses.prior_confidence(S, linear)
        chroma = R_hat - R_hat.mean(dim=1, keepdim=True)
        luma = L_hat.mean(dim=1, keepdim=True).detach()
        guide = luma / luma.mean(dim=(2, 3), keepdim=True).clamp_min(1e-6)
        with torch.no_grad():
            target = guided_filter(guide, chroma, radius, eps)
        cs = ((1.0 - conf) * (chroma - target).abs()).mean()
        terms["chroma_smooth"] = cs
        return total + w_r * cs, terms

    losses.supervision_loss = supervision_loss


def main() -> int:
    argv = sys.argv[1:]
    split = argv.index("--") if "--" in argv else len(argv)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--radius", type=int, default=8)
    parser.add_argument("--eps", type=float, default=0.01)
    args = parser.parse_args(argv[:split])
    patch(args.radius, args.eps)
    from retinexgs.cli import main as cli
    return cli(argv[split + 1:])


if __name__ == "__main__":
    sys.exit(main())
