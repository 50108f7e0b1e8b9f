"""Issue 52's check on real sensor data (CPU, a few seconds):

    python scripts/raw_samples.py [RAW_DIR] --out OUT_DIR

Opens every camera raw file in RAW_DIR (default ../shared/data/raw-samples: a Canon DNG of a colour chart,
14-bit, and a Canon CRW shot indoors at night), prints its metadata and notes, writes its preview (the one pose
estimation will see) as OUT_DIR/NAME.png, and prints the noise model estimated from its pixels beside the DNG
NoiseProfile where the file carries one, with the ratio estimate / profile of the predicted variance at a few
signal levels. The raw files are read in place, never copied.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from retinexgs.data.camera_raw import RAW_EXTENSIONS, estimate_noise, noise_from_profile, preview_srgb, read_raw
from retinexgs.errors import UserError


def _fmt(v) -> str:
    return "None" if v is None else f"{v:.4g}"


def main(argv=None) -> int:
    default = Path(__file__).resolve().parents[2] / "shared" / "data" / "raw-samples"
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("raw_dir", nargs="?", type=Path, default=default)
    ap.add_argument("--out", type=Path, required=True, help="folder for the preview PNGs")
    args = ap.parse_args(argv)
    files = sorted(p for p in args.raw_dir.iterdir() if p.suffix.lower() in RAW_EXTENSIONS)
    if not files:
        print(f"raw_samples: error: no camera raw files in {args.raw_dir}", file=sys.stderr)
        return 2
    import cv2
    from retinexgs.fileio import atomic_write

    for path in files:
        try:
            ph = read_raw(path)
        except UserError as exc:
            print(f"{path.name}: error: {exc}")
            continue
        h, w = ph.shape
        print(f"## {path.name}")
        camera = ph.model if ph.model.startswith(ph.make) else f"{ph.make} {ph.model}".strip()
        print(f"  camera        {camera or 'not named in the metadata'}")
        print(f"  mosaic        {w}x{h} uint16, CFA {ph.cfa_pattern}, raw values {ph.mosaic.min()}..{ph.mosaic.max()}")
        print(f"  black / white {ph.black_level.reshape(-1).tolist()} / {ph.white_level:g}"
              f"{' (+ per-pixel map)' if ph.black_map is not None else ''}")
        print(f"  white balance R {ph.white_balance[0]:.4f}  G 1  B {ph.white_balance[2]:.4f}")
        print(f"  camera->sRGB  {np.round(ph.cam_to_srgb, 4).tolist()}")
        print(f"  exposure      {_fmt(ph.exposure_time)} s, ISO {_fmt(ph.iso)}, f/{_fmt(ph.f_number)}")
        for note in ph.notes:
            print(f"  note: {note}")
        img = preview_srgb(ph)
        out = args.out / (path.stem + ".png")
        ok, buf = cv2.imencode(".png", img[..., ::-1])
        atomic_write(out, lambda f: f.write(buf.tobytes()))
        print(f"  preview       {out} ({img.shape[1]}x{img.shape[0]}, mean {img.mean():.1f} of 255)")
        a, b = estimate_noise(ph)
        rng = float(ph.white_level - ph.black_level.mean())
        for c, name in enumerate("RGB"):
            print(f"  noise {name} (data)    var = {a[c]:.4g} x + {b[c]:.4g}   "
                  f"(in DN: gain {a[c] * rng:.3g} DN/e-, read noise {np.sqrt(max(b[c], 0)) * rng:.3g} DN)")
        prof = noise_from_profile(ph)
        if prof is None:
            print("  noise profile none in this file (nothing to compare the estimate with)")
        else:
            pa, pb = prof
            for c, name in enumerate("RGB"):
                x = np.array([0.01, 0.1, 0.5])
                ratio = (a[c] * x + b[c]) / (pa[c] * x + pb[c])
                print(f"  noise {name} (profile) var = {pa[c]:.4g} x + {pb[c]:.4g}   estimate/profile at x = "
                      f"0.01, 0.1, 0.5: {', '.join(f'{r:.2f}' for r in ratio)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
