"""SfM on a bare night folder, scored against the scene's own poses (issue 64 item 5; notes/2026-11-28-sfm-night.md).

Runs ``run_sfm`` (``--denoise auto``, 2 threads, ``--min-registered 0``) on FOLDER, then aligns the registered camera
centres to the scene's transforms_{train,val,test}.json centres (Umeyama similarity, matched by file stem) and prints
one ``RESULT {json}`` line: registered / photos, points, and the median and largest centre error relative to the
scene's extent (the RMS distance of its camera centres from their mean); where the night settings' agreement check
(NIGHT_AGREE) ran, ``check`` holds the same figures for its strict model and each loose mapping, their agreement and
the decision (the note's sections 5-6). ``--night`` picks the night settings
(default off: today's code before them); ``H10_OPTS`` (JSON: {"sift": {...}, "mapper": {...}, "tri": {...},
"pipeline": {...}}) overrides pycolmap options on top, for the study's variants.

``H10_BIN=2`` (section 7) makes each raw preview from the 2x2 means of its linear light, the denoiser's noise model
divided by 4, at half size; with ``H10_UP=1`` the preview is resized back to the photo's size. ``--seed`` is
run_sfm's seed (the mapper's; the loose mappings use seed, seed + 1).

    python experiments/sfm_night_study.py FOLDER SCENE OUT [--night auto|on|off] [--seed N]
"""
import json, os, sys, time
from pathlib import Path
import numpy as np
import pycolmap

OPTS = json.loads(os.environ.get("H10_OPTS", "{}"))

def _set(obj, d):
    for k, v in d.items():
        cur = getattr(obj, k)
        if hasattr(cur, "__members__") or type(cur).__name__ in ("Normalization",):
            v = getattr(type(cur), v)
        setattr(obj, k, v)

_ext, _mex, _map = pycolmap.extract_features, pycolmap.match_exhaustive, pycolmap.incremental_mapping
def ext(*a, extraction_options=None, **k):
    _set(extraction_options.sift, OPTS.get("sift", {})); return _ext(*a, extraction_options=extraction_options, **k)
def mex(*a, matching_options=None, **k):
    _set(matching_options.sift, OPTS.get("match", {}))
    for kk, v in OPTS.get("matchopt", {}).items(): setattr(matching_options, kk, v)
    return _mex(*a, matching_options=matching_options, **k)
def mp(*a, options=None, **k):
    _set(options.mapper, OPTS.get("mapper", {})); _set(options, OPTS.get("pipeline", {})); _set(options.triangulation, OPTS.get("tri", {}))
    return _map(*a, options=options, **k)
if OPTS:  # only a variant replaces the stages
    pycolmap.extract_features, pycolmap.match_exhaustive, pycolmap.incremental_mapping = ext, mex, mp

from retinexgs.data.sfm import run_sfm

UP = os.environ.get("H10_UP") == "1"  # with BIN: the binned preview resized back to the photo's size
BIN = int(os.environ.get("H10_BIN", "1"))  # the study's variant (section 7): raw previews binned BIN x BIN first
if BIN > 1:
    import retinexgs.data.sfm as _S

    def _binned_preview(src, denoise=None):
        from retinexgs.data.camera_raw import _demosaiced_srgb_linear, read_raw
        from retinexgs.data.raw_noise import view_noise
        photo = read_raw(src)
        lin = _demosaiced_srgb_linear(photo)
        h, w = lin.shape[0] // BIN * BIN, lin.shape[1] // BIN * BIN
        lin = lin[:h, :w].reshape(h // BIN, BIN, w // BIN, BIN, 3).mean((1, 3))
        a, b, _s, _n = view_noise(photo)
        if denoise is not None and a is not None and b is not None and np.any(a > 0):
            lin = denoise.apply(lin, np.asarray(a) / BIN ** 2, np.asarray(b) / BIN ** 2)  # a mean of BIN^2 pixels
        out = _S._bright_preview(lin, percentile=99.0, target=0.9)
        if UP:  # variant a2: back to the photo's size (SIFT at full size, no intrinsics to scale)
            import cv2
            out = cv2.resize(out, (out.shape[1] * BIN, out.shape[0] * BIN), interpolation=cv2.INTER_LINEAR)
        return out
    _S._raw_preview = _binned_preview
from retinexgs.train.sfm_preview import sfm_preview_denoise

def gt_centres(scene):
    c = {}
    for part in ("train", "val", "test"):
        f = Path(scene) / f"transforms_{part}.json"
        if f.is_file():
            for fr in json.loads(f.read_text())["frames"]:
                m = np.array(fr["transform_matrix"], float)
                c[Path(fr["file_path"]).stem] = m[:3, 3]
    return c

def umeyama(src, dst):
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3); D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    s = np.trace(np.diag(S) @ D) / (xs ** 2).sum(1).mean()
    t = mu_d - s * R @ mu_s
    return s, R, t

