"""``lfcam decode`` and ``lfcam refocus`` (docs/conventions.md)."""

from __future__ import annotations

import argparse
import json
import math
import re
from pathlib import Path

from lfcam.atomic import check_output_dir, refuse_overwrite
from lfcam.cli.common import (
    add_no_verify,
    add_quiet,
    capture_files,
    finite_float,
    positive_float,
    positive_int,
    profile_file,
    verify_mode,
)
from lfcam.errors import InputFileError
from lfcam.progress import Progress, terminal_progress

LIGHTFIELD_FILES = ("lightfield.npy", "weight.npy", "views.tiff", "lightfield.json")
VIEW_NAME = re.compile(r"view_v\d+_u\d+\.png")


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``decode`` and ``refocus`` sub-commands."""
    p = sub.add_parser(
        "decode", help="decode a raw capture into a 4-D light field and its views",
        description="Resample a raw capture on the calibrated microlens grid into a 4-D light "
        "field L[v, u, t, s]; writes OUTPUT/lightfield.npy, weight.npy, views.tiff, "
        "lightfield.json and views/*.png.")
    _common(p)
    p.add_argument("-o", "--output", required=True,
                   help="output folder: lightfield.npy, weight.npy, views.tiff, views/*.png")
    p.add_argument("--no-png", action="store_true", help="skip the per-view PNG files")
    p.set_defaults(func=run_decode)

    r = sub.add_parser(
        "refocus", help="refocus a capture by shift-and-sum",
        description="Decode a capture and refocus it by shift-and-sum, either at a Hahne "
        "shift or at a metric distance (needs the optics of --profile); writes one image.")
    _common(r)
    g = r.add_mutually_exclusive_group(required=True)
    g.add_argument("--distance", type=positive_float,
                   help="plane to focus on, mm from the main lens's front vertex (needs optics)")
    g.add_argument("--shift", type=finite_float,
                   help="Hahne shift a: lenslets of spatial shift per pixel of angular offset")
    r.add_argument("--d-in", type=positive_float, help="main-lens centre → MLA distance, mm")
    r.add_argument("-o", "--output", required=True, help="OUT.png (16-bit) or OUT.tiff (float32)")
    r.set_defaults(func=run_refocus)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", help="raw capture (.lfp/.lfr, .raw + sidecar, camera raw, PNG, TIFF)")
    p.add_argument("--calibration", required=True, help="calibration JSON (lfcam calibrate)")
    p.add_argument("--profile", help="camera profile (name or TOML); optics for --distance")
    p.add_argument("--white", help="white image of the same camera/zoom, for devignetting")
    p.add_argument("--views", type=positive_int,
                   help="angular samples per axis (default 2⌊pitch/2⌋+1)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    add_no_verify(p)
    add_quiet(p)


def _inputs(args: argparse.Namespace) -> list:
    return [*capture_files(args.capture), args.calibration, profile_file(args.profile),
            *capture_files(args.white)]


def _load(args: argparse.Namespace, bar: Progress):
    from lfcam.calibrate import load_calibration
    from lfcam.camera import load_profile
    from lfcam.decode import decode
    from lfcam.io import load_capture
    from lfcam.io.capture import check_saturation

    bar("loading", 0, 1)
    profile = load_profile(args.profile) if args.profile else None
    grid = load_calibration(args.calibration)
    grid.check_quality()
    verify = verify_mode(args)
    cap = load_capture(args.capture, profile, verify=verify)
    check_saturation(cap)
    raw = cap.grey()
    white = None
    if args.white:
        wcap = load_capture(args.white, profile, verify=verify)
        white = wcap.grey()
    bar("loading", 1, 1)
    bar("decoding", 0, 1)
    lf = decode(raw, grid, white=white, n_views=args.views)
    bar("decoding", 1, 1)
    return lf, profile if profile is not None else cap.profile


def run_decode(args: argparse.Namespace) -> int:
    """Decode and write the light field (atomic writes)."""
    from lfcam.decode.export import write_lightfield

    out = Path(args.output)
    inputs = _inputs(args)
    views = [out / "views" / Path(i).name for i in inputs
             if i is not None and VIEW_NAME.fullmatch(Path(i).name)]
    refuse_overwrite(inputs, [*(out / n for n in LIGHTFIELD_FILES), *views])
    if out.exists() and not out.is_dir():
        raise InputFileError(f"output {out} exists and is not a folder")
    check_output_dir(out)
    with terminal_progress(args.quiet) as bar:
        lf, _ = _load(args, bar)
        bar("writing", 0, 1)
        files = write_lightfield(args.output, lf, png_views=not args.no_png)
        bar("writing", 1, 1)
    info = {"output": str(args.output), "shape": list(lf.data.shape), "files": len(files)}
    print(json.dumps(info) if args.json else
          f"light field {'x'.join(map(str, lf.data.shape))} (v, u, t, s) → {args.output}")
    return 0


def run_refocus(args: argparse.Namespace) -> int:
    """Refocus by shift or by metric distance and write one image."""
    from lfcam.decode import refocus, shift_for_distance
    from lfcam.decode.export import IMAGE_SUFFIXES, write_image

    if not str(args.output).lower().endswith(IMAGE_SUFFIXES):
        raise InputFileError(f"output {args.output}: use a .png, .tif or .tiff name")
    if args.shift is not None and not math.isfinite(args.shift):
        raise InputFileError(f"--shift must be finite, got {args.shift}")
    if args.distance is not None and args.profile is None:
        raise InputFileError("--distance needs the camera optics: pass --profile")
    refuse_overwrite(_inputs(args), [args.output])
    check_output_dir(Path(args.output).parent)
    with terminal_progress(args.quiet) as bar:
        lf, profile = _load(args, bar)
        if args.distance is not None:
            shift = float(shift_for_distance(profile, args.distance, args.d_in))
        else:
            shift = float(args.shift)
        bar("refocusing", 0, 1)
        out = refocus(lf, shift)
        write_image(args.output, out.image)
        bar("refocusing", 1, 1)
    info = {"output": str(args.output), "shift": shift, "distance_mm": args.distance}
    print(json.dumps(info) if args.json else f"refocused at shift a = {shift:.6g} → {args.output}")
    return 0
