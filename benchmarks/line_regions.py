"""Six line regions of the focus grid, each fitted several times: the least CPU (issue 17).

Run: ``python benchmarks/line_regions.py [--repeats N] [--cache DIR] [--render-cache DIR]``

The regions are the grid's slow kinds (``benchmarks/focus_grid.py --lines``: a line 3 mm
long on the MLA, a 1 m focus, photon and read noise, calibrated lenslet centres):

* system 2, hexagonal MLA, 380 mm in front of focus at 80 % of the half-field and at the
  centre (ray-sampled: the MLA cuts the caustic);
* system 2, hexagonal, 2900 mm behind focus at 60 % (on the lenslet cells);
* system 2, rectangular, 2200 mm behind at 80 %, and 560 mm in front at the centre;
* system 1, 3400 mm behind focus at 80 % (ray-sampled, refitted by the settled test).

Each region's :func:`lfcam.measure.fastfit.measure_lenslet` runs once to warm up, then
``--repeats`` times on one core; the least and the median CPU are printed with the answer.
Run two checkouts side by side (one core each) to compare them: the least CPU of several
runs is the figure least disturbed by the other process (docs/distance.md, "A smaller label
map and uncut rim cells (stop 49)").
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import focus_grid as fg  # noqa: E402

import lfcam.distance as distance  # noqa: E402
from lfcam.measure import fastfit as ff  # noqa: E402
from lfcam.measure import kernels  # noqa: E402
from lfcam.measure.lenslets import lenslet_stats  # noqa: E402
from lfcam.measure.regions import find_regions  # noqa: E402

# (system, MLA grid, sensor px, distance mm, line angle °, share of the half-field)
CASES = (
    ("system2", "hex", 1536, 380.0, 0.0, 0.8),
    ("system2", "hex", 1536, 380.0, 60.0, 0.0),
    ("system2", "hex", 1536, 2900.0, 60.0, 0.6),
    ("system2", "rect", 1536, 2200.0, 0.0, 0.8),
    ("system1", "rect", 1024, 3400.0, 135.0, 0.8),
    ("system2", "rect", 1024, 560.0, 0.0, 0.0),
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--cache", type=Path,
                    default=Path(tempfile.gettempdir()) / "lfcam_focus_grid",
                    help="folder for the white-image calibrations (as focus_grid.py's)")
    ap.add_argument("--render-cache", type=Path,
                    help="folder keeping the rendered captures (as focus_grid.py's)")
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    if args.render_cache:
        args.render_cache.mkdir(parents=True, exist_ok=True)
        fg.RENDER_CACHE[0] = args.render_cache
    kernels.warm_up()
    rows = []
    for system, grid, size, distance_mm, angle, field in CASES:
        cam = fg.Camera(system, 1000.0, size, args.cache, False, grid=grid)
        image, _, _ = cam.render([cam.line(distance_mm, angle, field, 1_000_000,
                                           fg.LINE_HALF_MM)], seed=3, rays=1_000_000)
        geom, profile = cam.geom, cam.used
        regions = find_regions(lenslet_stats(image, geom.lmap), geom.lmap, geom.pitch_px)
        region = max(regions, key=lambda r: len(r.lenslets))
        noise = distance.noise_sigma(image)
        ff.measure_lenslet(profile, geom, image, region, noise)  # warm up
        spent = []
        for _ in range(max(1, args.repeats)):
            c0 = time.process_time()
            m = ff.measure_lenslet(profile, geom, image, region, noise)
            spent.append(time.process_time() - c0)
        rows.append((f"{system}, {grid}, {distance_mm:.0f} mm, {100 * field:.0f} % of the "
                     f"field, {angle:.0f}°", len(region.lenslets), m.kind,
                     100.0 * (m.distance_mm / distance_mm - 1.0), 1e3 * min(spent),
                     1e3 * float(np.median(spent))))
    print(f"\n# least and median CPU of {args.repeats} fits, one core")
    print("| line region | lenslets | answer | least ms | median ms |\n|---|---|---|---|---|")
    for name, lenslets, kind, err, least, median in rows:
        print(f"| {name} | {lenslets} | {kind} {err:+.4f} % | {least:.1f} | {median:.1f} |")


if __name__ == "__main__":
    main()
