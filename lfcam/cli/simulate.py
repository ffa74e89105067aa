"""``lfcam simulate``: render a synthetic raw capture and its ground truth (docs/conventions.md)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from lfcam.atomic import check_output_dir, refuse_overwrite
from lfcam.cli.common import add_quiet, nonneg_int, positive_int, profile_file
from lfcam.errors import OutputPathError
from lfcam.progress import terminal_progress
from lfcam.sim.scene import MAX_TOTAL_RAYS


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``simulate`` sub-command."""
    p = sub.add_parser(
        "simulate",
        help="render a synthetic raw capture + CAPTURE.truth.json",
        description="Ray-trace a scene (docs/simulate.md) through the exact main lens and an "
        "ideal microlens array; writes CAPTURE (PNG/TIFF), CAPTURE.profile.toml and "
        "CAPTURE.truth.json (suffix replaced).",
    )
    p.add_argument("--profile", required=True, help="profile name (system1, system2) or TOML")
    p.add_argument("--scene", required=True, help="scene JSON file")
    p.add_argument("-o", "--output", required=True, help="output raster (.png, .tif, .tiff)")
    p.add_argument("--seed", type=nonneg_int, default=None, help="override the scene's seed")
    p.add_argument("--max-rays", type=positive_int, default=MAX_TOTAL_RAYS, metavar="N",
                   help=f"refuse scenes tracing more rays than this (default {MAX_TOTAL_RAYS:.0e}"
                   ", about 20 min on one core)")
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    add_quiet(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Render and write the capture."""
    from dataclasses import replace

    from lfcam.camera import load_profile
    from lfcam.errors import SceneError
    from lfcam.sim.capture import capture_paths, simulate, write_capture
    from lfcam.sim.scene import load_scene

    profile = load_profile(args.profile)
    scene = load_scene(args.scene)
    if args.seed is not None:
        if args.seed < 0:
            raise SceneError(f"--seed must not be negative, got {args.seed}")
        scene = replace(scene, seed=args.seed)
    # fail early: unsupported suffix, an output replacing an input, a missing output folder
    outputs = capture_paths(args.output, scene.output_format)
    refuse_overwrite([profile_file(args.profile), args.scene], outputs)
    if not Path(outputs[0]).parent.is_dir():
        raise OutputPathError(f"output folder does not exist: {Path(outputs[0]).parent}")
    check_output_dir(Path(outputs[0]).parent)
    with terminal_progress(args.quiet) as bar:
        raw, used, truth = simulate(profile, scene, max_rays=args.max_rays,
                                    progress=bar)
    img, prof, tru = write_capture(args.output, raw, used, truth, scene.output_format)
    summary = {"raster": str(img), "profile": str(prof), "truth": str(tru),
               "width_px": int(raw.shape[1]), "height_px": int(raw.shape[0]),
               "max_dn": int(raw.max()), "sources": len(truth["sources"]),
               "lenses_lit": truth["lenses"]["count"]}
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"wrote {img} ({raw.shape[1]}x{raw.shape[0]}, max {raw.max()}), {prof}, {tru}")
    return 0
