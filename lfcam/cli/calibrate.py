"""``lfcam calibrate WHITE [--dark DARK] [--profile P] [--reference CAPTURE
--reference-distance MM] -o calib.json``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from lfcam.errors import CalibrationError


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``calibrate`` sub-command."""
    p = sub.add_parser("calibrate", help="microlens grid from a white image")
    p.add_argument("white", help="white image: Lytro .lfp/.lfr or packed .raw, camera raw, "
                   "PNG/TIFF")
    p.add_argument("--dark", help="dark frame subtracted from the white image")
    p.add_argument("--profile", help="camera profile (name or TOML path): Bayer pattern, "
                   "expected pitch")
    p.add_argument("--reference", metavar="CAPTURE",
                   help="dot-target capture (PNG/TIFF, grey): isolated point sources on a plane "
                   "at --reference-distance; d_in is then calibrated and stored (needs --profile)")
    p.add_argument("--reference-distance", metavar="MM", type=float,
                   help="dot plane → front vertex of the main lens, mm")
    p.add_argument("-o", "--output", required=True, help="calibration JSON to write")
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    p.set_defaults(func=run)


class _Bar:
    """Minimal progress bar on stderr; silent when stderr is not a terminal."""

    def __init__(self) -> None:
        self.tty = sys.stderr.isatty()

    def __call__(self, stage: str, frac: float) -> None:
        if self.tty:
            n = int(30 * min(max(frac, 0.0), 1.0))
            sys.stderr.write(f"\r{stage:<11} [{'#' * n}{'.' * (30 - n)}] {100 * frac:5.1f}%")
            sys.stderr.flush()

    def close(self) -> None:
        if self.tty:
            sys.stderr.write("\n")


def run(args: argparse.Namespace) -> int:
    """Calibrate and write the JSON file."""
    from lfcam.calibrate import calibrate_white_file

    out = Path(args.output)
    if out.suffix.lower() != ".json":
        raise CalibrationError(f"output must be a .json file, got {out}")
    ref = getattr(args, "reference", None)
    ref_dist = getattr(args, "reference_distance", None)
    if (ref is None) != (ref_dist is None):
        raise CalibrationError("--reference and --reference-distance go together")
    if ref is not None and args.profile is None:
        raise CalibrationError("--reference needs --profile (main lens, MLA and sensor)")
    bar = _Bar()
    try:
        cal = calibrate_white_file(args.white, dark=args.dark, profile=args.profile,
                                   output=None if ref is not None else out, progress=bar)
    finally:
        bar.close()
    din = None
    if ref is not None:
        from lfcam.calibrate import calibrate_reference_file, save_calibration

        cal, din = calibrate_reference_file(cal, ref, args.profile, ref_dist)
        save_calibration(cal, out)
    summary = {
        "output": str(out), "grid": cal.grid, "pitch_px": cal.pitch_px,
        "rotation_rad": cal.rotation_rad, "offset_px": list(cal.offset_px),
        "n_lenses": cal.n_lenses, "model": cal.model, "residual_rms_px": cal.residual_rms_px,
        "rejected": cal.rejected, "d_in_mm": cal.d_in_mm, "d_in_method": cal.d_in_method,
    }
    if din is not None:
        summary.update(d_in_sigma_mm=din.sigma_mm, d_in_paraxial_mm=din.d_in_paraxial_mm,
                       reference_dots=din.n_dots)
    if args.json:
        print(json.dumps(summary))
    else:
        rej = ", ".join(f"{k} {v}" for k, v in sorted(cal.rejected.items())) or "none"
        print(f"{cal.n_lenses} lenses, {cal.grid} grid, pitch {cal.pitch_px:.5f} px, rotation "
              f"{cal.rotation_rad:.6f} rad, {cal.model} model, residual RMS "
              f"{cal.residual_rms_px:.4f} px; rejected: {rej} -> {out}")
        if din is not None:
            print(f"d_in {din.d_in_mm:.4f} ± {din.sigma_mm:.4f} mm from {din.n_dots} dots at "
                  f"{din.distance_mm:g} mm (paraxial seed eqs. 10-12: "
                  f"{din.d_in_paraxial_mm:.3f} mm)")
    return 0
