import sys, torch, faulthandler
faulthandler.enable()
from retinexgs.render._backend import kernels
K = kernels()
for dev in ["cpu", "cuda"]:
    m = torch.zeros(3, 3, device=dev)
    try:
        K.project_forward(m, torch.zeros(2, 4, device=dev), torch.ones(3, 3, device=dev), torch.ones(3, device=dev), [0.0]*16, 1.0, 1.0, 0.0, 0.0, 4, 4, 0.01, 100.0)
    except Exception as e:
        print(dev, "shape check ->", type(e).__name__, str(e)[:80], flush=True)
    try:
        K.rasterize_forward(torch.zeros(3, 2, device=dev), torch.zeros(3, 3, device=dev), torch.zeros(3, 65, device=dev), torch.zeros(3, device=dev),
                            torch.zeros(0, dtype=torch.int32, device=dev), torch.zeros(1, 2, dtype=torch.int32, device=dev), 4, 4)
        print(dev, "65 channels ok", flush=True)
    except Exception as e:
        print(dev, "65 channels ->", type(e).__name__, str(e)[:80], flush=True)
