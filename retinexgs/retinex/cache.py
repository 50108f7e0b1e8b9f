"""Per-scene cache of decompositions on disk.

Layout: ``<root>/<method>-<key>/<stem>-<pathhash>.npz`` where ``root`` defaults to
``<scene>/retinex_cache`` and ``key`` = :func:`retinexgs.retinex.base.cache_key` (method + params +
algorithm version). Each ``.npz`` holds ``R`` [H,W,3] and ``L`` [H,W,1] as float16 plus a JSON ``meta``
string naming the source image, its size and mtime (ns) and the key. An entry is trusted only if all of
these still match, so an edited photo or a changed parameter is recomputed.

Writes are atomic: the file is written under a ``.tmp-`` name in the same folder, flushed and fsynced,
then ``os.replace``d into place. An interrupted run leaves at worst a ``.tmp-`` file, which is never read
(and is swept by a later run once it is an hour old); a file that fails to load is recomputed.
"""
from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path
from typing import Any, Dict, Iterable, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from retinexgs.errors import UserError
from retinexgs.fileio import TMP_PREFIX, atomic_write
from retinexgs.retinex.base import enhance_for_viewing, get_decomposer, params_to_dict

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png")
CACHE_DIRNAME = "retinex_cache"
_TMP_PREFIX = TMP_PREFIX
_STALE_TMP_SECONDS = 3600.0
# Folder names that hold a scene's photos; the default cache goes next to them, in the scene folder.
_IMAGE_FOLDER_NAMES = {"low", "high", "images", "over_exp", "input", "rgb"}

PathLike = Union[str, os.PathLike]


def read_image(path: PathLike) -> torch.Tensor:
    """Read a photo as float32 [H,W,3] in [0,1] (8 or 16 bit, see :mod:`retinexgs.data.images`); raises
    UserError naming the file if it cannot be read."""
    from retinexgs.data.images import load_image_tensor  # local import: keeps ``import retinexgs.retinex`` light

    p = Path(path)
    if not p.is_file():
        raise UserError(f"image not found: {p}")
    return load_image_tensor(p)


def default_cache_root(image_paths: Sequence[PathLike]) -> Path:
    """``<scene>/retinex_cache``: the scene is the photos' common folder, or its parent when that folder
    is a known image folder such as ``low/``."""
    parents = [str(Path(p).resolve().parent) for p in image_paths]
    common = Path(os.path.commonpath(parents)) if parents else Path.cwd()
    if common.name.lower() in _IMAGE_FOLDER_NAMES:
        common = common.parent
    return common / CACHE_DIRNAME


def scene_cache_root(scene_root: PathLike, cache_dir: Optional[PathLike] = None) -> Path:
    """Where ``train`` and ``decompose`` keep a scene's decompositions: ``<cache_dir>/retinex`` when the
    config's ``data.cache_dir`` is set, else ``<scene>/retinex_cache``."""
    return Path(cache_dir) / "retinex" if cache_dir else Path(scene_root) / CACHE_DIRNAME


def entry_dir(cache_root: PathLike, method: str, params: Any = None) -> Path:
    """The folder holding one method+params' entries: ``<root>/<method>-<key>``."""
    dec = get_decomposer(method, params)
    return Path(cache_root) / f"{dec.name}-{dec.cache_key()}"


def _entry_name(image_path: Path) -> str:
    tag = hashlib.sha1(str(image_path.resolve()).encode("utf-8")).hexdigest()[:10]
    return f"{image_path.stem}-{tag}.npz"


def _source_meta(image_path: Path, key: str, method: str) -> Dict[str, Any]:
    st = image_path.stat()
    return {"source": str(image_path.resolve()), "size": int(st.st_size), "mtime_ns": int(st.st_mtime_ns),
            "key": key, "method": method}


def _atomic_write(path: Path, write) -> None:
    """Write via a temp file in the same folder + fsync + os.replace; the temp file never survives an error."""
    atomic_write(path, write)


def save_entry(path: Path, r: torch.Tensor, l: torch.Tensor, meta: Dict[str, Any]) -> None:
    """Atomically store R [H,W,3], L [H,W,1] (float16) and ``meta`` at ``path``."""
    r16 = r.detach().to("cpu", torch.float32).numpy().astype(np.float16)
    l16 = l.detach().to("cpu", torch.float32).numpy().astype(np.float16)
    meta_arr = np.array(json.dumps(meta, sort_keys=True))
    _atomic_write(path, lambda f: np.savez(f, R=r16, L=l16, meta=meta_arr))


