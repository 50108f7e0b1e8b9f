"""A coarse-to-fine resolution schedule for training (``train.resolution``, issue 65): early steps train on
area-downsampled views, late steps on the full-size ones. The early steps place and grow the Gaussians; the
raster backward, the SSIM filter and the per-pixel losses of such a step cost ~1/k² of a full-size one.

The config is a list of ``[until, downsample]`` pairs (``until``: a schedule point, a fraction of ``steps`` or an
absolute step; ``downsample``: an integer k >= 1): step s trains at 1/k of the first pair whose ``until`` >= s,
at full size after the last. ``[]`` trains at full size throughout.

Large views only (``train.resolution_min_pixels``): a view of fewer pixels trains at full size throughout. The
schedule pays where a view is large: on the 12 MP raw scene the default's ``[[0.8, 4], [0.95, 2]]`` scored above
full size throughout (PSNR +0.28 dB, 2 seeds) at 3.5x the steps/s, while on the same DNGs at 3 MP (half size) even
1/2 until 95 % lost 0.40 dB (2 seeds), and on fox-dark (0.23 MP) no schedule saved time. The default's 6 MP is the
geometric middle of the two sizes measured (at 6 MP itself the schedule was level on PSNR, 2 seeds); views of
1920 x 1080 or 2000 x 1500 train exactly as without a schedule
(experiments/notes/2026-11-30-resolution-large-views.md).

A view downsampled by k (:func:`downscale_view`):

- its maps (S, R, L, the baselines' target) are k × k area means (``avg_pool2d``, stride k). A side that k does
  not divide is **cropped** at the right and bottom edge (at most k − 1 pixels, for those steps only), never
  padded: padding would put pixels no camera saw into the loss, and a crop at the far edges leaves the pixel
  grid's origin where it was, so the principal point stays exact (:func:`downscale_camera`);
- its camera has fx, fy, cx, cy divided by k and the cropped size // k: with the pixel-centre convention of
  :class:`~retinexgs.render.Camera` (pixel i covers [i, i + 1)), pooled pixel j covers full-size pixels
  [jk, jk + k), so a point at u projects to u / k, inside the pooled pixel that holds its full-size pixel;
- the depth prior's edge weights are rebuilt from the pooled R (lazily, by :meth:`TrainView.edge_weights` and
  :meth:`TrainView.pack`, as for a full-size view).

Preloaded views are pooled once per (view, downsample) and kept on the device while that stage lasts (at 1/k a
view costs 1/k² of its full-size memory; a stage's copies are freed when the schedule leaves it). Streamed views
live in reused slots valid for one step; a stage whose pooled views all fit ``train.views_on_device_gb`` (the budget
the full-size views did not fit) keeps their pooled copies too, so that each view crosses to the device once a stage
instead of every step (a 12 MP view is ~130 MB a step, the pooled one at 1/4 ~8 MB once); a stage they do not fit
pools every step its view is used (a few kernels), keeping nothing.

How the rest of training reads a downscaled step:

- **Noise.** A k × k mean divides the per-pixel noise variance by k². The gain cap (``loss.rec_noise_floor``) is
  measured at full size, where the noise is k times larger than in a pooled view: the cap is lower than a pooled
  view needs, which is conservative (the exposed SSIM copies less noise, never more). A raw scene's linear
  reconstruction: its default weights (``loss.raw.unit: plain``) are normalised to mean 1, so a uniform 1/k² of the
  variance leaves them as they are; ``unit: sigma`` pulls 1/k as hard as the pooled noise would allow (weaker:
  conservative); ``prior_snr`` describes the 2D priors' own window of full-size pixels, whose noise is the
  full-size variance: right as it is.
- **Density statistics.** The strategy converts the 2D means' pixel gradients to NDC (× width / 2, height / 2 of
  the step's camera, which is the pooled one): the loss is a mean over pixels, so its gradient with respect to an
  NDC position does not depend on the pixel count, and ``density.grad_threshold`` keeps its meaning. The
  screen-size prune's running maximum of radii (pixels) mixes the stages' sizes; stages go coarse to fine (the
  downsample never grows along the schedule), so a coarse radius compared with a finer image size prunes less,
  never more.
- **CUDA graphs.** The image losses' graphs are keyed by shape (:class:`~retinexgs.train.graphs.LossGraphs`):
  each stage's size gets its own graph (a capture at the stage's first step), i.e. a few more graphs per view
  size; past ``max_graphs`` shapes (mixed-size scenes with several stages) a size trains eagerly, with one line
  in the log.
"""
from __future__ import annotations

