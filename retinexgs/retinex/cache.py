"""Per-scene cache of decompositions on disk.

Layout: ``<root>/<method>-<key>/<stem>-<contenthash>.npz`` where ``root`` defaults to
``<scene>/retinex_cache``, ``key`` = :func:`retinexgs.retinex.base.cache_key` (method + params +
algorithm version) and ``contenthash`` = the first 16 hex digits of the SHA-256 of the photo's bytes. Each
``.npz`` holds ``R`` [H,W,3] and ``L`` [H,W,1] as float16 plus a JSON ``meta`` string with the content hash,
byte size, method and key (and the photo's name, for humans). An entry is found by its content hash (under
any stem) and trusted only if its meta matches, so an edited photo or a changed parameter is recomputed,
while a copied, moved or renamed scene reuses its entries. Complete entries are never deleted on their own:
another resolution (``data.downscale``), other settings or another scene sharing the root (``data.cache_dir``)
may want them back. With ``sweep=True`` (``train``, ``decompose``) only entries of the older path-keyed format
(``<stem>-<10 hex>.npz``, never read by anyone) are deleted, and the entries these photos do not use at these
settings are counted (:func:`unused_entries`): ``train`` prints one line about them, ``decompose`` too, and
``retinexgs decompose --prune`` deletes them (:func:`prune_unused`). :func:`clean_cache` removes all of it,
:func:`cache_summary` describes it (``retinexgs decompose --clean`` / ``--info``).
The root also holds the trainer's view stores, ``views-<settings>-<8 hex>.bin`` (the photos and priors of a
scene's training views in one memory-mapped file, :mod:`retinexgs.train.view_store`); :func:`clean_cache` removes
them too.

Writes are atomic: the file is written under a ``.tmp-`` name in the same folder, flushed and fsynced,
then ``os.replace``d into place. An interrupted run leaves at worst a ``.tmp-`` file, which is never read
(and is swept by a later run once it is an hour old); a file that fails to load is recomputed.
"""
from __future__ import annotations

import errno
import json
import hashlib
import os
import re
import sys
import time
from pathlib import Path
from typing import Any, Dict, Iterable, Iterator, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from retinexgs.errors import UserError
from retinexgs.fileio import TMP_PREFIX, atomic_write
from retinexgs.retinex.base import enhance_for_viewing, get_decomposer, params_to_dict
from retinexgs.data.images import holds_unclipped, load_image_tensor
from retinexgs.data.photo_balance import balance_photo
from retinexgs.data.raw_noise import PREVIEW_RADIUS, denoised_preview
from retinexgs.data.undistort import image_key
from retinexgs.retinex.denoise import DENOISED_DIRNAME, DenoiseSpec, denoised_view

from retinexgs.data.images import IMAGE_EXTENSIONS  # the one list of readable types (data/images.py)
CACHE_DIRNAME = "retinex_cache"
_TMP_PREFIX = TMP_PREFIX
_STALE_TMP_SECONDS = 3600.0
# Folder names that hold a scene's photos; the default cache goes next to them, in the scene folder.
_IMAGE_FOLDER_NAMES = {"low", "high", "images", "over_exp", "input", "rgb"}

PathLike = Union[str, os.PathLike]


