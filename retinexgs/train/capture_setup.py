"""The capture's noise as training uses it, measured once at set-up (or read from the checkpoint, so that a resume
trains on the same figures): the photos' noise (:mod:`retinexgs.train.noise`) for the reconstruction's gain cap;
on a camera-raw scene the raw views' noise (:mod:`retinexgs.data.raw_noise`) for the linear reconstruction."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Dict, Optional

import torch
from torch import Tensor

from retinexgs.data import Scene
from retinexgs.data.capture import PHOTO, Capture
from retinexgs.data.raw_noise import RawNoise
from retinexgs.model.retinex_model import RetinexGSModel
from retinexgs.model.tone import exposure_gain
from retinexgs.config.schema import Config
from retinexgs.train import losses
from retinexgs.train.noise import CaptureNoise, measure_capture_noise, sigma_limit


@dataclass
class NoiseSetUp:
    """What the capture's noise set up for a run (each None where unused)."""

    capture: Capture = PHOTO                                # the views' kind (photo or camera raw)
    capture_noise: Optional[CaptureNoise] = None            # the photos' noise (a, b)
    rec_gain_cap: Optional[Tensor] = None                   # the reconstruction's gain cap (loss.rec_noise_floor)
    raw_noise: Optional[RawNoise] = None                    # the raw views' noise
    linear_target: Optional[losses.LinearTarget] = None     # the raw reconstruction in linear light

    def state_dict(self) -> Dict[str, object]:
        """The checkpoint's entries (a resume trains on the same figures)."""
        return {"capture_noise": self.capture_noise.state_dict() if self.capture_noise is not None else None,
                "raw_noise": asdict(self.raw_noise) if self.raw_noise is not None else None}


def set_up_noise(cfg: Config, scene: Scene, model: RetinexGSModel, state: Optional[Dict], device: torch.device,
                 dist, log: Callable[[str], None]) -> NoiseSetUp:
    """The run's :class:`NoiseSetUp` (RetinexGS only: the baselines get an empty one). ``dist``: this rank among
    several, or None; ``state``: the checkpoint resumed from, or None."""
    out = NoiseSetUp(capture=scene.capture)
    if cfg.method != "retinexgs":
        return out
    _photo_noise(out, cfg, scene, model, state, device, dist, log)
    _raw_noise(out, cfg, scene, state, device, dist, log)
    return out


def _photo_noise(out: NoiseSetUp, cfg: Config, scene: Scene, model: RetinexGSModel, state: Optional[Dict],
                 device: torch.device, dist, log: Callable[[str], None]) -> None:
    """Where ``loss.rec_noise_floor`` uses it: the reconstruction's gain cap as a device tensor made once (the
    captured CUDA graphs read it)."""
    c = cfg.loss
    if not c.rec_noise_floor:
        return
    saved = (state or {}).get("capture_noise")
    if saved:
        noise = CaptureNoise.from_state(saved)
    else:
        # The user's files where they still exist (undistorted copies hide part of the noise), else the copies.
        noise = measure_capture_noise([v.source_path if v.source_path is not None and Path(v.source_path).is_file()
                                       else v.image_path for v in scene.train],
                                      cfg.data.downscale, device, scale=c.rec_noise_scale)
    if dist is not None and dist.enabled:  # rank 0's figures everywhere (each rank measured the same views)
        noise = dist.broadcast_object(noise, "the capture's noise")
    if noise is None:
        return
    out.capture_noise = noise
    limit = sigma_limit(c.rec_noise_share)
    gain = None
    if c.rec_domain != "photo":  # L_ref: the checkpoint's on a resume (the model's is filled later)
        ref = (state or {}).get("model", {}).get("illum_ref", model.illum_ref)
        gain = float(exposure_gain(ref, ref.new_ones(())))
    log(noise.describe(limit, gain))
    cap = noise.gain_cap(limit)
    if c.rec_domain != "photo" and math.isfinite(cap):
        out.rec_gain_cap = torch.tensor(cap, dtype=torch.float32, device=device)


def _raw_noise(out: NoiseSetUp, cfg: Config, scene: Scene, state: Optional[Dict], device: torch.device, dist,
               log: Callable[[str], None]) -> None:
    """A camera raw scene (issue 52 stage 3b): unless ``loss.raw.mode`` is ``photo``, the reconstruction compares
    R̂∘L̂ with the views' unclipped values in linear light, weighted by the views' noise
    (:class:`retinexgs.train.losses.LinearTarget`; the noise from the DNG NoiseProfile or the mosaic)."""
    mode = out.capture.linear_mode(cfg.loss)  # None: photos, or a raw scene compared as the photos it shows
    if mode is None:
        return
    saved = (state or {}).get("raw_noise")
    if saved:
        noise: Optional[RawNoise] = RawNoise(**saved)
    else:
        noise = out.capture.noise([v.user_path for v in scene.train])
        if noise is not None:
            for note in noise.notes:
                log(f"warning: {note}")
    if dist is not None and dist.enabled:
        noise = dist.broadcast_object(noise, "the raw views' noise")
    if noise is None:  # no flat area anywhere: equal weights (plain least squares in linear light)
        log("warning: the raw views' noise could not be measured: the linear reconstruction weighs pixels equally")
        noise = RawNoise((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), "none")
    out.raw_noise = noise
    d2 = float(cfg.data.downscale) ** 2  # a downscaled view averages d × d pixels
    a = torch.tensor(noise.a, dtype=torch.float32, device=device).reshape(1, 3, 1, 1) / d2
    b = torch.tensor(noise.b, dtype=torch.float32, device=device).reshape(1, 3, 1, 1) / d2
    balance = scene.train[0].balance if scene.train else None
    if balance is not None:  # data.white_balance scaled each channel's light by g: its variance by g·a·y + g²·b
        g = torch.tensor(balance, dtype=torch.float32, device=device).reshape(1, 3, 1, 1)
        a, b = a * g, b * g * g
    c = cfg.loss.raw
    out.linear_target = losses.LinearTarget(mode, a, b, unit=c.unit, prior_snr=float(c.prior_snr))
    binned = float(cfg.data.downscale) > 1
    kappa = out.capture.r_prior_luma(cfg.loss, float(cfg.data.downscale))
    share = {0.0: "colour only", 1.0: "colour and brightness"}.get(kappa, f"colour and {kappa:g} of its brightness")
    key = "loss.raw.r_prior_luma_binned: the views are binned" if binned else "loss.raw.r_prior_luma"
    log(f"raw scene: reconstruction in linear light ({mode}); the reflectance prior supervises R̂'s {share} ({key}); "
        f"{noise.describe()}")
