"""Time and accuracy of ``lfcam distance`` on 1536×1536 raws (imaging system 2).

Run: ``python benchmarks/distance.py [--captures 6]``

For each of N committed synthetic captures (one point source each, spread over the seed's
distances) it times the stages of a distance run — calibration geometry (once per
calibration, reused across captures), region detection, measurement — for the full
light-field fit and for ``--fast`` (triangulation only), and prints the distance errors
against the truth files. The ratio column is each variant's per-capture time over the fast
variant's, measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcam.calibrate import load_calibration  # noqa: E402
from lfcam.camera import load_profile  # noqa: E402
from lfcam.distance import run_distance  # noqa: E402
from lfcam.io import load_capture  # noqa: E402
from lfcam.measure import prepare_geometry  # noqa: E402

DATA = ROOT / "data" / "synthetic"
PICKS = [(300, 0), (900, 5), (1500, 10), (2200, 0), (2800, 5), (3500, 10), (600, 10),
         (1100, 0), (1800, 5), (2500, 10), (3000, 0), (450, 5)]


def main() -> None:
    """Print the timing/accuracy table."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--captures", type=int, default=6)
    args = ap.parse_args()
    cal = load_calibration(DATA / "calib_system2.json")
    picks = PICKS[: args.captures]
    loaded = []
    for dist, dh in picks:
        name = f"point_system2_{dist}mm_dh{dh}"
        prof = load_profile(DATA / f"{name}.profile.toml")
        t0 = time.perf_counter()
        cap = load_capture(DATA / f"{name}.png", prof)
        img = cap.grey()
        t_load = time.perf_counter() - t0
        truth = json.loads((DATA / f"{name}.truth.json").read_text())["sources"][0]
        loaded.append((name, prof, img, truth, t_load))
    t0 = time.perf_counter()
    geom = prepare_geometry(loaded[0][1], cal, loaded[0][2].shape)
    t_geom = time.perf_counter() - t0
    rows = {}
    for variant, fast in (("fast", True), ("full", False)):
        times, errs = [], []
        for _name, prof, img, truth, t_load in loaded:
            t0 = time.perf_counter()
            run = run_distance(img, prof, cal, model="exact", fast=fast, geometry=geom)
            times.append(time.perf_counter() - t0 + t_load)
            r = run.regions[0]
            d = truth["distance_mm"]
            errs.append(abs(r.distance_mm - d) / (d + 3.0) * 100 if r.status == "ok"
                        else np.nan)
        rows[variant] = (np.array(times), np.array(errs))
    base = rows["fast"][0].mean()
    print(f"# lfcam distance, system 2, 1536×1536 raws, {len(loaded)} captures, one point source"
          " each; per-capture time = load + regions + measurement")
    print(f"calibration geometry (once per calibration): {t_geom:.2f} s")
    head = (f"{'variant':8} {'mean s':>7} {'max s':>7} {'vs fast':>8} | {'mean err %':>10} "
            f"{'max err %':>9} {'missing':>7}")
    print(head)
    print("-" * len(head))
    for variant, (times, errs) in rows.items():
        print(f"{variant:8} {times.mean():7.2f} {times.max():7.2f} {times.mean() / base:8.2f} | "
              f"{np.nanmean(errs):10.3f} {np.nanmax(errs):9.3f} {int(np.isnan(errs).sum()):7d}")
    print("\ntarget: a 1536² raw in ≤ 2 s (per capture, geometry reused)")


if __name__ == "__main__":
    main()
