"""Diagnosis of issue 16: point sources behind the focused plane measured short.

Renders single point sources with ``lfcam.sim`` (system 2, full 1536² sensor, MLA rotated by
0.012 rad, photon + read noise) on both sides of the focused plane and across the field, then
runs the distance pipeline (``method=lightfield``, ``model=exact``) with one truth input
swapped in at a time. Columns (signed distance errors in %, against the renderer's truth):

* ``path``: ``tri`` = triangulation + indirect inference (regions of ≥ 300 lenslets, every
  case behind a 1 m focus), ``pix`` = per-pixel image fit.
* ``truthC old``: the pipeline before the fix, with the renderer's exact lenslet centres.
* ``rayC``: indirect inference from the renderer's per-lenslet *ray* centroids (no pixels, no
  spot threshold, exact assignment) with the old forward model — is the model itself right?
* ``calC old``: the pipeline before the fix, lenslet centres from ``calibrate_white`` on a
  rendered white image of the same camera, through ``lfcam.measure.geometry``.
* ``truthC new`` / ``calC new``: the same after the fix (statistic simulated through pixels).
* ``dC µm``: RMS error of the calibrated lenslet centres against the truth, over the region.
* ``mis@T``, ``mis@fit``: the image fit's misfit at the true source and at its optimum
  (``pix`` rows only): higher at the truth means the forward model is biased, lower that the
  optimiser stopped early.

Run:  python benchmarks/diagnose_focus.py [--focus 1000,1500] [--distances ...] [--radii ...]
(~1 min per focus on 2 shared cores with the defaults' 5 × 3 sources).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import lfcam.measure.lightfield as LF  # noqa: E402
from lfcam.calibrate import calibrate_white  # noqa: E402
from lfcam.camera import load_profile  # noqa: E402
from lfcam.distance import run_distance  # noqa: E402
from lfcam.measure import Geometry, prepare_geometry  # noqa: E402
from lfcam.measure.base import neighbours  # noqa: E402
from lfcam.measure.lenslets import lenslet_stats  # noqa: E402
from lfcam.measure.pointfit import (  # noqa: E402
    _Patch,
    _statistic,
    chief_ray_offset,
    pupil_pattern,
    simulate_lenslets,
)
from lfcam.measure.regions import find_regions  # noqa: E402
from lfcam.sim.capture import apply_overrides, simulate  # noqa: E402
from lfcam.sim.geometry import truth_geometry  # noqa: E402
from lfcam.sim.render import Renderer  # noqa: E402
from lfcam.sim.scene import scene_from_dict  # noqa: E402

ROTATION = 0.012
NOISE = {"photon_noise": True, "full_well_e": 20000, "read_noise_e": 3.0}
HALF_FIELD_MM = 12.0


def camera(focus_mm: float) -> dict:
    """Scene camera overrides: focus and a slightly rotated MLA."""
    return {"mla": {"focus_mm": focus_mm, "rotation_rad": ROTATION}}


def calibrated_geometry(base, focus_mm: float, used, shape) -> Geometry:
    """Geometry from calibrate_white on a rendered white image of the same camera."""
    white, _, _ = simulate(base, scene_from_dict({"seed": 5, "objects": [{"type": "white"}],
                                                  "camera": camera(focus_mm)}))
    cal = calibrate_white(white.astype(np.float32)).with_d_in(used.d_in_mm, "profile")
    return prepare_geometry(used, cal, shape)


def run(img, used, geom, old: bool):
    """Distance of the main region: (distance_mm, path, region) — old = before the fix."""
    original = LF.fit_point
    if old:
        LF.fit_point = lambda p, d, s, e, c, extraction=None: original(p, d, s, e, c)
    try:
        res = run_distance(img, used, None, model="exact", geometry=geom)
    finally:
        LF.fit_point = original
    stats = lenslet_stats(img, geom.lmap)
    regions = find_regions(stats, geom.lmap, geom.pitch_px)
    k = int(np.argmax([len(r.lenslets) for r in regions]))
    r = res.regions[k]
    path = "tri" if len(regions[k].lenslets) >= LF.TRIANGULATION_ENOUGH else "pix"
    return (r.distance_mm if r.status == "ok" else float("nan")), path, regions[k]


def ray_centroid_ii(used, rend, truth, lens_mm):
    """Indirect inference (old forward model) on the renderer's per-lenslet ray centroids."""
    lens = used.main_lens
    fx = used.mla.focal_length_mm
    pp = used.sensor.pixel_pitch_mm
    ax, ay = used.sensor.axis_xy_px
    lenses = truth["lenses"]
    table = {(int(i), int(j)): k for k, (i, j) in enumerate(zip(rend.li, rend.lj, strict=True))}
    idx = np.array([table[tuple(v)] for v in lenses["index_ij"]])
    cen = np.array(lenses["centroid_px"])
    w = np.array(lenses["weight"])
    land = np.column_stack([(cen[:, 0] - ax) * pp, (cen[:, 1] - ay) * pp])
    meas = _statistic(lens, used.d_in_mm, fx, lens_mm[idx], w, land)
    if meas is None:
        return float("nan")
    # simulate only the lenslets whose light reached the sensor, as the renderer's truth does
    c = lens_mm[idx]
    tree = cKDTree(lens_mm)
    pattern = pupil_pattern(320)
    s = meas[0].copy()
    for _ in range(10):
        e, lsim = simulate_lenslets(used, used.d_in_mm, s, tree, lens_mm, pattern)
        e, lsim = e[idx], lsim[idx]
        good = e > 0
        sim = _statistic(lens, used.d_in_mm, fx, c[good], e[good], lsim[good])
        if sim is None:
            return float("nan")
        s = s + (meas[0] - sim[0])
    return float(lens.front_vertex_z_mm - s[2])


