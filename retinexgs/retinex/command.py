"""``retinexgs decompose``: Retinex-decompose every training photo of a scene into the on-disk cache."""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import List

from retinexgs.errors import UserError

_EXTS = (".jpg", ".jpeg", ".png")


def _images_in(folder: Path) -> List[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in _EXTS)


def _resolve_frame(scene: Path, file_path: str) -> Path:
    """A transforms ``file_path`` (with or without extension) -> an existing file, or the literal path."""
    p = (scene / file_path).resolve() if not Path(file_path).is_absolute() else Path(file_path)
    if p.is_file():
        return p
    if p.suffix.lower() not in _EXTS:
        for ext in _EXTS + tuple(e.upper() for e in _EXTS):
            cand = p.with_name(p.name + ext)
            if cand.is_file():
                return cand
    return p


def list_scene_images(scene: Path, images_subdir: str = "low") -> List[Path]:
    """The photos to decompose for a scene folder (see the ``decompose`` help); raises UserError."""
    if not scene.exists():
        raise UserError(f"scene folder not found: {scene}")
    if not scene.is_dir():
        raise UserError(f"--data must be a scene folder, got a file: {scene}")
    transforms = scene / "transforms_train.json"
    if transforms.is_file():
        try:
            frames = json.loads(transforms.read_text())["frames"]
            names = [str(f["file_path"]) for f in frames]
        except (ValueError, KeyError, TypeError) as exc:
            raise UserError(f"{transforms} is not a valid transforms file (need frames[].file_path): {exc}") from None
        if not names:
            raise UserError(f"{transforms} lists no frames")
        paths = [_resolve_frame(scene, n) for n in names]
        missing = [str(p) for p in paths if not p.is_file()]
        if missing:
            more = f" (and {len(missing) - 3} more)" if len(missing) > 3 else ""
            raise UserError(f"{len(missing)} image(s) listed in {transforms} are missing: "
                            f"{', '.join(missing[:3])}{more}")
        return paths
    folder = scene / images_subdir if images_subdir and (scene / images_subdir).is_dir() else scene
    paths = _images_in(folder)
    if not paths:
        raise UserError(f"no images (.jpg/.jpeg/.png) found in {folder}"
                        + (f" (and no {images_subdir}/ subfolder)" if folder == scene and images_subdir else ""))
    return paths


def run(args: argparse.Namespace) -> int:
    """Entry point of ``retinexgs decompose``."""
    from retinexgs.data.images import read_image
    from retinexgs.retinex.cache import CACHE_DIRNAME, decompose_images

    scene = Path(args.data).expanduser()
    paths = list_scene_images(scene, args.images_subdir)
    # An unreadable or truncated photo is refused before the cache folder is created (one extra decode per
    # photo; the decomposition itself costs far more).
    for p in paths:
        read_image(p)
    cache_root = Path(args.cache).expanduser() if args.cache else scene / CACHE_DIRNAME
    _, report = decompose_images(paths, args.method, None, cache_root, args.device, keep=False,
                                 preview=args.preview, progress=not args.quiet)
    print(f"{len(paths)} view(s) decomposed with {args.method}: {report['computed']} computed, "
          f"{report['reused']} reused from cache -> {report['folder']}")
    if args.preview:
        print(f"previews: {Path(report['folder']) / 'preview'}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``decompose`` sub-command."""
    from retinexgs.retinex.base import available_methods

    p = subparsers.add_parser(
        "decompose", help="split each low-light photo of a scene into reflectance R and illumination L (cached)",
        description="Decompose the training photos of SCENE into reflectance and illumination and cache the "
                    "results on disk. Photos: the frames of SCENE/transforms_train.json if present, otherwise "
                    "every .jpg/.jpeg/.png in SCENE/<images-subdir>/ if that folder exists, else in SCENE. "
                    "Cached entries are reused unless the photo or the parameters changed.")
    p.add_argument("--data", required=True, metavar="SCENE", help="scene folder")
    p.add_argument("--method", default="lr3m", choices=available_methods(), help="decomposer (default: lr3m)")
    p.add_argument("--device", default="auto", choices=["cpu", "cuda", "auto"],
                   help="where to compute: cpu, cuda or auto (default: cuda when available)")
    p.add_argument("--cache", metavar="DIR", default=None,
                   help="cache root (default: SCENE/retinex_cache); entries go in DIR/<method>-<hash>/")
    p.add_argument("--images-subdir", default="low", metavar="NAME",
                   help="photo subfolder used when there is no transforms_train.json (default: low)")
    p.add_argument("--preview", action="store_true",
                   help="also write a viewable PNG per view, R*(L/max L)^(1/2.2), into <entry folder>/preview/")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
