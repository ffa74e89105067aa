"""``lfcam lens import | info``: main-lens prescriptions (docs/lenses.md, docs/profiles.md)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from lfcam.cli.common import positive_float, positive_or_inf, print_json


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``lens`` sub-command and its ``import`` and ``info`` actions."""
    p = sub.add_parser("lens", help="import a Zemax lens into a profile; a lens's cardinal data")
    acts = p.add_subparsers(dest="lens_action", metavar="{import,info}", required=True)
    imp = acts.add_parser(
        "import",
        help="write a camera profile whose [main_lens] is a .zmx prescription",
        description="Write a camera profile with [main_lens] surfaces from a Zemax .zmx file. "
        "The [mla] and [sensor] tables come from --template (a profile name or path), else a "
        "generic plenoptic camera matched to the lens's F-number (0.1 mm lenslets, 16 px a "
        "lenslet, 1024 x 1024 px).",
    )
    imp.add_argument("zmx", help="sequential Zemax lens file (.zmx)")
    imp.add_argument("-o", "--output", required=True, help="profile to write (.toml)")
    imp.add_argument("--template", help="profile whose [mla] and [sensor] to keep")
    where = imp.add_mutually_exclusive_group()
    where.add_argument("--focus", type=positive_or_inf,
                       help="object distance in focus, mm from the front vertex (inf allowed); "
                       "default the .zmx object distance, else infinity")
    where.add_argument("--gap", type=positive_float, help="last lens vertex to MLA, mm")
    imp.add_argument("--name", help="profile name (default: the output file's stem)")
    imp.set_defaults(func=run_import)

    info = acts.add_parser("info", help="cardinal data of a profile's main lens; a drawn section")
    info.add_argument("profile", help="profile name or TOML path")
    info.add_argument("--png", help="write the lens section with marginal and chief rays")
    info.add_argument("--distance", type=positive_or_inf,
                      help="object distance of the drawn rays (default: the profile's focus)")
    info.add_argument("--json", action="store_true", help="print one JSON object")
    info.set_defaults(func=run_info)


def run_import(args: argparse.Namespace) -> int:
    """``lfcam lens import``."""
    from lfcam.atomic import atomic_write_text
    from lfcam.camera import load_profile, profile_from_dict
    from lfcam.errors import ProfileError
    from lfcam.optics.zmx import load_zmx, prescription_to_toml_dict
    from lfcam.sim.capture import profile_to_toml

    lens = load_zmx(args.zmx)
    rx = lens.prescription
    main = prescription_to_toml_dict(rx)["main_lens"]
    if rx.name:
        main = {"name": rx.name, **main}
    if args.template:
        tpl = load_profile(args.template)
        mla = {"focal_length_mm": tpl.mla.focal_length_mm, "pitch_mm": tpl.mla.pitch_mm,
               "grid": tpl.mla.grid, "rotation_rad": tpl.mla.rotation_rad,
               "offset_mm": list(tpl.mla.offset_mm), "fill_factor": tpl.mla.fill_factor}
        s = tpl.sensor
        sensor = {"pixel_pitch_mm": s.pixel_pitch_mm, "width_px": s.width_px,
                  "height_px": s.height_px, "bit_depth": s.bit_depth, "bayer": s.bayer,
                  "black_level": s.black_level, "white_level": s.white_level}
        if s.axis_px is not None:
            sensor["axis_px"] = list(s.axis_px)
    else:
        pitch = 0.1
        mla = {"focal_length_mm": round(pitch * rx.f_number, 6), "pitch_mm": pitch,
               "grid": "rect"}
        sensor = {"pixel_pitch_mm": pitch / 16, "width_px": 1024, "height_px": 1024,
                  "bit_depth": 16, "bayer": "none", "black_level": 0, "white_level": 65535}
    if args.gap is not None:
        mla["gap_mm"] = args.gap
    else:
        focus = args.focus
        if focus is None:
            obj = lens.object_distance_mm
            focus = obj if obj is not None and math.isfinite(obj) and obj > 0 else math.inf
        mla["focus_mm"] = focus
    name = args.name or Path(args.output).stem
    profile = profile_from_dict({"name": name, "main_lens": main, "mla": mla, "sensor": sensor},
                                source=str(args.zmx))
    if not Path(args.output).parent.resolve().is_dir():
        raise ProfileError(f"output folder does not exist: {Path(args.output).parent}")
    text = (f"# imported from {Path(args.zmx).name} by `lfcam lens import`; the MLA is "
            f"{'focused at ' + str(mla['focus_mm']) + ' mm' if 'focus_mm' in mla else 'placed'}"
            f" (gap_mm = last vertex → MLA)\n" + profile_to_toml(profile))
    atomic_write_text(args.output, text)
    load_profile(args.output)  # what we wrote must load back
    print(f"{rx.name or 'lens'}: {len(rx.surfaces)} surfaces, f {rx.paraxial.efl_mm:.3f} mm, "
          f"F/{profile.main_lens.f_number:.2f}, gap {profile.gap_mm:.3f} mm -> {args.output}")
    return 0


def run_info(args: argparse.Namespace) -> int:
    """``lfcam lens info``."""
    from lfcam.camera import load_profile
    from lfcam.optics.draw import cardinal_data

    profile = load_profile(args.profile)
    data = cardinal_data(profile)
    if args.png:
        import cv2

        from lfcam.atomic import atomic_write_bytes
        from lfcam.errors import InputFileError
        from lfcam.optics.draw import lens_section

        img = lens_section(profile, object_distance_mm=args.distance)
        ok, buf = cv2.imencode(".png", img)
        if not ok:  # pragma: no cover
            raise InputFileError("could not encode the PNG")
        atomic_write_bytes(args.png, buf.tobytes())
        data["png"] = str(args.png)
    if args.json:
        print_json(data)
    else:
        for key, value in data.items():
            print(f"{key:>24} = {value:.6g}" if isinstance(value, float)
                  else f"{key:>24} = {value}")
    return 0
