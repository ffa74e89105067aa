"""Does a correction of the white's centroid estimator learnt on one rendered white carry over
to another? (branch ``white-table-rule``; a lead, not a feature)

Run: ``python benchmarks/white_bias_transfer.py [--focus inf] [--cache DIR]``

For system 1 at ``--focus`` (1024² sensor), both of ``focus_grid.py``'s calibrated whites
(``sim``: ``lfcam.sim``; ``analytic``: ``benchmarks/whites_analytic.py``, no shared rendering
code) are compared with the white-offset table's prediction at the renderer's lenslets; the
radial difference (the estimator's bias, plus the table's) is fitted by an odd polynomial of
degree 9 in the field radius. Each white's centroids, corrected by the other's (or its own)
polynomial, are turned into a lattice as ``lfcam distance`` does; printed: the lattice's scale
error and the lens centres' RMS error against the renderer's.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import focus_grid as fg  # noqa: E402

from lfcam.calibrate.model import load_calibration  # noqa: E402
from lfcam.measure import fastfit  # noqa: E402
from lfcam.measure.geometry import prepare_geometry, white_offset_table  # noqa: E402

TERMS = 5  # odd powers 1 … 9 of the field radius


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--focus", default="inf")
    ap.add_argument("--cache", type=Path, default=ROOT / "benchmarks" / ".cache")
    args = ap.parse_args()
    focus = float(args.focus)
    truth = fg.Camera("system1", focus, None, args.cache, True)
    p = truth.used
    pp = p.sensor.pixel_pitch_mm
    ax, ay = p.sensor.axis_xy_px
    axis = np.array([ax, ay])
    lens = truth.geom.lens_centres_mm
    r = np.hypot(lens[:, 0], lens[:, 1])
    radii, r_w = white_offset_table(p, float(p.d_in_mm), float(r.max() * 1.05 + 1e-6))
    pred = lens * (np.interp(r, radii, r_w) / np.maximum(r, 1e-12))[:, None] / pp + axis
    lt = fastfit.lattice_of(truth.geom, p.mla.pitch_mm)
    scale_px = 0.5 * max(truth.shape)
    cals = {}
    for white in ("sim", "analytic"):
        fg.Camera("system1", focus, None, args.cache, False, white=white)  # (cached)
        name = f"calib_system1_{focus:g}_{truth.shape[1]}" + ("" if white == "sim" else
                                                              "_analytic")
        cals[white] = load_calibration(args.cache / f"{name}.json")

    def radial_unit(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rad = np.hypot(*(xy - axis).T)
        return rad, (xy - axis) / np.maximum(rad, 1e-9)[:, None]

    def powers(rad: np.ndarray) -> np.ndarray:
        return np.column_stack([(rad / scale_px) ** (2 * k + 1) for k in range(TERMS)])

    def bias(cal) -> np.ndarray:
        m = np.asarray(cal.centres_px, dtype=np.float64)
        ref = pred[cKDTree(pred).query(m)[1]]
        rad, unit = radial_unit(ref)
        return np.linalg.lstsq(powers(rad), ((m - ref) * unit).sum(axis=1), rcond=None)[0]

    def lattice_error(cal, coef: np.ndarray | None) -> str:
        if coef is not None:
            m = np.asarray(cal.centres_px, dtype=np.float64)
            rad, unit = radial_unit(m)
            cal = dataclasses.replace(cal, centres_px=m - (powers(rad) @ coef)[:, None] * unit)
        g = prepare_geometry(p, cal.with_d_in(p.d_in_mm, "profile"), truth.shape)
        got = g.lens_centres_mm
        nx, ny = lt.node(got[:, 0], got[:, 1])
        d = got - np.column_stack([nx, ny])
        a = np.column_stack([np.ones(len(nx)), nx, ny])
        c = np.linalg.lstsq(a, d, rcond=None)[0]
        return (f"{c[1, 0]:+.2e} / {c[2, 1]:+.2e}, RMS "
                f"{np.sqrt((d ** 2).sum(axis=1).mean()) / pp:.4f} px")

    print(f"# system 1, focus {args.focus}\n| white | as calibrated | corrected by the other "
          "white's bias | by its own |\n|---|---|---|---|")
    for white, other in (("sim", "analytic"), ("analytic", "sim")):
        print(f"| {white} | {lattice_error(cals[white], None)} | "
              f"{lattice_error(cals[white], bias(cals[other]))} | "
              f"{lattice_error(cals[white], bias(cals[white]))} |", flush=True)


if __name__ == "__main__":
    main()
