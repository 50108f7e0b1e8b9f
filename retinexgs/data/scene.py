"""The :class:`Scene` every reader returns: views with pinhole cameras and poses, initial points, and the
world normalisation that maps between the scene's working frame and the input's world frame.

Normalisation (applied by :func:`retinexgs.data.load_scene` unless ``normalize=False``): the centre is the
mean of the *train* camera centres and the scale makes the largest distance from that centre to a train
camera equal to 1 (scale 1 if all train cameras coincide). A world point ``x`` becomes
``(x - center) * scale``; camera rotations are unchanged, camera centres are mapped like points.
:meth:`Normalization.to_world` undoes it for exports.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Tuple, Union

import numpy as np
import torch

from retinexgs.data.camera import Intrinsics
from retinexgs.data.capture import Capture, capture_of_files
from retinexgs.data.images import is_raw_file, load_image_tensor
from retinexgs.data.photo_balance import balance_photo

ArrayLike = Union[np.ndarray, torch.Tensor]


def warn(message: str) -> None:
    """Report input that is doubtful but usable: one line ``warning: MESSAGE`` on stderr (the loaders' style;
    refused input raises :class:`~retinexgs.errors.UserError` instead)."""
    print(f"warning: {message}", file=sys.stderr, flush=True)


@dataclass
class Normalization:
    """Similarity from the input world frame to the working frame: ``x_norm = (x_world - center) * scale``."""

    center: torch.Tensor  # [3] float64, in world units
    scale: float

    @staticmethod
    def identity() -> "Normalization":
        """The normalisation that changes nothing."""
        return Normalization(torch.zeros(3, dtype=torch.float64), 1.0)

    def to_world(self, xyz: ArrayLike) -> ArrayLike:
        """Map [...,3] normalised points back to the input's world frame (same type and dtype as given)."""
        if isinstance(xyz, torch.Tensor):
            c = self.center.to(device=xyz.device, dtype=xyz.dtype)
            return xyz / self.scale + c
        a = np.asarray(xyz)
        return (a / self.scale + self.center.numpy()).astype(a.dtype if a.dtype.kind == "f" else np.float64)

    def to_normalized(self, xyz: ArrayLike) -> ArrayLike:
        """Map [...,3] world points into the normalised frame (same type as given)."""
        if isinstance(xyz, torch.Tensor):
            c = self.center.to(device=xyz.device, dtype=xyz.dtype)
            return (xyz - c) * self.scale
        a = np.asarray(xyz)
        return ((a - self.center.numpy()) * self.scale).astype(a.dtype if a.dtype.kind == "f" else np.float64)

    def pose_to_normalized(self, c2w: torch.Tensor) -> torch.Tensor:
        """Map a 4x4 camera-to-world matrix into the normalised frame (rotation kept, centre moved/scaled)."""
        out = c2w.clone()
        out[:3, 3] = (c2w[:3, 3] - self.center.to(c2w.dtype)) * self.scale
        return out

    def pose_to_world(self, c2w: torch.Tensor) -> torch.Tensor:
        """Map a normalised 4x4 camera-to-world matrix back to the input's world frame."""
        out = c2w.clone()
        out[:3, 3] = c2w[:3, 3] / self.scale + self.center.to(c2w.dtype)
        return out


