"""``lfcam calibrate WHITE [--dark DARK] [--profile P] [--reference CAPTURE
--reference-distance MM | --targets targets.csv] -o calib.json``."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from lfcam.atomic import check_output_dir, refuse_overwrite
from lfcam.cli.common import (
    add_quiet,
    capture_files,
    json_value,
    positive_float,
    profile_file,
)
from lfcam.errors import CalibrationError, CalibrationQualityError
from lfcam.progress import terminal_progress


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``calibrate`` sub-command."""
    p = sub.add_parser(
        "calibrate", help="microlens grid from a white image",
        description="Find the microlens centres of a white image and fit the lattice model "
        "(grid, pitch, rotation, offset, distortion); with a dot-target --reference capture at "
        "a known distance, also calibrate d_in. Writes one calibration JSON.")
    p.add_argument("white", help="white image: Lytro .lfp/.lfr or packed .raw, camera raw, "
                   "PNG/TIFF")
    p.add_argument("--dark", help="dark frame subtracted from the white image")
    p.add_argument("--profile", help="camera profile (name or TOML path): Bayer pattern, "
                   "expected pitch")
    p.add_argument("--reference", metavar="CAPTURE",
                   help="dot-target capture (PNG/TIFF, grey): isolated point sources on a plane "
                   "at --reference-distance; d_in is then calibrated and stored (needs --profile)")
    p.add_argument("--reference-distance", metavar="MM", type=positive_float,
                   help="dot plane → front vertex of the main lens, mm")
    p.add_argument("--targets", metavar="CSV",
                   help="learn a black-box main lens (and d_in) from captures of point sources "
                   "on planes at known distances: CSV columns capture,distance_mm (paths "
                   "relative to the CSV's folder; distance = plane → lens front, mm). Needs "
                   "--profile in the black-box form (focal_length_mm, f_number)")
    p.add_argument("--lens-model", choices=("ideal", "ideal+spherical"),
                   default="ideal+spherical",
                   help="--targets: the learned lens's terms (ideal: first order and the "
                   "exit pupil only, several times faster; default also tries spherical "
                   "aberration and keeps it where the data support it)")
    p.add_argument("-o", "--output", required=True, help="calibration JSON to write")
    p.add_argument("--accept-poor", action="store_true",
                   help="write a calibration that fails the quality gates (coverage, lattice "
                   "residual, model misfit; docs/robustness.md), marked accepted_poor; commands "
                   "then use it with a warning instead of refusing it")
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    add_quiet(p)
    p.set_defaults(func=run)


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
    targets_csv = getattr(args, "targets", None)
    target_profile = None
    if targets_csv is not None:
        # --profile, else the white's .profile.toml sidecar, else a Lytro file's own metadata
        from lfcam.errors import ProfileError
        from lfcam.io.profiles import profile_for_capture

        try:
            target_profile = profile_for_capture(args.white, args.profile)
        except ProfileError as exc:
            if args.profile is not None:
                raise
            raise CalibrationError(f"--targets needs --profile (the black-box main lens, MLA "
                                   f"and sensor): {exc}") from None
        if ref is not None:
            raise CalibrationError("--targets learns d_in with the lens: leave out --reference")
    refuse_overwrite([*capture_files(args.white), *capture_files(args.dark),
                      profile_file(args.profile), ref, targets_csv], [out])
    check_output_dir(out.parent)
    with terminal_progress(args.quiet) as bar:
        cal = calibrate_white_file(args.white, dark=args.dark, profile=args.profile,
                                   output=None if (ref or targets_csv) else out,
                                   progress=bar, accept_poor=args.accept_poor)
        fit = None
        if targets_csv is not None and not (cal.is_poor and not args.accept_poor):
            from dataclasses import replace

            from lfcam.calibrate import save_calibration
            from lfcam.calibrate.lensfit import fit_lens, read_targets

            prof = target_profile
            fit = fit_lens(prof, cal, read_targets(targets_csv, prof), progress=bar,
                           search_spherical=args.lens_model == "ideal+spherical")
            cal = replace(cal, learned_lens=fit.to_dict(), d_in_mm=fit.d_in_mm,
                          d_in_method="lens-fit")
            save_calibration(cal, out)
    if cal.is_poor and not args.accept_poor:  # the reference route: nothing written yet
        raise CalibrationQualityError(
            f"{args.white}: poor calibration, not written: {'; '.join(cal.quality['reasons'])}"
            " (pass --accept-poor to write it anyway)")
    if cal.is_poor:
        import sys

        print(f"lfcam calibrate: warning: poor calibration accepted: "
              f"{'; '.join(cal.quality['reasons'])}", file=sys.stderr)
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
        "quality": cal.quality,
    }
    if fit is not None:
        summary["learned_lens"] = fit.to_dict()
    if din is not None:
        summary.update(d_in_sigma_mm=din.sigma_mm, d_in_paraxial_mm=din.d_in_paraxial_mm,
                       reference_dots=din.n_dots)
    if args.json:
        print(json.dumps({k: json_value(v) for k, v in summary.items()}))
    else:
        rej = ", ".join(f"{k} {v}" for k, v in sorted(cal.rejected.items())) or "none"
        print(f"{cal.n_lenses} lenses, {cal.grid} grid, pitch {cal.pitch_px:.5f} px, rotation "
              f"{cal.rotation_rad:.6f} rad, {cal.model} model, residual RMS "
              f"{cal.residual_rms_px:.4f} px; rejected: {rej}; quality "
              f"{cal.quality['verdict'] if cal.quality else 'unknown'} -> {out}")
        if fit is not None:
            print(f"learned lens from {fit.n_sources} sources on {fit.n_planes} planes "
                  f"({fit.iterations} rounds):")
            for name, v, sg in zip(fit.names, fit.values, fit.sigma, strict=True):
                print(f"  {name:18s} {v:12.4f} ± {sg:.4f}   {fit.why[name]}")
            print(f"  kept terms: {', '.join(fit.kept)}")
            if "planes_without_distance" in fit.why:
                print(f"  planes not used: {fit.why['planes_without_distance']}")
            print("  target  plane_mm  fitted_mm  error_%  x_px  y_px")
            for r in fit.residuals:
                print(f"  {r.target}  {r.distance_mm:9.2f}  {r.fitted_mm:9.2f}  "
                      f"{r.error_pct:+7.3f}  {r.x_px:6.1f}  {r.y_px:6.1f}")
        if din is not None:
            # σ needs at least two dots; the paraxial seed may not exist: print only numbers
            sigma = f" ± {din.sigma_mm:.4f}" if math.isfinite(din.sigma_mm) else ""
            seed = (f" (paraxial seed eqs. 10-12: {din.d_in_paraxial_mm:.3f} mm)"
                    if math.isfinite(din.d_in_paraxial_mm) else "")
            print(f"d_in {din.d_in_mm:.4f}{sigma} mm from {din.n_dots} dots at "
                  f"{din.distance_mm:g} mm{seed}")
    return 0
