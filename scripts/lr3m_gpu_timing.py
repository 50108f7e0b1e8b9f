"""Time LR3M variants on one fox-dark image on the GPU; prints the fastest setting as KEY=VALUE overrides."""
import sys
import time

import torch

from retinexgs.data.images import load_image_tensor
from retinexgs.retinex import get_decomposer

img = load_image_tensor(sys.argv[1]).cuda()
best = None
for name, params in [("gram40", {}), ("gram32", {"group_size": 32}), ("svd40", {"solver": "svd"})]:
    d = get_decomposer("lr3m", **params)
    d(img)  # warm-up
    torch.cuda.synchronize()
    t0 = time.time()
    d(img)
    torch.cuda.synchronize()
    dt = time.time() - t0
    print(f"lr3m {name}: {dt:.2f} s / image", flush=True)
    if best is None or dt < best[0]:
        best = (dt, params)
print("BEST " + " ".join(f"--set decomposer.params.{k}={v}" for k, v in best[1].items()) + f" # {best[0]:.2f}")
