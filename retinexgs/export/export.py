"""``retinexgs export``: a trained run as a standard INRIA 3DGS PLY in the input's world frame.

For RetinexGS runs the illumination and the enhancement are baked into the SH colours (see
:mod:`retinexgs.export.bake` for the method and what it cannot reproduce); ``reflectance_only`` exports
R̂'s SH instead. For the plain-3DGS baselines the Gaussians' SH already are the rendered colours and are
exported as they are (the ``post`` baseline's 2D LR3M enhancement cannot go into a PLY and is left out).

``white_balance`` (``export --white-balance``, the forms of ``render --white-balance``:
:mod:`retinexgs.model.white_balance`) is baked as the exposure is: applied to the enhanced colour's linear light
before the highlight shoulder and the sRGB curve (:func:`retinexgs.export.bake.enhanced_colour`), and recorded in
the PLY's colour comment beside the exposure. It needs the enhanced bake: with ``reflectance_only`` or a baseline
it is refused (R̂ is the surfaces' colour without their light, and the white balance is an edit of the light:
balancing R̂ would change what a relighting or a material edit reads as the albedo; a baseline's SH hold sRGB
colours as trained, not linear light to balance).
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional

import torch

from retinexgs.errors import UserError
from retinexgs.export import DEFAULT_DIRECTIONS
from retinexgs.export.bake import (baked_colour_text, bake_enhanced_sh, enhanced_colour, export_params, mean_gamma,
                                   reflectance_sh)
from retinexgs.export.common import check_enhancement_flags, read_run_config, refuse_existing
from retinexgs.fileio import check_writable_file
from retinexgs.export.ply import write_ply
from retinexgs.model.tone import apply_exposure
from retinexgs.model.white_balance import describe_balance, parse_white_balance
from retinexgs.run.folder import load_run
from retinexgs.run.render import active_sh_degree, view_camera, white_balance_of


def export_run(run_dir: Path, out: Path, reflectance_only: bool = False, directions: int = DEFAULT_DIRECTIONS,
               exposure: Optional[float] = None, gamma: Optional[float] = None, device: Optional[str] = None,
               force: bool = False, progress: bool = True, log: Callable[[str], None] = print,
               white_balance: Optional[str] = None) -> Path:
    """Write the run's Gaussians to the PLY ``out`` (refused if it exists unless ``force``); returns ``out``.

    The baked gamma is the mean the EnhancementNet predicts over the training views, adjusted by ``exposure``
    or replaced by ``gamma``; ``directions`` is the number of view directions of the SH fit. ``white_balance``:
    the ``--white-balance`` text (None: as trained), baked in linear light before the shoulder (module docstring).
    """
    run_dir, out = Path(run_dir), Path(out)
    wb = parse_white_balance(white_balance)  # first: a typo costs no config read
    cfg = read_run_config(run_dir)
    check_enhancement_flags(cfg, run_dir, exposure, gamma)
    bake = cfg.method == "retinexgs" and not reflectance_only
    if reflectance_only and (exposure is not None or gamma is not None):
        raise UserError("--reflectance-only exports R̂ without illumination; --exposure/--gamma do not apply")
    if wb.kind != "as-trained" and reflectance_only:
        raise UserError(f"--white-balance {wb.text}: --reflectance-only exports R̂, the surfaces' colour without "
                        "their light, and a white balance edits the light; drop one of the two")
    if wb.kind != "as-trained" and cfg.method != "retinexgs":
        raise UserError(f"--white-balance {wb.text} needs a RetinexGS run, but {run_dir} was trained with "
                        f"method={cfg.method} (its PLY holds the SH colours as trained, with no linear light to "
                        "balance); render --white-balance applies it to the baseline's images")
    k = (int(cfg.model.sh_degree) + 1) ** 2
    if bake and directions < k:
        raise UserError(f"--directions must be at least {k} to fit the run's degree-{cfg.model.sh_degree} "
                        f"SH ({k} coefficients), got {directions}")
    if out.is_dir():  # --force replaces a file, never a folder: do not suggest it
        raise UserError(f"--out {out} is a folder; --out is the .ply file to write, e.g. "
                        f"--out {out / 'point_cloud.ply'}")
    refuse_existing([out], force)
    check_writable_file(out)  # before the model load and the bake, which take the time

    cfg, scene, model, step = load_run(run_dir, device)
    degree = active_sh_degree(cfg, step)
    comments = [f"retinexgs export of {run_dir.name} (step {step}, method {cfg.method})",
                f"world frame: normalisation undone (center {scene.normalization.center.tolist()}, "
                f"scale {scene.normalization.scale})"]
    balance = None
    if bake:
        if gamma is not None:
            g = torch.full((3,), float(gamma), dtype=torch.float64)
        else:
            if not scene.train:
                raise UserError(f"the scene of {run_dir} has no train views to average the gamma over; "
                                "pass --gamma G")
            g = mean_gamma(model, (view_camera(v) for v in scene.train), degree)
            if exposure is not None:
                g = apply_exposure(g, float(exposure), model.illum_ref.to(g), model.tone)
        # auto and pick measure renders of the scene at the same exposure/gamma, as render --white-balance does
        balance = white_balance_of(wb, model, cfg, scene, degree, exposure, gamma)
        if balance is not None:
            log(describe_balance(wb, balance))
            balance = torch.as_tensor(balance, dtype=torch.float32)
            eye = torch.ones(3) if balance.dim() == 1 else torch.eye(3)
            balance = None if torch.equal(balance, eye) else balance  # as trained: bit for bit the plain bake
        from tqdm import tqdm
        with tqdm(total=len(model.gaussians), desc="bake", unit="gaussian", disable=not progress,
                  dynamic_ncols=True) as bar:
            sh = bake_enhanced_sh(model, degree, g, directions, progress=bar.update, balance=balance)
        # the run's own tone, not one fixed formula; the white balance beside the exposure's numbers
        comments.append(baked_colour_text(model, g, directions, wb, balance))
    else:
        sh = reflectance_sh(model, degree)
        comments.append("colour: reflectance R (SH as trained)" if cfg.method == "retinexgs" else
                        f"colour: the {cfg.method} baseline's SH as trained")
        if cfg.method == "post":
            log("note: the post baseline's 2D LR3M enhancement is applied to images and is not in the PLY")
    if model.has_background:  # model.background "mean": what the model shows where nothing is
        bg = model.background.detach().float()
        rgb = (enhanced_colour(model, bg[None, :3], bg[None, 3:6], g.to(bg), balance)[0] if bake
               else bg[:3]).clamp(0, 1)
        text = " ".join(f"{x:.4f}" for x in rgb.tolist())
        comments.append(f"background: {text} (RGB in [0, 1]: the model's colour where no Gaussian covers a pixel; "
                        "set a viewer's background to it)")
        log(f"background colour (set your viewer's background to it; the model renders it where no Gaussian "
            f"covers a pixel): RGB {text}, #{''.join(f'{round(255 * x):02x}' for x in rgb.tolist())}")
    near = model.near_plane()
    if near > 0:  # model.near_fraction: in the PLY's (the input's) world units, as its centres are
        world = near / scene.normalization.scale
        comments.append(f"near plane: {world:.6g} (the model draws no Gaussian closer to the camera; set a viewer's "
                        "near plane to it)")
        log(f"near plane {world:.6g} (input units): set your viewer's near plane to it; the model draws no Gaussian "
            "closer to the camera")
    params = export_params(model, scene.normalization, sh)
    write_ply(out, params, comments)
    log(f"wrote {len(model.gaussians)} Gaussians (SH degree {model.gaussians.sh_degree}) to {out}")
    return out