from typing import Callable, Dict, List, Optional, Sequence, Tuple, Union

import torch.nn.functional as F
from torch import Tensor

from retinexgs.config.schema import Config
from retinexgs.errors import UserError
from retinexgs.model.schedule import at_step
from retinexgs.render import Camera
from retinexgs.train.views import TrainView

# The smallest side a pooled view may have: the SSIM window (11 px) and the noise estimate need a few pixels.
MIN_SIDE = 16


def pool_map(x: Tensor, k: int) -> Tensor:
    """[H,W,C] -> [H // k, W // k, C]: k × k area means, the right and bottom edges cropped to multiples of k."""
    if k == 1:
        return x
    H, W = x.shape[0] // k * k, x.shape[1] // k * k
    y = F.avg_pool2d(x[:H, :W].permute(2, 0, 1).unsqueeze(0), k)
    return y[0].permute(1, 2, 0).contiguous()


def downscale_camera(camera: Camera, k: int) -> Camera:
    """``camera`` for its image area-pooled by k (cropped to multiples of k at the right and bottom): focal
    lengths and principal point / k (the pixel grid's origin stays put), size // k."""
    if k == 1:
        return camera
    return Camera(camera.viewmat, camera.fx / k, camera.fy / k, camera.cx / k, camera.cy / k,
                  camera.width // k, camera.height // k, camera.near, camera.far)


def downscale_view(tv: TrainView, k: int) -> TrainView:
    """``tv`` downsampled by k (module docstring): its camera and maps; packed targets and edge weights are
    rebuilt from the pooled maps when the loss asks for them."""
    if k == 1:
        return tv
    S = pool_map(tv.S, k)
    R = pool_map(tv.R, k) if tv.R is not None else None
    L = pool_map(tv.L, k) if tv.L is not None else None
    if tv.target is None or tv.target is tv.S:
        target = S if tv.target is not None else None
    else:
        target = pool_map(tv.target, k)
    return TrainView(downscale_camera(tv.camera, k), S, R, L, target, center=tv.center)


class ResolutionSchedule:
    """``train.resolution`` resolved for a run of ``steps``: the downsample of each step and the views at it."""

    def __init__(self, stages: Sequence[Tuple[int, int]], steps: int, min_pixels: int = 0,
                 sizes: Optional[Sequence[Tuple[int, int]]] = None) -> None:
        """``stages``: (until step, downsample k) pairs, in order: ``until`` not decreasing and k not increasing
        (coarse to fine); a UserError (one line) names the first pair that is not. ``min_pixels``
        (``train.resolution_min_pixels``): a view of fewer pixels trains at full size throughout. ``sizes``: the
        training views' (width, height), for :attr:`enabled`, :meth:`describe` and :meth:`plan_streamed` (None: as
        if every view were pooled by its stage's k)."""
        self.steps = int(steps)
        self.min_pixels = int(min_pixels)
        self.sizes = [(int(w), int(h)) for w, h in sizes] if sizes is not None else None
        pairs = [(int(u), int(k)) for u, k in stages]
        for (u0, k0), (u1, k1) in zip(pairs, pairs[1:]):
            if u1 < u0:
                raise UserError(f"train.resolution: the steps must increase, got step {u1} after step {u0} (decimals "
                                "are fractions of steps, integers are steps)")
            if k1 > k0:
                raise UserError(f"train.resolution: the downsample must not grow along the run (coarse to fine), "
                                f"got {k1} after {k0}")
        # A stage ending where the one before it ends trains no step (the default's 0.8 and 0.95 in a run of a
        # few steps): dropped, as is one ending at step 0.
        self.stages: List[Tuple[int, int]] = []
        for u, k in pairs:
            if u > (self.stages[-1][0] if self.stages else 0):
                self.stages.append((u, k))
        self._cache: Dict[int, TrainView] = {}  # view index -> pooled view, for the current downsample
        self._cache_k = 1
        self._keep_streamed: Dict[int, bool] = {}  # downsample -> whether a streamed run keeps its pooled views
        self._checked: set = set()  # (view index, k) whose pooled size was checked

    @classmethod
    def from_config(cls, cfg: Config, sizes: Optional[Sequence[Tuple[int, int]]] = None) -> "ResolutionSchedule":
        """The schedule of ``cfg.train.resolution`` for ``cfg.steps`` (``sizes``: the training views')."""
        return cls([(at_step(u, cfg.steps), k) for u, k in cfg.train.resolution], cfg.steps,
                   cfg.train.resolution_min_pixels, sizes)

    def on_schedule(self, width: int, height: int) -> bool:
        """Whether a view of ``width`` x ``height`` trains on the schedule (it has ``min_pixels`` or more); a view
        that does not trains at full size throughout."""
        return width * height >= self.min_pixels

    def plan_streamed(self, bytes_per_pixel: int, budget_gb: float) -> None:
        """For streamed views (:attr:`sizes`; None: keep none): keep a stage's pooled views on the device where they
        fit ``budget_gb`` (10^9 bytes, ``train.views_on_device_gb``) at ``bytes_per_pixel`` (a preloaded view's)."""
        if self.sizes is None:  # nothing to size the pooled views by: keep none
            self._keep_streamed = {}
            return
        pixels = {k: sum((w // k) * (h // k) for w, h in self.sizes if self.on_schedule(w, h))
                  for _, k in self.stages if k > 1}
        self._keep_streamed = {k: n * bytes_per_pixel <= budget_gb * 1e9 for k, n in pixels.items()}

    def keeps_streamed(self, k: int) -> bool:
        """Whether a streamed run keeps the pooled views of downsample ``k`` (:meth:`plan_streamed`)."""
        return self._keep_streamed.get(k, False)

    @property
    def enabled(self) -> bool:
        """Whether any step trains a view below full size (:attr:`sizes` None: whether any stage's k > 1)."""
        return any(k > 1 for _, k in self.stages) and (
            self.sizes is None or any(self.on_schedule(w, h) for w, h in self.sizes))

    def downsample_at(self, step: int) -> int:
        """The stage's k of ``step`` (1-based): the first stage whose ``until`` >= step, else 1 (full size). A view
        trains at it where it is :meth:`on_schedule`, else at full size."""
        for until, k in self.stages:
            if step <= until:
                return k
        return 1

    def describe(self) -> str:
        """One line for the training log."""
        floor = f"train.resolution_min_pixels={self.min_pixels}"
        if not self.enabled:
            unpooled = any(k > 1 for _, k in self.stages)
            return "resolution: full size throughout" + (f" (every view below {floor})" if unpooled else "")
        # enabled: some view is on the schedule; a mixed scene trains its others at full size throughout
        mixed = self.sizes is not None and not all(self.on_schedule(w, h) for w, h in self.sizes)
        parts = [("full size" if k == 1 else ("full size or " if mixed else "") + f"1/{k}") + f" until step {u}"
                 for u, k in self.stages]
        return ("resolution: " + ", ".join(parts) + ", full size after"
                + (f" (views below {floor} at full size)" if mixed else ""))

    def forget_views(self) -> None:
        """Drop the pooled views kept for the current stage (their full-size views changed)."""
        self._cache.clear()

    def view_at(self, tv: Union[TrainView, Callable[[], TrainView]], index: int, step: int,
                cache: bool = True) -> TrainView:
        """The view ``tv`` (view ``index`` of the run; or a function that fetches it, called only when it is
        needed) as ``step`` trains on it: the view itself at full size, else its downscaled twin, kept on the device
        for the stage's later steps where ``cache`` (preloaded views) or :meth:`keeps_streamed` (streamed views
        whose pooled copies fit the device budget); otherwise pooled every time (a streamed view's slot is reused)."""
        k = self.downsample_at(step)
        if k != self._cache_k:  # a new stage: the previous one's pooled views are not needed again
            self._cache.clear()
            self._cache_k = k
        if k == 1:
            return tv() if callable(tv) else tv
        keep = cache or self.keeps_streamed(k)
        pooled: Optional[TrainView] = self._cache.get(index) if keep else None
        if pooled is None:
            full = tv() if callable(tv) else tv
            if not self.on_schedule(full.camera.width, full.camera.height):
                return full  # below train.resolution_min_pixels: this view trains at full size throughout
            if (index, k) not in self._checked:
                W, H = full.camera.width // k, full.camera.height // k
                if min(W, H) < MIN_SIDE:
                    raise UserError(f"train.resolution: downsample {k} makes training view {index} "
                                    f"({full.camera.width}x{full.camera.height}) {W}x{H}, below {MIN_SIDE} px a "
                                    "side: use a smaller downsample")
                self._checked.add((index, k))
            pooled = downscale_view(full, k)
            if keep:
                self._cache[index] = pooled
        return pooled


__all__ = ["ResolutionSchedule", "downscale_view", "downscale_camera", "pool_map", "MIN_SIDE"]
