"""A method's training objective (nerfstudio's ``Model.get_loss_dict`` is the model): every loss term of a step
from the render and the training view, eagerly or through the captured CUDA graphs of the image losses.

- :class:`RetinexObjective`: RetinexGS (the paper's §3.3 and §3.4): the 2D priors' supervision of R̂ and L̂ (from
  ``loss.prior_late_from`` at :func:`late_prior_scale` of their weights), the reconstruction R̂∘L̂ ≈ S (in linear
  light on a camera-raw scene), L_TV, L_SH, the depth prior and, from ``loss.enhance_from``, the EnhancementNet's
  L_enhance;
- :class:`PlainObjective`: the 3DGS baselines (``method`` 3dgs, pre, post): L1 + D-SSIM on the target.

The trainer builds one with :func:`build_objective` and only loops; the density strategy's regulariser
(:meth:`retinexgs.strategy.Strategy.extra_loss`) is added here, to both paths.
"""
from __future__ import annotations

from typing import Callable, Dict, List, Optional, Tuple, Union

import torch
from torch import Tensor
from torch.profiler import record_function

from retinexgs.model.retinex_model import RetinexGSModel
from retinexgs.model.schedule import Schedule
from retinexgs.model.tones import fused_curve
from retinexgs.model.tones.exposure import reference_gain
from retinexgs.config.schema import Config, Loss
from retinexgs.strategy import Strategy
from retinexgs.train import fused_enhance, fused_loss, losses
from retinexgs.train.capture_setup import NoiseSetUp
from retinexgs.train.graphs import LossGraphs
from retinexgs.train.losses import to_bchw
from retinexgs.train.views import TrainView, unpack_edges, unpack_targets


def enhancement_objective(model: RetinexGSModel, c: Loss, R_img: Tensor, L_img: Tensor, S_b: Tensor
                          ) -> Tuple[Tensor, Dict[str, Tensor]]:
    """L_enhance (weighted sum, unweighted terms) of the enhanced render of [H,W,3] maps R̂, L̂ against the
    low-light view ``S_b`` [1,3,H,W], with the loss section ``c`` of a config (L_exp's target from
    :func:`retinexgs.train.losses.exposure_target`). Unless
    ``c.enhance_trains_scene``, R̂ and L̂ are detached: only the EnhancementNet learns from it. The terms
    include ``exp_E``, L_exp's target (for the log; not part of the sum)."""
    if not c.enhance_trains_scene:
        # The paper trains the EnhancementNet alone with L_enhance: without this the exposure term would
        # flatten R̂ and L̂ towards E instead of adjusting the gamma.
        R_img, L_img = R_img.detach(), L_img.detach()
    if fused_enhance.applies(model, c, R_img):  # the default on the GPU: two kernels for the terms and their gradient
        return fused_enhance.enhancement_terms(model, c, R_img, L_img, S_b)
    out = model.enhance(R_img, L_img)
    light = to_bchw(out["L_enh"]) if c.exp_on == "illumination" else None
    E = losses.exposure_target(c, model.tone, R_img * L_img, model.shoulder)
    total, terms = losses.enhancement_loss(
        to_bchw(out["rgb"]), S_b, c.w_spa, c.w_exp, c.w_col, E,
        illumination=light, exp_patch=c.exp_patch, exp_form=c.exp_form, spa_form=c.spa_form,
        scale_invariant=c.enhance_scale_invariant)
    # Logged, not a loss: L_exp's target, below exposure_E where the highlight meter caps it (issue 32).
    terms["exp_E"] = E.detach().float() if torch.is_tensor(E) else torch.full((), float(E), device=R_img.device)
    return total, terms


