"""Where a large line region's CPU goes: by compiled kernel and by model (issue 17).

Run: ``python benchmarks/line_region_kernels.py [--grid rect|hex] [--distance MM] [--repeats N]``

System 2 behind a 1 m focus (``benchmarks/lines_on_cells.py``'s capture: a 3 mm line through
the field centre at 0°, photon and read noise, the renderer's own lenslet centres, the MLA's
grid set to ``--grid``). Its largest region is measured by
:func:`lfcam.measure.fastfit.measure_lenslet` ``--repeats`` times on one core; the run with
the least CPU is reported:

* the region's CPU and the line fit's share of it;
* each compiled kernel (:mod:`lfcam.measure.kernels`): calls, items (samples or rays), CPU and
  ns an item;
* each model the fit evaluated (the point fit's and the line fit's, ray-sampled or on the
  cells with n × n samples a cell): point evaluations and CPU.

docs/distance.md, "Speed at stop 42" and "Cells integrated whole (stop 43)".
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from lines_on_cells import line_capture  # noqa: E402

from lfcam.measure import fastfit as ff  # noqa: E402
from lfcam.measure import kernels  # noqa: E402
from lfcam.measure.lenslets import lenslet_stats  # noqa: E402
from lfcam.measure.regions import find_regions  # noqa: E402

KERNELS = {  # kernel: how its items are counted (the size of which argument or output)
    "cell_samples": ("out", 0),
    "trace_sample_rays": ("out", 0),
    "trace_model_rays": ("out", 0),
    "deposit_moments": ("arg", 0),
    "cell_centres": ("out", 0),
    "deposit_cells": ("arg", 1),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--grid", choices=("rect", "hex"), default="rect")
    ap.add_argument("--distance", type=float, default=3400.0, help="the line's distance, mm")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    kernels.warm_up()
    image, profile, geom = line_capture(args.grid, args.distance, 0.0)
    regions = find_regions(lenslet_stats(image, geom.lmap), geom.lmap, geom.pitch_px)
    region = max(regions, key=lambda r: len(r.lenslets))

    spent: dict[str, float] = defaultdict(float)
    counts: dict[str, int] = defaultdict(int)
    items: dict[str, int] = defaultdict(int)

    def timed_kernel(name, fn, how):
        def run(*a, **k):
            c0 = time.process_time()
            out = fn(*a, **k)
            spent[name] += time.process_time() - c0
            counts[name] += 1
            items[name] += (out if how[0] == "out" else a)[how[1]].size
            return out
        return run

    for name, how in KERNELS.items():
        setattr(kernels, name, timed_kernel(name, getattr(kernels, name), how))
    phase = ["point"]
    simulate = ff.LensletModel._simulate

    def timed_simulate(self, sources, group=None, groups=1):
        c0 = time.process_time()
        out = simulate(self, sources, group, groups)
        key = (f"{phase[0]} fit, cells n = {self.cells}" if self.cells and not self.folded
               else f"{phase[0]} fit, {self.rx.size} rays a point")
        spent[key] += time.process_time() - c0
        counts[key] += len(np.atleast_2d(sources))
        return out

    ff.LensletModel._simulate = timed_simulate
    line_fit = ff.fit_lenslet_line

    def timed_line(*a, **k):
        phase[0] = "line"
        c0 = time.process_time()
        try:
            return line_fit(*a, **k)
        finally:
            spent["line fit"] += time.process_time() - c0
            phase[0] = "point"

    ff.fit_lenslet_line = timed_line
    best = None
    for _ in range(max(1, args.repeats)):
        spent.clear()
        counts.clear()
        items.clear()
        c0 = time.process_time()
        m = ff.measure_lenslet(profile, geom, image, region, 0.0)
        total = time.process_time() - c0
        if best is None or total < best[0]:
            best = (total, dict(spent), dict(counts), dict(items), m)
    total, spent, counts, items, m = best
    print(f"# system 2, {args.grid} MLA, a 3 mm line at {args.distance:.0f} mm behind a 1 m "
          f"focus: {len(region.lenslets)} lenslets, answer {m.kind} "
          f"{100.0 * (m.distance_mm / args.distance - 1.0):+.3f} %")
    print(f"region {1e3 * total:.0f} ms CPU, line fit {1e3 * spent.get('line fit', 0.0):.0f} ms "
          f"(best of {args.repeats})\n")
    print("| kernel | calls | items | ms | ns an item |\n|---|---|---|---|---|")
    for name in sorted(KERNELS, key=lambda k: -spent.get(k, 0.0)):
        if counts.get(name):
            print(f"| {name} | {counts[name]} | {items[name]} | {1e3 * spent[name]:.1f} | "
                  f"{1e9 * spent[name] / max(items[name], 1):.1f} |")
    print("\n| model | point evaluations | ms |\n|---|---|---|")
    models = [k for k in spent if k.endswith(("rays a point",)) or "cells n" in k]
    for key in sorted(models, key=lambda k: -spent[k]):
        print(f"| {key} | {counts[key]} | {1e3 * spent[key]:.1f} |")


if __name__ == "__main__":
    main()
