"""d_in from a 3 × 3 dot target on either side of the focused plane (issue 16).

Renders a white image and a dot target (9 point sources on one plane, dots ``--spacing`` mm
apart on the sensor, photon and read noise) for system 2 focused at ``--focus``, on a square
``--size`` crop, then solves d_in with ``lfcam.calibrate.reference.measure_d_in`` from starts
0, +0.4 and −0.4 mm off the true d_in (the start enters as the profile's d_in). Micro-image
centres: the renderer's white-image centroids (``--centres truth``, default) or
``calibrate_white`` on the rendered white (``--centres calibrated``). Prints the relative
d_in error, the dots used and the worst dot's rms.

Run::

    python benchmarks/din_focus.py --distances 1500,600 --size 1280 --spacing 6.5

(~1–3 min a distance on 2 shared cores.)
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

from lfcam.calibrate import calibrate_white  # noqa: E402
from lfcam.calibrate.reference import measure_d_in  # noqa: E402
from lfcam.camera import load_profile  # noqa: E402
from lfcam.errors import LfcamError  # noqa: E402
from lfcam.measure.pointfit import chief_ray_offset  # noqa: E402
from lfcam.sim.capture import apply_overrides, simulate  # noqa: E402
from lfcam.sim.scene import scene_from_dict  # noqa: E402

NOISE = {"photon_noise": True, "full_well_e": 20000, "read_noise_e": 3.0}
STARTS_MM = (0.0, 0.4, -0.4)


def main() -> None:
    """Render, solve, print one line per distance and start."""
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--system", default="system2")
    ap.add_argument("--focus", type=float, default=1000.0, help="focused distance, mm")
    ap.add_argument("--distances", default="1500,600", help="dot-plane distances, mm")
    ap.add_argument("--size", type=int, default=1280, help="square sensor crop, px")
    ap.add_argument("--spacing", type=float, default=6.5, help="dot spacing on the sensor, mm")
    ap.add_argument("--centres", choices=("truth", "calibrated"), default="truth")
    ap.add_argument("--rays", type=int, default=200_000, help="rays per dot")
    args = ap.parse_args()
    cam = {"sensor": {"width_px": args.size, "height_px": args.size},
           "mla": {"focus_mm": args.focus}}
    base = load_profile(ROOT / "calibration" / f"{args.system}.toml")
    prof = apply_overrides(base, cam)
    white, _, truth = simulate(base, scene_from_dict(
        {"seed": 1, "objects": [{"type": "white"}], "camera": cam, "rays_per_source": 200_000}))
    if args.centres == "truth":
        lenses = truth["lenses"]
        complete = np.array(lenses["complete"], dtype=bool)
        centres = np.array(lenses["centroid_px"])[complete]
    else:
        centres = calibrate_white(white.astype(np.float32)).centres_px
    mag = 1 + prof.mla.focal_length_mm / (prof.d_in_mm - prof.main_lens.exit_pupil_z_mm)
    print(f"# {args.system}, focus {args.focus:g} mm, {args.size}² crop, dots "
          f"{args.spacing} mm apart on the sensor, {args.centres} centres, d_in "
          f"{prof.d_in_mm:.4f} mm")
    print(f"{'Ad':>6} {'side':>6} {'start':>6} {'d_in mm':>9} {'err %':>8} {'dots':>4} "
          f"{'max rms px':>10} {'s':>4}")
    for dist in [float(v) for v in args.distances.split(",")]:
        step = abs(chief_ray_offset(prof, prof.d_in_mm, dist,
                                    np.array([args.spacing / mag, 0.0]))[0])
        dots = [{"type": "point", "distance_mm": dist, "position_mm": [i * step, j * step]}
                for i in (-1, 0, 1) for j in (-1, 0, 1)]
        raw, used, _ = simulate(base, scene_from_dict(
            {"seed": 2, "objects": dots, "camera": cam, "rays_per_source": args.rays,
             "sensor": NOISE}))
        side = "front" if dist < args.focus else "behind"
        for off in STARTS_MM:
            start = used.with_d_in(used.d_in_mm + off)
            t0 = time.perf_counter()
            try:
                r = measure_d_in(raw.astype(np.float64), centres, start, dist)
            except LfcamError as exc:
                print(f"{dist:6.0f} {side:>6} {off:+6.1f} refused: {exc} "
                      f"({time.perf_counter() - t0:.0f} s)", flush=True)
                continue
            err = 100.0 * (r.d_in_mm / used.d_in_mm - 1.0)
            worst = max((f.rms_px for f in r.exact), default=math.nan)
            print(f"{dist:6.0f} {side:>6} {off:+6.1f} {r.d_in_mm:9.4f} {err:+8.4f} "
                  f"{len(r.exact):4d} {worst:10.3f} {time.perf_counter() - t0:4.0f}",
                  flush=True)


if __name__ == "__main__":
    main()
