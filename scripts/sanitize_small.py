"""A small forward + backward render on the GPU, for compute-sanitizer (memcheck / racecheck)."""
import torch

from retinexgs.bench.scenes import orbit_camera, random_scene
from retinexgs.bench.raster import render_ours

for n, w, h in [(3000, 97, 61), (500, 33, 17)]:
    scene = {k: v.requires_grad_() for k, v in random_scene(n, device="cuda").items()}
    for C in (3,):
        image = render_ours(scene, orbit_camera(w, h), 3)
        image.sum().backward()
torch.cuda.synchronize()
print("sanitize run finished")
