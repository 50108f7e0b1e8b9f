"""Small fused-colour and inference-renderer frames on the GPU, for compute-sanitizer (memcheck / racecheck of the
shared-memory weight staging)."""
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_fused_colors import SHAPES, make_field, make_gaussians, make_model  # noqa: E402

from retinexgs.model.inference import InferenceRenderer, fused_gaussian_colors  # noqa: E402
from scenes import make_camera  # noqa: E402

for dtype in (torch.float32, torch.float64):
    for shape in SHAPES + [(10, 4, 128, 3, 32)]:  # the last one reads float64 weights from global memory
        g, f = make_gaussians(n=333, dtype=dtype).cuda(), make_field(shape, dtype).cuda()
        fused_gaussian_colors(g, [0.3, -0.2, 2.5], 3, f)
    fused_gaussian_colors(g, [0.3, -0.2, 2.5], 3, None)
model = make_model(n=500).cuda()
renderer = InferenceRenderer(model, 3)
cam = make_camera(width=50, height=30, eye=(0.3, -0.2, -3.0))
for _ in range(3):
    renderer.render(cam, exposure=0.8)
torch.cuda.synchronize()
print("sanitize frame run finished")
