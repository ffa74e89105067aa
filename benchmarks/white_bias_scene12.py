"""Scratch measurement (branch ``white-table-rule``): the 12-source captures of system 1 with
the sim white's centroids corrected by the estimator bias learnt on the analytic white
(``white_bias_transfer.py``'s polynomial), through this branch's table.

Run: ``python benchmarks/white_bias_scene12.py 5-14`` (the seeds; caches as in the file).
"""
import os, sys, math, dataclasses
for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[v] = "1"
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT); sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
import numpy as np
from pathlib import Path
from scipy.spatial import cKDTree
import focus_grid as fg
import point_regions as pr
from lfcam.calibrate.model import load_calibration
from lfcam.measure.geometry import prepare_geometry, white_offset_table
orig = fg.calibrated_geometry
def corrected_geometry(base, cam, used, shape, cache, key, white_source="sim"):
    g = orig(base, cam, used, shape, cache, key, white_source)
    if white_source != "sim" or not key.startswith("system1"):
        return g
    # the bias learnt on the analytic white (same camera), applied to the sim white's centroids
    p = used; pp = p.sensor.pixel_pitch_mm; axis = np.array(p.sensor.axis_xy_px)
    tg = fg.truth_geometry(used, shape)
    lens = tg.lens_centres_mm; r = np.hypot(*lens.T)
    radii, r_w = white_offset_table(p, float(p.d_in_mm), float(r.max() * 1.05 + 1e-6))
    pred = lens * (np.interp(r, radii, r_w) / np.maximum(r, 1e-12))[:, None] / pp + axis
    sc = 0.5 * max(shape)
    pw = lambda rad: np.column_stack([(rad / sc) ** (2 * k + 1) for k in range(5)])
    an = load_calibration(cache / f"calib_{key}_analytic.json")
    m = np.asarray(an.centres_px); ref = pred[cKDTree(pred).query(m)[1]]
    rad = np.hypot(*(ref - axis).T); u = (ref - axis) / np.maximum(rad, 1e-9)[:, None]
    coef = np.linalg.lstsq(pw(rad), ((m - ref) * u).sum(1), rcond=None)[0]
    cal = load_calibration(cache / f"calib_{key}.json")
    m = np.asarray(cal.centres_px); rad = np.hypot(*(m - axis).T); u = (m - axis) / np.maximum(rad, 1e-9)[:, None]
    cal = dataclasses.replace(cal, centres_px=m - (pw(rad) @ coef)[:, None] * u)
    print("# corrected", key, flush=True)
    return prepare_geometry(used, cal.with_d_in(used.d_in_mm, "profile"), shape)
fg.calibrated_geometry = corrected_geometry
sys.argv = ["point_regions.py", "--scene12", "--systems", "system1", "--seeds", sys.argv[1], "--repeats", "1", "--cache", "/work/b54/cache", "--render-cache", "/work/b62/rc"]
pr.main()