def misfits(img, used, geom, region, src_true, distance_fit):
    """Image-fit misfit at the true source and at the fitted distance (same line of sight)."""
    x0, y0, x1, y1 = region.box_px
    near = np.unique(np.concatenate([region.lenslets, neighbours(geom, region)]))
    pad = int(math.ceil(0.5 * geom.pitch_px))
    h, w = img.shape
    box = (max(0, x0 - pad), max(0, y0 - pad), min(w, x1 + pad), min(h, y1 + pad))
    patch = _Patch(used, used.d_in_mm, img, box, geom.lens_centres_mm[near])
    pupil = np.array([0.0, 0.0, used.main_lens.rim_z_mm])
    z_front = used.main_lens.front_vertex_z_mm
    scale = (distance_fit + (used.main_lens.rim_z_mm - z_front)) / (
        z_front - src_true[2] + (used.main_lens.rim_z_mm - z_front))
    return patch.misfit(src_true), patch.misfit(pupil + scale * (src_true - pupil))


def main() -> None:
    """Render, measure, print the table."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--focus", default="1000,1500")
    ap.add_argument("--distances", default="300,700,1750,2900,3500")
    ap.add_argument("--radii", default="0,5,9.6", help="field radius on the sensor, mm")
    ap.add_argument("--no-old", action="store_true", help="skip the pre-fix columns")
    args = ap.parse_args()
    base = load_profile("system2")
    shape = (base.sensor.height_px, base.sensor.width_px)
    rows = []
    print("# system 2, 1536² sensor, MLA rotated 0.012 rad, noisy; errors in % vs truth")
    print(f"{'focus':>6} {'Ad':>6} {'r mm':>5} {'side':>6} {'path':>4} | {'truthC old':>10} "
          f"{'rayC':>7} {'calC old':>9} | {'truthC new':>10} {'calC new':>9} | {'dC µm':>6} "
          f"{'mis@T':>7} {'mis@fit':>7} {'s':>5}")
    for focus in [float(v) for v in args.focus.split(",")]:
        used = apply_overrides(base, camera(focus))
        used = used.with_d_in(used.d_in_mm)
        geom_t, rend = truth_geometry(used, shape), Renderer(used)
        geom_c = calibrated_geometry(base, focus, used, shape)
        z_ep = used.main_lens.exit_pupil_z_mm
        mag = 1 + used.mla.focal_length_mm / (used.d_in_mm - z_ep)
        for dist in [float(v) for v in args.distances.split(",")]:
            for r in [float(v) for v in args.radii.split(",")]:
                t0 = time.perf_counter()
                az = math.radians(30.0)
                target = np.array([math.cos(az), math.sin(az)]) * r / mag
                xy = chief_ray_offset(used, used.d_in_mm, dist, target)
                scene = {"seed": 3, "rays_per_source": 1_000_000, "sensor": NOISE,
                         "exposure": {"peak": 0.8}, "camera": camera(focus),
                         "objects": [{"type": "point", "distance_mm": dist,
                                      "position_mm": [float(xy[0]), float(xy[1])]}]}
                raw, used2, truth = simulate(base, scene_from_dict(scene))
                img = raw.astype(np.float64)
                src = np.array([xy[0], xy[1], used.main_lens.front_vertex_z_mm - dist])

                def e(d, dist=dist):
                    return 100.0 * (d / dist - 1.0)

                old_t = old_c = ray = float("nan")
                if not args.no_old:
                    old_t, path, _ = run(img, used, geom_t, True)
                    old_c, _, _ = run(img, used, geom_c, True)
                new_t, path, region = run(img, used, geom_t, False)
                new_c, _, region_c = run(img, used, geom_c, False)
                if path == "tri" and not args.no_old:
                    ray = ray_centroid_ii(used, rend, truth, geom_t.lens_centres_mm)
                # calibrated vs true lenslet centres over the region's lenslets
                tc = cKDTree(geom_t.lens_centres_mm)
                dd, _ = tc.query(geom_c.lens_centres_mm[region_c.lenslets])
                dc = float(np.sqrt((dd**2).mean())) * 1000.0
                m_t = m_f = float("nan")
                if path == "pix" and np.isfinite(new_t):
                    m_t, m_f = misfits(img, used, geom_t, region, src, new_t)
                side = "front" if dist < focus else "behind"
                dt = time.perf_counter() - t0
                print(f"{focus:6.0f} {dist:6.0f} {r:5.1f} {side:>6} {path:>4} | {e(old_t):10.3f} "
                      f"{e(ray):7.3f} {e(old_c):9.3f} | {e(new_t):10.3f} {e(new_c):9.3f} | "
                      f"{dc:6.2f} {m_t:7.4f} {m_f:7.4f} {dt:5.1f}", flush=True)
                rows.append((focus, side, r, e(old_c), e(new_c), e(old_t), e(new_t)))
    print("\n# summary by side of focus and field radius: mean |err| / max |err| % (calibrated "
          "centres, then truth centres)")
    print(f"{'focus':>6} {'side':>6} {'r mm':>5} | {'old cal':>15} {'new cal':>15} | "
          f"{'old truth':>15} {'new truth':>15}")
    keys = sorted({(f, s, r) for f, s, r, *_ in rows})
    for key in keys:
        sel = np.array([v[3:] for v in rows if v[:3] == key], dtype=float)
        cells = []
        for j in range(4):
            a = np.abs(sel[:, j])
            cells.append(f"{np.nanmean(a):7.3f}/{np.nanmax(a):7.3f}" if np.isfinite(a).any()
                         else f"{'—':>15}")
        print(f"{key[0]:6.0f} {key[1]:>6} {key[2]:5.1f} | {cells[0]} {cells[1]} | "
              f"{cells[2]} {cells[3]}")
    allv = np.abs(np.array([v[3:] for v in rows], dtype=float))
    print(f"{'all':>6} {'':>6} {'':>5} | " + " ".join(
        f"{np.nanmean(allv[:, j]):7.3f}/{np.nanmax(allv[:, j]):7.3f}" for j in range(4)))


if __name__ == "__main__":
    main()
