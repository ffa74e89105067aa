"""Where a point region's CPU goes on the focus grid: its line fit, its polish, the rest.

Run: ``python benchmarks/point_stages.py [--scene12] [--csv DIR] [focus_grid.py options]``

Runs ``benchmarks/focus_grid.py --method lenslet`` (the 108 single points, or with
``--scene12`` the six 12-source scenes) with timers around each region's
:func:`lfcam.measure.fastfit.measure_lenslet`, the line fits it tries
(:func:`~lfcam.measure.fastfit.fit_lenslet_line`) and the evaluations of the
``POLISH_RAYS`` model. Prints the focus grid's own table, then one table: the regions' CPU
(mean, median, max, how many over 50 ms) and how many would be over 50 ms without the line
fits they tried, without their polish, and without both (docs/distance.md, "Points a region,
measured per region (stop 41)"). ``--csv DIR`` keeps ``points.csv`` (the focus grid's rows)
and ``stages.csv`` (one row a region) there.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # (as focus_grid.py)

import argparse  # noqa: E402
import csv  # noqa: E402
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

BUDGET_S = 0.05  # issue 17's point region: 50 ms on one core


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--csv", type=Path, help="directory for points.csv and stages.csv")
    args, rest = ap.parse_known_args()
    out = args.csv or Path(tempfile.mkdtemp(prefix="point_stages_"))
    out.mkdir(parents=True, exist_ok=True)
    spent = {"line": 0.0, "polish": 0.0}
    rows: list[tuple[float, float, float, str, int]] = []

    line_fit = ff.fit_lenslet_line

    def timed_line(*a, **k):
        c0 = time.process_time()
        try:
            return line_fit(*a, **k)
        finally:
            spent["line"] += time.process_time() - c0

    simulate = ff.LensletModel._simulate

    def timed_simulate(self, sources, group=None, groups=1):
        c0 = time.process_time()
        try:
            return simulate(self, sources, group, groups)
        finally:
            if not self.cells and self.rx.size == ff.POLISH_RAYS:
                spent["polish"] += time.process_time() - c0

    measure = ff.measure_lenslet

    def timed_measure(profile, geom, image, region, *a, **k):
        spent.update(line=0.0, polish=0.0)
        c0 = time.process_time()
        got = measure(profile, geom, image, region, *a, **k)
        rows.append((time.process_time() - c0, spent["line"], spent["polish"], got.kind,
                     len(region.lenslets)))
        return got

    ff.fit_lenslet_line = timed_line
    ff.LensletModel._simulate = timed_simulate
    distance.measure_lenslet = timed_measure
    sys.argv = ["focus_grid.py", "--method", "lenslet", "--csv", str(out / "points.csv"),
                *rest]
    fg.main()
    with (out / "stages.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["cpu_s", "line_s", "polish_s", "kind", "lenslets"])
        w.writerows(rows)
    t = np.array([r[0] for r in rows])
    line = np.array([r[1] for r in rows])
    polish = np.array([r[2] for r in rows])
    print(f"\n# {len(t)} regions, CPU of each region's measure_lenslet (one core)")
    print("| mean ms | median ms | max ms | over 50 ms | … without its line fit | … without "
          "its polish | … without both | line fits tried |")
    print("|---|---|---|---|---|---|---|---|")
    print(f"| {1e3 * t.mean():.1f} | {1e3 * np.median(t):.1f} | {1e3 * t.max():.0f} | "
          f"{int((t > BUDGET_S).sum())} | {int((t - line > BUDGET_S).sum())} | "
          f"{int((t - polish > BUDGET_S).sum())} | {int((t - line - polish > BUDGET_S).sum())} "
          f"| {int((line > 0).sum())} ({1e3 * line[line > 0].mean() if (line > 0).any() else 0:.0f}"
          f" ms each) |")


if __name__ == "__main__":
    main()
