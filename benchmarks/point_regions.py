"""The focus grid's 108 point regions, each fitted several times in one process: the least CPU
(issue 17).

Run: ``python benchmarks/point_regions.py [--repeats N] [--ab NAME=VALUE,...] [--systems S]
[--scene12 [--seeds 4|5-24|5,7]] [--foci 1000,1500,inf] [--renderer independent --white
analytic] [--cache DIR] [--render-cache DIR]``

The captures are ``benchmarks/focus_grid.py``'s single points (system 1 and 2, foci 1000 mm,
1500 mm and infinity, the grid's distances, 0, 40 and 80 % of the half-field; photon and read
noise, calibrated lenslet centres), measured as it measures them (its measuring profile and
the capture's noise model: ``line_regions.prepare``; the largest region). Each region's
:func:`lfcam.measure.fastfit.measure_lenslet` runs once to warm up, then ``--repeats`` times
on one core; ``--ab`` fits each region alternately as the code is and with those fastfit
constants set, as ``line_regions.py --ab`` does for lines, so the machine's drift falls on
both alike. Prints a row a region and a summary: mean, max and count over 50 ms of the least
CPUs, the ratio of their sums, the errors and how many answers moved (docs/distance.md, "One
cells match a basin (stop 58)").

``--scene12``: every region of ``focus_grid.py --scene12``'s six 12-source captures instead
(the same captures, seed and noise), each one's error against the source its box holds: the
crowded, far and dim blurs of a real scene, where the single points are one a capture.
``--foci`` keeps some of the foci; ``--renderer independent --white analytic`` renders the
12-source captures with ``benchmarks/render_independent.py`` and calibrates on the analytic
white, as ``focus_grid.py`` does: the second rendering path, over as many draws.
``--seeds``: the captures rendered with each of these seeds (rays and noise; 4 is
``focus_grid.py``'s), every region of every draw a row: one draw's photon-limited answers
scatter by their σ, so an ``--ab`` whose answers move is judged on many draws. The summary
then adds, with ``--ab``, the ratio of B's mean squared error to A's in units of A's σ
(``z²``) and of their mean |error|, each with a bootstrap 95 % interval over the regions
(docs/distance.md, "The polish's rays where photons dominate (stop 62)").
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
sys.path.insert(0, str(ROOT / "benchmarks"))

import focus_grid as fg  # noqa: E402
import line_regions as lr  # noqa: E402

from lfcam.measure.regions import nearby_regions  # noqa: E402

BUDGET_MS = 50.0  # issue 17's point region on one core


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    lr.add_ab_options(ap, 3, "SUMMARY_SAME_LOG=0")
    ap.add_argument("--systems", default="system1,system2")
    ap.add_argument("--scene12", action="store_true",
                    help="the regions of focus_grid.py's six 12-source captures instead")
    ap.add_argument("--seeds", default="4", type=_seeds,
                    help="--scene12's render seeds: N, A-B or a comma list (default 4)")
    ap.add_argument("--foci", default="1000,1500,inf", type=_foci,
                    help="the captures' foci, mm or inf (default 1000,1500,inf)")
    ap.add_argument("--renderer", choices=("sim", "independent"), default="sim",
                    help="focus_grid.py's --renderer (independent: --scene12 only, with "
                         "--white analytic as focus_grid.py pairs them)")
    ap.add_argument("--white", choices=("sim", "analytic"), default="sim",
                    help="focus_grid.py's --white: the white the lattice is calibrated on")
    args = ap.parse_args()
    if args.renderer == "independent" and not args.scene12:
        ap.error("--renderer independent: with --scene12 only")
    settings = lr.ab_settings(ap, args)
    print("| point region | lenslets | " + " | ".join(
        f"{k} error % ± σ | {k} least ms" for k in "AB"[:len(settings)]) + " |")
    print("|---|---|" + "---|---|" * len(settings))
    rows = scene12_rows(args, settings) if args.scene12 else []
    for system in args.systems.split(",") if not args.scene12 else ():
        for focus in args.foci:
            cam = fg.Camera(system, focus, None, args.cache, False)
            dists = fg.DEFAULT_DISTANCES.get(focus, fg.DEFAULT_DISTANCES[1000.0])
            for ad in (float(v) for v in dists.split(",")):
                for frac in (0.0, 0.4, 0.8):
                    obj = {"type": "point", "distance_mm": ad,
                           "position_mm": cam.position(ad, cam.field_xy(frac))}
                    image, _, _ = cam.render([obj], seed=3, rays=1_000_000)
                    profile, geom, region, noise = lr.prepare(cam, image)
                    rows.append(fit_row(f"{_case(system, focus)}, {ad:.0f} mm, "
                                        f"{100 * frac:.0f} %", args, settings, profile, geom,
                                        image, region, noise, ad))
    summary(rows, settings, args.ab)


def scene12_rows(args, settings: list[dict]) -> list[tuple]:
    """Each region of the six 12-source captures (``focus_grid.py --scene12``: systems 1
    and 2, foci 1000 mm, 1500 mm and ∞) of each of ``--seeds``' draws, fitted as :func:`main`
    fits the single points; its error against the source whose centroid its box holds (NaN:
    none or several)."""
    rows = []
    for seed in args.seeds:
        for system in args.systems.split(","):
            for focus in args.foci:
                cam = fg.Camera(system, focus, None, args.cache, False,
                                renderer=args.renderer, white=args.white)
                draw = f", seed {seed}" if len(args.seeds) > 1 else ""
                for profile, geom, image, noise, region, near, ad in scene12_regions(cam, seed):
                    rows.append(fit_row(f"{_case(system, focus)}{draw}, scene12, {ad:.0f} mm",
                                        args, settings, profile, geom, image, region, noise,
                                        ad, near))
    return rows


def scene12_regions(cam, seed: int):
    """Each region of ``focus_grid.py --scene12``'s capture on ``cam``, rendered with ``seed``
    (less the camera's black level, as :meth:`lfcam.io.Capture.grey` gives a raw), with what
    a fit reads and the distance of the one source whose centroid its box holds (NaN: none or
    several): (profile, geometry, image, pixel noise, region, its nearby regions, mm)."""
    objects, placed = fg.scene12_objects(cam)
    image, truth, _ = cam.render(objects, seed=seed, rays=1_000_000)
    if cam.used.sensor.black_level:
        image = image - cam.used.sensor.black_level  # (the noise below it kept)
    profile, geom, regions, noise = lr.prepare(cam, image, every=True)
    for region, near in zip(regions, nearby_regions(regions), strict=True):
        x0, y0, x1, y1 = region.box_px
        held = [p[0] for p, src in zip(placed, truth["sources"], strict=True)
                if x0 <= src["centroid_px"][0] < x1 and y0 <= src["centroid_px"][1] < y1]
        yield profile, geom, image, noise, region, near, held[0] if len(held) == 1 else math.nan


def _seeds(text: str) -> list[int]:
    """``--seeds``: ``N``, ``A-B`` (inclusive) or ``A,B,…``."""
    if "-" in text:
        lo, hi = (int(v) for v in text.split("-", 1))
        return list(range(lo, hi + 1))
    return [int(v) for v in text.split(",")]


def _foci(text: str) -> list[float]:
    """``--foci``: a comma list of foci, mm or ``inf``."""
    return [fg.parse_focus(v) for v in text.split(",")]


def _case(system: str, focus: float) -> str:
    return f"{system}, focus {'inf' if math.isinf(focus) else f'{focus:.0f}'}"


def fit_row(label: str, args, settings: list[dict], profile, geom, image, region, noise,
            ad: float, others: tuple = ()) -> tuple[list[float], list[float], list[float]]:
    """One region fitted alternately with each of ``settings`` (``line_regions.alternate``;
    ``others``: the capture's nearby regions, as ``run_distance`` passes them), its table row
    printed: each setting's least CPU (ms), error (%) against ``ad`` and σ (%)."""
    spent, answers, _ = lr.alternate(profile, geom, image, region, noise, settings,
                                     args.repeats, others)
    errors = [100.0 * (m.distance_mm / ad - 1.0) if m.status == "ok" else math.nan
              for m in answers]
    sigmas = [100.0 * m.sigma_distance_mm / ad if m.status == "ok" else math.nan
              for m in answers]
    least = [1e3 * min(t) for t in spent]
    cells = [f"{e:+.4f} ± {s:.4f} | {t:.1f}"
             for e, s, t in zip(errors, sigmas, least, strict=True)]
    print(f"| {label} | {len(region.lenslets)} | " + " | ".join(cells) + " |", flush=True)
    return least, errors, sigmas


def summary(rows: list[tuple], settings: list[dict], ab: str) -> None:
    """The summary lines: each setting's least CPUs (mean, max, over the budget) and errors;
    with ``--ab``, the ratio of the sums and the answers moved."""
    other = settings[-1]
    for k, name in enumerate("AB"[:len(settings)]):
        t = np.array([r[0][k] for r in rows])
        e = np.abs([r[1][k] for r in rows])
        label = "the code as it is" if k == 0 else ab
        print(f"# {name} ({label}): {len(rows)} regions, least CPU mean {t.mean():.1f} ms, "
              f"max {t.max():.0f} ms, over {BUDGET_MS:.0f} ms {int((t > BUDGET_MS).sum())}; "
              f"error mean {np.nanmean(e):.4f} %, max {np.nanmax(e):.3f} %")
    if other:
        ta = sum(r[0][0] for r in rows)
        tb = sum(r[0][1] for r in rows)
        moved = [abs(r[1][0] - r[1][1]) for r in rows
                 if r[1][0] != r[1][1] and not (math.isnan(r[1][0]) and math.isnan(r[1][1]))]
        print(f"# sum of least B/A {tb / ta:.3f}; {len(moved)} answers moved"
              + (f", by at most {max(moved):.4f} %" if moved else ""))
        if moved:
            print("# B/A, in A's σ: " + error_ratios(rows))


def error_ratios(rows: list[tuple], draws: int = 2000) -> str:
    """B's mean z² and mean |error| over A's (z: the error in units of A's σ; the regions both
    answered), each with a bootstrap 95 % interval over the regions."""
    e = np.array([r[1] for r in rows], dtype=float)
    s = np.array([r[2][0] for r in rows], dtype=float)
    both = np.isfinite(e).all(1) & (s > 0)
    if not both.any():
        return "no region answered by both"
    z = e[both] / s[both, None]
    rng = np.random.default_rng(0)
    picks = rng.integers(0, len(z), (draws, len(z)))
    out = []
    for name, v in (("mean z²", z * z), ("mean |error|", np.abs(z))):
        ratio = v[:, 1].mean() / v[:, 0].mean()
        boot = v[picks, 1].mean(1) / v[picks, 0].mean(1)
        lo, hi = np.percentile(boot, [2.5, 97.5])
        out.append(f"{name} {ratio:.3f} [{lo:.3f}, {hi:.3f}]")
    return f"{int(both.sum())} regions; " + ", ".join(out)


if __name__ == "__main__":
    main()
