"""Reader for instant-ngp / LOM ``transforms_{train,test,val}.json`` scenes (or a single transforms.json).

Camera poses are camera-to-world in the OpenGL/Blender convention and are converted to OpenCV axes.
Intrinsics: ``fl_x``/``fl_y`` (``fl_y`` defaults to ``fl_x``), else ``camera_angle_x``/``camera_angle_y``;
``cx``/``cy`` default to the image centre; ``w``/``h`` default to the image's size; OPENCV distortion
``k1 k2 p1 p2`` (and ``k3``). Any of these may be overridden per frame. ``cx``/``cy`` are read in the
pixel-centre convention (as COLMAP and instant-ngp write them).

LOM layout: train frames list ``low/X``; test frames list ``high/X``. Each view's input is always the
``low/`` file and its paired normal-light image the ``high/`` file of the same name, whenever both
folders exist (they must then hold the same file names). Camera raw inputs pair by stem: ``low/X.dng`` with
``high/X.png`` (or ``.jpg``), and a frame listing ``high/X.png`` takes ``low/X.dng`` as its input. ``file_path`` may omit the extension.
Initial points come from ``colmap_sparse/0`` (or any COLMAP model found in the folder) when present,
mapped into the JSON's frame by matching camera centres by file name or stem (the model's ``X.JPG`` for a
photo saved as ``X.png``; :func:`retinexgs.data.colmap.match_views_to_model`); when too few match, or the centres
do not agree, a warning says so and the points are random.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

from retinexgs.data.camera import Intrinsics, check_camera, check_rotation, opengl_to_opencv
from retinexgs.data.images import IMAGE_EXTENSIONS, image_size, is_raw_file, list_images
from retinexgs.data.pairing import check_same_files, high_partner
from retinexgs.data.declared import DeclaredScene, DeclaredView
from retinexgs.errors import UserError
from retinexgs.data.colmap import find_model_dir, points_in_frame_of, read_model

SPLITS = ("train", "test", "val")
_INTRINSIC_KEYS = ("fl_x", "fl_y", "camera_angle_x", "camera_angle_y", "cx", "cy", "w", "h",
                   "k1", "k2", "k3", "p1", "p2", "is_fisheye")


def has_transforms(root: Path) -> bool:
    """True when ``root`` holds transforms_train.json or transforms.json."""
    return (Path(root) / "transforms_train.json").is_file() or (Path(root) / "transforms.json").is_file()


def _load_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise UserError(f"{path} is not valid JSON: {exc}") from None
    except UnicodeDecodeError:
        raise UserError(f"{path} is not valid JSON: not UTF-8 text") from None
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise UserError(f"{path} is malformed: expected an object with a 'frames' list")
    return data


def _resolve_file(root: Path, file_path: str, json_path: Path, index: int) -> Path:
    """The image a frame names; tries known extensions when the name has none."""
    rel = Path(str(file_path).replace("\\", "/"))
    p = rel if rel.is_absolute() else root / rel
    if p.is_file():
        return p
    if p.suffix.lower() not in IMAGE_EXTENSIONS and p.parent.is_dir():
        for q in sorted(p.parent.iterdir()):
            if q.stem == p.name and q.suffix.lower() in IMAGE_EXTENSIONS and q.is_file():
                return q
    raise UserError(f"{json_path.name} frame {index} names image {file_path!r}, which does not exist "
                    f"(looked for {p})")


def _number(settings: Dict, key: str, where: str) -> float:
    """``settings[key]`` as a float; UserError naming the key and its value when it is not a number."""
    value = settings[key]
    if isinstance(value, bool):
        raise UserError(f"{where}: {key!r} must be a number, got {value!r}")
    try:  # numbers written as strings ("800") are accepted, words are not
        return float(value)
    except (TypeError, ValueError):
        raise UserError(f"{where}: {key!r} must be a number, got {value!r}") from None


def _size(settings: Dict, key: str, where: str) -> int:
    """``settings[key]`` as a positive whole number of pixels; UserError naming the key and value."""
    value = _number(settings, key, where)
    if not (math.isfinite(value) and value == int(value) and value > 0):
        raise UserError(f"{where}: {key!r} must be a positive whole number of pixels, got {settings[key]!r}")
    return int(value)


def _camera(settings: Dict, image: Path, where: str) -> Intrinsics:
    if settings.get("is_fisheye"):
        raise UserError(f"{where}: fisheye cameras are not supported")
    if "w" in settings and "h" in settings:
        w, h = _size(settings, "w", where), _size(settings, "h", where)
    else:
        for key in ("w", "h"):
            if key in settings:
                _size(settings, key, where)
        w, h = image_size(image)
    num = {k: _number(settings, k, where) for k in _INTRINSIC_KEYS if k in settings and k != "is_fisheye"}
    if "fl_x" in num:
        fx = num["fl_x"]
    elif "camera_angle_x" in num:
        if not 0 < num["camera_angle_x"] < math.pi:
            raise UserError(f"{where}: 'camera_angle_x' must be an angle in radians between 0 and pi, "
                            f"got {settings['camera_angle_x']!r}")
        fx = 0.5 * w / math.tan(0.5 * num["camera_angle_x"])
    else:
        raise UserError(f"{where}: no focal length (fl_x or camera_angle_x)")
    if "fl_y" in num:
        fy = num["fl_y"]
    elif "camera_angle_y" in num and "fl_x" not in num:
        if not 0 < num["camera_angle_y"] < math.pi:
            raise UserError(f"{where}: 'camera_angle_y' must be an angle in radians between 0 and pi, "
                            f"got {settings['camera_angle_y']!r}")
        fy = 0.5 * h / math.tan(0.5 * num["camera_angle_y"])
    else:
        fy = fx
    cx = num.get("cx", w / 2.0)
    cy = num.get("cy", h / 2.0)
    dist = tuple(num.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3"))
    if dist[4] == 0.0:
        dist = dist[:4]
    cam = Intrinsics(w, h, fx, fy, cx, cy, dist if any(dist) else ())
    check_camera(cam, where)
    return cam


def _pose(frame: dict, where: str) -> np.ndarray:
    try:
        m = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except KeyError:
        raise UserError(f"{where}: no transform_matrix") from None
    except (TypeError, ValueError):
        raise UserError(f"{where}: transform_matrix is not a 4x4 list of numbers") from None
    if m.shape == (3, 4):
        m = np.vstack([m, [0, 0, 0, 1]])
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise UserError(f"{where}: transform_matrix is not a finite 4x4 matrix")
    check_rotation(m[:3, :3], where, "transform_matrix rotation (upper-left 3x3)")
    return opengl_to_opencv(m)


def _pair(path: Path, root: Path) -> Tuple[Path, Optional[Path]]:
    """(input image, paired normal-light image) for a listed file, following the LOM layout."""
    parent = path.parent
    if parent.name in ("low", "high") and (parent.parent / "low").is_dir() and (parent.parent / "high").is_dir():
        low = parent.parent / "low" / path.name
        if not low.is_file():  # a raw input listed by its truth's name (high/X.png): low/X.dng, by stem
            low = next((q for q in list_images(parent.parent / "low") if q.stem == path.stem and is_raw_file(q)),
                       low)
        high = high_partner(low, parent.parent / "high")
        if not low.is_file():
            raise UserError(f"low-light input {low} for {path} does not exist")
        if not high.is_file():
            raise UserError(f"normal-light image {high} for {path} does not exist")
        return low, high
    return path, None


def read_split_json(root: Path, json_path: Path) -> List[DeclaredView]:
    """Views of one transforms JSON file."""
    data = _load_json(json_path)
    top = {k: data[k] for k in _INTRINSIC_KEYS if k in data}
    views = []
    for i, frame in enumerate(data["frames"]):
        where = f"{json_path} frame {i}"
        if not isinstance(frame, dict) or "file_path" not in frame:
            raise UserError(f"{where}: expected an object with 'file_path' and 'transform_matrix'")
        where = f"{json_path} frame {i} ({frame['file_path']})"
        listed = _resolve_file(root, frame["file_path"], json_path, i)
        image, paired = _pair(listed, root)
        settings = dict(top)
        settings.update({k: frame[k] for k in _INTRINSIC_KEYS if k in frame})
        views.append(DeclaredView(image.name, image, _camera(settings, image, where), _pose(frame, where), paired))
    return views


def read_transforms_scene(root: Path) -> DeclaredScene:
    """Read a transforms-JSON scene folder (see the module docstring)."""

    root = Path(root)
    if (root / "low").is_dir() and (root / "high").is_dir():
        check_same_files(root / "low", root / "high")
    splits: Dict[str, List[DeclaredView]] = {s: [] for s in SPLITS}
    if (root / "transforms_train.json").is_file():
        for s in SPLITS:
            p = root / f"transforms_{s}.json"
            if p.is_file():
                splits[s] = read_split_json(root, p)
    else:
        splits["train"] = read_split_json(root, root / "transforms.json")
    if not splits["train"]:
        raise UserError(f"{root}: transforms JSON lists no train frames")
    scene = DeclaredScene(root, "transforms", splits["train"], splits["test"], splits["val"], None, None, "random")
    model_dir = find_model_dir(root)
    if model_dir is not None:
        model = read_model(model_dir)
        points = points_in_frame_of(model, scene.train + scene.test) if len(model.points) else None
        if points is not None:  # None: the frames could not be related (a warning said so): random points
            scene.points = points
            scene.colors = model.colors
            scene.points_source = "colmap"
    return scene
