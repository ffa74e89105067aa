"""Where one line region's CPU goes: the lenslet line fit's time by forward model.

Run: ``python benchmarks/line_profile.py [--distance 3400] [--angle 0] [--grid rect|hex]
[--repeats 3]``

System 2 with its MLA's grid set to ``--grid`` (focus 1 m, a 1024² sensor, photon and read
noise, the renderer's own lenslet centres), one 3 mm line through the field centre. The point
fit runs once, then the line fit ``--repeats`` times on its answer; the fastest run's CPU is
split by the model that spent it (``LensletModel``: ray-sampled with its rays a point, or on
the lenslet cells with its n), with the number of calls (a Jacobian is one batched call of its
three sets) and the points they simulated. Prints one table (docs/distance.md, "Fewer
evaluations on the cells").
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcam.measure import fastfit as ff  # noqa: E402
from lfcam.measure.kernels import warm_up  # noqa: E402
from lfcam.measure.lenslets import lenslet_stats  # noqa: E402
from lfcam.measure.regions import find_regions  # noqa: E402

sys.path.insert(0, str(ROOT / "benchmarks"))
from lines_on_cells import SIZE, line_capture  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--distance", type=float, default=3400.0, help="mm, behind a 1 m focus")
    ap.add_argument("--angle", type=float, default=0.0, help="the line's angle, degrees")
    ap.add_argument("--grid", choices=("rect", "hex"), default="rect")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    warm_up()
    image, used, geom = line_capture(args.grid, args.distance, args.angle)
    regions = find_regions(lenslet_stats(image, geom.lmap), geom.lmap, geom.pitch_px)
    region = max(regions, key=lambda r: len(r.lenslets))
    mom = ff.data_moments(geom, image, ff._region_box(geom, region, image.shape))
    point = ff.fit_lenslet_point(used, geom, image, region, mom=mom)

    spent: dict[str, list[float]] = defaultdict(lambda: [0.0, 0, 0])
    simulate_model = ff.LensletModel._simulate

    def timed(self, sources, group=None, groups=1):
        c0 = time.process_time()
        out = simulate_model(self, sources, group, groups)
        key = f"cells, n = {self.cells}" if self.cells else f"rays, {self.rx.size} a point"
        row = spent[key]
        row[0] += time.process_time() - c0
        row[1] += 1
        row[2] += len(np.atleast_2d(sources))
        return out

    ff.LensletModel._simulate = timed
    best = None
    try:
        for _ in range(max(args.repeats, 1)):
            spent.clear()
            c0 = time.process_time()
            line = ff.fit_lenslet_line(used, geom, image, region, point, mom=mom)
            total = time.process_time() - c0
            if best is None or total < best[0]:
                best = (total, {k: list(v) for k, v in spent.items()}, line)
    finally:
        ff.LensletModel._simulate = simulate_model
    total, rows, line = best
    distance = used.main_lens.front_vertex_z_mm - line.source_mm[2]
    print(f"# system 2, {args.grid} MLA, focus 1 m, {SIZE}² sensor, photon noise; 3 mm line "
          f"at {args.distance:.0f} mm, {args.angle:.0f}°, {ff.lit_lenslets(mom)} lenslets lit")
    print(f"# line fit: {total:.3f} s CPU (fastest of {args.repeats}), error "
          f"{100.0 * (distance / args.distance - 1.0):+.3f} %, "
          f"σ {100.0 * line.sigma_distance_mm / args.distance:.3f} %")
    print(f"{'model':24s} {'calls':>5s} {'points':>6s} {'CPU s':>7s} {'share':>6s}")
    for key, (cpu, calls, points) in sorted(rows.items(), key=lambda kv: -kv[1][0]):
        print(f"{key:24s} {calls:5d} {points:6d} {cpu:7.3f} {100.0 * cpu / total:5.0f} %")
    rest = total - sum(v[0] for v in rows.values())
    print(f"{'the rest':24s} {'':5s} {'':6s} {rest:7.3f} {100.0 * rest / total:5.0f} %")


if __name__ == "__main__":
    main()
