"""2D check for issue 32's colour target (CPU, about 4 minutes on 2 cores):

    python experiments/colour_2d.py DATA_ROOT      # DATA_ROOT holds fox-dark, lom/{buu,sofa,bike}, strecha/...

Prints a markdown row per scene: test views, ΔE of the dark photos, of LR3M's enhancement, of that enhancement
after grey-world gains, after grey-edge gains, and the two sets of gains. Measures the colour error (CIELAB ΔE of the average colours after GT-mean
alignment) of the dark photos and of LR3M's enhancement of them, against the normal-light photos, on each dev scene's
test views; and the same after a grey-world white balance whose gains come from the LR3M reflectance R of 4
training views (mean R per channel scaled to their grey mean), and after a grey-edge one (van de Weijer et al. 2007,
p = 6: the Minkowski mean of each channel's gradient magnitude in linear light, of the same R, taken as the cast).
"""
import json
import sys
from pathlib import Path

import numpy as np
import torch

from retinexgs.data.images import load_image_tensor
from retinexgs.retinex import decompose, enhance_for_viewing
from retinexgs.evaluate.metrics import colour_error
from retinexgs.model.tone import linear_to_srgb, srgb_to_linear

root = Path(sys.argv[1])
for scene in ["fox-dark", "lom/buu", "lom/sofa", "lom/bike", "strecha/fountain-dark", "strecha/castlep30-dark"]:
    d = root / scene
    test = [f["file_path"] for f in json.loads((d / "transforms_test.json").read_text())["frames"]]
    train = [f["file_path"] for f in json.loads((d / "transforms_train.json").read_text())["frames"]]
    def img(rel):
        p = d / rel
        if not p.suffix:
            p = next(p.parent.glob(p.name + ".*"))
        return p
    Rs, edges = [], []
    for rel in train[:: max(1, len(train) // 4)][:4]:
        R, L = decompose(load_image_tensor(img(rel)), "lr3m")
        Rs.append(R.reshape(-1, 3).double().mean(0))
        lin = srgb_to_linear(R.double().clamp(0, 1))
        gx, gy = lin[:, 1:] - lin[:, :-1], lin[1:] - lin[:-1]
        mag = (gx[:-1] ** 2 + gy[:, :-1] ** 2).sqrt().reshape(-1, 3)
        edges.append((mag ** 6).mean(0) ** (1 / 6))
    m = torch.stack(Rs).mean(0)
    gains = (m.mean() / m).float()
    e = torch.stack(edges).mean(0)
    edge_gains = (e.mean() / e).float()  # in linear light: applied to the enhancement's linear values
    low_e, enh_e, wb_e, ge_e = [], [], [], []
    for rel in test:
        low = load_image_tensor(img(rel.replace("high/", "low/")))
        high = load_image_tensor(img(rel.replace("low/", "high/")))
        R, L = decompose(low, "lr3m")
        enh = enhance_for_viewing(R, L)
        low_e.append(colour_error(low, high)); enh_e.append(colour_error(enh, high))
        wb_e.append(colour_error((enh * gains).clamp(0, 1), high))
        ge_e.append(colour_error(linear_to_srgb((srgb_to_linear(enh.double().clamp(0, 1)) * edge_gains).clamp(0, 1)).float(), high))
    print(f"| {scene} | {len(test)} | {np.mean(low_e):.2f} | {np.mean(enh_e):.2f} | {np.mean(wb_e):.2f} | "
          f"{np.mean(ge_e):.2f} | {', '.join(f'{g:.3f}' for g in gains.tolist())} | "
          f"{', '.join(f'{g:.3f}' for g in edge_gains.tolist())} |", flush=True)
