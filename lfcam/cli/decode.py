"""``lfcam decode`` and ``lfcam refocus`` (docs/conventions.md)."""

from __future__ import annotations

import argparse
import json
import math

from lfcam.errors import InputFileError


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``decode`` and ``refocus`` sub-commands."""
    p = sub.add_parser("decode", help="decode a raw capture into a 4-D light field and its views")
    _common(p)
    p.add_argument("-o", "--output", required=True,
                   help="output folder: lightfield.npy, weight.npy, views.tiff, views/*.png")
    p.add_argument("--no-png", action="store_true", help="skip the per-view PNG files")
    p.set_defaults(func=run_decode)

    r = sub.add_parser("refocus", help="refocus a capture by shift-and-sum")
    _common(r)
    g = r.add_mutually_exclusive_group(required=True)
    g.add_argument("--distance", type=float,
                   help="plane to focus on, mm from the main lens's front vertex (needs optics)")
    g.add_argument("--shift", type=float,
                   help="Hahne shift a: lenslets of spatial shift per pixel of angular offset")
    r.add_argument("--d-in", type=float, help="main-lens centre → MLA distance, mm")
    r.add_argument("-o", "--output", required=True, help="OUT.png (16-bit) or OUT.tiff (float32)")
    r.set_defaults(func=run_refocus)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", help="raw capture (.lfp/.lfr, .raw + sidecar, camera raw, PNG, TIFF)")
    p.add_argument("--calibration", required=True, help="calibration JSON (lfcam calibrate)")
    p.add_argument("--profile", help="camera profile (name or TOML); optics for --distance")
    p.add_argument("--white", help="white image of the same camera/zoom, for devignetting")
    p.add_argument("--views", type=int, help="angular samples per axis (default 2⌊pitch/2⌋+1)")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def _load(args: argparse.Namespace):
    from lfcam.calibrate import load_calibration
    from lfcam.camera import load_profile
    from lfcam.decode import decode
    from lfcam.io import load_capture

    profile = load_profile(args.profile) if args.profile else None
    grid = load_calibration(args.calibration)
    cap = load_capture(args.capture, profile)
    raw = cap.grey()
    white = None
    if args.white:
        wcap = load_capture(args.white, profile)
        white = wcap.grey()
    lf = decode(raw, grid, white=white, n_views=args.views)
    return lf, profile if profile is not None else cap.profile


def run_decode(args: argparse.Namespace) -> int:
    """Decode and write the light field (atomic writes)."""
    from lfcam.decode.export import write_lightfield

    lf, _ = _load(args)
    files = write_lightfield(args.output, lf, png_views=not args.no_png)
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
    lf, profile = _load(args)
    if args.distance is not None:
        if profile is None:
            raise InputFileError("--distance needs the camera optics: pass --profile")
        shift = float(shift_for_distance(profile, args.distance, args.d_in))
    else:
        shift = float(args.shift)
    out = refocus(lf, shift)
    write_image(args.output, out.image)
    info = {"output": str(args.output), "shift": shift, "distance_mm": args.distance}
    print(json.dumps(info) if args.json else f"refocused at shift a = {shift:.6g} → {args.output}")
    return 0
