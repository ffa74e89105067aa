"""``lenslet`` against ``lightfield`` behind focus and off axis (issue 17; cases of issue 16).

Run: ``python benchmarks/lenslet_focus.py [--focus 1000,1500] [--quick]``

Renders single point sources like ``benchmarks/diagnose_focus.py`` (system 2, full 1536²
sensor, MLA rotated 0.012 rad, photon and read noise, focus set through the scene's ``camera``
override ``[mla] focus_mm``), calibrates the geometry from a rendered white image, and runs
``run_distance`` with ``method=lenslet`` and ``method=lightfield`` (model ``exact``) on the same
capture. Prints signed errors (% of Ad, against the renderer's truth) and the CPU time of the
measurement of the source's region, for both methods, measured in the same run.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcam.calibrate import calibrate_white  # noqa: E402
from lfcam.camera import load_profile  # noqa: E402
from lfcam.distance import run_distance  # noqa: E402
from lfcam.measure import prepare_geometry  # noqa: E402
from lfcam.measure.pointfit import chief_ray_offset  # noqa: E402
from lfcam.sim.capture import apply_overrides, simulate  # noqa: E402
from lfcam.sim.scene import scene_from_dict  # noqa: E402

ROTATION = 0.012
NOISE = {"photon_noise": True, "full_well_e": 20000, "read_noise_e": 3.0}
# (focus, Ad) pairs on both sides of focus; field radii on the sensor (mm)
CASES = {1000.0: (600.0, 1750.0, 2500.0, 3500.0), 1500.0: (700.0, 1100.0, 2400.0, 2900.0)}
RADII = (0.0, 5.0, 9.6)


def camera(focus_mm: float) -> dict:
    """Scene camera overrides: focus and a slightly rotated MLA."""
    return {"mla": {"focus_mm": focus_mm, "rotation_rad": ROTATION}}


def main(argv=None) -> list[tuple]:
    """Run the grid; return (focus, Ad, r, side, method, error %, ms) rows."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--focus", default="1000,1500")
    ap.add_argument("--radii", default=",".join(str(r) for r in RADII))
    ap.add_argument("--methods", default="lenslet,lightfield")
    ap.add_argument("--quick", action="store_true", help="one distance per focus, on axis")
    args = ap.parse_args(argv)
    base = load_profile("system2")
    shape = (base.sensor.height_px, base.sensor.width_px)
    methods = args.methods.split(",")
    rows = []
    print("# system 2, 1536², MLA rotated 0.012 rad, noisy; signed error % vs truth; "
          "region CPU ms")
    print(f"{'focus':>6} {'Ad':>6} {'r mm':>5} {'side':>6} | " + " | ".join(
        f"{m:>10} err% {'ms':>7}" for m in methods))
    for focus in [float(v) for v in args.focus.split(",")]:
        used = apply_overrides(base, camera(focus))
        white, _, _ = simulate(base, scene_from_dict({"seed": 5, "objects": [{"type": "white"}],
                                                      "camera": camera(focus)}))
        cal = calibrate_white(white.astype(np.float32)).with_d_in(used.d_in_mm, "profile")
        geom = prepare_geometry(used, cal, shape)
        z_ep = used.main_lens.exit_pupil_z_mm
        mag = 1 + used.mla.focal_length_mm / (used.d_in_mm - z_ep)
        dists = CASES[focus][1:2] if args.quick else CASES[focus]
        radii = (0.0,) if args.quick else [float(v) for v in args.radii.split(",")]
        for dist in dists:
            for r in radii:
                az = math.radians(30.0)
                target = np.array([math.cos(az), math.sin(az)]) * r / mag
                xy = chief_ray_offset(used, used.d_in_mm, dist, target)
                scene = {"seed": 3, "rays_per_source": 1_000_000, "sensor": NOISE,
                         "exposure": {"peak": 0.8}, "camera": camera(focus),
                         "objects": [{"type": "point", "distance_mm": dist,
                                      "position_mm": [float(xy[0]), float(xy[1])]}]}
                raw, _, _ = simulate(base, scene_from_dict(scene))
                img = raw.astype(np.float64)
                side = "front" if dist < focus else "behind"
                cells = []
                for method in methods:
                    res = run_distance(img, used, None, model="exact", method=method,
                                       geometry=geom, jobs=1)
                    k = int(np.argmax([np.prod(np.subtract(g.bbox_px[2:], g.bbox_px[:2]))
                                       for g in res.regions]))
                    d = res.regions[k].distance_mm
                    err = 100.0 * (d / dist - 1.0)
                    ms = 1e3 * res.timings_s["region_s"][k]
                    rows.append((focus, dist, r, side, method, err, ms))
                    cells.append(f"{err:+15.3f} {ms:7.0f}")
                print(f"{focus:6.0f} {dist:6.0f} {r:5.1f} {side:>6} | " + " | ".join(cells),
                      flush=True)
    print("\n# summary: mean |err| / max |err| % and max region ms per method and side")
    for method in methods:
        for side in ("front", "behind", "all"):
            sel = [v for v in rows if v[4] == method and (side == "all" or v[3] == side)]
            if not sel:
                continue
            e = np.abs([v[5] for v in sel])
            t = [v[6] for v in sel]
            print(f"{method:>10} {side:>6}: {np.nanmean(e):.3f} / {np.nanmax(e):.3f} %  "
                  f"({len(sel)} cases, worst {max(t):.0f} ms)")
    return rows


if __name__ == "__main__":
    main()
