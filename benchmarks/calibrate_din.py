"""Benchmark: d_in from a rendered dot target, exact vs paraxial route (docs/calibration.md).

For system 1 (dots at 400 mm, 40 mm apart) and system 2 (800 mm, 20 mm apart), 3×3 dots on a
512² crop, the camera's d_in at the profile value (focus 3500 mm) and 0.5 mm further back; the
solve always starts from the nominal profile. Centres: the renderer's ray-traced white
centroids ("truth") and ``calibrate_white`` on the rendered white image ("white-cal").
Baseline for the time ratio: the paraxial route (seed eqs. 10–12) on the same dots, same run.

Run:  python benchmarks/calibrate_din.py      (~2 min on 2 cores)
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lfcam.calibrate import calibrate_white  # noqa: E402
from lfcam.calibrate.reference import (  # noqa: E402
    MAX_RMS_PX,
    CentreMap,
    find_dots,
    fit_dot_exact,
    fit_dot_paraxial,
)
from lfcam.camera import load_profile  # noqa: E402
from lfcam.sim.capture import simulate  # noqa: E402
from lfcam.sim.scene import scene_from_dict  # noqa: E402

CASES = (("system1", 400.0, 40.0), ("system2", 800.0, 20.0))
SIZE = 512


def main() -> None:
    """Render, solve, print the table."""
    rows = []
    for name, dist, spacing in CASES:
        nominal = load_profile(name)
        for shift in (0.0, 0.5):
            cam = {"sensor": {"width_px": SIZE, "height_px": SIZE}}
            camera = nominal.with_d_in(nominal.d_in_mm + shift)
            white, _, tw = simulate(camera, scene_from_dict(
                {"seed": 1, "objects": [{"type": "white"}], "camera": cam}))
            dots = [{"type": "point", "distance_mm": dist,
                     "position_mm": [i * spacing, j * spacing]}
                    for i in (-1, 0, 1) for j in (-1, 0, 1)]
            raw, used, _ = simulate(camera, scene_from_dict(
                {"seed": 2, "objects": dots, "camera": cam}))
            prof = replace(nominal, sensor=used.sensor)
            truth = used.d_in_mm
            lenses = tw["lenses"]
            complete = np.array(lenses["complete"], dtype=bool)
            sources = {"truth": np.array(lenses["centroid_px"])[complete],
                       "white-cal": calibrate_white(white.astype(float)).centres_px}
            for label, centres in sources.items():
                pitch = prof.mla.pitch_mm / prof.sensor.pixel_pitch_mm * (
                    1 + prof.mla.focal_length_mm / (prof.d_in_mm
                                                    - prof.main_lens.exit_pupil_z_mm))
                lmap, found = find_dots(raw, centres, pitch)
                cmap = CentreMap(prof, centres)
                t0 = time.perf_counter()
                ex = [fit_dot_exact(prof, lmap, d, cmap, dist, nominal.d_in_mm) for d in found]
                t_ex = time.perf_counter() - t0
                ok = [k for k, f in enumerate(ex) if f.rms_px <= MAX_RMS_PX]
                if not ok:  # measure_d_in raises CalibrationError here
                    rows.append((name, shift, label, 0, np.nan, np.nan, np.nan, t_ex, np.nan))
                    continue
                t0 = time.perf_counter()
                par = [fit_dot_paraxial(prof, found[k], centres, dist, nominal.d_in_mm)
                       for k in ok]
                t_par = time.perf_counter() - t0
                d_ex = np.mean([ex[k].d_in_mm for k in ok])
                d_par = np.mean([f.d_in_mm for f in par])
                spread = np.std([ex[k].d_in_mm for k in ok], ddof=1) / np.sqrt(len(ok))
                rows.append((name, shift, label, len(ok), 100 * (d_ex - truth) / truth,
                             100 * spread / truth, 100 * (d_par - truth) / truth, t_ex, t_par))
    print(f"{'system':8} {'shift':>5} {'centres':9} {'dots':>4} | {'exact err %':>11} "
          f"{'σ %':>6} | {'paraxial err %':>14} | {'exact s':>7} {'parax s':>7} {'ratio':>7}")
    print("-" * 96)
    for name, shift, label, n, e_ex, s_ex, e_par, t_ex, t_par in rows:
        print(f"{name:8} {shift:5.1f} {label:9} {n:4d} | {e_ex:+11.4f} {s_ex:6.4f} | "
              f"{e_par:+14.3f} | {t_ex:7.2f} {t_par:7.3f} {t_ex / t_par:7.0f}")


if __name__ == "__main__":
    main()
