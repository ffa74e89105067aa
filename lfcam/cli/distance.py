"""``lfcam distance``: per-region metric distances of a capture (docs/conventions.md)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from lfcam.atomic import check_output_dir, refuse_overwrite
from lfcam.calibrate.lensfit import default_method
from lfcam.cli.common import (
    add_no_verify,
    add_quiet,
    add_tolerance,
    capture_files,
    json_value,
    positive_int,
    profile_file,
    verify_mode,
)
from lfcam.io.grey import GREY_WHITE
from lfcam.io.profiles import profile_for_capture
from lfcam.measure import METHODS
from lfcam.models import DISTANCE_MODELS
from lfcam.progress import terminal_progress

OUTPUT_FILES = ("regions.csv", "distance.tiff", "distance.png")


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``distance`` sub-command."""
    p = sub.add_parser(
        "distance", help="per-region distance map of a capture",
        description="Detect the regions (point and line images) of a capture, measure each "
        "one's blur through the calibrated microlens grid and turn it into a metric distance; "
        "writes OUTPUT/regions.csv, distance.tiff and distance.png.")
    p.add_argument("capture", help="raw capture (LFP/LFR, raw + sidecar, camera raw, PNG/TIFF)")
    p.add_argument("--calibration", required=True, help="calibration JSON (lfcam calibrate)")
    p.add_argument("--profile", help="camera profile (default: CAPTURE's .profile.toml sidecar)")
    p.add_argument("--model", default="auto",
                   choices=DISTANCE_MODELS,
                   help="refocus = Hahne et al.'s depth from refocus (the seed's baseline)")
    p.add_argument("--method", choices=METHODS,
                   help="blur measurement: lightfield (exact fit of the pixels), lenslet (exact "
                   "fit of per-lenslet moments, fast), diameter (the seed's), auto (cheapest "
                   "meeting --tolerance; a spot's lenslet answer stands where 3σ meets it, "
                   "the pixel fit measures the rest); default: auto with --model auto "
                   "--tolerance, the "
                   "method a learned lens was learned with (lenslet), else lightfield")
    add_tolerance(p)
    p.add_argument("--fast", action="store_true",
                   help="lightfield: triangulation only (no per-pixel fit)")
    p.add_argument("--jobs", type=positive_int, metavar="N",
                   help="worker processes for the regions (default: all cores)")
    p.add_argument("-o", "--output", required=True, help="output folder")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--timings", action="store_true",
                   help="print the wall time of each stage (load, geometry, regions, fits, "
                   "export) and the slowest region's CPU time on stderr")
    add_no_verify(p)
    add_quiet(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the distance pipeline and write the outputs."""
    from lfcam.calibrate import load_calibration
    from lfcam.distance import run_distance, write_outputs
    from lfcam.io import load_capture
    from lfcam.io.capture import check_saturation
    from lfcam.measure.lenslets import start_frame_kernels

    capture_path = Path(args.capture)
    out = Path(args.output)
    sidecar = capture_path.with_name(capture_path.stem + ".profile.toml")
    refuse_overwrite([*capture_files(capture_path), args.calibration,
                      profile_file(args.profile) if args.profile else sidecar],
                     [out / name for name in OUTPUT_FILES])
    check_output_dir(out)
    profile = profile_for_capture(capture_path, args.profile)
    start_frame_kernels((profile.sensor.height_px, profile.sensor.width_px))
    with terminal_progress(args.quiet) as bar:
        t0 = time.perf_counter()
        bar("loading", 0, 1)
        calibration = load_calibration(args.calibration)
        calibration.check_quality()
        cap = load_capture(capture_path, profile, verify=verify_mode(args))
        check_saturation(cap)
        image = cap.grey()
        bar("loading", 1, 1)
        t_load = time.perf_counter() - t0
        method = args.method or ("auto" if args.model == "auto" and args.tolerance is not None
                                 else default_method(profile, calibration))
        result = run_distance(image, profile, calibration, model=args.model,
                              method=method, tolerance_pct=args.tolerance, fast=args.fast,
                              progress=bar, jobs=args.jobs, white_value=GREY_WHITE)
        bar("writing", 0, 1)
        t1 = time.perf_counter()
        write_outputs(out, result, f"{capture_path.name}  model {args.model}, method "
                      f"{method}{' (fast)' if args.fast else ''}")
        bar("writing", 1, 1)
        timings = {"load": t_load, **result.timings_s, "export": time.perf_counter() - t1}
    if args.timings:
        print(_timing_line(timings), file=sys.stderr)
    ok = sum(r.status == "ok" for r in result.regions)
    if args.json:
        print(json.dumps({
            "regions": [{**{k: json_value(v) for k, v in r.__dict__.items() if k != "bbox_px"},
                         "time_ms": json_value(1e3 * t)}
                        for r, t in zip(result.regions, result.timings_s["region_s"],
                                        strict=True)],
            "output": str(args.output),
            "timings_s": timings,
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


def _timing_line(timings: dict) -> str:
    """One line of stage wall times (s) and the slowest region's CPU time (ms)."""
    stages = " ".join(f"{name} {timings[key]:.2f}" for name, key in (
        ("load", "load"), ("geometry", "geometry"), ("regions", "regions"),
        ("fits", "measure"), ("export", "export")))
    worst = 1e3 * max(timings["region_s"], default=0.0)
    return (f"timings (s wall): {stages}; {len(timings['region_s'])} regions over "
            f"{timings['jobs']} jobs, slowest region {worst:.0f} ms CPU")
