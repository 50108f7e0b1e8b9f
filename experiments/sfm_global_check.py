"""Global SfM (COLMAP's global mapper, GLOMAP, through pycolmap.global_mapping) on the matches of a night SfM run,
scored against the scene's own poses (issue 64 item 5; notes/2026-11-28-sfm-night.md section 9).

OUT is a folder with database.db and enhanced/ (the previews SfM matched): sfm_night_study.py's OUT, or a mapping
kept by sfm_keep_mappings.py with OUT/enhanced linked to its run's previews. The database is copied first (the global
mapper writes to it). Prints each model's posed photos, points and camera-centre error (median / largest, relative to
the RMS radius of the scene's centres), as sfm_pair_check.py measures it.

    python experiments/sfm_global_check.py OUT SCENE [SEED]
"""
import shutil
import sys
import tempfile
import time
from pathlib import Path

import pycolmap

sys.path.insert(0, str(Path(__file__).parent))
from sfm_pair_check import centre_error  # noqa: E402
from retinexgs.data import load_scene  # noqa: E402


def main(out: Path, scene: str, seed: int = 0) -> None:
    work = Path(tempfile.mkdtemp(prefix="sfm-global-"))
    db = work / "database.db"
    shutil.copy(out / "database.db", db)
    opts = pycolmap.GlobalPipelineOptions()
    opts.num_threads, opts.random_seed = 2, seed
    t = time.time()
    models = pycolmap.global_mapping(db, out / "enhanced", work / "models", options=opts)
    truth = {Path(v.name).stem: v for v in load_scene(scene).views}
    for k, r in models.items():
        n, med, mx = centre_error(r, truth)
        print(f"{out}: seed {seed}, model {k}: {r.num_reg_images()} posed, {r.num_points3D()} points, centres off "
              f"{100 * med:.1f} % / {100 * mx:.1f} % ({time.time() - t:.0f} s)")
    shutil.rmtree(work)


if __name__ == "__main__":
    main(Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]) if len(sys.argv) > 3 else 0)