def load_entry(path: Path, expected: Dict[str, Any]) -> Optional[Tuple[torch.Tensor, torch.Tensor]]:
    """(R, L) as float32 CPU tensors if ``path`` exists, loads and its meta equals ``expected``; else None."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            if meta != expected:
                return None
            r = torch.from_numpy(z["R"].astype(np.float32))
            l = torch.from_numpy(z["L"].astype(np.float32))
    except Exception:  # truncated or foreign file: recompute rather than trust it
        return None
    if r.dim() != 3 or r.shape[-1] != 3 or l.shape[:2] != r.shape[:2]:
        return None
    return r, l


def _sweep_stale_temps(folder: Path) -> None:
    now = time.time()
    for p in folder.glob(_TMP_PREFIX + "*"):
        try:
            if now - p.stat().st_mtime > _STALE_TMP_SECONDS:
                p.unlink()
        except OSError:
            pass


def _save_preview(path: Path, r: torch.Tensor, l: torch.Tensor, gamma: float = 2.2) -> None:
    from PIL import Image

    img = enhance_for_viewing(r.float(), l.float(), gamma)
    arr = (img.clamp(0, 1).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)
    _atomic_write(path, lambda f: Image.fromarray(arr).save(f, format="PNG"))


def resolve_device(device: Union[str, torch.device, None]) -> torch.device:
    """``cpu``/``cuda``/``cuda:N``/``auto`` (CUDA when available) -> torch.device; UserError if CUDA is asked
    for but not available."""
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    dev = torch.device(device or "cpu")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UserError("--device cuda was requested but torch reports no usable CUDA device "
                        f"(torch {torch.__version__}); use --device cpu")
    return dev


def decompose_images(image_paths: Sequence[PathLike], method: str = "lr3m", params: Any = None,
                     cache_dir: Optional[PathLike] = None, device: Union[str, torch.device] = "cpu", *,
                     keep: bool = True, preview: bool = False, progress: bool = True, cache_hint: str = ""
                     ) -> Tuple[List[Optional[Tuple[torch.Tensor, torch.Tensor]]], Dict[str, Any]]:
    """Make sure every image has a valid cache entry; return (results, report).

    ``results[i]`` is (R, L) on the CPU when ``keep`` else None. ``report`` has ``folder`` (the entry
    folder), ``computed`` and ``reused`` counts and ``files`` (entry paths, in input order).
    ``cache_hint``: the caller's spelling of the cache option, named when the cache cannot be created.
    """
    paths = [Path(p) for p in image_paths]
    if not paths:
        raise UserError("no images to decompose")
    dev = resolve_device(device)
    dec = get_decomposer(method, params)
    root = Path(cache_dir) if cache_dir is not None else default_cache_root(paths)
    folder = root / f"{dec.name}-{dec.cache_key()}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        hint = f"; put the caches elsewhere with {cache_hint}" if cache_hint else ""
        raise UserError(f"cannot create the cache folder {folder}: {exc.strerror or exc}{hint}") from None
    _sweep_stale_temps(folder)
    settings = folder / "params.json"
    if not settings.is_file():  # for humans: what produced this folder
        text = json.dumps({"method": dec.name, "params": params_to_dict(dec.params)}, indent=2, sort_keys=True)
        _atomic_write(settings, lambda f: f.write(text.encode("utf-8")))

    results: List[Optional[Tuple[torch.Tensor, torch.Tensor]]] = []
    files: List[str] = []
    computed = reused = 0
    iterator: Iterable[Path] = paths
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(paths, desc=f"decompose ({dec.name})", unit="view", leave=True)
        iterator = bar
    try:
        for p in iterator:
            if not p.is_file():
                raise UserError(f"image not found: {p}")
            target = folder / _entry_name(p)
            meta = _source_meta(p, dec.cache_key(), dec.name)
            hit = load_entry(target, meta)
            if hit is None:
                image = read_image(p).to(dev)
                try:
                    r, l = dec.decompose(image)
                except ValueError as exc:  # e.g. an all-black photo
                    raise UserError(f"cannot decompose {p}: {exc}") from None
                r, l = r.to("cpu", torch.float32), l.to("cpu", torch.float32)
                save_entry(target, r, l, meta)
                # What later runs will load is the float16 copy: return exactly that.
                hit = (r.half().float(), l.half().float())
                computed += 1
            else:
                reused += 1
            if preview:
                pv = folder / "preview" / f"{target.stem}.png"
                if not pv.is_file() or pv.stat().st_mtime_ns < target.stat().st_mtime_ns:
                    pv.parent.mkdir(exist_ok=True)
                    _save_preview(pv, hit[0], hit[1], 2.2)
            results.append(hit if keep else None)
            files.append(str(target))
    finally:
        if bar is not None:
            bar.close()
    return results, {"folder": str(folder), "computed": computed, "reused": reused, "files": files}


def load_or_compute(image_paths: Sequence[PathLike], method: str = "lr3m", params: Any = None,
                    cache_dir: Optional[PathLike] = None, device: Union[str, torch.device] = "cpu", *,
                    progress: bool = True, cache_hint: str = "") -> List[Tuple[torch.Tensor, torch.Tensor]]:
    """(R [H,W,3], L [H,W,1]) float32 CPU tensors for each image, from the cache or freshly computed.

    ``params``: a params dataclass or a dict of overrides (None = defaults). ``cache_dir``: the cache root
    (default ``<scene>/retinex_cache``, see :func:`default_cache_root`); entries go in
    ``<cache_dir>/<method>-<key>/``. ``device``: where missing entries are computed.
    """
    results, _ = decompose_images(image_paths, method, params, cache_dir, device, keep=True, progress=progress,
                                  cache_hint=cache_hint)
    return [r for r in results if r is not None]