def read_image(path: PathLike, raw_denoise: bool = False, balance: Optional[Sequence[float]] = None,
               denoise: Optional[DenoiseSpec] = None, cache_root: Optional[PathLike] = None,
               cache_hint: str = "") -> torch.Tensor:
    """Read a photo as float32 [H,W,3] in [0,1] (8 or 16 bit, see :mod:`retinexgs.data.images`); raises
    UserError naming the file if it cannot be read. ``raw_denoise`` (``decomposer.raw.preview_denoise``): a camera raw
    view (or its float copy) is read as :func:`retinexgs.data.raw_noise.denoised_preview` of its unclipped values.
    ``balance``: the photo's white balance (``data.white_balance``, :func:`retinexgs.data.photo_balance.balance_photo`),
    applied to its light first. ``denoise`` (``decomposer.denoise``, not ``none``): every photo, raw or not, is read
    through :func:`retinexgs.retinex.denoise.denoised_view` instead (the raw preview's filter is then not used),
    cached under ``cache_root`` by the photo's content."""

    p = Path(path)
    if not p.is_file():
        raise UserError(f"image not found: {p}")
    if denoise is not None and denoise.method != "none":
        raw = holds_unclipped(p)
        image = balance_photo(load_image_tensor(p, unclipped=raw), balance, unclipped=raw)
        return denoised_view(p, image, denoise.noise, denoise.method, raw, cache_root, denoise.params,
                             content=prior_key(p, False, balance), hint=cache_hint, backend=denoise.backend,
                             device=denoise.device)[0]
    if raw_denoise and holds_unclipped(p):
        return denoised_preview(balance_photo(load_image_tensor(p, unclipped=True), balance, unclipped=True))
    return balance_photo(load_image_tensor(p), balance)


def prior_key(path: PathLike, raw_denoise: bool = False, balance: Optional[Sequence[float]] = None,
              denoise: Optional[DenoiseSpec] = None) -> str:
    """What a photo's entry is keyed by: :func:`content_hash`, and for a raw view read through the denoised
    preview also that preview's recipe (its window), so the clipped photo's priors and the preview's never mix;
    a balanced photo's (``data.white_balance``) also by its gains; a photo read through the denoiser
    (``decomposer.denoise``) also by its recipe (method, settings, noise model)."""
    digest = content_hash(path)
    if denoise is not None and denoise.method != "none":
        digest = hashlib.sha256(f"{digest}:denoise-{denoise.recipe}".encode()).hexdigest()[:_HASH_LEN]
    elif raw_denoise and holds_unclipped(Path(path)):
        digest = hashlib.sha256(f"{digest}:raw-preview-wiener-r{PREVIEW_RADIUS}".encode()).hexdigest()[:_HASH_LEN]
    if balance is not None:
        gains = ",".join(f"{float(v):.9g}" for v in balance)
        digest = hashlib.sha256(f"{digest}:balance-{gains}".encode()).hexdigest()[:_HASH_LEN]
    return digest


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


# Names this module writes, and nothing else is ever deleted: settings folders ``<method>-<12 hex>``,
# entries ``<stem>-<16 hex>.npz`` (content-keyed; ``<stem>-<10 hex>.npz``: the older path-keyed format),
# their previews ``preview/<entry stem>.png`` and each folder's ``params.json``.
_SETTINGS_DIR = re.compile(r"^[a-z0-9_]+-[0-9a-f]{12}$")
_ENTRY = re.compile(r"^.+-(?P<hash>[0-9a-f]{16}|[0-9a-f]{10})\.npz$")
_HASH_LEN = 16
# The trainer's view stores in the root (retinexgs.train.view_store names them so).
_VIEW_STORE = re.compile(r"^views-[a-z0-9_]+(-[0-9a-f]{12})?-[0-9a-f]{8}\.bin$")
_UNWRITABLE = (errno.EROFS, errno.EACCES, errno.EPERM)


def content_hash(image_path: PathLike) -> str:
    """The first 16 hex digits of the SHA-256 of the file's bytes: what an entry is keyed by (memoised within
    the process while the file is unchanged, so the view store's key does not read the photos again)."""
    return image_key(Path(image_path))


def _entry_name(image_path: Path, digest: str) -> str:
    return f"{image_path.stem}-{digest}.npz"


def _source_meta(image_path: Path, key: str, method: str, digest: str) -> Dict[str, Any]:
    """What an entry must record to be trusted for this photo and these settings."""
    return {"content": digest, "size": int(image_path.stat().st_size), "key": key, "method": method}


