"""Lines behind focus fitted on the lenslet cells and ray-sampled, on either lattice.

Run: ``python benchmarks/lines_on_cells.py [--grid hex|rect] [--distances 1500,2200,2900,3400]``

System 2 with its MLA's grid set to ``--grid`` (focus 1 m, a 1024² sensor, photon and read
noise, the renderer's own lenslet centres), 3 mm lines at 0°, 60° and 135° through the field
centre, each fitted by ``run_distance(..., method="lenslet")`` twice in the same process: with
the line fit on the cells (``fastfit.LINE_CELLS_MIN_LIT`` as shipped) and without
(``LINE_CELLS_MIN_LIT`` out of reach: every model ray-sampled). Prints a row a line (signed
error %, its z-score against the stated σ, CPU s of the whole run) and the means
(docs/distance.md, "Samples fixed on the lenslet cells").
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcam.camera import load_profile  # noqa: E402
from lfcam.distance import run_distance  # noqa: E402
from lfcam.measure import fastfit as ff  # noqa: E402
from lfcam.measure.pointfit import chief_ray_offset  # noqa: E402
from lfcam.sim.capture import apply_overrides, simulate  # noqa: E402
from lfcam.sim.geometry import truth_geometry  # noqa: E402
from lfcam.sim.scene import scene_from_dict  # noqa: E402

SIZE = 1024
NOISE = {"photon_noise": True, "full_well_e": 20000, "read_noise_e": 3.0}


def system2(grid: str) -> tuple[dict, object, object]:
    """System 2 with a ``grid`` MLA, focus 1 m, a 1024² sensor: the camera overrides, the
    profile file's profile and the profile with the overrides."""
    camera = {"mla": {"focus_mm": 1000.0, "grid": grid},
              "sensor": {"width_px": SIZE, "height_px": SIZE}}
    base = load_profile(ROOT / "calibration" / "system2.toml")
    return camera, base, apply_overrides(base, camera)


def render(grid: str, objects: list[dict],
           sensor: dict = NOISE) -> tuple[np.ndarray, object, object]:
    """``objects`` in :func:`system2` with a ``grid`` MLA, rendered by ``lfcam.sim`` (seed 3)
    with ``sensor``'s noise. Returns the image (float64), the profile the renderer used and
    the renderer's own lenslet geometry."""
    camera, base, prof = system2(grid)
    scene = {"seed": 3, "camera": camera, "sensor": sensor, "objects": objects}
    raw, used, _ = simulate(base, scene_from_dict(scene))
    return raw.astype(np.float64), used, truth_geometry(prof, (SIZE, SIZE))


def line_capture(grid: str, distance_mm: float, angle_deg: float,
                 rays: int = 1_000_000) -> tuple[np.ndarray, object, object]:
    """System 2 with a ``grid`` MLA (focus 1 m, 1024², photon and read noise): a 3 mm line
    (on the MLA) at ``distance_mm`` through the field centre at ``angle_deg`` (:func:`render`).
    """
    prof = system2(grid)[2]
    u = np.array([math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))])
    ends = [chief_ray_offset(prof, prof.d_in_mm, distance_mm, s * 1.5 * u).tolist()
            for s in (-1.0, 1.0)]
    return render(grid, [{"type": "line", "distance_mm": distance_mm, "start_mm": ends[0],
                          "end_mm": ends[1], "rays": rays}])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--grid", choices=("hex", "rect"), default="hex")
    ap.add_argument("--distances", default="1500,2200,2900,3400", help="mm, behind a 1 m focus")
    ap.add_argument("--rays", type=int, default=1_000_000, help="rays a line in the render")
    args = ap.parse_args()
    from lfcam.measure.kernels import warm_up

    warm_up()  # the compiled kernels loaded (or compiled) before the first line is timed
    shipped = ff.LINE_CELLS_MIN_LIT
    totals: dict[str, list[tuple[float, float, float]]] = {"rays": [], "cells": []}
    print(f"# system 2, {args.grid} MLA, focus 1 m, {SIZE}² sensor, photon noise")
    print("distance_mm angle_deg | rays: error_pct z cpu_s | cells: error_pct z cpu_s")
    for d in (float(v) for v in args.distances.split(",")):
        for angle in (0.0, 60.0, 135.0):
            image, used, geom = line_capture(args.grid, d, angle, args.rays)
            cols = []
            for tag, lit in (("rays", 10**9), ("cells", shipped)):
                ff.LINE_CELLS_MIN_LIT = lit
                c0 = time.process_time()
                run = run_distance(image, used, None, model="exact", method="lenslet",
                                   geometry=geom, jobs=1)
                cpu = time.process_time() - c0
                best = max(run.regions,
                           key=lambda r: r.diameter_mm if r.status == "ok" else -1.0)
                err = 100.0 * (best.distance_mm / d - 1.0)
                z = (best.distance_mm - d) / best.uncertainty_mm
                totals[tag].append((abs(err), z, cpu))
                cols.append(f"{err:+.3f} {z:+.2f} {cpu:.2f}"
                            + ("" if best.kind == "line" and best.status == "ok"
                               else f" ({best.kind}, {best.status})"))
            ff.LINE_CELLS_MIN_LIT = shipped
            print(f"{d:.0f} {angle:.0f} | " + " | ".join(cols), flush=True)
    print_means(totals, lambda cpu_s: f"CPU {cpu_s:.3f} s a line")


def print_means(totals: dict[str, list[tuple[float, float, float]]], cpu_text) -> None:
    """A line of means for each way of fitting: ``(|error| %, z, CPU s)`` rows; ``cpu_text``
    words their mean CPU."""
    for tag, rows in totals.items():
        err = [r[0] for r in rows]
        print(f"{tag}: mean / max error {sum(err) / len(err):.3f} / {max(err):.3f} %, "
              f"within 3σ {sum(abs(r[1]) <= 3.0 for r in rows)} of {len(rows)}, "
              + cpu_text(sum(r[2] for r in rows) / len(rows)))


if __name__ == "__main__":
    main()