@dataclass
class View:
    """One photo with its camera.

    ``image_path`` is the file the pixels are read from (a cached undistorted/resized copy when the
    input needed it); ``source_path`` is the user's original file. ``paired_path`` is the normal-light
    image of the same view when the dataset has one (LOM's ``high/``), preprocessed like the input.
    Intrinsics are pinhole, in pixels, centre of pixel (0,0) at (0.5, 0.5). ``camera_to_world`` is 4x4
    float64 in OpenCV axes (x right, y down, z forward), in the scene's normalised frame.
    """

    name: str
    image_path: Path
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    camera_to_world: torch.Tensor
    paired_path: Optional[Path] = None
    source_path: Optional[Path] = None
    # data.white_balance (retinexgs.data.photo_balance): gains on the photo's linear light, set for every view of a
    # scene by retinexgs.run.folder.open_scene; None: the photo as shot. The paired truth is never balanced.
    balance: Optional[Tuple[float, float, float]] = None
    _image: Optional[torch.Tensor] = field(default=None, repr=False, compare=False)
    _paired: Optional[torch.Tensor] = field(default=None, repr=False, compare=False)

    @property
    def image(self) -> torch.Tensor:
        """The input image as float32 [H,W,3] in [0,1], read on first use and kept."""
        if self._image is None:
            self._image = self.load_image()
        return self._image

    @property
    def paired_image(self) -> Optional[torch.Tensor]:
        """The paired normal-light image as float32 [H,W,3] in [0,1], or None when there is none."""
        if self.paired_path is None:
            return None
        if self._paired is None:
            paired = load_image_tensor(self.paired_path)
            if tuple(paired.shape[:2]) != (self.height, self.width) and self.is_raw:
                # the truth of a raw view whose odd last row/column was dropped (data.load._fit_camera): the same crop
                paired = paired[:self.height, :self.width].contiguous()
            self._paired = paired
        return self._paired

    def load_image(self) -> torch.Tensor:
        """Read the input image from disk (not cached) as float32 [H,W,3] in [0,1] (with :attr:`balance`)."""
        return balance_photo(load_image_tensor(self.image_path), self.balance)

    def load_target(self) -> torch.Tensor:
        """What training compares renders with: :meth:`load_image`, except for a camera raw view, whose values are
        not clipped (its unclipped encoding, :func:`retinexgs.data.srgb.linear_to_srgb_extended`: the noise around
        black stays zero-mean; issue 52 stage 3b), rounded to float16: 11 bits of mantissa, a relative step of
        2⁻¹¹, far below any raw view's noise, and half the view store's bytes (6 per pixel, a 24 MP raw 144 MB as
        for a 16-bit RGB photo; preloaded and streamed views stay bit-identical)."""
        capture = self.capture
        target = balance_photo(load_image_tensor(self.image_path, unclipped=True), self.balance,
                               unclipped=capture.unclipped)
        return capture.encode_target(target)

    @property
    def is_raw(self) -> bool:
        """True when the user's file is a camera raw file."""
        return is_raw_file(self.user_path)

    @property
    def user_path(self) -> Path:
        """The user's file (:attr:`source_path`, else :attr:`image_path`)."""
        return Path(self.source_path if self.source_path is not None else self.image_path)

    @property
    def capture(self) -> Capture:
        """The kind of capture the user's file is (:mod:`retinexgs.data.capture`)."""
        return capture_of_files([self.user_path])

    def release_images(self) -> None:
        """Drop the cached image tensors (they are read again on next use)."""
        self._image = None
        self._paired = None

    @property
    def camera(self) -> Intrinsics:
        """The view's pinhole camera."""
        return Intrinsics(self.width, self.height, self.fx, self.fy, self.cx, self.cy)

    def K(self) -> torch.Tensor:
        """3x3 float64 intrinsics matrix (pixel-centre convention)."""
        return torch.tensor(self.camera.K(), dtype=torch.float64)

    def world_to_camera(self) -> torch.Tensor:
        """4x4 float64 world-to-camera matrix (inverse of ``camera_to_world``, computed in closed form)."""
        R = self.camera_to_world[:3, :3]
        t = self.camera_to_world[:3, 3]
        out = torch.eye(4, dtype=torch.float64)
        out[:3, :3] = R.T
        out[:3, 3] = -R.T @ t
        return out

    @property
    def camera_center(self) -> torch.Tensor:
        """[3] float64 camera centre in the scene frame."""
        return self.camera_to_world[:3, 3]

    def project(self, points: ArrayLike) -> torch.Tensor:
        """Project [N,3] scene points to [N,2] float64 pixel positions and return them with depth as [N,3]."""
        p = torch.as_tensor(np.asarray(points) if not isinstance(points, torch.Tensor) else points,
                            dtype=torch.float64)
        w2c = self.world_to_camera()
        pc = p @ w2c[:3, :3].T + w2c[:3, 3]
        z = pc[:, 2]
        u = self.fx * pc[:, 0] / z + self.cx
        v = self.fy * pc[:, 1] / z + self.cy
        return torch.stack([u, v, z], dim=-1)


@dataclass
class Scene:
    """A loaded scene: train/test (and optional val) views, initial points and the world normalisation.

    ``points`` is [P,3] float32 and ``colors`` [P,3] float32 in [0,1], both in the normalised frame.
    ``points_source`` says where the points came from ("colmap", "sfm" or "random").
    """

    root: Path
    reader: str
    train: List[View]
    test: List[View]
    points: torch.Tensor
    colors: torch.Tensor
    normalization: Normalization
    points_source: str = "colmap"
    val: List[View] = field(default_factory=list)
    # what the training views are (photo or camera raw; retinexgs.data.capture): made by load_scene, else here
    capture: Optional[Capture] = None

    def __post_init__(self) -> None:
        if self.capture is None:
            self.capture = capture_of_files([v.user_path for v in self.train])

    @property
    def views(self) -> List[View]:
        """Train views followed by test views."""
        return list(self.train) + list(self.test)

    @property
    def raw(self) -> bool:
        """True when the training views are camera raw files (:attr:`capture`'s kind; a split is all raw or none:
        the loader refuses a mix)."""
        return self.capture.kind == "raw"

    def views_per_point(self, max_points: int = 20000) -> Optional[float]:
        """The median number of training views whose frustum holds a scene point (in front of the camera and
        inside its frame; occlusion ignored), over the reconstructed points (at most ``max_points`` of them, evenly
        taken): how many views the multi-view fit averages at a point. None without SfM/COLMAP points (random
        points say nothing about the scene) or without training views."""
        if self.points_source == "random" or len(self.points) == 0 or not self.train:
            return None
        step = max(1, -(-len(self.points) // max_points))
        pts = self.points[::step].to(torch.float64)
        seen = torch.zeros(len(pts), dtype=torch.int64)
        for v in self.train:
            uvz = v.project(pts)
            u, w, z = uvz[:, 0], uvz[:, 1], uvz[:, 2]
            seen += ((z > 0) & (u >= 0) & (u < v.width) & (w >= 0) & (w < v.height)).to(torch.int64)
        return float(seen.to(torch.float64).median())

    def summary(self) -> str:
        """One line describing the scene (counts and resolution)."""
        sizes = sorted({(v.width, v.height) for v in self.views})
        res = ", ".join(f"{w}x{h}" for w, h in sizes)
        paired = sum(v.paired_path is not None for v in self.test)
        return (f"{self.root} [{self.reader}]: {len(self.train)} train / {len(self.test)} test views "
                f"({paired} test views paired), {res}, {len(self.points)} {self.points_source} points")


def scene_label(scene: Path) -> str:
    """``lom/buu`` for .../lom/buu, ``fox-dark`` for .../fox-dark (the parent is kept when it is a collection)."""
    scene = Path(scene).resolve()
    return f"{scene.parent.name}/{scene.name}" if scene.parent.name.lower() in ("lom", "llnerf", "data_lom") \
        else scene.name
