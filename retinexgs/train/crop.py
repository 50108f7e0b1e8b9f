"""Full-resolution crops of large views (``train.crop_pixels``, issue 65): a step whose view has more than
``crop_pixels`` pixels trains on a window of it, at full resolution. A step's raster, SSIM filter and per-pixel
losses cost about 10 ms per megapixel at 12 MP (H200), so a 1 MP crop of a 12 MP view costs ~1/12 of a whole-view
step while keeping the full-size detail that the coarse-to-fine schedule (:mod:`retinexgs.train.resolution`) loses.
``0`` (the default) trains every view whole, as before.

The crop of a view of W × H pixels (after ``train.resolution``'s pooling, if any; the view itself where
W·H <= ``crop_pixels``):

- **size** (:func:`crop_size`): w = ⌊W·s⌋, h = ⌊H·s⌋ with s = sqrt(crop_pixels / (W·H)): the view's aspect ratio
  (to a pixel), w·h <= crop_pixels, fixed per view size; each side must be >= :data:`MIN_SIDE` and >=
  ``loss.exp_patch`` (a UserError of one line naming ``train.crop_pixels`` and the view, raised when the trainer is
  built);
- **position** (:meth:`CropPolicy.corner`): the top-left corner uniform over the (W − w + 1) × (H − h + 1) valid
  positions, drawn from a generator seeded by (``seed``, step, view index) alone: a resumed run trains on the
  crops of the uninterrupted one (no generator state to checkpoint), another seed on other crops;
- **camera** (:func:`crop_camera`): cx − x0, cy − y0 and the crop's size; with the pixel-centre convention of
  :class:`~retinexgs.render.Camera` (pixel i covers [i, i + 1)), crop pixel j is whole-view pixel x0 + j. The
  camera also carries the whole view's rectangle (``Camera.frame``): the projection clamps the EWA Jacobian of a
  Gaussian far off-screen to a guard band of 1.3× the image's extent around the principal point, and measured on
  the crop that band would cut through crops away from the principal point (a crop of a 4000 px wide view at its
  right edge: the left 245 px of the crop clamped); measured on the frame, a render of the crop camera is that
  window of the whole-view render, to float round-off;
- **maps** (:func:`crop_view`): S, R, L and a baseline's target sliced (views, no copy; ``target is S`` kept); the
  packed targets and the depth prior's edge weights are rebuilt from the slices when the loss asks for them
  (pointwise differences: the crop's edge weights are the whole view's, sliced).

How the rest of training reads a crop step (each term audited):

- **Density statistic** (default strategy). Every image term is a mean over the step's pixels, so a Gaussian's
  pixel-space gradient on a crop of n of the view's N pixels is N / n times what the whole view's step gives it
  for the same per-pixel error; and the strategy converts pixel gradients to NDC with width / 2, height / 2: the
  crop camera's would give (w / W) of the view's. Uncorrected the statistic would be (N / n)·(w / W) =
  sqrt(N / n) times the whole view's (3.5× for 1 MP of 12 MP) and ``density.grad_threshold`` would densify far
  more. So a crop's :class:`TrainView` carries its view's size (``whole_size``): the trainer hands the strategy
  the whole view's width and height and the pixel share n / N, by which the gradient is multiplied
  (:meth:`retinexgs.strategy.Strategy.after_backward`): the statistic of a crop step equals the whole-view step's
  for a Gaussian inside the crop. The visibility count counts the steps whose crop saw a Gaussian. MCMC keeps no
  gradient statistic (its moves read opacities and scales): nothing to convert.
- **Screen-size prune**: radii (pixels at the view's scale: the crop's pixels are the view's) are compared with a
  fraction of the whole view's size (the trainer's ``image_size`` is the largest whole side of the step's views).
- **Per-pixel means** (L1 terms, the priors' supervision, L_TV, the reconstruction, the exposed SSIM's mean): a
  mean over the crop's pixels is an unbiased sample of the whole view's mean per pixel; with uniform positions
  the expected gradient of a Gaussian is about the whole view's (pixels near the view's border fall in fewer
  crops: the border band of width w is seen less often than the centre).
- **SSIM (11 px window, "same" padding)** and the raw priors' confidence (9 px window, replicate padding): the
  crop's inner edges are padded as the view's edges are, a 5 (4) px band per crop edge differs from the whole
  view's value there; MIN_SIDE (16) is above both windows.
- **Regularisers on the Gaussians** (L_SH, MCMC's L1 on opacity and scale) are per step, not per pixel: their
  balance with the image terms (means per pixel) is that of a whole-view step.
- **Linear reconstruction's weights** (``loss.raw``): ``unit: plain`` normalises the weights to mean 1 per image,
  ``sigma`` scales by the image's mean weight: a crop is normalised as its own image, as every view already is
  (the relative weights within the crop are the view's; crops of dark and bright regions weigh alike, as dark and
  bright views do). The noise model (a, b), the gain cap (``loss.rec_noise_floor``) and the illumination reference
  are measured at set-up on the whole photos: unchanged.
- **Depth prior**: the disparity is divided by its mean over the crop's covered pixels (the term is scale-free by
  design: a crop of near or far content weighs alike, as views do); edge weights as above.
- **Enhancement losses** (from ``loss.enhance_from``): they train the EnhancementNet, which predicts one gamma
  per image from the light it is given, and L_exp with ``exp_patch: 0`` (the default) meters the whole image. On
  a crop the net sees, and L_exp meters, the crop: the net learns to expose each crop as a photo of its own,
  while evaluation gives it the whole view. This is the one term whose meaning a crop changes; crop sides are at
  least ``exp_patch`` (a patched L_exp keeps one patch), and L_spa's 4 px pooling and the highlight meter's share
  read the crop. Left as is for the ablation to measure (configs/ablations/crop_1mp.yaml); if it costs, the
  enhancement terms need a whole (pooled) view.
- **CUDA graphs** are keyed by shape: a view size has one crop size, so a run keeps one graph per view size (the
  crop's) as before; with ``train.resolution`` each stage's pooled size has its own crop size (or none).
- **Streamed views** are cropped on the device after the view's fetch: the host-to-device copy stays whole (~130
  MB for a 12 MP view): the known remaining cost of a crop step on a streamed run.
"""
from __future__ import annotations

