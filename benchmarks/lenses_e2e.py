"""End to end through multi-element main lenses: render, calibrate, measure, refocus.

Run: ``PYTHONPATH=. python benchmarks/lenses_e2e.py [--quick] [--lenses cooke,dg28]``

Two prescriptions (``calibration/cooke_triplet.toml``, f 50 mm F/4, stop inside the lens on a
curved surface; the double Gauss of ``calibration/double_gauss.toml`` opened to F/2.8 with an
F/2.8 MLA), each focused at 1 m and at infinity. Per camera:

* a full-size white image renders the reference calibration (traced micro-image centroids,
  ``data/synthetic/make_calibration.py``);
* point sources at 300 … 3500 mm (both sides of the 1 m focus), on axis and off axis
  (offset 1.2 % of the distance), photon and read noise, go through ``run_distance``
  (``lightfield`` method, ``exact`` model): ERROR = |Ad − Ed| / Ad, Ad from the front vertex;
* 10 mm line sources at three distances (focus 1 m): the line fit's distance;
* metric refocus (focus 1 m): the point's capture is decoded and refocused at the exact shift for
  its own distance D and for 0.9·D and 1.1·D; the refocused spot's RMS radius (lenslets) must
  be smallest at D. Measured two ways: from the decoded views (each view's light centroid
  moved by the shift: the refocused spot without resampling, the criterion) and on the
  refocused image itself (whole-lenslet sampling and bilinear shifting add up to ~0.5 lenslet,
  which hides differences at far distances);
* the point fit's time per region.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "data" / "synthetic"))

from make_calibration import reference_calibration  # noqa: E402

from lfcam.camera import MainLens, load_profile  # noqa: E402
from lfcam.decode import decode, focal_stack, shift_for_distance  # noqa: E402
from lfcam.distance import run_distance  # noqa: E402
from lfcam.io import load_capture  # noqa: E402
from lfcam.measure import prepare_geometry  # noqa: E402
from lfcam.optics.lens import Prescription  # noqa: E402
from lfcam.sim.capture import simulate, write_capture  # noqa: E402
from lfcam.sim.scene import scene_from_dict  # noqa: E402

SEED = 20261123
NOISE = {"photon_noise": True, "full_well_e": 20000.0, "read_noise_e": 3.0}
DISTANCES = [300, 500, 750, 1500, 2500, 3500]
LINE_DISTANCES = [500, 1500, 3000]
REFOCUS_DISTANCES = [500, 1500, 3000]
OFFSET_FRACTION = 0.012


def double_gauss_f28():
    """The shipped double Gauss opened to F/2.8 (every clear aperture ×4/2.8), F/2.8 MLA."""
    p = load_profile("double_gauss")
    rx = p.main_lens.as_prescription
    k = 4.0 / 2.8
    rx = Prescription(tuple(dataclasses.replace(s, semi_diameter_mm=s.semi_diameter_mm * k)
                            for s in rx.surfaces), name="double Gauss f100 F/2.8")
    mla = dataclasses.replace(p.mla, focal_length_mm=0.55)
    return dataclasses.replace(p, name="double_gauss_f28", main_lens=MainLens(prescription=rx),
                               mla=mla)


def cameras(which: list[str]):
    """(label, profile focused at 1 m) per lens."""
    out = []
    if "cooke" in which:
        out.append(("Cooke triplet F/4", load_profile("cooke_triplet")))
    if "dg28" in which:
        out.append(("double Gauss F/2.8", double_gauss_f28()))
    if "dg4" in which:
        out.append(("double Gauss F/4", load_profile("double_gauss")))
    return out


def render(profile, objects, seed, folder: Path, name: str, noise=True, rays=300_000):
    """Render to ``folder/name.png``; returns (grey image, used profile, truth)."""
    body = {"seed": seed, "rays_per_source": rays, "objects": objects}
    if noise:
        body["sensor"] = NOISE
    raw, used, truth = simulate(profile, scene_from_dict(body))
    img, _, _ = write_capture(folder / f"{name}.png", raw, used, truth)
    return load_capture(img, used).grey(), used, truth


def best_region(run):
    ok = [r for r in run.regions if r.status == "ok"]
    if not ok:
        return None
    return max(ok, key=lambda r: r.diameter_mm if np.isfinite(r.diameter_mm) else 0.0)


def rms_spot(image: np.ndarray, centre_st, half: int = 6) -> float:
    """RMS radius (lenslets) of a refocused spot about its centroid, in a window at centre."""
    s0, t0 = (int(round(v)) for v in centre_st)
    win = image[t0 - half:t0 + half + 1, s0 - half:s0 + half + 1].astype(np.float64)
    win = np.clip(win - np.median(image), 0.0, None)
    yy, xx = np.mgrid[-half:half + 1, -half:half + 1]
    tot = win.sum()
    mx, my = (win * xx).sum() / tot, (win * yy).sum() / tot
    return float(np.sqrt((win * ((xx - mx) ** 2 + (yy - my) ** 2)).sum() / tot))


def view_rms(lf, shift: float, centre_st, half: int = 6) -> float:
    """RMS radius (lenslets) of the refocused point from the decoded views, without
    resampling: each view's light centroid near ``centre_st`` moved by the shift
    (``s + a·du``, ``t + a·dv·k_y``, the refocus convention), energy-weighted."""
    nv, nu = lf.data.shape[:2]
    vc, uc = lf.angular_centre
    ky = lf.spacing_px[0] / lf.spacing_px[1]
    s0, t0 = (int(round(v)) for v in centre_st)
    pts, ws = [], []
    yy, xx = np.mgrid[t0 - half:t0 + half + 1, s0 - half:s0 + half + 1]
    for v in range(nv):
        for u in range(nu):
            win = (lf.data[v, u] * (lf.weight[v, u] > 0))[t0 - half:t0 + half + 1,
                                                          s0 - half:s0 + half + 1]
            e = float(win.sum())
            if e <= 0:
                continue
            pts.append(((win * xx).sum() / e + shift * (u - uc),
                        (win * yy).sum() / e + shift * (v - vc) * ky))
            ws.append(e)
    pts, ws = np.array(pts), np.array(ws)
    keep = ws > 0.02 * ws.max()
    pts, ws = pts[keep], ws[keep]
    m = (pts * ws[:, None]).sum(0) / ws.sum()
    return float(np.sqrt((ws * ((pts - m) ** 2).sum(1)).sum() / ws.sum()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="three distances, one focus")
    ap.add_argument("--lenses", default="cooke,dg28")
    args = ap.parse_args()
    dists = [300, 1500, 3500] if args.quick else DISTANCES
    focuses = [1000.0] if args.quick else [1000.0, math.inf]
    tmp = Path(tempfile.mkdtemp(prefix="lfcam_lenses_e2e_"))
    all_point, all_line, fit_times = [], [], []
    refocus_ok = []
    for label, base in cameras(args.lenses.split(",")):
        for focus in focuses:
            prof = base.with_focus(focus)
            t0 = time.perf_counter()
            cal = reference_calibration(prof)
            print(f"\n# {label}, focus {focus:g} mm: EFL {prof.main_lens.focal_length_mm:.3f} mm, "
                  f"F/{prof.main_lens.f_number:.2f}, gap {prof.gap_mm:.3f} mm "
                  f"(calibration {time.perf_counter() - t0:.0f} s)", flush=True)
            print(f"{'Ad mm':>7} {'Δh mm':>7} {'Ed mm':>10} {'Eh mm':>8} {'ERROR %':>8} "
                  f"{'fit s':>6}")
            geom = None
            for d in dists:
                for off in (0.0, OFFSET_FRACTION * d):
                    img, used, _ = render(prof, [{"type": "point", "distance_mm": d,
                                                  "offset_mm": off}],
                                          SEED + d + int(off), tmp, f"p_{d}_{off:g}")
                    if geom is None:
                        geom = prepare_geometry(used, cal, img.shape)
                    run = run_distance(img, used, cal, model="exact", method="lightfield",
                                       geometry=geom)
                    r = best_region(run)
                    fit = sum(v for k, v in run.timings_s.items() if k != "geometry")
                    fit_times.append(fit / max(len(run.regions), 1))
                    if r is None:
                        status = run.regions[0].status if run.regions else "no region"
                        print(f"{d:7d} {off:7.2f} {status:>28}")
                        all_point.append(np.nan)
                        continue
                    err = abs(r.distance_mm - d) / d * 100.0
                    all_point.append(err)
                    print(f"{d:7d} {off:7.2f} {r.distance_mm:10.2f} {r.offset_mm:8.3f} "
                          f"{err:8.3f} {fit:6.2f}", flush=True)
            if focus != 1000.0:
                continue
            for d in LINE_DISTANCES:
                img, used, _ = render(prof, [{"type": "line", "distance_mm": d,
                                              "start_mm": [0.0, 0.0], "end_mm": [0.0, 10.0]}],
                                      SEED + 7 * d, tmp, f"l_{d}", rays=1_000_000)
                run = run_distance(img, used, cal, model="exact", method="lightfield",
                                   geometry=geom)
                lines = [r for r in run.regions if r.kind == "line" and r.status == "ok"]
                if not lines:
                    print(f"line {d:5d} mm: {[(r.kind, r.status) for r in run.regions]}")
                    all_line.append(np.nan)
                    continue
                err = abs(lines[0].distance_mm - d) / d * 100.0
                all_line.append(err)
                print(f"line {d:5d} mm: Ed {lines[0].distance_mm:9.2f}  ERROR {err:.3f} %")
            for d in REFOCUS_DISTANCES:
                img, used, truth = render(prof, [{"type": "point", "distance_mm": d,
                                                  "offset_mm": 0.0}],
                                          SEED + 3 * d, tmp, f"r_{d}", noise=False)
                lf = decode(img, cal)
                shifts = [float(shift_for_distance(used, x)) for x in (d, 0.9 * d, 1.1 * d)]
                stack = focal_stack(lf, shifts)
                own = stack[0].image
                t_pk, s_pk = np.unravel_index(np.argmax(own), own.shape)
                sizes = [rms_spot(o.image, (s_pk, t_pk)) for o in stack]
                views = [view_rms(lf, a, (s_pk, t_pk)) for a in shifts]
                good = views[0] < min(views[1:])
                refocus_ok.append(good)
                print(f"refocus {d:5d} mm (shifts {shifts[0]:.4f} / {shifts[1]:.4f} / "
                      f"{shifts[2]:.4f}): RMS spot (lenslets) at D, 0.9·D, 1.1·D: views "
                      f"{views[0]:.4f} {views[1]:.4f} {views[2]:.4f}; refocused image "
                      f"{sizes[0]:.3f} {sizes[1]:.3f} {sizes[2]:.3f}  "
                      f"{'sharpest at D' if good else 'NOT sharpest at D'}", flush=True)
    e = np.array(all_point)
    print(f"\npoints: mean {np.nanmean(e):.3f} %  max {np.nanmax(e):.3f} %  no answer "
          f"{int(np.isnan(e).sum())} of {e.size}")
    if all_line:
        e = np.array(all_line)
        print(f"lines: mean {np.nanmean(e):.3f} %  max {np.nanmax(e):.3f} %  no answer "
              f"{int(np.isnan(e).sum())} of {e.size}")
    if refocus_ok:
        print(f"refocus: sharpest at its own distance in {sum(refocus_ok)} of {len(refocus_ok)}")
    print(f"point fit: {np.median(fit_times):.2f} s per region (median; "
          f"{np.min(fit_times):.2f}–{np.max(fit_times):.2f})")


if __name__ == "__main__":
    main()
