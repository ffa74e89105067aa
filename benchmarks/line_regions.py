"""Six line regions of the focus grid, each fitted several times: the least CPU (issue 17).

Run: ``python benchmarks/line_regions.py [--repeats N] [--more | --far1] [--ab NAME=VALUE,...]
[--cache DIR] [--render-cache DIR]``

The regions are the grid's slow kinds (``benchmarks/focus_grid.py --lines``: a line 3 mm
long on the MLA, a 1 m focus, photon and read noise, calibrated lenslet centres):

* system 2, hexagonal MLA, 380 mm in front of focus at 80 % of the half-field and at the
  centre (ray-sampled: the MLA cuts the caustic);
* system 2, hexagonal, 2900 mm behind focus at 60 % (on the lenslet cells);
* system 2, rectangular, 2200 mm behind at 80 %, and 560 mm in front at the centre;
* system 1, 3400 mm behind focus at 80 % (ray-sampled, refitted by the settled test).

Each region's :func:`lfcam.measure.fastfit.measure_lenslet` runs once to warm up, then
``--repeats`` times on one core; the least and the median CPU are printed with the answer.
Run two checkouts side by side (one core each) to compare them: the least CPU of several
runs is the figure least disturbed by the other process (docs/distance.md, "A smaller label
map and uncut rim cells (stop 49)").

``--ab NAME=VALUE,...`` compares the code with itself with those constants of
:mod:`lfcam.measure.fastfit` set (a switch such as ``SUMMARY_SCAN_FIRST=0``): each region is
fitted alternately both ways in one process, so the machine's drift, which moves whole runs
by ±10 % on this machine, falls on both alike; it prints both least CPUs, both answers and
the ratio of their sums. ``--more`` adds eleven regions: system 2's lines on the cells behind
focus (hexagonal and rectangular, 1500–3400 mm, the field's centre to 80 %), a rectangular
380 mm line, a hexagonal one at the centre, a 720 mm line, and three more of system 1's far
lines (docs/distance.md, "The summary matched on the scan's rays (stop 57)"). ``--far1`` fits
instead system 1's 24 lines behind focus at 60 and 80 % of the half-field (1500–3400 mm,
0°, 60°, 135°): the ray-sampled, refitted kind (docs/distance.md, "The settled test before
the fine fit's last iteration (stop 58)").
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import focus_grid as fg  # noqa: E402

import lfcam.distance as distance  # noqa: E402
from lfcam.measure import fastfit as ff  # noqa: E402
from lfcam.measure import kernels  # noqa: E402
from lfcam.measure.lenslets import lenslet_stats  # noqa: E402
from lfcam.measure.noise import capture_noise  # noqa: E402
from lfcam.measure.regions import find_regions  # noqa: E402

# (system, MLA grid, sensor px, distance mm, line angle °, share of the half-field)
CASES = (
    ("system2", "hex", 1536, 380.0, 0.0, 0.8),
    ("system2", "hex", 1536, 380.0, 60.0, 0.0),
    ("system2", "hex", 1536, 2900.0, 60.0, 0.6),
    ("system2", "rect", 1536, 2200.0, 0.0, 0.8),
    ("system1", "rect", 1024, 3400.0, 135.0, 0.8),
    ("system2", "rect", 1024, 560.0, 0.0, 0.0),
)
MORE = (  # (--more)
    ("system2", "hex", 1536, 1500.0, 60.0, 0.6),
    ("system2", "hex", 1536, 2200.0, 0.0, 0.8),
    ("system2", "hex", 1024, 2900.0, 0.0, 0.0),
    ("system2", "rect", 1536, 3400.0, 135.0, 0.6),
    ("system2", "rect", 1024, 2900.0, 60.0, 0.0),
    ("system2", "rect", 1536, 380.0, 60.0, 0.6),
    ("system2", "hex", 1024, 380.0, 135.0, 0.0),
    ("system2", "rect", 1024, 720.0, 60.0, 0.0),
    ("system1", "rect", 1024, 2900.0, 0.0, 0.6),
    ("system1", "rect", 1024, 2200.0, 0.0, 0.8),
    ("system1", "rect", 1024, 1500.0, 135.0, 0.8),
)
FAR1 = tuple(  # (--far1) system 1's 24 lines behind focus at 60 and 80 % of the half-field
    ("system1", "rect", 1024, d, a, fld) for fld in (0.6, 0.8)
    for d in (1500.0, 2200.0, 2900.0, 3400.0) for a in (0.0, 60.0, 135.0))


def prepare(cam, image: np.ndarray, every: bool = False) -> tuple:
    """(profile, geometry, largest region, pixel noise) of a capture, made ready as
    ``focus_grid.py`` measures it: its measuring profile, and the capture's noise model (the
    fits' gates read it) registered as :func:`lfcam.distance.run_distance` registers it.
    ``every``: the list of all its regions instead of the largest."""
    geom, profile = cam.geom, cam.measuring_profile()
    regions, noise = capture_regions(profile, geom, image, float(
        cam.used.sensor.white_level - cam.used.sensor.black_level))
    return (profile, geom, regions if every else max(regions, key=lambda r: len(r.lenslets)),
            noise)


def capture_regions(profile, geom, image: np.ndarray, white_value: float) -> tuple:
    """(regions, pixel noise) of a capture on ``geom``, its noise model (which the fits'
    gates read) registered as :func:`lfcam.distance.run_distance` registers it (``white_value``:
    the image's white level less its black level)."""
    stats = lenslet_stats(image, geom.lmap)
    capture_noise(image, geom.lmap, geom.pitch_px, stats,
                  sensor_gain=distance.sensor_gain(profile, white_value))
    return find_regions(stats, geom.lmap, geom.pitch_px), distance.noise_sigma(image)


def add_ab_options(ap: argparse.ArgumentParser, repeats: int, example: str) -> None:
    """``--repeats``, ``--cache``, ``--render-cache`` and ``--ab`` (``example``: a switch
    to name in its help), as this script and ``point_regions.py`` take them."""
    ap.add_argument("--repeats", type=int, default=repeats)
    ap.add_argument("--cache", type=Path,
                    default=Path(tempfile.gettempdir()) / "lfcam_focus_grid",
                    help="folder for the white-image calibrations (as focus_grid.py's)")
    ap.add_argument("--render-cache", type=Path,
                    help="folder keeping the rendered captures (as focus_grid.py's)")
    ap.add_argument("--ab", default="", metavar="NAME=VALUE,...",
                    help="fit each region alternately as it is and with these fastfit "
                         f"constants (e.g. {example})")


def ab_settings(ap: argparse.ArgumentParser, args) -> list[dict]:
    """The fastfit settings to fit with: ``[{}]`` (the code as it is), or with ``--ab``
    ``[{}, its constants]``; the caches made and the kernels warmed up first (``--cache``,
    ``--render-cache``)."""
    try:
        other = fg.fastfit_overrides(args.ab)
    except ValueError as exc:
        ap.error(f"--ab: {exc}")
    args.cache.mkdir(parents=True, exist_ok=True)
    if args.render_cache:
        args.render_cache.mkdir(parents=True, exist_ok=True)
        fg.RENDER_CACHE[0] = args.render_cache
    kernels.warm_up()
    return [{}, other] if other else [{}]


def _fit(profile, geom, image, region, noise, settings: dict,
         others: tuple = (), accept=None) -> tuple[float, object]:
    """One fit of the region with ``settings`` (fastfit constants) in force: its CPU (s) and
    measurement (``others``: the capture's nearby regions, as ``run_distance`` passes them;
    ``accept``: as ``run_distance`` passes it with a tolerance)."""
    saved = {name: getattr(ff, name) for name in settings}
    for name, value in settings.items():
        setattr(ff, name, value)
    try:
        c0 = time.process_time()
        m = ff.measure_lenslet(profile, geom, image, region, noise, accept, others=others)
        return time.process_time() - c0, m
    finally:
        for name, value in saved.items():
            setattr(ff, name, value)


def alternate(profile, geom, image, region, noise, settings: list[dict],
              repeats: int, others: tuple = (), accept=None
              ) -> tuple[list[list[float]], list, list[int]]:
    """Each of ``settings`` fitted once to warm up, then ``repeats`` rounds of one fit a
    setting in turn (the machine's drift falls on all alike): each setting's CPU (s) of
    every round, its last measurement and the model rays its last fit traced
    (:func:`lfcam.measure.fastfit.counting_rays`: a cost the machine's load does not move)
    (``others``, ``accept``: as :func:`_fit`)."""
    for s in settings:
        _fit(profile, geom, image, region, noise, s, others, accept)  # warm up
    spent: list[list[float]] = [[] for _ in settings]
    answers: list = [None] * len(settings)
    rays = [0] * len(settings)
    for _ in range(max(1, repeats)):
        for k, s in enumerate(settings):
            with ff.counting_rays() as count:
                cpu, answers[k] = _fit(profile, geom, image, region, noise, s, others, accept)
            spent[k].append(cpu)
            rays[k] = count[0]
    return spent, answers, rays


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_ab_options(ap, 7, "SUMMARY_SCAN_FIRST=0")
    ap.add_argument("--more", action="store_true", help="eleven more regions (module doc)")
    ap.add_argument("--far1", action="store_true",
                    help="system 1's 24 lines behind focus at 60 and 80 %% of the field only")
    args = ap.parse_args()
    settings = ab_settings(ap, args)
    other = settings[-1]
    rows = []
    cases = FAR1 if args.far1 else CASES + (MORE if args.more else ())
    for system, grid, size, distance_mm, angle, field in cases:
        cam = fg.Camera(system, 1000.0, size, args.cache, False, grid=grid)
        image, _, _ = cam.render([cam.line(distance_mm, angle, field, 1_000_000,
                                           fg.LINE_HALF_MM)], seed=3, rays=1_000_000)
        profile, geom, region, noise = prepare(cam, image)
        spent, answers, _ = alternate(profile, geom, image, region, noise, settings,
                                      args.repeats)
        rows.append((f"{system}, {grid}, {distance_mm:.0f} mm, {100 * field:.0f} % of the "
                     f"field, {angle:.0f}°", len(region.lenslets),
                     [f"{m.kind} {100.0 * (m.distance_mm / distance_mm - 1.0):+.4f} %"
                      for m in answers],
                     [1e3 * min(t) for t in spent], [1e3 * float(np.median(t)) for t in spent]))
    print(f"\n# least and median CPU of {args.repeats} fits, one core")
    if not other:
        print("| line region | lenslets | answer | least ms | median ms |\n|---|---|---|---|---|")
        for name, lenslets, ans, least, median in rows:
            print(f"| {name} | {lenslets} | {ans[0]} | {least[0]:.1f} | {median[0]:.1f} |")
        return
    print(f"# B: {args.ab}, fitted alternately with A (the code as it is)")
    print("| line region | lenslets | answer A | answer B | least ms A | B | median ms A | B |\n"
          "|---|---|---|---|---|---|---|---|")
    for name, lenslets, ans, least, median in rows:
        print(f"| {name} | {lenslets} | {ans[0]} | {ans[1]} | {least[0]:.1f} | {least[1]:.1f} "
              f"| {median[0]:.1f} | {median[1]:.1f} |")
    sums = [sum(r[3][k] for r in rows) for k in range(2)]
    print(f"| sum of least | | | | {sums[0]:.1f} | {sums[1]:.1f} | B/A {sums[1] / sums[0]:.3f} | |")


if __name__ == "__main__":
    main()