import math
from typing import Iterable, Optional, Sequence, Tuple

import numpy as np

from retinexgs.config.schema import Config
from retinexgs.errors import UserError
from retinexgs.render import Camera
from retinexgs.train.resolution import MIN_SIDE
from retinexgs.train.views import TrainView


def crop_size(width: int, height: int, pixels: int) -> Tuple[int, int]:
    """(w, h) of the crop of a ``width`` × ``height`` view to at most ``pixels`` pixels, the view's aspect kept
    (each side ⌊side·s⌋, s = sqrt(pixels / (width·height))); the view's own size where it has at most ``pixels``."""
    if pixels <= 0 or width * height <= pixels:
        return width, height
    s = math.sqrt(pixels / (width * height))
    w, h = int(width * s), int(height * s)
    while w * h > pixels:  # float round-off at an exact fit: shrink the longer side
        if w * height >= h * width:
            w -= 1
        else:
            h -= 1
    return w, h


def crop_camera(camera: Camera, x0: int, y0: int, w: int, h: int) -> Camera:
    """``camera`` for the window [x0, x0 + w) × [y0, y0 + h) of its image: the principal point moves by the
    window's corner (pixel i covers [i, i + 1), so crop pixel j is image pixel x0 + j), focal lengths stay, and
    the frame (the whole image, whose extent the projection's guard band is measured on) moves with it."""
    fx0, fy0, fx1, fy1 = camera.frame_box
    return Camera(camera.viewmat, camera.fx, camera.fy, camera.cx - x0, camera.cy - y0, w, h, camera.near,
                  camera.far, frame=(fx0 - x0, fy0 - y0, fx1 - x0, fy1 - y0))


