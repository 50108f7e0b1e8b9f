"""Does a night SfM model that is wrong as a whole contradict its own verified pairs? (issue 64 item 5;
notes/2026-11-28-sfm-night.md section 8)

For a SfM output folder (database.db + sparse/0, e.g. one kept by sfm_keep_mappings.py) and the scene with its own
poses: per verified image pair with >= 15 inliers, both photos posed, the median Sampson error (px) of its inlier
matches under the model's poses and under the scene's; then the model's camera-centre error against the scene's
(Umeyama similarity, relative to the RMS radius of the scene's centres), as sfm_night_study.py measures it.

    python experiments/sfm_pair_check.py OUT SCENE
"""
import sys, json
from pathlib import Path
import numpy as np
import pycolmap
from retinexgs.data import load_scene

def skew(t):
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])

def sampson(E, x1, x2):
    # x1, x2: [N,3] normalized homogeneous
    Ex1 = x1 @ E.T; Etx2 = x2 @ E
    num = np.sum(x2 * Ex1, 1) ** 2
    den = Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-30))

def centre_error(rec, truth):
    est, ref = [], []
    for iid in rec.reg_image_ids():
        im = rec.images[iid]; st = Path(im.name).stem
        if st in truth:
            est.append(im.projection_center()); ref.append(truth[st].camera_to_world.numpy()[:3, 3])
    est, ref = np.array(est), np.array(ref)
    allgt = np.array([v.camera_to_world.numpy()[:3, 3] for v in truth.values()])
    extent = np.sqrt(((allgt - allgt.mean(0)) ** 2).sum(1).mean())
    mu_s, mu_d = est.mean(0), ref.mean(0); a, b = est - mu_s, ref - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(a)); D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0: D[2, 2] = -1
    R = U @ D @ Vt; s = np.trace(np.diag(S) @ D) / (a ** 2).sum(1).mean(); t = mu_d - s * R @ mu_s
    err = np.linalg.norm((s * (R @ est.T)).T + t - ref, axis=1) / extent
    return len(est), float(np.median(err)), float(err.max())

def main(out, scene_dir, min_inliers=15):
    out = Path(out)
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    db = pycolmap.Database.open(str(out / "database.db"))
    scene = load_scene(scene_dir)
    truth = {Path(v.name).stem: v for v in scene.views}
    dbimgs = {im.image_id: im for im in db.read_all_images()}
    posed = {}
    for iid in rec.reg_image_ids():
        im = rec.images[iid]
        posed[Path(im.name).stem] = im
    pair_ids, geoms = db.read_two_view_geometries()
    rows = []
    for pid, g in zip(pair_ids, geoms):
        i1, i2 = pycolmap.pair_id_to_image_pair(pid)
        n1, n2 = Path(dbimgs[i1].name).stem, Path(dbimgs[i2].name).stem
        m = np.asarray(g.inlier_matches)
        if len(m) < min_inliers or n1 not in posed or n2 not in posed:
            continue
        k1 = np.asarray(db.read_keypoints(i1))[m[:, 0], :2]; k2 = np.asarray(db.read_keypoints(i2))[m[:, 1], :2]
        # model
        a, b = posed[n1], posed[n2]
        ca, cb = rec.cameras[a.camera_id], rec.cameras[b.camera_id]
        x1 = np.c_[ca.cam_from_img(k1), np.ones(len(k1))]; x2 = np.c_[cb.cam_from_img(k2), np.ones(len(k2))]
        Pa, Pb = a.cam_from_world().matrix(), b.cam_from_world().matrix()
        R = Pb[:, :3] @ Pa[:, :3].T; t = Pb[:, 3] - R @ Pa[:, 3]
        e_model = np.median(sampson(skew(t / np.linalg.norm(t)) @ R, x1, x2)) * ca.mean_focal_length()
        # truth
        ta, tb = truth[n1], truth[n2]
        y1 = np.c_[(k1[:, 0] - ta.cx) / ta.fx, (k1[:, 1] - ta.cy) / ta.fy, np.ones(len(k1))]
        y2 = np.c_[(k2[:, 0] - tb.cx) / tb.fx, (k2[:, 1] - tb.cy) / tb.fy, np.ones(len(k2))]
        Wa = np.linalg.inv(ta.camera_to_world.numpy()); Wb = np.linalg.inv(tb.camera_to_world.numpy())
        R = Wb[:3, :3] @ Wa[:3, :3].T; t = Wb[:3, 3] - R @ Wa[:3, 3]
        e_truth = np.median(sampson(skew(t / np.linalg.norm(t)) @ R, y1, y2)) * ta.fx
        rows.append((n1, n2, len(m), float(e_model), float(e_truth)))
    rows.sort(key=lambda r: -r[3])
    em = np.array([r[3] for r in rows]); et = np.array([r[4] for r in rows])
    for thr in (2, 4, 8):
        print(f"pairs with median Sampson > {thr} px: model {np.mean(em > thr):.3f}, truth {np.mean(et > thr):.3f}  (of {len(rows)})")
    print("worst pairs under the model:", [(r[0], r[1], r[2], round(r[3], 1), round(r[4], 1)) for r in rows[:8]])
    n, med, mx = centre_error(rec, truth)
    print(json.dumps(dict(model=str(out), reg=n, centre_med=round(med, 3), centre_max=round(mx, 3), max_pair=round(float(em.max()), 1),
                          n_gt4=int(np.sum(em > 4)), n_gt8=int(np.sum(em > 8)), pairs=len(rows), model_med=float(np.median(em)), truth_med=float(np.median(et)),
                          model_gt4=float(np.mean(em > 4)), truth_gt4=float(np.mean(et > 4)))))

if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