def truth_error(centres, gt, extent):
    """{"reg", "med", "max"}: camera centres ({name: centre}) against the scene's, after a similarity."""
    names = [n for n in centres if Path(n).stem in gt]
    if len(names) < 3:
        return dict(reg=len(centres), med=None, max=None)
    est = np.array([centres[n] for n in names]); ref = np.array([gt[Path(n).stem] for n in names])
    s, R, t = umeyama(est, ref)
    e = np.linalg.norm((s * (R @ est.T)).T + t - ref, axis=1) / extent
    return dict(reg=len(centres), med=round(float(np.median(e)), 4), max=round(float(e.max()), 4))

def record_check(scene, check):
    """Wrap the agreement check's decision (choose_consensus) so that ``check`` records each model's truth error."""
    import retinexgs.data.sfm as S
    gt = gt_centres(scene)
    allgt = np.array(list(gt.values())); extent = np.sqrt(((allgt - allgt.mean(0)) ** 2).sum(1).mean())
    consensus = S.choose_consensus
    def rnd(fit):
        return fit and {k: (round(v, 4) if isinstance(v, float) else v) for k, v in fit.items()}
    def consensus_rec(strict, mappings, n, agree):
        chosen, why, info = consensus(strict, mappings, n, agree)
        ms = agree["min_shared_photos"]
        check.update(strict=truth_error(strict or {}, gt, extent),
                     mappings=[dict(truth=m and truth_error(m, gt, extent), agree=rnd(x["strict"]),
                                    candidate=x["candidate"], supporters=x["supporters"],
                                    pairs={j: rnd(S.centre_agreement(m, o, ms)) for j, o in enumerate(mappings)
                                           if m and o and j != i})
                               for i, (m, x) in enumerate(zip(mappings, info))],
                     used="strict" if chosen is None else f"loose{chosen + 1}", why=why)
        return chosen, why, info
    S.choose_consensus = consensus_rec

def main(folder, scene, out):
    t0 = time.time()
    check = {}
    record_check(scene, check)
    den = sfm_preview_denoise(folder, "auto", "auto", None)
    from retinexgs.errors import UserError
    Path(out, "enhanced").mkdir(parents=True, exist_ok=True)  # keep the previews across failed runs
    try:
        r = run_sfm(folder, out, denoise=den, num_threads=2, min_registered=0, force=True, night=os.environ.get("H10_NIGHT", "off"),
                    seed=int(os.environ.get("H10_SEED", "0")))
    except UserError as e:
        print("RESULT", json.dumps(dict(folder=str(folder), reg=0, n=len(os.listdir(folder)), err=str(e)[:80], sec=round(time.time()-t0,1), opts=OPTS, check=check)), flush=True)
        return
    rec = pycolmap.Reconstruction(str(r.model_dir))
    gt = gt_centres(scene)
    names, est, ref = [], [], []
    for i in rec.reg_image_ids():
        im = rec.images[i]
        st = Path(im.name).stem
        if st in gt:
            names.append(st); est.append(im.projection_center()); ref.append(gt[st])
    est, ref = np.array(est), np.array(ref)
    allgt = np.array(list(gt.values()))
    extent = np.sqrt(((allgt - allgt.mean(0)) ** 2).sum(1).mean())  # RMS radius of the GT camera centres
    if len(est) >= 3:
        s, R, t = umeyama(est, ref)
        err = np.linalg.norm((s * (R @ est.T)).T + t - ref, axis=1) / extent
        med, mx = float(np.median(err)), float(err.max())
    else:
        med = mx = float("nan")
    res = dict(folder=str(folder), bin=BIN, up=UP, seed=int(os.environ.get("H10_SEED", "0")), reg=r.num_registered, n=r.num_images, points=r.num_points,
               med_err=med, max_err=mx, sec=round(time.time() - t0, 1), opts=OPTS, check=check)
    print("RESULT", json.dumps(res), flush=True)

if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", help="bare folder of photos (no poses)")
    ap.add_argument("scene", help="the scene folder with transforms_*.json (the reference poses)")
    ap.add_argument("out", help="SfM output folder")
    ap.add_argument("--night", default="off", choices=["auto", "on", "off"])
    ap.add_argument("--seed", type=int, default=0, help="run_sfm's seed (the mapper's)")
    args = ap.parse_args()
    os.environ["H10_NIGHT"] = args.night
    os.environ["H10_SEED"] = str(args.seed)
    main(args.folder, args.scene, args.out)