class PlainObjective:
    """The 3DGS baselines' loss: L1 + λ·D-SSIM of the render against the view's target (and the strategy's
    regulariser). The base of :class:`RetinexObjective`."""

    decomposed = False  # the render carries R̂ and L̂ (6 channels) rather than RGB

    def __init__(self, cfg: Config, model: RetinexGSModel, schedule: Schedule, strategy: Strategy,
                 noise: NoiseSetUp, depth_prior: bool = False) -> None:
        self.cfg, self.model, self.schedule, self.strategy, self.noise = cfg, model, schedule, strategy, noise
        self.depth_prior = depth_prior

    # ---- the terms -----------------------------------------------------------------------------------------
    def image_loss(self, image: Tensor, S: Tensor, R: Optional[Tensor], L: Optional[Tensor],
                   enhance: bool) -> Tuple[Tensor, Dict[str, Tensor]]:
        """Every loss term that depends only on the rendered ``image`` [H,W,C] and their weighted sum. The same
        function runs eagerly and inside the captured CUDA graphs (:mod:`retinexgs.train.graphs`): it never
        syncs with the host."""
        rgb = losses.l1_ssim(to_bchw(image), to_bchw(S), self.cfg.loss.lambda_ssim)
        return rgb, {"rgb": rgb}

    def target(self, tv: TrainView) -> Tensor:
        """What the render is compared with."""
        return tv.target

    def sh_loss(self) -> Optional[Tensor]:
        """L_SH (unweighted), or None where the method has none."""
        return None

    def depth_loss(self, res: Dict[str, Tensor], tv: TrainView) -> Optional[Tensor]:
        """The depth prior (unweighted) of a render made with ``depth=True``; None while it is off."""
        if not self.depth_prior:
            return None
        depth, alpha = self._depth_maps(res)
        wx, wy = tv.edge_weights(self.cfg.loss.depth_edge)
        return losses.depth_smoothness_loss(to_bchw(depth), to_bchw(alpha), wx, wy)

    @staticmethod
    def _depth_maps(res: Dict[str, Tensor]) -> Tuple[Tensor, Tensor]:
        """(depth, alpha) [H,W,1] of a render made with ``depth=True``, the depth prior's inputs."""
        out = res["out"]
        if out.depth is None:
            raise ValueError("loss.w_depth > 0 needs the render's depth: render with depth=True (render_view does)")
        return out.depth, out.alpha

    def assemble_terms(self, image_total: Tensor, image_terms: Dict[str, Tensor], sh: Optional[Tensor],
                       depth: Optional[Tensor] = None, depth_in_total: bool = False) -> Dict[str, Tensor]:
        """Every logged term in the log's order, with ``total``."""
        return {"total": image_total, **image_terms}

    def enhance_at(self, step: int) -> bool:
        """Whether the enhancement losses are on at ``step``."""
        return False

    def _add_strategy_loss(self, terms: Dict[str, Tensor], extra: Optional[Tensor], detach: bool
                           ) -> Dict[str, Tensor]:
        if extra is not None:  # the strategy's regulariser (MCMC: L1 on opacity and scale)
            terms["density"] = extra.detach()
            terms["total"] = terms["total"] + (extra.detach() if detach else extra)
        return terms

    # ---- eager -----------------------------------------------------------------------------------------------
    def loss(self, res: Dict[str, Tensor], tv: TrainView, step: int) -> Dict[str, Tensor]:
        """Every loss term of this step (weighted terms sum to ``total``), eagerly, from a render's ``res``."""
        total, terms = self.image_loss(res["out"].image, self.target(tv), tv.R, tv.L, self.enhance_at(step))
        terms = self.assemble_terms(total, terms, self.sh_loss(), self.depth_loss(res, tv))
        return self._add_strategy_loss(terms, self.strategy.extra_loss(self.model.gaussians), detach=False)

    # ---- through the captured graphs -------------------------------------------------------------------------
    def graphed_params(self) -> List[Tensor]:
        """The parameters the captured image losses reach (their gradients come out of the graph)."""
        return []

    def graphed_loss(self, image: Tensor, packed: Tensor, enhance: bool) -> Tuple[Tensor, Dict[str, Tensor]]:
        """The captured loss: :meth:`image_loss`, and with the depth prior on, its term as the last ("depth",
        weighted into the sum) on the two channels that :meth:`graph_input` appends (depth, alpha)."""
        S, R, L = unpack_targets(packed, self.decomposed, self.depth_prior)
        if not self.depth_prior:
            return self.image_loss(image, S, R, L, enhance)
        # split, not slices: its backward is one concatenation, a slice's a zero-filled full-size gradient each
        rendered, depth, alpha = image.split([image.shape[-1] - 2, 1, 1], dim=-1)
        total, terms = self.image_loss(rendered, S, R, L, enhance)
        terms["depth"] = losses.depth_smoothness_loss(to_bchw(depth), to_bchw(alpha), *unpack_edges(packed))
        return torch.add(total, terms["depth"], alpha=self.cfg.loss.w_depth), terms

    def graph_input(self, res: Dict[str, Tensor]) -> Tensor:
        """The captured loss's input [H,W,C(+2)]: the rendered channels, then the depth prior's depth and alpha
        (its ~60 small kernels run inside the graph instead of eagerly): the render's packed tensor as the
        compositing wrote it (a render with ``packed``, as the trainer's), else their concatenation."""
        out = res["out"]
        if not self.depth_prior:
            return out.image
        if out.packed is not None:
            return out.packed
        return torch.cat([out.image, *self._depth_maps(res)], dim=-1)

    def backward_graphed(self, graphs: LossGraphs, res: Dict[str, Tensor], tv: TrainView, step: int,
                         log_failures: Callable[[Dict], None]) -> Optional[Dict[str, Tensor]]:
        """The loss and its backward through the captured graph; None when this view must run eagerly (the
        capture's failures go to ``log_failures``)."""
        enhance = self.enhance_at(step)
        out = res["out"]
        with record_function("step/loss_graph"):
            edge = self.cfg.loss.depth_edge if self.depth_prior else None
            result = graphs.run(self.graph_input(res), tv.pack(self.decomposed, edge), enhance)
        if result is None:
            log_failures(graphs.failures)
            return None
        values = result.values
        image_terms = {name: values[i + 1] for i, name in enumerate(result.names)}
        depth = image_terms.pop("depth", None)  # already weighted into values[0]
        with record_function("step/backward"):
            grad = result.grad_image
            if depth is None:
                roots, grads = [out.image], [grad]
            elif out.packed is not None:  # the gradient of the packed render reaches the compositing as it is
                roots, grads = [out.packed], [grad]
            else:
                C = out.image.shape[-1]
                roots = [out.image, out.depth, out.alpha]
                grads = [grad[..., :C], grad[..., C:C + 1], grad[..., C + 1:]]
            sh = self.sh_loss()
            if sh is not None and sh.requires_grad and self.cfg.loss.w_sh:
                roots.append(self.cfg.loss.w_sh * sh)
                grads.append(None)
            extra = self.strategy.extra_loss(self.model.gaussians)
            if extra is not None:
                roots.append(extra)
                grads.append(None)
            torch.autograd.backward(roots, grads)
            # The EnhancementNet's gradients are the graph's static buffers: read by this step's optimiser
            # step, overwritten only by the next replay (zero_grad sets .grad to None in between).
            for p, g in zip(graphs.params if enhance else [], result.param_grads):
                p.grad = g if p.grad is None else p.grad + g
        terms = self.assemble_terms(values[0], image_terms, None if sh is None else sh.detach(), depth,
                                    depth_in_total=True)
        return self._add_strategy_loss(terms, extra, detach=True)