def _atomic_write(path: Path, write, hint: str = "") -> None:
    """Write via a temp file in the same folder + fsync + os.replace; the temp file never survives an error.
    A cache folder that cannot be written (read-only scene) or a full disk -> UserError naming ``hint``."""
    try:
        atomic_write(path, write, elsewhere=hint)
    except OSError as exc:
        if exc.errno not in _UNWRITABLE:
            raise
        where = f"; put the caches elsewhere with {hint}" if hint else ""
        raise UserError(f"cannot write the cache folder {path.parent}: {exc.strerror or exc}{where}") from None


def save_entry(path: Path, r: torch.Tensor, l: torch.Tensor, meta: Dict[str, Any], hint: str = "") -> None:
    """Atomically store R [H,W,3], L [H,W,1] (float16) and ``meta`` at ``path``."""
    r16 = r.detach().to("cpu", torch.float32).numpy().astype(np.float16)
    l16 = l.detach().to("cpu", torch.float32).numpy().astype(np.float16)
    meta_arr = np.array(json.dumps(meta, sort_keys=True))
    _atomic_write(path, lambda f: np.savez(f, R=r16, L=l16, meta=meta_arr), hint)


def load_entry(path: Path, expected: Dict[str, Any]) -> Optional[Tuple[torch.Tensor, torch.Tensor]]:
    """(R, L) as float32 CPU tensors if ``path`` exists, loads and its meta has every item of ``expected``;
    else None."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            if not isinstance(meta, dict) or any(meta.get(k) != v for k, v in expected.items()):
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


def _save_preview(path: Path, r: torch.Tensor, l: torch.Tensor, gamma: float = 2.2, hint: str = "") -> None:
    from PIL import Image

    img = enhance_for_viewing(r.float(), l.float(), gamma)
    arr = (img.clamp(0, 1).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)
    _atomic_write(path, lambda f: Image.fromarray(arr).save(f, format="PNG"), hint)


def _entries_by_hash(folder: Path) -> Dict[str, Path]:
    """Content hash -> an entry file of ``folder`` (content-keyed names only)."""
    found: Dict[str, Path] = {}
    try:
        names = sorted(os.listdir(folder))
    except OSError:
        return found
    for name in names:
        m = _ENTRY.match(name)
        if m and len(m.group("hash")) == _HASH_LEN:
            found.setdefault(m.group("hash"), folder / name)
    return found


def _settings_folders(root: Path) -> List[Path]:
    try:
        return sorted(p for p in Path(root).iterdir() if p.is_dir() and _SETTINGS_DIR.match(p.name))
    except OSError:
        return []


def _entry_files(folder: Path) -> List[Path]:
    try:
        return sorted(p for p in folder.iterdir() if p.is_file() and _ENTRY.match(p.name))
    except OSError:
        return []


def _remove(path: Path) -> int:
    """Delete one file; its size, or 0 if it could not be deleted (a read-only cache is left as it is)."""
    try:
        size = path.stat().st_size
        path.unlink()
        return size
    except OSError:
        return 0


def _is_old_format(entry: Path) -> bool:
    return len(_ENTRY.match(entry.name).group("hash")) != _HASH_LEN


def _remove_entries(entries: Iterable[Path]) -> Tuple[int, int]:
    """Delete entries and their previews (files that cannot be deleted are left); (entries deleted, bytes)."""
    count = freed = 0
    folders = set()
    for entry in entries:
        size = _remove(entry)
        if size:
            count += 1
            freed += size + _remove(entry.parent / "preview" / f"{entry.stem}.png")
        folders.add(entry.parent)
    for folder in sorted(folders):
        _drop_if_empty(folder)
    return count, freed


def sweep_old_format(root: PathLike) -> int:
    """Delete the entries of the older path-keyed format (``<stem>-<10 hex>.npz``, never read) and their
    previews under ``root``; a folder left with nothing but its ``params.json`` goes too. Returns the count."""
    old = [e for folder in _settings_folders(Path(root)) for e in _entry_files(folder) if _is_old_format(e)]
    return _remove_entries(old)[0]


def unused_entries(root: PathLike, folder: PathLike, keep_hashes: Iterable[str]) -> List[Path]:
    """The entries under ``root`` that photos with ``keep_hashes`` at the settings of ``folder`` (their
    ``<method>-<key>`` folder) do not use: those of other settings folders, those of other photos in ``folder``
    (another resolution, another scene sharing the root, an edited photo's older content), and old-format ones."""
    keep, folder = set(keep_hashes), Path(folder)
    out = []
    for f in _settings_folders(Path(root)):
        for entry in _entry_files(f):
            if f != folder or _is_old_format(entry) or _ENTRY.match(entry.name).group("hash") not in keep:
                out.append(entry)
    return out


def entries_size(entries: Iterable[Path]) -> int:
    """Bytes of the entries and of their previews."""
    total = 0
    for e in entries:
        for p in (e, e.parent / "preview" / f"{e.stem}.png"):
            try:
                total += p.stat().st_size
            except OSError:
                pass
    return total


def prune_unused(root: PathLike, folder: PathLike, keep_hashes: Iterable[str]) -> Tuple[int, int]:
    """Delete :func:`unused_entries` (with their previews; settings folders left empty go too): only files named
    as this module names them, and what cannot be deleted (read-only cache) is left. (entries deleted, bytes)."""
    return _remove_entries(unused_entries(root, folder, keep_hashes))


def unused_note(root: PathLike, count: int, nbytes: int, scene: str = "SCENE") -> str:
    """The one line that says a cache holds entries the current photos and settings do not use."""
    return (f"note: the decomposition cache {root} also holds {count} entr{'y' if count == 1 else 'ies'} "
            f"({nbytes / 2**20:.1f} MiB) not used by these photos at these settings (other resolutions, parameters "
            f"or scenes; kept for switching back): `retinexgs decompose --data {scene} --prune` with the same "
            "--config/--set deletes them, --clean deletes the whole cache")


def _drop_if_empty(folder: Path) -> None:
    """Remove a settings folder that holds no entry any more (only ``params.json`` / an empty preview/)."""
    try:
        if _entry_files(folder):
            return
        preview = folder / "preview"
        if preview.is_dir() and not any(preview.iterdir()):
            preview.rmdir()
        rest = [p.name for p in folder.iterdir()]
        if rest in ([], ["params.json"]):
            (folder / "params.json").unlink(missing_ok=True)
            folder.rmdir()
    except OSError:
        pass


def cache_summary(root: PathLike) -> List[Dict[str, Any]]:
    """One dict per ``<method>-<key>`` folder under ``root``: ``folder``, ``method``, ``params`` (from its
    ``params.json``, or None), ``entries`` (content-keyed), ``old_entries`` (path-keyed format, never read),
    ``previews`` and ``bytes`` (all of these files)."""
    out = []
    for folder in _settings_folders(Path(root)):
        entries = _entry_files(folder)
        previews = sorted((folder / "preview").glob("*.png")) if (folder / "preview").is_dir() else []
        try:
            params = json.loads((folder / "params.json").read_text()).get("params")
        except (OSError, ValueError, AttributeError):
            params = None
        size = sum(p.stat().st_size for p in entries + previews)
        old = sum(1 for p in entries if len(_ENTRY.match(p.name).group("hash")) != _HASH_LEN)
        out.append({"folder": str(folder), "method": folder.name.rsplit("-", 1)[0], "params": params,
                    "entries": len(entries) - old, "old_entries": old, "previews": len(previews), "bytes": size})
    return out


def _delete(path: Path) -> int:
    """Delete ``path``; its size in bytes. UserError naming it if it cannot be deleted."""
    try:
        size = path.stat().st_size
        path.unlink()
    except OSError as exc:
        raise UserError(f"cannot delete {path}: {exc.strerror or exc}") from None
    return size


def clean_cache(root: PathLike) -> Tuple[int, int]:
    """Delete every decomposition under ``root`` (entries, previews, ``params.json``, temporaries of an
    interrupted write), the trainer's view stores in ``root``, the denoised views (``decomposer.denoise``) and the
    folders left empty, ``root`` included;
    files this module did not name are left where they are. Returns (entries deleted, bytes freed); UserError if
    something cannot be deleted."""
    root = Path(root)
    count = freed = 0
    for folder in _settings_folders(root):
        victims = _entry_files(folder)
        extra = [folder / "params.json"] + sorted(folder.glob(_TMP_PREFIX + "*"))
        preview = folder / "preview"
        if preview.is_dir():
            extra += sorted(p for p in preview.iterdir() if p.is_file() and
                            (p.suffix == ".png" and _ENTRY.match(p.stem + ".npz") or p.name.startswith(_TMP_PREFIX)))
        for p in victims + extra:
            if p.is_file():
                freed += _delete(p)
                count += p in victims
        for d in (preview, folder):
            try:
                d.rmdir()
            except OSError:  # missing, or holds a file we did not write
                pass
    try:
        stores = sorted(p for p in root.iterdir() if p.is_file() and (
            _VIEW_STORE.match(p.name) or p.name.startswith(_TMP_PREFIX) and p.suffix == ".bin"))
    except OSError:
        stores = []
    for p in stores:
        freed += _delete(p)
    freed += _clean_denoised(root / DENOISED_DIRNAME)
    try:
        root.rmdir()
    except OSError:
        pass
    return count, freed


def _clean_denoised(folder: Path) -> int:
    """Delete the denoised views under ``folder`` (only names :func:`retinexgs.retinex.denoise.denoised_view` writes,
    and temporaries of an interrupted write) and the folders left empty; the bytes freed."""
    freed = 0
    try:
        recipes = sorted(p for p in folder.iterdir() if p.is_dir() and _SETTINGS_DIR.match(p.name))
    except OSError:
        return 0
    for d in recipes:
        for p in sorted(d.iterdir()):
            if p.is_file() and (_ENTRY.match(p.name) or p.name.startswith(_TMP_PREFIX)):
                freed += _delete(p)
        for gone in (d, folder):
            try:
                gone.rmdir()
            except OSError:  # holds a file we did not write
                pass
    return freed


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


def iter_decompositions(image_paths: Sequence[PathLike], method: str = "lr3m", params: Any = None,
                        cache_dir: Optional[PathLike] = None, device: Union[str, torch.device] = "cpu", *,
                        preview: bool = False, progress: bool = True, cache_hint: str = "", sweep: bool = False,
                        report: Optional[Dict[str, Any]] = None, announce: bool = True, scene: str = "SCENE",
                        raw_denoise: bool = False, balance: Optional[Sequence[float]] = None,
                        names: Optional[Sequence[PathLike]] = None, denoise: Optional[DenoiseSpec] = None
                        ) -> Iterator[Tuple[torch.Tensor, torch.Tensor]]:
    """(R [H,W,3], L [H,W,1]) float32 CPU tensors for each image in turn, from the cache or computed and
    written to it (on a thread, while the next image is decomposed: each entry is on disk before the next image's
    maps are yielded): the caller holds one image's priors at a time, and an interrupted run keeps every entry
    computed so far (a write in flight is finished when the iteration is closed). The values are the cache's
    float16 ones (a freshly computed entry is rounded as it is stored). ``report`` (a dict, filled as it goes): ``folder``, ``computed``, ``reused``,
    ``swept``, ``unused``, ``unused_bytes`` and ``files``, as :func:`decompose_images` returns it; the sweep
    (``sweep=True``) runs once the last image has been yielded and the caller asks for the next, and with
    ``announce`` prints :func:`unused_note` (naming ``scene`` in its command) on stderr when there are unused
    entries. ``raw_denoise``: camera raw views are decomposed from their denoised preview (:func:`read_image`,
    keyed by :func:`prior_key`). ``balance``: every photo's white balance (``data.white_balance``; the views'
    :attr:`~retinexgs.data.scene.View.balance`), applied before the decomposition and part of the key. ``names``:
    the user's file for each image, named in errors instead (a view's ``source_path``: the photo an undistorted or
    downscaled copy was made from). ``denoise``: every photo is decomposed from its denoised view
    (``decomposer.denoise``, :func:`read_image`; cached in ``<root>/denoised/``, keyed by :func:`prior_key`). Other
    arguments: :func:`decompose_images`.
    """
    paths = [Path(p) for p in image_paths]
    if not paths:
        raise UserError("no images to decompose")
    if names is not None and len(names) != len(paths):
        raise ValueError(f"names: {len(names)} for {len(paths)} images")
    shown = dict(zip(paths, (Path(n) for n in names))) if names is not None else {}
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
        _atomic_write(settings, lambda f: f.write(text.encode("utf-8")), cache_hint)

    report = report if report is not None else {}
    report.update(folder=str(folder), computed=0, reused=0, swept=0, unused=0, unused_bytes=0, files=[])
    by_hash = _entries_by_hash(folder)
    hashes = []
    iterator: Iterable[Path] = paths
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(paths, desc=f"decompose ({dec.name})", unit="view", leave=True)
        iterator = bar
    # The next photos are read (decoded, balanced, denoised) on threads while this one is decomposed: a 12 MP raw
    # file's decode alone takes seconds of CPU. A photo whose entry was on disk when the run began is not read.
    cached = set(by_hash)

    def prepare(p: Path) -> Tuple[str, Optional[torch.Tensor]]:
        digest = prior_key(p, raw_denoise, balance, denoise) if p.is_file() else ""
        if not digest or digest in cached:
            return digest, None
        return digest, read_image(p, raw_denoise, balance, denoise, root, cache_hint)

    ahead = _ReadAhead(prepare, paths, READ_AHEAD)
    writer = _WriteBehind()  # an entry is written while the next photo is decomposed
    try:
        for n, p in enumerate(iterator):
            if not p.is_file():
                raise UserError(f"image not found: {p}")
            digest, image = ahead.result(n)
            hashes.append(digest)
            meta = _source_meta(p, dec.cache_key(), dec.name, digest)
            target = by_hash.get(digest, folder / _entry_name(p, digest))  # any name: a renamed photo too
            if writer.pending == digest:  # the same photo twice in a row: its entry is being written
                writer.wait()
            hit = load_entry(target, meta)
            if hit is None:
                target = folder / _entry_name(p, digest)
                if image is None:  # its entry was there at the start, or a photo of the same content
                    image = read_image(p, raw_denoise, balance, denoise, root, cache_hint)
                image = image.to(dev)
                try:
                    r, l = dec.decompose(image)
                except ValueError as exc:  # e.g. an all-black photo: named as the user knows it, not the cache copy
                    raise UserError(f"cannot decompose {shown.get(p, p)}: {exc}") from None
                del image
                r, l = r.to("cpu", torch.float32), l.to("cpu", torch.float32)
                writer.submit(digest, save_entry, target, r, l, {**meta, "source": p.name}, cache_hint)
                by_hash[digest] = target
                # What later runs will load is the float16 copy: return exactly that.
                hit = (r.half().float(), l.half().float())
                del r, l
                report["computed"] += 1
            else:
                report["reused"] += 1
            if preview:
                writer.wait()  # the preview's freshness is read from its entry's file
                pv = folder / "preview" / f"{target.stem}.png"
                if not pv.is_file() or pv.stat().st_mtime_ns < target.stat().st_mtime_ns:
                    _save_preview(pv, hit[0], hit[1], 2.2, cache_hint)
            report["files"].append(str(target))
            image = None
            yield hit
            hit = None  # the caller's reference is the only one left
        writer.wait()  # the last entry on disk (or its error raised) before the sweep and the end
    finally:
        writer.close()
        ahead.close()
        if bar is not None:
            bar.close()
    if sweep:
        # Only what nobody can read goes on its own; entries of other resolutions, settings or scenes stay.
        report["swept"] = sweep_old_format(root)
        unused = unused_entries(root, folder, hashes)
        report["unused"], report["unused_bytes"] = len(unused), entries_size(unused)
        if unused and announce:
            print(unused_note(root, len(unused), report["unused_bytes"], scene), file=sys.stderr)


# Photos read ahead of the one being decomposed (threads: decoding, numpy and the denoiser release the GIL). Few:
# each is a full-size float image in host memory (a 12 MP one 144 MB) and may hold the GPU denoiser's buffers.
READ_AHEAD = max(1, min(3, (os.cpu_count() or 1) - 1))


class _WriteBehind:
    """One write at a time on a thread: :meth:`submit` first waits for the previous write (so one entry's maps at most
    are held for it) and raises its error, if any; :meth:`wait` waits for the last. A 12 MP entry (96 MB, fsynced)
    takes ~0.5-0.9 s of host time, which the next photo's decomposition now covers."""

    def __init__(self) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="retinexgs-decompose-write")
        self._job = None
        self.pending: Optional[str] = None  # the key of the write in flight

    def submit(self, key: str, fn, *args) -> None:
        self.wait()
        self._job, self.pending = self._pool.submit(fn, *args), key

    def wait(self) -> None:
        job, self._job, self.pending = self._job, None, None
        if job is not None:
            job.result()

    def close(self) -> None:
        self._pool.shutdown(wait=True)  # an entry being written is finished (atomically) or never appears