def crop_view(tv: TrainView, x0: int, y0: int, w: int, h: int) -> TrainView:
    """The window [x0, x0 + w) × [y0, y0 + h) of ``tv``: its camera and sliced maps (views of ``tv``'s), carrying
    ``tv``'s whole size for the density statistics (module docstring); packed targets and edge weights are
    rebuilt from the slices when the loss asks for them."""
    def cut(x):
        return None if x is None else x[y0:y0 + h, x0:x0 + w]

    S = cut(tv.S)
    target = S if tv.target is tv.S else cut(tv.target)
    return TrainView(crop_camera(tv.camera, x0, y0, w, h), S, cut(tv.R), cut(tv.L), target, center=tv.center,
                     whole_size=tv.size)


class CropPolicy:
    """``train.crop_pixels`` for a run: which step trains on which window of which view."""

    def __init__(self, pixels: int, seed: int, min_side: int = MIN_SIDE) -> None:
        """``pixels``: the most pixels a step trains on (0: off); ``seed``: the run's; ``min_side``: the smallest
        crop side allowed."""
        if pixels < 0:
            raise UserError(f"train.crop_pixels must be 0 (off) or a positive number of pixels, got {pixels}")
        self.pixels, self.seed, self.min_side = int(pixels), int(seed), int(min_side)

    @classmethod
    def from_config(cls, cfg: Config, sizes: Iterable[Tuple[int, int]] = (),
                    downsamples: Sequence[int] = (1,)) -> "CropPolicy":
        """The policy of ``cfg``; every view size of ``sizes`` (width, height) at each of ``downsamples``
        (train.resolution's) is checked now, before any step: a crop too small is a UserError."""
        policy = cls(cfg.train.crop_pixels, cfg.seed, max(MIN_SIDE, cfg.loss.exp_patch))
        for index, (W, H) in enumerate(sizes):
            for k in sorted(set(downsamples) | {1}):
                if policy.crops(W // k, H // k):  # a view trained whole is not cropped: nothing to check
                    policy.size_for(W // k, H // k, index)
        return policy

    def crops(self, width: int, height: int) -> bool:
        """Whether a view of ``width`` × ``height`` trains on crops (crops on, and more pixels than a crop)."""
        return self.enabled and width * height > self.pixels

    @property
    def enabled(self) -> bool:
        return self.pixels > 0

    def describe(self) -> str:
        """One line for the training log."""
        return (f"crops: views above {self.pixels} pixels train on a random full-resolution crop of at most that "
                "many (train.crop_pixels)")

    def size_for(self, width: int, height: int, index: int) -> Tuple[int, int]:
        """The crop size of view ``index`` at ``width`` × ``height``; a UserError if a side falls below the floor."""
        w, h = crop_size(width, height, self.pixels)
        if min(w, h) < self.min_side:
            raise UserError(f"train.crop_pixels: {self.pixels} pixels crop training view {index} ({width}x{height}) "
                            f"to {w}x{h}, below {self.min_side} px a side: use more pixels (or 0: off)")
        return w, h

    def corner(self, width: int, height: int, w: int, h: int, step: int, index: int) -> Tuple[int, int]:
        """(x0, y0) of the crop of view ``index`` at ``step``: uniform over the valid positions, from a generator
        seeded by (seed, step, view index) only, so a resumed run draws what the uninterrupted one drew."""
        rng = np.random.default_rng([self.seed, int(step), int(index)])
        x0, y0 = rng.integers(0, width - w + 1), rng.integers(0, height - h + 1)
        return int(x0), int(y0)

    def view_at(self, tv: TrainView, index: int, step: int) -> TrainView:
        """What ``step`` trains on of view ``index`` (``tv``, after train.resolution): ``tv`` itself where it has
        at most ``pixels`` pixels (or crops are off), else its crop."""
        W, H = tv.camera.width, tv.camera.height
        if not self.crops(W, H):
            return tv
        w, h = self.size_for(W, H, index)
        x0, y0 = self.corner(W, H, w, h, step, index)
        return crop_view(tv, x0, y0, w, h)


__all__ = ["CropPolicy", "crop_camera", "crop_size", "crop_view"]