class RetinexObjective(PlainObjective):
    """RetinexGS's loss: the priors' supervision, the reconstruction, L_TV, L_SH, the depth prior and
    L_enhance (``cfg.loss``; the capture's noise set-up in ``noise``)."""

    decomposed = True

    def __init__(self, cfg: Config, model: RetinexGSModel, schedule: Schedule, strategy: Strategy,
                 noise: NoiseSetUp, depth_prior: bool = False, prior_late_scale: float = 1.0) -> None:
        super().__init__(cfg, model, schedule, strategy, noise, depth_prior)
        self.capture = noise.capture
        # (w_r, w_l, w_s) on the device while the priors' late scale is in use: the captured graphs read it, and
        # :meth:`_prior_phase` rewrites it in place when the schedule reaches loss.prior_late_from.
        self.prior_late_scale = float(prior_late_scale)
        self._sup_w: Optional[Tensor] = None
        self._late: Optional[bool] = None

    def _prior_phase(self, step: int, device: torch.device) -> None:
        """Set the priors' weights for ``step`` (× :attr:`prior_late_scale` from loss.prior_late_from on); a
        device write only when the phase changes, so a step never waits for the host."""
        c = self.cfg.loss
        if self.prior_late_scale == 1.0:
            return
        late = self.schedule.prior_late_at(step)
        if self._sup_w is None:  # filled on the device, not copied from the host: no sync
            self._sup_w = torch.full((3,), c.w_s, dtype=torch.float32, device=device)
        if late != self._late:
            scale = self.prior_late_scale if late else 1.0
            self._sup_w[0].fill_(c.w_r * scale)
            self._sup_w[1].fill_(c.w_l * scale)
            self._late = late

    def loss(self, res: Dict[str, Tensor], tv: TrainView, step: int) -> Dict[str, Tensor]:
        self._prior_phase(step, res["out"].image.device)
        return super().loss(res, tv, step)

    def backward_graphed(self, graphs: LossGraphs, res: Dict[str, Tensor], tv: TrainView, step: int,
                         log_failures: Callable[[Dict], None]) -> Optional[Dict[str, Tensor]]:
        self._prior_phase(step, res["out"].image.device)
        return super().backward_graphed(graphs, res, tv, step, log_failures)

    def _sup_weights(self) -> Tuple[Union[float, Tensor], Union[float, Tensor], float]:
        """(w_r, w_l, w_s) of this step: the config's, or the device's scheduled ones (:meth:`_prior_phase`)."""
        c = self.cfg.loss
        if self._sup_w is None:
            return c.w_r, c.w_l, c.w_s
        return self._sup_w[0], self._sup_w[1], c.w_s

    def target(self, tv: TrainView) -> Tensor:
        return tv.S

    def enhance_at(self, step: int) -> bool:
        return self.schedule.enhance_at(step)

    def graphed_params(self) -> List[Tensor]:
        return self.model.enhancement.used_parameters()

    def rec_gain(self) -> Optional[Tensor]:
        """The reconstruction's exposure gain (a scalar tensor; None for ``rec_domain: photo``): the tone's gain at
        g = 1, 1 / lin(L_ref), a constant of the scene, capped where the photos' noise asks (train/noise.py)."""
        if self.cfg.loss.rec_domain == "photo":
            return None
        gain = reference_gain(self.model.illum_ref)
        cap = self.noise.rec_gain_cap
        return gain if cap is None else torch.minimum(gain, cap)

    def _r_luma(self) -> float:
        """κ of the R prior, the capture's answer for these views (:meth:`Capture.r_prior_luma`)."""
        return self.capture.r_prior_luma(self.cfg.loss, float(self.cfg.data.downscale))

    def _rec_targets(self) -> Tuple[Optional[Tensor], Optional[losses.LinearTarget]]:
        """(the reconstruction's gain, a raw scene's linear target at the scene's own exposure, or None)."""
        linear = self.noise.linear_target
        if linear is not None:  # at the scene's own exposure, not the noise floor's cap (LinearTarget)
            linear = linear._replace(gain=reference_gain(self.model.illum_ref))
        return self.rec_gain(), linear

    def _add_enhancement(self, total: Tensor, terms: Dict[str, Tensor], image: Tensor, S_b: Tensor) -> Tensor:
        """``total`` + L_enhance of the render ``image`` [H,W,6+] against the view ``S_b`` [1,3,H,W] (its terms into
        ``terms``)."""
        R_img, L_img = image.split(3, dim=-1)[:2]
        # loss.raw.spa photo: L_spa's input is a raw view as the photo it shows (its mean undragged by the noise)
        S_spa = self.capture.spa_input(S_b, self.cfg.loss)
        enh, enh_terms = enhancement_objective(self.model, self.cfg.loss, R_img, L_img, S_spa)
        terms.update(enh_terms)
        return total + enh

    def image_loss(self, image: Tensor, S: Tensor, R: Optional[Tensor], L: Optional[Tensor],
                   enhance: bool) -> Tuple[Tensor, Dict[str, Tensor]]:
        """All but L_SH; ``S`` is the low-light view, ``R``/``L`` its 2D priors or None; ``enhance``: the
        enhancement losses are on."""
        c = self.cfg.loss
        R_img, L_img = image.split(3, dim=-1)[:2]  # (split: one concatenation backward, see graphed_loss)
        R_hat, L_hat, S_b = to_bchw(R_img), to_bchw(L_img), to_bchw(S)
        gain, linear = self._rec_targets()
        if linear is None:  # compared as photos (loss.raw.mode photo on a raw scene: the raw view clipped)
            S_b = self.capture.as_photo(S_b)
        terms: Dict[str, Tensor] = {}
        l1_exposed = c.rec_domain == "exposed"
        if R is not None:
            sup, sup_terms = losses.supervision_loss(R_hat, L_hat, to_bchw(R), to_bchw(L), S_b, *self._sup_weights(),
                                                     c.lambda_ssim, gain, l1_exposed, linear, self._r_luma())
            terms.update(sup_terms)
        else:  # no 2D priors: only the reconstruction is supervised
            terms["sup_rec"] = losses.reconstruction_loss(R_hat * L_hat, S_b, c.lambda_ssim, gain, l1_exposed,
                                                          linear)
            sup = c.w_s * terms["sup_rec"]
        terms["tv"] = losses.tv_loss(R_hat)
        total = sup + c.w_tv * terms["tv"]
        if enhance:
            total = self._add_enhancement(total, terms, image, S_b)
        return total, terms

    def graphed_loss(self, image: Tensor, packed: Tensor, enhance: bool) -> Tuple[Tensor, Dict[str, Tensor]]:
        """The captured loss; on the GPU its supervision, L_TV and depth prior as one kernel each way
        (:mod:`retinexgs.train.fused_loss`, the same values as the torch terms) where the configuration allows."""
        c = self.cfg.loss
        gain, linear = self._rec_targets()
        sup = None
        if (fused_curve.runs_fused(image) and packed.shape[-1] in (7, 9) and image.shape[-1] == packed.shape[-1] - 1
                and (linear is not None or not self.capture.unclipped)):  # as_photo is the identity on photos
            sup = fused_loss.plan(gain, c.rec_domain == "exposed", linear, image, self._r_luma())
        if sup is None:
            return super().graphed_loss(image, packed, enhance)
        weights = (c.w_r, c.w_l, c.w_s) if self._sup_w is None else self._sup_w
        total, terms = fused_loss.supervision_terms(image, packed, sup, weights, c.lambda_ssim, linear)
        depth = terms.pop("depth", None)
        total = total + c.w_tv * terms["tv"]
        if enhance:
            total = self._add_enhancement(total, terms, image, to_bchw(packed[..., :3]))
        if depth is not None:
            terms["depth"] = depth
            total = torch.add(total, depth, alpha=c.w_depth)
        return total, terms

    def sh_loss(self) -> Tensor:
        """L_SH on the Gaussians' higher-order SH (unweighted; its shape follows the Gaussian count, so it is
        not part of the graphed image losses)."""
        return losses.sh_sparsity_loss(self.model.gaussians.sh_rest, self.cfg.loss.sh_reduction)

    def assemble_terms(self, image_total: Tensor, image_terms: Dict[str, Tensor], sh: Optional[Tensor],
                       depth: Optional[Tensor] = None, depth_in_total: bool = False) -> Dict[str, Tensor]:
        """Every logged term in the log's order (L_SH after L_TV, then the depth prior) with ``total`` = image
        losses + w_sh·L_SH (+ w_depth·depth prior, unless ``depth_in_total``: the graphed sum holds it)."""
        terms: Dict[str, Tensor] = {}
        for name, value in image_terms.items():
            terms[name] = value
            if name == "tv":
                terms["sh"] = sh
                if depth is not None:
                    terms["depth"] = depth
        total = torch.add(image_total, sh, alpha=self.cfg.loss.w_sh)
        if depth is not None and not depth_in_total:
            total = torch.add(total, depth, alpha=self.cfg.loss.w_depth)
        terms["total"] = total
        return terms