def produced_ahead(items: Iterable[Any], depth: int = 1, name: str = "retinexgs-decompose-ahead") -> Iterator[Any]:
    """``items`` in order, produced on a thread up to ``depth`` items ahead of the consumer: the next view's
    decomposition (the GPU's work) runs while the caller stores this one (the host's). The values, their order and
    the errors are those of iterating ``items`` here; an error is raised where its item would have come. Closing
    early (an error of the caller, or Ctrl-C) stops the thread after the item it is making, and waits for that: a
    thread left inside torch when the interpreter exits aborts the process. So use it where an item takes seconds
    (a decomposition on the GPU), not minutes (a 12 MP photo's on the CPU)."""
    import queue
    import threading

    q: "queue.Queue" = queue.Queue(maxsize=max(1, int(depth)))
    stop = threading.Event()

    def put(entry) -> bool:
        while not stop.is_set():
            try:
                q.put(entry, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    # a new thread starts on CUDA device 0: it takes this one's (a rank's own GPU under torchrun)
    cuda_device = torch.cuda.current_device() if torch.cuda.is_available() and torch.cuda.is_initialized() else None

    def produce() -> None:
        if cuda_device is not None:
            torch.cuda.set_device(cuda_device)
        it = iter(items)
        try:
            for x in it:
                if not put(("item", x)):
                    return
            put(("done", None))
        except BaseException as exc:  # handed to the consumer, raised there
            put(("error", exc))
        finally:
            close = getattr(it, "close", None)
            if close is not None:
                close()  # a generator's own clean-up (its threads, its progress bar) in its own thread

    thread = threading.Thread(target=produce, name=name)
    thread.start()
    try:
        while True:
            kind, x = q.get()
            if kind == "item":
                yield x
            elif kind == "done":
                return
            else:
                raise x
    finally:
        stop.set()
        thread.join()


class _ReadAhead:
    """``fn(items[i])`` computed on ``workers`` threads up to ``workers`` items ahead of the one asked for, in order;
    :meth:`result` returns (or raises) item i's outcome when its turn comes."""

    def __init__(self, fn, items: Sequence[Any], workers: int) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self._fn, self._items, self._workers = fn, list(items), max(1, int(workers))
        self._pool = ThreadPoolExecutor(max_workers=self._workers, thread_name_prefix="retinexgs-decompose-read")
        self._jobs: Dict[int, Any] = {}
        self._next = 0

    def result(self, i: int):
        while self._next < len(self._items) and self._next <= i + self._workers:
            self._jobs[self._next] = self._pool.submit(self._fn, self._items[self._next])
            self._next += 1
        return self._jobs.pop(i).result()

    def close(self) -> None:
        for job in self._jobs.values():
            job.cancel()
        self._pool.shutdown(wait=True)
        self._jobs.clear()


def decompose_images(image_paths: Sequence[PathLike], method: str = "lr3m", params: Any = None,
                     cache_dir: Optional[PathLike] = None, device: Union[str, torch.device] = "cpu", *,
                     keep: bool = True, preview: bool = False, progress: bool = True, cache_hint: str = "",
                     sweep: bool = False, announce: bool = True, raw_denoise: bool = False,
                     balance: Optional[Sequence[float]] = None, names: Optional[Sequence[PathLike]] = None,
                     denoise: Optional[DenoiseSpec] = None
                     ) -> Tuple[List[Optional[Tuple[torch.Tensor, torch.Tensor]]], Dict[str, Any]]:
    """Make sure every image has a valid cache entry; return (results, report).

    ``results[i]`` is (R, L) on the CPU when ``keep`` else None. ``report`` has ``folder`` (the entry
    folder), ``computed``, ``reused`` and ``swept`` counts, ``unused`` / ``unused_bytes`` (entries these photos
    do not use at these settings, with ``sweep``) and ``files`` (entry paths, in input order).
    ``cache_hint``: the caller's spelling of the cache option, named when the cache cannot be created or
    written (a read-only scene) or its disk is full. Entries present and valid are read from a read-only
    cache; only a needed write fails. ``sweep``: ``image_paths`` are a scene's train views: once all are in
    place, old-format entries are deleted (:func:`sweep_old_format`) and the entries they do not use are counted
    (:func:`unused_entries`; nothing of them is deleted), and with ``announce`` one line says so on stderr.
    One image's priors at a time: :func:`iter_decompositions` (``raw_denoise``, ``balance``, ``names``, ``denoise``
    as there).
    """
    report: Dict[str, Any] = {}
    results: List[Optional[Tuple[torch.Tensor, torch.Tensor]]] = []
    for hit in iter_decompositions(image_paths, method, params, cache_dir, device, preview=preview,
                                   progress=progress, cache_hint=cache_hint, sweep=sweep, report=report,
                                   announce=announce, raw_denoise=raw_denoise, balance=balance, names=names,
                                   denoise=denoise):
        results.append(hit if keep else None)
    return results, report


def load_or_compute(image_paths: Sequence[PathLike], method: str = "lr3m", params: Any = None,
                    cache_dir: Optional[PathLike] = None, device: Union[str, torch.device] = "cpu", *,
                    progress: bool = True, cache_hint: str = "", sweep: bool = False
                    ) -> List[Tuple[torch.Tensor, torch.Tensor]]:
    """(R [H,W,3], L [H,W,1]) float32 CPU tensors for each image, from the cache or freshly computed.

    ``params``: a params dataclass or a dict of overrides (None = defaults). ``cache_dir``: the cache root
    (default ``<scene>/retinex_cache``, see :func:`default_cache_root`); entries go in
    ``<cache_dir>/<method>-<key>/``. ``device``: where missing entries are computed. ``sweep``: delete
    old-format entries and note unused ones (see :func:`decompose_images`).
    """
    results, _ = decompose_images(image_paths, method, params, cache_dir, device, keep=True, progress=progress,
                                  cache_hint=cache_hint, sweep=sweep)
    return [r for r in results if r is not None]
