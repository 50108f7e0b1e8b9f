"""Gaussians as the standard INRIA 3DGS PLY, read by the common 3DGS viewers.

Layout (binary little endian, one ``vertex`` element, float32 properties in this order)::

    x y z  nx ny nz  f_dc_0..2  f_rest_0..(3·(K-1)-1)  opacity  scale_0..2  rot_0..3

``f_rest`` is stored channel-major like the INRIA code (all K-1 higher-order coefficients of R, then of G,
then of B), ``opacity`` is the logit, ``scale_*`` the log of the standard deviations and ``rot_*`` the
quaternion as (w, x, y, z), not necessarily normalised (viewers normalise it). The normals are zeros.

In memory, a Gaussians dict uses the names of :class:`retinexgs.model.gaussians.GaussianModel`'s
parameters: ``means`` [N,3], ``quats`` [N,4], ``log_scales`` [N,3], ``opacity_logits`` [N], ``sh_dc``
[N,1,3] and ``sh_rest`` [N,K-1,3] (coefficient-major, as the model keeps them).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Union

import numpy as np
import torch

from retinexgs.errors import UserError
from retinexgs.fileio import atomic_write

ArrayLike = Union[np.ndarray, torch.Tensor]


def _plyfile():
    try:
        import plyfile
    except ImportError as exc:
        raise UserError("reading and writing PLY files needs the plyfile package: pip install plyfile") from exc
    return plyfile


def property_names(num_sh: int) -> List[str]:
    """The INRIA vertex property names, in order, for ``num_sh`` = (degree + 1)² SH coefficients."""
    rest = 3 * (num_sh - 1)
    return (["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)]
            + [f"f_rest_{i}" for i in range(rest)] + ["opacity"] + [f"scale_{i}" for i in range(3)]
            + [f"rot_{i}" for i in range(4)])


def _np32(x: ArrayLike) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float32)


def ascii_comment(text: str) -> str:
    """``text`` as one line of ASCII for a PLY header (the format allows nothing else): non-ASCII
    characters become ``\\xNN``/``\\uNNNN`` escapes, line breaks become spaces."""
    one_line = " ".join(str(text).splitlines())
    return one_line.encode("ascii", "backslashreplace").decode("ascii")


def write_ply(path: Union[str, Path], gaussians: Dict[str, ArrayLike], comments: Sequence[str] = ()) -> Path:
    """Write a Gaussians dict (see the module docstring) as an INRIA 3DGS PLY, atomically.

    ``comments`` become PLY header comments (e.g. how the colours were made), made ASCII by
    :func:`ascii_comment`. Returns ``path``.
    """
    plyfile = _plyfile()
    means = _np32(gaussians["means"]).reshape(-1, 3)
    n = means.shape[0]
    dc = _np32(gaussians["sh_dc"]).reshape(n, 3)
    rest = _np32(gaussians["sh_rest"]).reshape(n, -1, 3)
    k = rest.shape[1] + 1
    if math.isqrt(k) ** 2 != k:
        raise ValueError(f"sh_rest has {k - 1} coefficients per channel; (degree + 1)² - 1 was expected")
    columns = [means, np.zeros((n, 3), np.float32), dc,
               rest.transpose(0, 2, 1).reshape(n, -1),  # channel-major, as the INRIA code stores f_rest
               _np32(gaussians["opacity_logits"]).reshape(n, 1), _np32(gaussians["log_scales"]).reshape(n, 3),
               _np32(gaussians["quats"]).reshape(n, 4)]
    flat = np.concatenate(columns, axis=1)
    names = property_names(k)
    data = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        data[name] = flat[:, i]
    element = plyfile.PlyElement.describe(data, "vertex")
    ply = plyfile.PlyData([element], text=False, byte_order="<", comments=[ascii_comment(c) for c in comments])
    return atomic_write(path, ply.write)


def read_background(path: Union[str, Path]) -> Optional[torch.Tensor]:
    """The background colour [3] (RGB in [0, 1]) that ``retinexgs export`` records in a PLY's header for a model
    with a background (``model.background: mean``), or None: what the model shows where no Gaussian covers a
    pixel, for a viewer's background."""
    for comment in _plyfile().PlyData.read(str(path)).comments:
        if comment.startswith("background: "):
            try:  # another tool's comment of the same prefix is not ours: skip it
                return torch.tensor([float(x) for x in comment.split()[1:4]]).reshape(3)
            except (ValueError, RuntimeError):
                continue
    return None


def read_near(path: Union[str, Path]) -> Optional[float]:
    """The near plane (in the PLY's world units) that ``retinexgs export`` records for a model with one
    (``model.near_fraction``), or None: no Gaussian closer to the camera is drawn by the model."""
    for comment in _plyfile().PlyData.read(str(path)).comments:
        if comment.startswith("near plane: "):
            try:  # another tool's comment of the same prefix is not ours: skip it
                return float(comment.split()[2])
            except (ValueError, IndexError):
                continue
    return None


def read_ply(path: Union[str, Path]) -> Dict[str, torch.Tensor]:
    """Read an INRIA 3DGS PLY into a Gaussians dict of float32 tensors (names as in the module docstring).

    Properties are found by name, so files with extra properties (or another order) read too; a PLY
    without the Gaussian properties raises a :class:`UserError` naming what is missing.
    """
    plyfile = _plyfile()
    path = Path(path)
    try:
        ply = plyfile.PlyData.read(str(path))
    except OSError as exc:
        raise UserError(f"cannot read {path}: {exc.strerror or exc}") from exc
    except Exception as exc:  # plyfile raises its own PlyParseError and ValueErrors for malformed files
        raise UserError(f"{path} is not a readable PLY file: {exc}") from exc
    if "vertex" not in ply:
        raise UserError(f"{path} has no vertex element; it is not a 3DGS PLY")
    v = ply["vertex"].data
    present = set(v.dtype.names)
    num_rest = sum(1 for name in present if name.startswith("f_rest_"))
    k = num_rest // 3 + 1
    missing = [name for name in property_names(k) if name not in present and not name.startswith("n")]
    if missing or num_rest % 3 or math.isqrt(k) ** 2 != k:
        what = f"missing properties {', '.join(missing[:6])}" if missing else f"{num_rest} f_rest properties"
        raise UserError(f"{path} is not a 3DGS PLY ({what})")

    def cols(names: Sequence[str]) -> torch.Tensor:
        return torch.from_numpy(np.stack([np.asarray(v[name], dtype=np.float32) for name in names], axis=1))

    n = len(v)
    rest = cols([f"f_rest_{i}" for i in range(num_rest)]).reshape(n, 3, k - 1).transpose(1, 2)
    return {
        "means": cols(["x", "y", "z"]),
        "quats": cols([f"rot_{i}" for i in range(4)]),
        "log_scales": cols([f"scale_{i}" for i in range(3)]),
        "opacity_logits": cols(["opacity"]).reshape(n),
        "sh_dc": cols([f"f_dc_{i}" for i in range(3)]).reshape(n, 1, 3),
        "sh_rest": rest.contiguous(),
    }