def late_prior_scale(views: float, views_per_point: Optional[float]) -> float:
    """The priors' weight share after ``loss.prior_late_from``: min(1, n0 / n) for n = ``views_per_point`` training
    views a point and n0 = ``views`` (``loss.prior_late_views``; 0 = off). Why: each view's 2D prior carries the
    single-view denoiser's bias (its blur, its colour), which the n views' copies share, while the n views' noise
    averages out in the reconstruction; past n0 views the priors' total pull is held at n0 views' worth. 1 without
    a count (no SfM points)."""
    if not views or not views_per_point or views_per_point <= views:
        return 1.0
    return float(views) / float(views_per_point)


def build_objective(cfg: Config, model: RetinexGSModel, schedule: Schedule, strategy: Strategy,
                    noise: NoiseSetUp, views_per_point: Optional[Callable[[], Optional[float]]] = None,
                    log: Callable[[str], None] = lambda s: None) -> PlainObjective:
    """RetinexGS's objective for ``method: retinexgs``, the plain one for the 3DGS baselines. The depth prior is
    RetinexGS's (the baselines stay as published). ``views_per_point``: the scene's
    :meth:`retinexgs.data.Scene.views_per_point`, read where ``loss.prior_late_views`` is on."""
    if cfg.method == "retinexgs":
        scale = 1.0
        if cfg.loss.prior_late_views and views_per_point is not None:
            n = views_per_point()
            scale = late_prior_scale(cfg.loss.prior_late_views, n)
            if scale < 1.0:
                log(f"priors: w_r, w_l × {scale:.2f} from step {schedule.prior_late_from} ({n:g} training views see "
                    f"a point; up to {cfg.loss.prior_late_views:g} keep the full weights)")
        return RetinexObjective(cfg, model, schedule, strategy, noise, depth_prior=cfg.loss.w_depth > 0,
                                prior_late_scale=scale)
    return PlainObjective(cfg, model, schedule, strategy, noise)
