"""Scene loading: cameras, poses, images and initial points from transforms JSON (LOM / instant-ngp),
COLMAP models, or plain photo folders (SfM with pycolmap). See docs/data.md."""
from retinexgs.data.camera import Intrinsics
from retinexgs.data.load import load_scene
from retinexgs.data.scene import Normalization, Scene, View
from retinexgs.data.sfm import SfmResult, run_sfm

__all__ = ["Intrinsics", "Normalization", "Scene", "SfmResult", "View", "load_scene", "run_sfm"]
