"""Which photo scenes does the denoiser help: does the brightened previews' chroma noise at a few pixels' scale tell
them apart (issue 64)?

For each folder of photos: the brightened preview of up to 5 photos (the enhancement's auto exposure, as
``retinexgs/train/sfm_preview.py`` makes it), the noise σ of its luma and of its two opponent chroma components
((R−B)/√2, (R−2G+B)/√6; sRGB in [0, 1]) by Immerkær's estimate on 1×1, 2×2, 4×4 and 8×8 averages
(``measured_sigma``, expressed per pixel: white noise reads the same at every scale, noise correlated over several
pixels and texture read higher the coarser the scale), the median over the photos; then the chroma σ of the 4×4
averages themselves (σ@4 / 4). Usage: python experiments/photo_chroma_sigma_study.py NAME=FOLDER ...
"""
import sys
from pathlib import Path

import numpy as np
import torch

from retinexgs.data.enhance import auto_exposure
from retinexgs.data.images import list_images, read_image
from retinexgs.data.sensor import JpegCodec
from retinexgs.retinex.denoise import measured_sigma
from retinexgs.train.sfm_preview import PROBE_PHOTOS

BASIS = np.array([[0.299, 0.587, 0.114], [1 / np.sqrt(2), 0, -1 / np.sqrt(2)],
                  [1 / np.sqrt(6), -2 / np.sqrt(6), 1 / np.sqrt(6)]], np.float32)
SCALES = (1, 2, 4, 8)


def sigmas(path: Path) -> np.ndarray:
    """[scale, component] σ of one photo's brightened preview."""
    bright = auto_exposure(read_image(path)).astype(np.float32) / 255.0
    comps = np.einsum("ij,hwj->ihw", BASIS, bright)
    return np.array([[measured_sigma(torch.from_numpy(c).double(), s) for c in comps] for s in SCALES])


def main(args):
    print("| scene | format, size | luma σ @1, 2, 4, 8 | chroma σ @1, 2, 4, 8 (mean of the two) | chroma σ of the 4×4 averages |")
    print("|---|---|---|---|---|")
    for arg in args:
        name, folder = arg.split("=", 1)
        paths = list_images(Path(folder))
        chosen = paths[::max(1, len(paths) // PROBE_PHOTOS)][:PROBE_PHOTOS]
        s = np.median(np.array([sigmas(p) for p in chosen]), axis=0)
        chroma = s[:, 1:].mean(1)
        fmt = "JPEG" if JpegCodec.of_file(chosen[0]) is not None else chosen[0].suffix.lstrip(".").upper()
        w, h = read_image(chosen[0]).shape[1::-1]
        print(f"| {name} | {fmt} {w}×{h} | " + ", ".join(f"{v:.3f}" for v in s[:, 0]) + " | "
              + ", ".join(f"{v:.3f}" for v in chroma) + f" | **{chroma[SCALES.index(4)] / 4:.3f}** |")


if __name__ == "__main__":
    main(sys.argv[1:])
