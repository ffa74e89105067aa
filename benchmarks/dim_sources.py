"""The 12-source captures' far, dim sources over noise draws: the lenslet fit against the pixel
fit (bias, scatter, stated σ), with the capture's noise clipped at zero as the renderer writes
raws, or unclipped (a black level under the noise).

Run: ``python benchmarks/dim_sources.py [--systems system1,system2] [--foci 1000]
[--distances 2700,3100,3500] [--seeds 5-14] [--black-level DN] [--no-pixel] [--tolerance T]
[--cache DIR] [--render-cache DIR]``

The captures are ``focus_grid.py --scene12``'s (the same scene, renderer, noise and
measuring profile), rendered with each of ``--seeds`` (rays and noise). Each region that
holds one of ``--distances``' sources is fitted by :func:`lfcam.measure.fastfit.measure_lenslet`
and (unless ``--no-pixel``) :func:`lfcam.measure.lightfield.measure_lightfield`, as
``lfcam distance --method lenslet`` and ``--method lightfield`` fit it. ``--black-level``: the
raws offset by that many DN before their noise is clipped at zero (the renderer's default is
0: most dark pixels of the dim blurs then read exactly 0), and the fits given the raws less
that level, as ``lfcam.io.Capture.grey`` gives a raw with a black level: noise below zero.
``--tolerance T``: also the answer ``lfcam distance --method auto --tolerance T`` gives, the
lenslet fit's where 3σ meets T (:func:`lfcam.models.auto.lenslet_answer_meets`), else the
pixel fit's (the lenslet fit here without auto's ``accept``, which may spare it a polish).
Prints a row a fit and, per source, each method's mean signed error with its standard error,
the scatter (SD) and the mean stated σ (docs/distance.md, "The lenslet fit on dim far sources
(stop 62)").
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

import focus_grid as fg  # noqa: E402
from point_regions import _seeds, scene12_regions  # noqa: E402

from lfcam.measure.fastfit import measure_lenslet  # noqa: E402
from lfcam.measure.lightfield import measure_lightfield  # noqa: E402
from lfcam.models.auto import lenslet_answer_meets  # noqa: E402
from lfcam.sim.capture import apply_overrides  # noqa: E402


def camera(system: str, focus: float, black_level: int, cache: Path) -> fg.Camera:
    """``focus_grid.py``'s camera, its raws offset by ``black_level`` DN (0: as rendered)."""
    cam = fg.Camera(system, focus, None, cache, False)
    if black_level:
        cam.cam.setdefault("sensor", {})["black_level"] = black_level
        cam.used = apply_overrides(cam.base, cam.cam).with_d_in(cam.used.d_in_mm)
    return cam


def fits(cam: fg.Camera, seed: int, distances: set[float], pixel: bool,
         tolerance: float | None = None) -> list[dict]:
    """Each wanted source's region of one draw, fitted by each method: {ad, method: (error %,
    σ %, CPU s)}; with ``tolerance``, also ``auto``'s choice of the two."""
    rows = []
    for profile, geom, image, noise, region, near, ad in scene12_regions(cam, seed):
        if ad not in distances:
            continue
        row = {"ad": ad}
        runs = [("lenslet", measure_lenslet, (None, near))]
        if pixel:
            runs.append(("pixel", measure_lightfield, (False, near)))
        for name, run, more in runs:
            c0 = time.process_time()
            m = run(profile, geom, image, region, noise, *more)
            spent = time.process_time() - c0
            ok = m.status == "ok"
            row[name] = (100.0 * (m.distance_mm / ad - 1.0) if ok else math.nan,
                         100.0 * m.sigma_distance_mm / ad if ok else math.nan, spent)
        if tolerance is not None and pixel:
            d_l, s_l = (1.0 + 0.01 * row["lenslet"][0]) * ad, 0.01 * row["lenslet"][1] * ad
            kept = math.isfinite(d_l) and lenslet_answer_meets(d_l, s_l, tolerance)
            row["auto"] = row["lenslet"] if kept else row["pixel"]
        rows.append(row)
        print(f"| {cam.system}, focus {cam.focus_mm:g}, seed {seed}, {ad:.0f} mm | "
              + " | ".join(f"{row[k][0]:+.3f} ± {row[k][1]:.3f} ({1e3 * row[k][2]:.0f} ms)"
                           for k, _, _ in runs) + " |", flush=True)
    return rows


def summary(label: str, rows: list[dict], methods: list[str]) -> None:
    """Per source and method: mean signed error ± its standard error, SD, mean σ."""
    for ad in sorted({r["ad"] for r in rows}):
        got = [r for r in rows if r["ad"] == ad]
        parts = []
        for name in methods:
            e = np.array([r[name][0] for r in got])
            s = np.array([r[name][1] for r in got])
            e, s = e[np.isfinite(e)], s[np.isfinite(s)]
            if not e.size:
                parts.append(f"{name}: no answer")
                continue
            sd = float(e.std(ddof=1)) if e.size > 1 else math.nan
            parts.append(f"{name} {e.mean():+.2f} ± {sd / math.sqrt(e.size):.2f} %, SD {sd:.2f}, "
                         f"σ {s.mean():.2f} ({e.size} answers)")
        print(f"# {label}, {ad:.0f} mm: " + "; ".join(parts))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--systems", default="system1,system2")
    ap.add_argument("--foci", default="1000")
    ap.add_argument("--distances", default="2700,3100,3500")
    ap.add_argument("--seeds", default="5-14", type=_seeds)
    ap.add_argument("--black-level", type=int, default=0, metavar="DN")
    ap.add_argument("--no-pixel", action="store_true", help="the lenslet fit alone")
    ap.add_argument("--tolerance", type=float, default=None, metavar="T",
                    help="also auto's answer at this tolerance (%%)")
    ap.add_argument("--cache", type=Path, default=ROOT / "benchmarks" / ".cache")
    ap.add_argument("--render-cache", type=Path, default=None)
    args = ap.parse_args()
    if args.render_cache is not None:
        args.render_cache.mkdir(parents=True, exist_ok=True)
        fg.RENDER_CACHE[0] = args.render_cache
    from lfcam.measure import kernels

    kernels.warm_up()
    distances = {float(v) for v in args.distances.split(",")}
    methods = ["lenslet"] + ([] if args.no_pixel else ["pixel"])
    summarised = methods + (["auto"] if args.tolerance is not None and not args.no_pixel else [])
    print("| capture, source | " + " | ".join(f"{m} error % ± σ (CPU)" for m in methods) + " |")
    print("|---|" + "---|" * len(methods))
    for system in args.systems.split(","):
        for focus in (float(v) for v in args.foci.split(",")):
            cam = camera(system, focus, args.black_level, args.cache)
            rows = [r for seed in args.seeds for r in fits(cam, seed, distances,
                                                           not args.no_pixel, args.tolerance)]
            summary(f"{system}, focus {focus:g}, black level {args.black_level}", rows,
                    summarised)


if __name__ == "__main__":
    main()
