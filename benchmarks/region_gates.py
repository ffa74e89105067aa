"""Figures of the per-region gates (lfcam.measure.verify) on clean synthetic captures.

Run from the repository root: ``python benchmarks/region_gates.py [--fast] [NAME ...]``
(default: the seed grid's 3500, 1500 and 300 mm points of both systems, and three lines).
Prints per region the fit misfit, the noise-only misfit, the explained energy fraction and
the final status.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcam.calibrate import load_calibration  # noqa: E402
from lfcam.camera import load_profile  # noqa: E402
from lfcam.distance import run_distance  # noqa: E402
from lfcam.io import load_capture  # noqa: E402

DATA = ROOT / "data" / "synthetic"
DEFAULT = [f"point_{s}_{d}mm_dh{o}" for s in ("system1", "system2") for d in (3500, 1500, 300)
           for o in (0, 5, 10)] + [f"line_system1_{d}mm" for d in (3500, 1500, 300)]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("names", nargs="*", default=DEFAULT)
    ap.add_argument("--fast", action="store_true")
    ap.add_argument("--calibration", help="default data/synthetic/calib_<system>.json")
    args = ap.parse_args()
    print(f"{'capture':28s} {'id':>3s} {'kind':5s} {'misfit':>7s} {'noise':>7s} "
          f"{'expl':>6s} {'distance':>9s}  status")
    worst = {"misfit": 0.0, "explained": 1.0}
    for name in args.names:
        prof = load_profile(DATA / f"{name}.profile.toml")
        system = "system1" if "system1" in name else "system2"
        cal = load_calibration(args.calibration or DATA / f"calib_{system}.json")
        img = load_capture(DATA / f"{name}.png", prof).grey()
        run = run_distance(img, prof, cal, fast=args.fast)
        for r, c in zip(run.regions, run.checks, strict=True):
            print(f"{name:28s} {r.region_id:3d} {r.kind:5s} {c.misfit:7.4f} "
                  f"{c.noise_misfit:7.4f} {c.explained:6.3f} {r.distance_mm:9.2f}  {r.status}",
                  flush=True)
            if c.misfit == c.misfit:
                worst["misfit"] = max(worst["misfit"], c.misfit)
            if c.explained == c.explained:
                worst["explained"] = min(worst["explained"], c.explained)
    print(f"worst misfit {worst['misfit']:.4f}, lowest explained fraction "
          f"{worst['explained']:.3f}")


if __name__ == "__main__":
    main()
