"""``lfcam batch``: the distance pipeline over a folder of captures (see ``docs/batch.md``)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from lfcam.atomic import check_output_dir, refuse_overwrite
from lfcam.cli.common import add_tolerance, positive_int, profile_file
from lfcam.measure import METHODS
from lfcam.models import DISTANCE_MODELS


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``batch`` sub-command."""
    p = sub.add_parser("batch", help="distance maps of every capture under a folder")
    p.add_argument("input", help="folder searched recursively for captures (by content)")
    p.add_argument("--calibration", required=True, help="calibration JSON (lfcam calibrate)")
    p.add_argument("--profile",
                   help="camera profile for every capture (default: each capture's "
                        ".profile.toml sidecar)")
    p.add_argument("-o", "--output", required=True,
                   help="output folder: summary.csv, failures.csv, captures/<path>/")
    p.add_argument("--model", default="auto",
                   choices=DISTANCE_MODELS)
    p.add_argument("--method", default="lightfield", choices=METHODS)
    add_tolerance(p)
    p.add_argument("--fast", action="store_true",
                   help="lightfield: triangulation only (no per-pixel fit)")
    p.add_argument("--workers", type=positive_int, metavar="N",
                   help="local worker processes (default: all cores)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="Dask scheduler, e.g. tcp://host:8786 (needs lfcam[dask])")
    p.add_argument("--force", action="store_true", help="recompute finished captures too")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the batch; exit 1 when at least one capture failed (listed in failures.csv)."""
    from lfcam.batch import run_batch

    out = Path(args.output)
    refuse_overwrite([args.calibration, profile_file(args.profile)],
                     [out / "summary.csv", out / "failures.csv"])
    check_output_dir(out)
    res = run_batch(args.input, args.calibration, args.output, args.profile,
                    model=args.model, method=args.method, tolerance_pct=args.tolerance,
                    fast=args.fast, workers=args.workers, scheduler=args.scheduler,
                    force=args.force)
    n_ok = len(res.captures) - len(res.failures)
    if args.json:
        print(json.dumps({
            "captures": len(res.captures), "finished": n_ok, "computed": len(res.computed),
            "skipped": len(res.skipped), "duplicates": len(res.duplicates),
            "failed": len(res.failures), "regions": len(res.summary),
            "elapsed_s": res.elapsed_s, "output": str(args.output),
        }))
    else:
        print(f"{len(res.captures)} captures: {len(res.computed)} computed, "
              f"{len(res.skipped)} already finished, {len(res.duplicates)} duplicates, "
              f"{len(res.failures)} failed; {len(res.summary)} regions → "
              f"{args.output}/summary.csv ({res.elapsed_s:.1f} s)")
    if res.failures:
        print(f"lfcam batch: {len(res.failures)} capture(s) failed, see "
              f"{args.output}/failures.csv", file=sys.stderr)
        return 1
    return 0
