"""White balance as an edit of a trained scene's enhanced light, at render time (issue 53).

The edit acts on the enhanced image's linear light (Rec.709 primaries: :func:`retinexgs.model.tone.exposure_linear`
for tone ``exposure``, lin(S_enh) for the gamma tones) before the highlight shoulder and the sRGB curve, as a
3×3 ``balance`` (per-channel gains, or a matrix for a colour temperature; :func:`retinexgs.model.tone.white_balance`).
Every form leaves the green channel of a neutral unchanged (gains are divided by their G), so the exposure edit
stays the one control of brightness. The forms (``render --white-balance``):

- ``as-trained``: no edit (the default; the output is bit for bit what it was without the option).
- ``gains:R,G,B``: those gains, divided by G (``gains:2,2,2`` is as trained: brightness is ``--exposure``'s).
- ``temp:KELVIN[,TINT]``: the light of the trained scene is taken to be a black body of KELVIN (1000..40000) and
  adapted to the scene's own neutral, the black body of :data:`REFERENCE_KELVIN` (≈ D65, the sRGB white the scene
  was trained to): a Bradford chromatic adaptation from the Planckian white of KELVIN to that of 6504 K, as a 3×3
  matrix in linear Rec.709. As in photo editors, a higher KELVIN gives a warmer (redder) image, a lower one a cooler
  image; 6504 is as trained. A diagonal of white-point ratios in linear sRGB cannot reach 1000 K (its white lies
  outside the sRGB gamut: a negative blue), the adaptation in cone space can. TINT (-100..100, default 0) moves
  along green–magenta: R and B times 2^(TINT/200) against G (+100: half a stop towards magenta).
- ``pick:VIEW,X,Y``: the pixel X (column), Y (row) of the render of view VIEW (its image name without suffix)
  is neutral: gains G/R, 1, G/B of its linear colour make it grey.
- ``auto``: grey-edge (van de Weijer, Gevers & Gijsenij, 2007; first order, Minkowski norm 1): the average
  gradient magnitude of each channel of the enhanced linear light over the training views is taken to be
  achromatic, gains G/R, 1, G/B. Why: grey-world (the average colour is grey) was measured worse on every dev
  scene, since a scene is seldom grey on average (a warm façade, a green lawn); edges are: the differences between
  neighbouring surfaces average out the surfaces' own colours far more than their levels do, while a cast of the
  light scales every edge of its channel alike. It is measured on the enhanced light, not on R̂ alone, because a
  cast carried by the coloured illumination L̂ shows in the image the user sees and not in R̂.

The numbers used are recorded beside the outputs (``render``: the PNG text chunk and the EXR header).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Iterable, Optional, Sequence, Tuple

import numpy as np
from torch import Tensor

from retinexgs.data.photo_balance import grey_edge_light
from retinexgs.errors import UserError

__all__ = ["REFERENCE_KELVIN", "KELVIN_RANGE", "TINT_RANGE", "MAX_GAIN_RATIO", "WhiteBalance", "parse_white_balance",
           "normalized_gains", "temperature_matrix", "neutral_gains", "grey_edge_gains", "describe_balance"]

REFERENCE_KELVIN = 6504.0  # the black body nearest D65, sRGB's white: the trained scene's neutral
KELVIN_RANGE = (1000.0, 40000.0)
TINT_RANGE = (-100.0, 100.0)
# Gains R/G and B/G (after the division by G) lie in [1/MAX_GAIN_RATIO, MAX_GAIN_RATIO], 9 stops each way: the
# widest the temperature range reaches on a neutral is B/G = 418 (1000 K, tint +100) and the viewer's gain sliders
# span 0.05..20 (a ratio of 400); a gain beyond it leaves one channel (gains:1e9,1,1 is a red frame), a typo.
MAX_GAIN_RATIO = 512.0
FORMS = "as-trained, auto, gains:R,G,B, temp:KELVIN[,TINT] or pick:VIEW,X,Y"

# CIE 1931 2° colour-matching functions as Wyman, Sloan & Shirley's multi-lobe piecewise Gaussian fit (JCGT 2013),
# ample for white points (their fit is within the CIE tables' own spread of a few 0.001 in xy).
_CMF_LOBES = {
    "x": ((1.056, 599.8, 37.9, 31.0), (0.362, 442.0, 16.0, 26.7), (-0.065, 501.1, 20.4, 26.2)),
    "y": ((0.821, 568.8, 46.9, 40.5), (0.286, 530.9, 16.3, 31.1)),
    "z": ((1.217, 437.0, 11.8, 36.0), (0.681, 459.0, 26.0, 13.8)),
}
# Linear Rec.709 (sRGB) <-> CIE XYZ, D65 white; the Bradford cone response.
_XYZ_FROM_RGB = np.array([[0.4124564, 0.3575761, 0.1804375],
                          [0.2126729, 0.7151522, 0.0721750],
                          [0.0193339, 0.1191920, 0.9503041]])
_BRADFORD = np.array([[0.8951, 0.2664, -0.1614],
                      [-0.7502, 1.7135, 0.0367],
                      [0.0389, -0.0685, 1.0296]])


@dataclass(frozen=True)
class WhiteBalance:
    """A parsed ``--white-balance``: ``kind`` (as-trained, auto, gains, temp, pick), ``text`` (as given), and the
    form's numbers: ``gains`` (gains, normalised to G = 1), ``kelvin``/``tint`` (temp), ``view``/``x``/``y``
    (pick)."""
    kind: str
    text: str
    gains: Optional[Tuple[float, float, float]] = None
    kelvin: Optional[float] = None
    tint: float = 0.0
    view: Optional[str] = None
    x: Optional[int] = None
    y: Optional[int] = None


def _numbers(text: str, what: str, spec: str) -> Sequence[float]:
    try:
        values = [float(t) for t in text.split(",")]
    except ValueError:
        raise UserError(f"--white-balance {spec}: {what} must be numbers separated by commas") from None
    if not all(math.isfinite(v) for v in values):
        raise UserError(f"--white-balance {spec}: {what} must be finite numbers")
    return values


def normalized_gains(gains: Sequence[float], spec: str = "") -> Tuple[float, float, float]:
    """Gains R, G, B (each > 0) divided by G; UserError (naming ``spec``) for a gain ≤ 0 or not finite, or a ratio
    R/G or B/G outside [1/MAX_GAIN_RATIO, MAX_GAIN_RATIO]."""
    if len(gains) != 3 or not all(math.isfinite(g) and g > 0 for g in gains):
        raise UserError(f"--white-balance {spec}: gains must be three positive numbers R,G,B "
                        f"(e.g. gains:1.2,1,0.8), got {','.join(f'{g:g}' for g in gains)}")
    g = float(gains[1])
    out = (float(gains[0]) / g, 1.0, float(gains[2]) / g)
    _check_ratios(out, f"--white-balance {spec}", "a balance that far leaves one colour channel: check the numbers")
    return out


def _check_ratios(gains: Sequence[float], where: str, advice: str) -> None:
    """UserError when R/G or B/G of ``gains`` (G = 1) lies outside [1/MAX_GAIN_RATIO, MAX_GAIN_RATIO]."""
    for name, ratio in (("R/G", gains[0]), ("B/G", gains[2])):
        if not 1.0 / MAX_GAIN_RATIO <= ratio <= MAX_GAIN_RATIO:
            raise UserError(f"{where}: the gain ratio {name} = {ratio:.4g} lies outside 1/{MAX_GAIN_RATIO:g}.."
                            f"{MAX_GAIN_RATIO:g} (9 stops each way, past the widest temperature, 1000 K); {advice}")


def parse_white_balance(text: Optional[str]) -> WhiteBalance:
    """``--white-balance`` text -> :class:`WhiteBalance` (module docstring); a UserError names what is wrong."""
    spec = "as-trained" if text is None else str(text).strip()
    kind, _, rest = spec.partition(":")
    kind = kind.strip().lower()
    if kind in ("as-trained", "auto") and not rest:
        return WhiteBalance(kind, spec)
    if kind == "gains" and rest:
        return WhiteBalance("gains", spec, gains=normalized_gains(_numbers(rest, "the gains", spec), spec))
    if kind == "temp" and rest:
        values = _numbers(rest, "KELVIN[,TINT]", spec)
        if len(values) not in (1, 2):
            raise UserError(f"--white-balance {spec}: give temp:KELVIN or temp:KELVIN,TINT (e.g. temp:5000,10)")
        kelvin, tint = values[0], (values[1] if len(values) == 2 else 0.0)
        if not KELVIN_RANGE[0] <= kelvin <= KELVIN_RANGE[1]:
            raise UserError(f"--white-balance {spec}: the temperature must lie in {KELVIN_RANGE[0]:g}.."
                            f"{KELVIN_RANGE[1]:g} K (the trained scene's neutral is {REFERENCE_KELVIN:g}), "
                            f"got {kelvin:g}")
        if not TINT_RANGE[0] <= tint <= TINT_RANGE[1]:
            raise UserError(f"--white-balance {spec}: the tint must lie in {TINT_RANGE[0]:g}..{TINT_RANGE[1]:g} "
                            f"(+ magenta, - green), got {tint:g}")
        return WhiteBalance("temp", spec, kelvin=kelvin, tint=tint)
    if kind == "pick" and rest:
        m = re.fullmatch(r"\s*(.+?)\s*,\s*([+-]?\d+)\s*,\s*([+-]?\d+)\s*", rest)
        if m is None:
            raise UserError(f"--white-balance {spec}: give pick:VIEW,X,Y with VIEW a view's image name and X, Y "
                            "whole pixel numbers (column, row from the top left), e.g. pick:0001,120,80")
        return WhiteBalance("pick", spec, view=m.group(1), x=int(m.group(2)), y=int(m.group(3)))
    raise UserError(f"unknown --white-balance {spec!r}; choose from {FORMS}")


def _planck_xyz(kelvin: float) -> np.ndarray:
    """XYZ of a black body at ``kelvin``, Y = 1 (Planck's law integrated against the CMFs, 360-830 nm)."""
    lam = np.arange(360.0, 831.0, 1.0)
    spectrum = lam ** -5.0 / np.expm1(1.4388e7 / (lam * kelvin))  # c2 = 1.4388e-2 m·K, λ in nm
    xyz = []
    for lobes in _CMF_LOBES.values():
        cmf = np.zeros_like(lam)
        for a, mu, s1, s2 in lobes:
            s = np.where(lam < mu, s1, s2)
            cmf += a * np.exp(-0.5 * ((lam - mu) / s) ** 2)
        xyz.append(float((cmf * spectrum).sum()))
    xyz = np.asarray(xyz)
    return xyz / xyz[1]


def temperature_matrix(kelvin: float, tint: float = 0.0) -> np.ndarray:
    """[3, 3] float64 acting on linear Rec.709 RGB: the Bradford adaptation from the black body of ``kelvin`` to
    that of :data:`REFERENCE_KELVIN`, then R and B times 2^(tint/200), scaled so a neutral's green is unchanged
    (module docstring). Exactly the identity at (REFERENCE_KELVIN, 0)."""
    if float(kelvin) == REFERENCE_KELVIN and float(tint) == 0.0:
        return np.eye(3)
    src = _BRADFORD @ _planck_xyz(float(kelvin))
    dst = _BRADFORD @ _planck_xyz(REFERENCE_KELVIN)
    adapt = np.linalg.inv(_BRADFORD) @ np.diag(dst / src) @ _BRADFORD
    m = np.linalg.inv(_XYZ_FROM_RGB) @ adapt @ _XYZ_FROM_RGB
    t = 2.0 ** (float(tint) / 200.0)
    m = np.diag([t, 1.0, t]) @ m
    return m / (m @ np.ones(3))[1]


def neutral_gains(colour: Sequence[float], where: str) -> Tuple[float, float, float]:
    """Gains G/R, 1, G/B that make the linear colour ``colour`` grey; UserError (naming ``where``) when a channel
    is about black (below 1e-4 of the default exposure's white: its ratio is noise)."""
    c = [float(v) for v in colour]
    if min(c) < 1e-4:
        raise UserError(f"--white-balance {where}: the picked pixel is black (linear {c[0]:.2g}, {c[1]:.2g}, "
                        f"{c[2]:.2g}) and has no colour to neutralise; pick a brighter neutral (grey or white) "
                        "surface")
    gains = (c[1] / c[0], 1.0, c[1] / c[2])
    _check_ratios(gains, f"--white-balance {where}", "the picked pixel is strongly coloured, not a neutral: pick a "
                  "grey or white surface")
    return gains


def grey_edge_gains(images: Iterable[Tensor]) -> Tuple[float, float, float]:
    """Grey-edge gains (module docstring) of linear images [H,W,3] (H, W ≥ 2): per channel the mean over all
    pixels of all images of the gradient magnitude (forward differences), e; gains e_G/e_R, 1, e_G/e_B. Summed in
    float64 in a fixed order: deterministic. UserError when the images have no edges in some channel."""
    e = grey_edge_light(images)  # the same sums as the training-time balance of the photos (data.white_balance)
    if min(e) <= 1e-12:
        raise UserError("--white-balance auto: the training views' renders have no edges to estimate a white "
                        "balance from (a flat or black render); give gains:R,G,B, temp:KELVIN or pick:VIEW,X,Y")
    return (e[1] / e[0], 1.0, e[1] / e[2])


def describe_balance(wb: WhiteBalance, balance: Optional[np.ndarray]) -> str:
    """One line for the outputs' metadata and the log: the form given and the numbers used."""
    if balance is None:
        return f"white balance {wb.text}: none (as trained)"
    b = np.asarray(balance, dtype=np.float64)
    if b.ndim == 1:
        nums = "gains R,G,B = " + ", ".join(f"{v:.6g}" for v in b.tolist())
    else:
        nums = "matrix (linear Rec.709, rows R,G,B) = " + "; ".join(
            ", ".join(f"{v:.6g}" for v in row) for row in b.tolist())
    return f"white balance {wb.text}: {nums}, in linear light before the highlight shoulder and the sRGB curve"
