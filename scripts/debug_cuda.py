import sys, torch, faulthandler
faulthandler.enable()
sys.path.insert(0, "tests")
from retinexgs.render.functions import ProjectGaussians, bin_gaussians
from retinexgs.render._backend import kernels
from scenes import make_camera, random_gaussians
cam = make_camera(width=173, height=91)
for C in [1, 2, 3, 4, 5, 6, 7, 8, 9, 16, 17, 33, 64]:
    args = [a.float().cuda() for a in random_gaussians(4000, C, seed=9)]
    m2, d, cn, r = ProjectGaussians.apply(*args[:4], cam)
    ids, tr = bin_gaussians(m2, r, d, cam.width, cam.height)
    print("C", C, "pairs", ids.shape[0], flush=True)
    img, T, last = kernels().rasterize_forward(m2, cn, args[4], args[3], ids, tr, cam.width, cam.height)
    torch.cuda.synchronize()
    print("  fwd ok", float(img.sum()), flush=True)
    v = kernels().rasterize_backward(m2, cn, args[4], args[3], ids, tr, cam.width, cam.height, T, last,
                                     torch.ones_like(img), torch.zeros_like(T))
    torch.cuda.synchronize()
    print("  bwd ok", flush=True)
