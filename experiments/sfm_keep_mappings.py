"""sfm_night_study.py with every mapping's largest model and its database kept under $KEEP/<n>-<database name>/
(the strict model, then each mapping of the looser matches), for sfm_pair_check.py (notes/2026-11-28-sfm-night.md
section 8). run_sfm keeps only the model it uses.

    KEEP=DIR python experiments/sfm_keep_mappings.py FOLDER SCENE OUT --night auto --seed S
"""
import os, shutil, sys, itertools
from pathlib import Path
import pycolmap
KEEP = Path(os.environ["KEEP"]); KEEP.mkdir(parents=True, exist_ok=True)
_map = pycolmap.incremental_mapping
counter = itertools.count()
def mp(database, image_path, output_path, *a, **k):
    models = _map(database, image_path, output_path, *a, **k)
    if models:
        best = max(models, key=lambda i: models[i].num_reg_images())
        d = KEEP / f"{next(counter)}-{Path(database).stem}"
        (d / "sparse" / "0").mkdir(parents=True, exist_ok=True)
        models[best].write_binary(str(d / "sparse" / "0"))
        shutil.copy(database, d / "database.db")
    return models
pycolmap.incremental_mapping = mp
import runpy
runpy.run_path(str(Path(__file__).with_name("sfm_night_study.py")), run_name="__main__")
