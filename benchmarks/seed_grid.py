"""The seed's Table 2 / Table 3 grid through the whole pipeline, in the seed's layout.

Run: ``python benchmarks/seed_grid.py --system system1 [--method lightfield|diameter]
[--model exact|offaxis|onaxis|thin|auto] [--lines] [--distances 3500,1500,300]``

Every committed synthetic capture of the grid (Ad = 300…3500 mm, Δh = 0/5/10 mm; with
``--lines`` the 10 mm line sources of system 1) is loaded, calibrated from
``data/synthetic/calib_<system>.json``, measured and modelled; the table prints Ed and the
seed's ERROR = |Ad − Ed| / (Ad + T/2) per offset, then the mean and max, as in the seed.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcam.calibrate import load_calibration  # noqa: E402
from lfcam.camera import load_profile  # noqa: E402
from lfcam.distance import run_distance  # noqa: E402
from lfcam.io import load_capture  # noqa: E402
from lfcam.measure import prepare_geometry  # noqa: E402

DATA = ROOT / "data" / "synthetic"
GRID = [3500, 3250, 3000, 2800, 2500, 2200, 2000, 1800, 1500, 1300, 1100, 900, 750, 600, 450,
        300]


def estimate(name: str, cal, geom_cache: dict, **kw) -> tuple[float, float, str]:
    """(Ed, Ad, status) of one committed capture."""
    prof = load_profile(DATA / f"{name}.profile.toml")
    cap = load_capture(DATA / f"{name}.png", prof)
    img = cap.grey()
    geom = geom_cache.setdefault(img.shape, prepare_geometry(prof, cal, img.shape))
    run = run_distance(img, prof, cal, geometry=geom, **kw)
    truth = json.loads((DATA / f"{name}.truth.json").read_text())["sources"][0]
    ok = [r for r in run.regions if r.status == "ok"]
    if not ok:
        return float("nan"), truth["distance_mm"], run.regions[0].status if run.regions else "none"
    r = max(ok, key=lambda r: r.diameter_mm if np.isfinite(r.diameter_mm) else 0)
    return r.distance_mm, truth["distance_mm"], "ok"


def main() -> None:
    """Print the table."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--system", default="system1", choices=("system1", "system2"))
    ap.add_argument("--method", default="lightfield", choices=("lightfield", "diameter"))
    ap.add_argument("--model", default="exact")
    ap.add_argument("--fast", action="store_true")
    ap.add_argument("--lines", action="store_true", help="the 10 mm line captures (system 1)")
    ap.add_argument("--distances", help="comma-separated subset of the grid")
    args = ap.parse_args()
    dists = [int(v) for v in args.distances.split(",")] if args.distances else GRID
    cal = load_calibration(DATA / f"calib_{args.system}.json")
    half_t = 0.5 * load_profile(args.system).main_lens.thickness_mm
    offsets = [None] if args.lines else [0, 5, 10]
    cache: dict = {}
    t0 = time.perf_counter()
    what = "10 mm line" if args.lines else "point source"
    print(f"# {args.system}, {what}, method {args.method}{' (fast)' if args.fast else ''}, "
          f"model {args.model}; ERROR = |Ad − Ed| / (Ad + T/2)")
    cols = " ".join(f"{'Ed' if dh is None else f'Ed Δh={dh}':>12} {'ERROR %':>8}"
                    for dh in offsets)
    print(f"{'Ad (mm)':>8} {cols}")
    errors = []
    for d in dists:
        cells = []
        for dh in offsets:
            name = (f"line_{args.system}_{d}mm" if dh is None
                    else f"point_{args.system}_{d}mm_dh{dh}")
            ed, ad, status = estimate(name, cal, cache, model=args.model, method=args.method,
                                      fast=args.fast)
            err = abs(ad - ed) / (ad + half_t) * 100.0
            errors.append(err)
            cells.append(f"{ed:12.2f} {err:8.3f}" if status == "ok" else f"{status:>21}")
        print(f"{d:8d} {' '.join(cells)}", flush=True)
    e = np.array(errors)
    print(f"{'mean':>8} {np.nanmean(e):.3f} %   max {np.nanmax(e):.3f} %   no answer "
          f"{int(np.isnan(e).sum())} of {e.size}   ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
