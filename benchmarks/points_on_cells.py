"""Large point blurs behind focus fitted on the lenslet cells and ray-sampled.

Run: ``python benchmarks/points_on_cells.py [--grid rect|hex] [--noise]
[--distances 1500,2200,2900,3500] [--rays 16000000]``

System 2 with its MLA's grid set to ``--grid`` (focus 1 m, a 1024² sensor, the renderer's own
lenslet centres; no photon or read noise unless ``--noise``), a point at each distance on the
axis and 40 mm a metre off it (azimuth 30°), rendered by ``lfcam.sim`` with ``--rays`` rays
(seed 3). The largest region is fitted by :func:`lfcam.measure.fastfit.measure_lenslet` twice
in the same process, best CPU of two runs each: with the point fit on the cells
(``fastfit.POINT_CELLS``, as shipped) and without (every model ray-sampled, the 80 000-ray
settled test and polish). Prints a row a point (signed error %, its z-score against the
stated σ, region CPU ms) and the means (docs/distance.md, "Large point blurs on the cells
(stop 44)").
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from lines_on_cells import NOISE, SIZE, print_means, render  # noqa: E402

from lfcam.measure import fastfit as ff  # noqa: E402
from lfcam.measure.lenslets import lenslet_stats  # noqa: E402
from lfcam.measure.regions import find_regions  # noqa: E402

QUIET = {"photon_noise": False, "read_noise_e": 0.0}


def point_capture(grid: str, distance_mm: float, offset_per_m_mm: float, rays: int,
                  noise: bool) -> tuple[np.ndarray, object, object]:
    """System 2 (``grid`` MLA, focus 1 m, 1024²: :func:`lines_on_cells.render`): a point at
    ``distance_mm``, ``offset_per_m_mm`` × the distance in metres off the axis."""
    return render(grid, [{"type": "point", "distance_mm": distance_mm,
                          "offset_mm": offset_per_m_mm * distance_mm / 1000.0,
                          "azimuth_deg": 30.0, "rays": rays}], NOISE if noise else QUIET)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--grid", choices=("hex", "rect"), default="rect")
    ap.add_argument("--distances", default="1500,2200,2900,3500", help="mm, behind a 1 m focus")
    ap.add_argument("--rays", type=int, default=16_000_000, help="rays a point in the render")
    ap.add_argument("--noise", action="store_true", help="photon and read noise")
    args = ap.parse_args()
    from lfcam.measure.kernels import warm_up

    warm_up()
    shipped = ff.POINT_CELLS
    totals: dict[str, list[tuple[float, float, float]]] = {"rays": [], "cells": []}
    print(f"# system 2, {args.grid} MLA, focus 1 m, {SIZE}² sensor, "
          f"{'photon and read noise' if args.noise else 'no noise'}, {args.rays} rays a point")
    print("distance_mm offset_mm lenslets | rays: error_pct z cpu_ms | cells: error_pct z cpu_ms")
    for d in (float(v) for v in args.distances.split(",")):
        for off in (0.0, 40.0):
            image, used, geom = point_capture(args.grid, d, off, args.rays, args.noise)
            regions = find_regions(lenslet_stats(image, geom.lmap), geom.lmap, geom.pitch_px)
            region = max(regions, key=lambda r: len(r.lenslets))
            cols = []
            for tag, on in (("rays", False), ("cells", shipped)):
                ff.POINT_CELLS = on
                cpu = math.inf
                for _ in range(2):
                    c0 = time.process_time()
                    m = ff.measure_lenslet(used, geom, image, region, 0.0)
                    cpu = min(cpu, time.process_time() - c0)
                err = 100.0 * (m.distance_mm / d - 1.0)
                z = (m.distance_mm - d) / m.sigma_distance_mm
                totals[tag].append((abs(err), z, cpu))
                cols.append(f"{err:+.3f} {z:+.2f} {1e3 * cpu:.0f}"
                            + ("" if m.status == "ok" else f" ({m.status})"))
            ff.POINT_CELLS = shipped
            print(f"{d:.0f} {off * d / 1000.0:.0f} {len(region.lenslets)} | "
                  + " | ".join(cols), flush=True)
    print_means(totals, lambda cpu_s: f"region CPU {1e3 * cpu_s:.0f} ms mean")


if __name__ == "__main__":
    main()
