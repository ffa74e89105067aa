"""How well the cells' polynomial pupil → MLA map gives each sample's pupil area.

Run: ``python benchmarks/cell_area_element.py [--system system2] [--focus 1000]
[--distance 2900] [--field 0.0]``

A sample on the lenslet cells weighs the pupil area it stands for: the sub-cell's area over
the determinant of the map's Jacobian (:func:`lfcam.measure.kernels.cell_samples`). The map
is a polynomial fitted by least squares to the 81 traced rays of
:func:`lfcam.measure.fastfit._cell_ring`. This script fits polynomials of degree 5 (the
kernel's, :data:`lfcam.measure.kernels.MAP_DEGREE`), 7 and 9 to those rays for one point
source, and compares each one's Jacobian determinant with the exact map's on a polar grid of
the pupil (the exact map's by central differences of the compiled trace). Prints the ratio by
zone of the pupil radius, and the worst miss of the values (docs/distance.md, "The cells'
area element (stop 41)").
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcam.camera import load_profile  # noqa: E402
from lfcam.measure import fastfit as ff  # noqa: E402
from lfcam.measure.kernels import trace_model_rays  # noqa: E402
from lfcam.measure.pointfit import chief_ray_offset  # noqa: E402
from lfcam.sim.capture import apply_overrides  # noqa: E402

ZONES = ((0.0, 0.3), (0.3, 0.6), (0.6, 0.8), (0.8, 0.9), (0.9, 0.98))
STEP = 1e-5  # central-difference step in the unit pupil


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--system", default="system2")
    ap.add_argument("--focus", type=float, default=1000.0, help="mm")
    ap.add_argument("--distance", type=float, default=2900.0, help="mm, the point source's")
    ap.add_argument("--field", type=float, default=0.0, help="share of a 1024² half-field")
    args = ap.parse_args()
    prof = apply_overrides(load_profile(ROOT / "calibration" / f"{args.system}.toml"),
                           {"mla": {"focus_mm": args.focus}})
    lens = prof.main_lens
    half_field = 512 * prof.sensor.pixel_pitch_mm
    xy = chief_ray_offset(prof, prof.d_in_mm, args.distance,
                          np.array([args.field * half_field, 0.0]))
    src = np.array([[xy[0], xy[1], lens.front_vertex_z_mm - args.distance]])
    packed = ff._packed_lens(lens)
    maps = ff.compiled_pupil_maps(lens, src, packed)
    half = 0.5 * lens.pupil_diameter_mm
    trace_args = (packed.table, packed.coef, float(lens.front_vertex_z_mm),
                  float(lens.rim_z_mm), float(prof.d_in_mm), float(prof.mla.focal_length_mm))

    def trace(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x, y, *_, rows, _, _ = trace_model_rays(src, maps, np.array([[1.0, 0.0]]), u * half,
                                                v * half, *trace_args)
        if len(rows) != len(u):
            raise SystemExit("the pupil is vignetted here: the cells do not apply")
        return x, y

    ring = ff._cell_ring()[0]
    xr, yr = trace(ring[:, 0], ring[:, 1])
    # a polar grid of the pupil, inside the rim by more than the difference step
    rad = np.sqrt((np.arange(40) + 0.5) / 40) * 0.98
    ang = 2.0 * math.pi * (np.arange(64) + 0.5) / 64
    r = np.repeat(rad, ang.size)
    u, v = r * np.cos(np.tile(ang, rad.size)), r * np.sin(np.tile(ang, rad.size))

    def det_of(f) -> np.ndarray:
        xu1, yu1 = f(u + STEP, v)
        xu0, yu0 = f(u - STEP, v)
        xv1, yv1 = f(u, v + STEP)
        xv0, yv0 = f(u, v - STEP)
        return ((xu1 - xu0) * (yv1 - yv0) - (xv1 - xv0) * (yu1 - yu0)) / (4 * STEP * STEP)

    exact = det_of(trace)
    x0, y0 = trace(u, v)
    pitch = prof.mla.pitch_mm
    print(f"# {args.system}, focus {args.focus:g} mm, source at {args.distance:g} mm, "
          f"{args.field:.0%} of the half-field; {len(ring)} traced rays fit each polynomial")
    print("| degree | values: worst miss (pitch) | determinant ÷ exact: "
          + " | ".join(f"r {lo:g}–{hi:g}" for lo, hi in ZONES) + " | RMS off 1 |")
    print("|---|---|" + "---|" * (len(ZONES) + 1))
    for degree in (5, 7, 9):
        pinv = np.linalg.pinv(ff._map_basis(ring[:, 0], ring[:, 1], degree))
        cx, cy = pinv @ xr, pinv @ yr

        def poly(a, b, cx=cx, cy=cy, degree=degree):
            t = ff._map_basis(a, b, degree)
            return t @ cx, t @ cy

        ratio = det_of(poly) / exact
        px, py = poly(u, v)
        miss = float(np.hypot(px - x0, py - y0).max()) / pitch
        zones = " | ".join(f"{ratio[(r >= lo) & (r < hi)].mean():.5f}" for lo, hi in ZONES)
        print(f"| {degree} | {miss:.1e} | {zones} | {np.sqrt(np.mean((ratio - 1) ** 2)):.1e} |")


if __name__ == "__main__":
    main()
