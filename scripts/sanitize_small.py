"""A small forward + backward render on the GPU, for compute-sanitizer (memcheck / racecheck)."""
import torch

from retinexgs.bench.scenes import orbit_camera, random_scene
from retinexgs.bench.raster import render_ours

for n, w, h in [(3000, 97, 61), (500, 33, 17)]:
    scene = {k: v.requires_grad_() for k, v in random_scene(n, device="cuda").items()}
    for C in (3,):
        image = render_ours(scene, orbit_camera(w, h), 3)
        image.sum().backward()
# The projection's finiteness check on a bad input (its flag write and the pinned read-back), then a clean render.
scene = random_scene(500, device="cuda")
scene["means"][7, 1] = float("nan")
try:
    render_ours(scene, orbit_camera(33, 17), 3)
    raise SystemExit("a NaN mean was not refused")
except ValueError as err:
    print("refused as expected:", str(err)[:60])
torch.cuda.synchronize()
print("sanitize run finished")
