"""``retinexgs decompose``: Retinex-decompose every training photo of a scene into the on-disk cache that
``retinexgs train`` reads (same scene loading, same cache folder; see :func:`run`)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import List, Optional

from retinexgs.errors import UserError
from retinexgs.formats import IMAGE_EXTENSIONS, readable_formats  # the one list train, sfm, noise, darken read


def _resolve_frame(scene: Path, file_path: str) -> Path:
    """A transforms ``file_path`` (with or without extension) -> an existing file, or the literal path."""
    p = (scene / file_path).resolve() if not Path(file_path).is_absolute() else Path(file_path)
    if p.is_file():
        return p
    if p.suffix.lower() not in IMAGE_EXTENSIONS and p.parent.is_dir():  # any case: NAME.HEIC, NAME.dng
        for q in sorted(p.parent.iterdir()):
            if q.stem == p.name and q.suffix.lower() in IMAGE_EXTENSIONS and q.is_file():
                return q
    return p


def list_scene_images(scene: Path, images_subdir: Optional[str] = None) -> List[Path]:
    """The photos to decompose for a scene folder (see the ``decompose`` help); raises UserError. A named
    ``images_subdir`` must exist; without one, ``low/`` is used when there is one, else the scene folder."""
    if not scene.exists():
        raise UserError(f"scene folder not found: {scene}")
    if not scene.is_dir():
        raise UserError(f"--data must be a scene folder, got a file: {scene}")
    if images_subdir is not None and not (scene / images_subdir).is_dir():
        raise UserError(f"--images-subdir {images_subdir}: {scene / images_subdir} is not a folder"
                        + ("" if (scene / images_subdir).exists() else " (it does not exist)"))
    images_subdir = "low" if images_subdir is None else images_subdir
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
    from retinexgs.data.images import list_images, no_images_reason  # lazy: --help stays fast

    folder = scene / images_subdir if images_subdir and (scene / images_subdir).is_dir() else scene
    paths = list_images(folder)
    if not paths:
        raise UserError(f"no photos in {folder}"
                        + (f" (and no {images_subdir}/ subfolder)" if folder == scene and images_subdir else "")
                        + f": {no_images_reason(folder)}")
    return paths


def _has_poses(scene: Path, cache_dir: Optional[str]) -> bool:
    """True when ``train`` would load the scene without computing SfM: a transforms JSON, a COLMAP model, or
    the SfM model an earlier ``train``/``sfm`` cached for it."""
    from retinexgs.data.colmap import find_model_dir  # lazy: --help stays fast
    from retinexgs.data.transforms_json import has_transforms  # lazy: --help stays fast

    sfm = Path(cache_dir) / "sfm" if cache_dir else scene / "retinexgs_sfm"
    return has_transforms(scene) or find_model_dir(scene) is not None or (sfm / "retinexgs_sfm.json").is_file()


def run(args: argparse.Namespace) -> int:
    """Entry point of ``retinexgs decompose``."""
    from retinexgs.data.images import read_image  # lazy: --help stays fast
    from retinexgs.retinex.base import available_methods  # lazy: --help stays fast
    from retinexgs.retinex.cache import (decompose_images, prune_unused, resolve_device, scene_cache_root,  # lazy: --help stays fast
                                         unused_note)
    from retinexgs.run.config import load_config  # lazy: --help stays fast

    scene = Path(args.data).expanduser()
    if args.prune and (args.clean or args.info):
        raise UserError(f"--prune and --{'clean' if args.clean else 'info'} do not go together: --prune decomposes "
                        "and then deletes the entries this scene does not use, --clean deletes the whole cache, "
                        "--info lists it")
    if args.clean or args.info:
        return _clean_or_info(scene, args)
    paths = list_scene_images(scene, args.images_subdir)
    overrides = list(args.set or [])
    if args.method is not None:  # first: the --set decomposer.params that follow are this method's
        overrides.insert(0, f"decomposer.method={args.method}")
    if args.cache:
        overrides.append(f"data.cache_dir={Path(args.cache).expanduser()}")
    cfg = load_config(args.config or [], overrides)  # the settings train would use, checked before any work
    dcfg = cfg.decomposer
    if dcfg.method not in available_methods():
        raise UserError(f"decomposer.method is {dcfg.method}: there is nothing to decompose "
                        f"(choose {' or '.join(available_methods())})")
    # An unreadable or truncated photo is refused before the cache folder is created (one extra decode per
    # photo; the decomposition itself costs far more).
    for p in paths:
        read_image(p)
    hint = "--cache DIR (or --set data.cache_dir=DIR)"
    balance = None  # data.white_balance: the scene's views carry it (open_scene)
    names = None  # the user's photos, named in errors where paths are the loader's undistorted/downscaled copies
    train_views = None  # the scene's training views as train opens them (where it has poses)
    views_per_point = None  # the scene's Scene.views_per_point (the denoiser's luma strength), read if it denoises
    if _has_poses(scene, cfg.data.cache_dir):
        # Decompose exactly the images train will read: undistorted and downscaled copies where the scene
        # needs them, so that train finds every entry in the cache.
        from retinexgs.run.folder import open_scene  # lazy: --help stays fast
        from retinexgs.train.sfm_preview import scene_sfm_denoise

        # the SfM model train uses (data.sfm_denoise names its previews' recipe, part of the cache key)
        opened = open_scene(scene, cfg, cache_hint=hint, sfm_denoise=scene_sfm_denoise(cfg.data.sfm_denoise))
        train = opened.train
        paths, balance = [v.image_path for v in train], (train[0].balance if train else None)
        train_views, views_per_point = train, opened.views_per_point
        names = [v.source_path or v.image_path for v in train]
    else:
        if cfg.data.downscale != 1:
            raise UserError(f"{scene} has no camera poses yet (no transforms JSON, COLMAP model or cached SfM), so "
                            "there are no downscaled views to decompose: train once (it runs SfM), or decompose "
                            "without data.downscale")
        print(f"note: {scene} has no camera poses yet; train will run SfM and decompose the undistorted copies it "
              "makes, which these entries do not cover", file=sys.stderr)
    cache_root = scene_cache_root(scene, cfg.data.cache_dir)
    denoise = None
    if train_views is not None:  # the denoiser train reads the views through (decomposer.denoise), keying its entries
        from retinexgs.train.view_setup import denoise_spec

        denoise = denoise_spec(train_views, cfg, str(resolve_device(args.device)),
                               note=lambda line: print(line, file=sys.stderr),  # auto's choice on photos, as train says it
                               views_per_point=views_per_point)
    _, report = decompose_images(paths, dcfg.method, dict(dcfg.params) or None, cache_root,
                                 args.device, keep=False, preview=args.preview, progress=not args.quiet,
                                 cache_hint=hint, sweep=True, announce=False, raw_denoise=dcfg.raw.preview_denoise,
                                 balance=balance, names=names, denoise=denoise)
    n = report["swept"]
    swept = f", {n} old-format entr{'y' if n == 1 else 'ies'} deleted" if n else ""
    print(f"{len(paths)} view(s) decomposed with {dcfg.method}: {report['computed']} computed, "
          f"{report['reused']} reused from cache{swept} -> {report['folder']}")
    if args.preview:
        print(f"previews: {Path(report['folder']) / 'preview'}")
    if args.prune:
        hashes = {Path(f).stem.rsplit("-", 1)[1] for f in report["files"]}
        count, freed = prune_unused(cache_root, report["folder"], hashes)
        print(f"--prune: deleted {count} entr{'y' if count == 1 else 'ies'} ({_mib(freed)}) not used by this "
              "scene at these settings")
    elif report["unused"]:
        print(unused_note(cache_root, report["unused"], report["unused_bytes"], str(args.data)))
    print(_cache_size_line(cache_root))
    return 0


def _mib(n: int) -> str:
    return f"{n / 2**20:.1f} MiB"


def _cache_size_line(root: Path) -> str:
    from retinexgs.retinex.cache import cache_summary  # lazy: --help stays fast

    rows = cache_summary(root)
    entries = sum(r["entries"] + r["old_entries"] for r in rows)
    return (f"cache {root}: {entries} entr{'y' if entries == 1 else 'ies'} in {len(rows)} setting(s), "
            f"{_mib(sum(r['bytes'] for r in rows))} (see --info; --clean deletes them)")


def _clean_or_info(scene: Path, args: argparse.Namespace) -> int:
    """``--info``: list the scene's decomposition cache; ``--clean``: delete it. Neither loads the scene."""
    from retinexgs.retinex.cache import cache_summary, clean_cache, scene_cache_root  # lazy: --help stays fast
    from retinexgs.run.config import load_config  # lazy: --help stays fast

    if args.clean and args.info:
        raise UserError("--clean and --info do not go together: --info lists the cache, --clean deletes it")
    if not scene.is_dir():
        raise UserError(f"scene folder not found: {scene}" if not scene.exists()
                        else f"--data must be a scene folder, got a file: {scene}")
    overrides = list(args.set or [])
    if args.cache:
        overrides.append(f"data.cache_dir={Path(args.cache).expanduser()}")
    root = scene_cache_root(scene, load_config(args.config or [], overrides).data.cache_dir)
    if args.info:
        rows = cache_summary(root)
        if not rows:
            print(f"cache {root}: empty")
            return 0
        for r in rows:
            params = json.dumps(r["params"], sort_keys=True) if r["params"] is not None else "?"
            old = f" + {r['old_entries']} of the old format (never read; the next run deletes them)" \
                if r["old_entries"] else ""
            pv = f", {r['previews']} preview(s)" if r["previews"] else ""
            print(f"{Path(r['folder']).name}: {r['method']} {params}: {r['entries']} entr"
                  f"{'y' if r['entries'] == 1 else 'ies'}{old}{pv}, {_mib(r['bytes'])}")
        print(_cache_size_line(root))
        return 0
    count, freed = clean_cache(root)
    print(f"deleted {count} cached decomposition(s), {_mib(freed)}, from {root}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``decompose`` sub-command."""
    from retinexgs.retinex.base import available_methods  # lazy: --help stays fast

    p = subparsers.add_parser(
        "decompose", help="split each low-light photo of a scene into reflectance R and illumination L (cached)",
        description="Decompose the training photos of SCENE into reflectance and illumination and cache the "
                    "results where train looks for them (same settings: --config/--set as for train). A "
                    "scene with poses (transforms JSON or COLMAP model) is loaded as train loads it "
                    "(undistorted, downscaled by data.downscale) and its train views are decomposed; a "
                    "folder of photos without poses has every photo in SCENE/<images-subdir>/ (or SCENE) "
                    f"decomposed ({readable_formats()}, as train reads them). Entries are keyed by the photo's "
                    "content and the settings, so "
                    "they are reused unless the photo or the parameters changed (also in a copy of the "
                    "scene). Nothing is deleted on its own: entries of other resolutions (data.downscale), "
                    "parameters, edited or removed photos, or other scenes sharing --cache DIR are kept for "
                    "switching back, and a note counts them; --prune deletes them. The last line gives "
                    "the cache's size; --info lists it, --clean deletes it.")
    p.add_argument("--data", required=True, metavar="SCENE", help="scene folder")
    p.add_argument("--method", default=None, choices=available_methods(),
                   help="decomposer (default: decomposer.method of the config, lr3m)")
    p.add_argument("--device", default="auto", choices=["cpu", "cuda", "auto"],
                   help="where to compute: cpu, cuda or auto (default: cuda when available)")
    p.add_argument("--cache", metavar="DIR", default=None,
                   help="the caches' folder, as train's --set data.cache_dir=DIR (default: in SCENE: "
                        "SCENE/retinex_cache); entries go in DIR/retinex/<method>-<hash>/")
    p.add_argument("--config", action="append", default=[],
                   help="config override file or name in configs/, as for train; repeatable")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override one config key as for train, e.g. --set data.downscale=2; repeatable")
    p.add_argument("--images-subdir", default=None, metavar="NAME",
                   help="photo subfolder used when there is no transforms_train.json (default: low when "
                        "there is one, else SCENE itself)")
    p.add_argument("--preview", action="store_true",
                   help="also write a viewable PNG per view, R*(L/max L)^(1/2.2), into <entry folder>/preview/")
    p.add_argument("--info", action="store_true",
                   help="list the scene's decomposition cache (one line per method and parameters: entries, "
                        "MiB) and exit; nothing is computed or written")
    p.add_argument("--clean", action="store_true",
                   help="delete the scene's decomposition cache (SCENE/retinex_cache, or DIR/retinex with "
                        "--cache DIR) and exit: the cached entries, previews and params.json of every method "
                        "and parameter set; other files there are kept. train recomputes what it needs")
    p.add_argument("--prune", action="store_true",
                   help="decompose as usual, then delete every cached decomposition this scene does not use at "
                        "the current settings: other parameters and methods, other resolutions, photos edited or "
                        "removed since, and (in a --cache DIR shared by several scenes) the other scenes' "
                        "entries. Without it nothing is deleted")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
