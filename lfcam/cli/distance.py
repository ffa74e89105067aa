"""``lfcam distance``: per-region metric distances of a capture (docs/conventions.md)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from lfcam.camera import profile_for_capture
from lfcam.cli.common import json_value
from lfcam.measure import METHODS
from lfcam.models import DISTANCE_MODELS


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``distance`` sub-command."""
    p = sub.add_parser("distance", help="per-region distance map of a capture")
    p.add_argument("capture", help="raw capture (LFP/LFR, raw + sidecar, camera raw, PNG/TIFF)")
    p.add_argument("--calibration", required=True, help="calibration JSON (lfcam calibrate)")
    p.add_argument("--profile", help="camera profile (default: CAPTURE's .profile.toml sidecar)")
    p.add_argument("--model", default="auto",
                   choices=DISTANCE_MODELS,
                   help="refocus = Hahne et al.'s depth from refocus (the seed's baseline)")
    p.add_argument("--method", default="lightfield", choices=METHODS,
                   help="blur measurement: exact light-field fit, or the seed's diameter")
    p.add_argument("--tolerance", type=float, metavar="PCT",
                   help="--model auto: allowed distance error in percent (default: best)")
    p.add_argument("--fast", action="store_true",
                   help="lightfield: triangulation only (no per-pixel fit)")
    p.add_argument("-o", "--output", required=True, help="output folder")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def _progress(done: int, total: int) -> None:
    if sys.stderr.isatty():
        print(f"\rregions {done}/{total}", end="" if done < total else "\n", file=sys.stderr,
              flush=True)


def run(args: argparse.Namespace) -> int:
    """Run the distance pipeline and write the outputs."""
    from lfcam.calibrate import load_calibration
    from lfcam.distance import run_distance, write_outputs
    from lfcam.io import load_capture

    capture_path = Path(args.capture)
    profile = profile_for_capture(capture_path, args.profile)
    calibration = load_calibration(args.calibration)
    cap = load_capture(capture_path, profile)
    image = cap.grey()
    result = run_distance(image, profile, calibration, model=args.model, method=args.method,
                          tolerance_pct=args.tolerance, fast=args.fast, progress=_progress)
    write_outputs(args.output, result)
    ok = sum(r.status == "ok" for r in result.regions)
    if args.json:
        print(json.dumps({
            "regions": [{k: json_value(v) for k, v in r.__dict__.items() if k != "bbox_px"}
                        for r in result.regions],
            "output": str(args.output),
            "timings_s": result.timings_s,
        }))
    else:
        print(f"{len(result.regions)} regions ({ok} with a distance) → {args.output}/"
              "regions.csv, distance.tiff, distance.png")
        for r in result.regions:
            d = f"{r.distance_mm:10.2f} ± {r.uncertainty_mm:.2f} mm" if r.status == "ok" else \
                f"{'—':>10}"
            print(f"  #{r.region_id:<3} {r.kind:5} ({r.x_px:7.1f}, {r.y_px:7.1f}) px  {d}  "
                  f"[{r.model}] {r.status}")
    return 0
