"""``lfcam optics forward | inverse | refocus-distance`` (docs/conventions.md)."""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

import numpy as np

from lfcam.atomic import check_output_dir, refuse_overwrite
from lfcam.cli.common import (
    add_profile_args,
    finite_float,
    positive_float,
    positive_or_inf,
    print_json,
    profile_file,
    profile_from_args,
    read_csv_columns,
)
from lfcam.errors import LfcamError, UsageError
from lfcam.export import write_csv
from lfcam.models import POINT_MODELS, hahne, point_model
from lfcam.optics.trace import TraceStatus, forward


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``optics`` and its three sub-commands."""
    p = sub.add_parser("optics", help="forward trace, model inversion, Hahne refocusing distance")
    osub = p.add_subparsers(dest="optics_command", metavar="ACTION")
    osub.required = True

    f = osub.add_parser("forward", help="rim-ray sensor heights of a point source (exact trace)")
    add_profile_args(f)
    f.add_argument("--distance", type=positive_float, help="object plane → front vertex, mm")
    f.add_argument("--offset", type=finite_float, default=0.0,
                   help="source height above the axis, mm")
    _add_batch_args(f)
    f.set_defaults(func=run_forward)

    i = osub.add_parser("inverse", help="distance and offset from rim-ray sensor heights")
    add_profile_args(i)
    i.add_argument("--model", required=True, choices=sorted(POINT_MODELS))
    i.add_argument("--y1", type=finite_float, help="sensor height of the upper-rim ray, mm")
    i.add_argument("--y2", type=finite_float, help="sensor height of the lower-rim ray, mm")
    _add_batch_args(i)
    i.set_defaults(func=run_inverse)

    r = osub.add_parser(
        "refocus-distance",
        help="Hahne et al.'s refocusing distance for shift a (PlenoptiSign parameters)",
    )
    r.add_argument("--profile", help="take any parameter not given from this camera profile")
    r.add_argument("--d-in", type=positive_float, help="with --profile: MLA distance, mm")
    for flag, text in (
        ("--pp", "pixel pitch, mm"),
        ("--fs", "micro-lens focal length, mm"),
        ("--hh", "micro-lens principal-plane spacing, mm (not used by the model)"),
        ("--pm", "micro-lens pitch, mm"),
        ("--dA", "exit pupil → MLA distance, mm"),
        ("--fU", "main-lens focal length, mm"),
        ("--HH", "main-lens principal-plane spacing, mm"),
        ("--df", "focused object distance from the MLA, mm (inf allowed)"),
        ("--f-num", "main-lens f-number (not used by the model)"),
        ("--M", "1-D micro-image size, px"),
    ):
        r.add_argument(flag, type=positive_or_inf if flag == "--df" else finite_float, help=text)
    r.add_argument("--a", type=finite_float, required=True, help="refocusing shift parameter")
    r.add_argument("--json", action="store_true", help="print one JSON object")
    r.set_defaults(func=run_refocus_distance)


def _add_batch_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--input", help="batch: CSV of cases")
    p.add_argument("--output", help="batch: CSV to write (with --input)")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def _batch_mode(args: argparse.Namespace, single: tuple[str, ...]) -> bool:
    if args.input or args.output:
        if not (args.input and args.output):
            raise UsageError("--input and --output go together")
        refuse_overwrite([args.input, profile_file(args.profile)], [args.output])
        check_output_dir(Path(args.output).parent)
        return True
    missing = [f"--{name.replace('_', '-')}" for name in single if getattr(args, name) is None]
    if missing:
        raise UsageError(f"give {' and '.join(missing)} (or --input/--output for a batch)")
    return False


def run_forward(args: argparse.Namespace) -> int:
    """``lfcam optics forward``."""
    profile = profile_from_args(args)
    if _batch_mode(args, ("distance",)):
        cols = read_csv_columns(args.input, ("distance_mm", "offset_mm"))
        res = forward(profile, None, cols["distance_mm"], cols["offset_mm"])
        rows = zip(cols["distance_mm"], cols["offset_mm"], res.y1_mm, res.y2_mm,
                   np.abs(res.y1_mm - res.y2_mm), strict=True)
        write_csv(args.output, ("distance_mm", "offset_mm", "y1_mm", "y2_mm", "diameter_mm"), rows)
        return 0
    res = forward(profile, None, args.distance, args.offset)
    status = TraceStatus(int(res.status))
    if status != TraceStatus.OK:
        raise LfcamError(f"the rim rays do not reach the sensor: {status.name.lower()}")
    y1, y2 = float(res.y1_mm), float(res.y2_mm)
    out = {"y1_mm": y1, "y2_mm": y2, "diameter_mm": abs(y1 - y2)}
    _emit(out, args.json)
    return 0


def run_inverse(args: argparse.Namespace) -> int:
    """``lfcam optics inverse``."""
    profile = profile_from_args(args)
    model = point_model(args.model)
    if _batch_mode(args, ("y1", "y2")):
        cols = read_csv_columns(args.input, ("y1_mm", "y2_mm"))
        inv = model(profile, None, cols["y1_mm"], cols["y2_mm"])
        rows = zip(
            cols["y1_mm"], cols["y2_mm"], inv.distance_mm, inv.offset_mm, inv.labels(), strict=True
        )
        write_csv(args.output, ("y1_mm", "y2_mm", "distance_mm", "offset_mm", "status"), rows)
        return 0
    inv = model(profile, None, args.y1, args.y2)
    out = {
        "distance_mm": float(inv.distance_mm),
        "offset_mm": float(inv.offset_mm),
        "status": str(inv.labels()),
    }
    _emit(out, args.json)
    return 0


def run_refocus_distance(args: argparse.Namespace) -> int:
    """``lfcam optics refocus-distance``."""
    given = {
        "pp": args.pp, "fs": args.fs, "hh": args.hh, "pm": args.pm, "dA": args.dA,
        "fU": args.fU, "HH": args.HH, "df": args.df, "f_num": args.f_num, "M": args.M,
    }
    if args.profile:
        from lfcam.camera import load_profile

        profile = load_profile(args.profile)
        if args.d_in is not None:
            profile = profile.with_d_in(args.d_in)
        base = dataclasses.asdict(hahne.parameters_for(profile))
    else:
        base = {"hh": 0.0, "f_num": math.nan, "df": math.inf}
    values = {k: (v if v is not None else base.get(k)) for k, v in given.items()}
    missing = [f"--{k.replace('_', '-')}" for k, v in values.items() if v is None]
    if missing:
        raise UsageError(f"missing {', '.join(missing)} (or give --profile)")
    for key in ("pp", "fs", "pm", "dA", "fU", "M"):
        if not (math.isfinite(values[key]) and values[key] > 0):
            raise UsageError(f"--{key} must be a positive number, got {values[key]}")
    params = hahne.HahneParameters(**values)
    res = hahne.refocus_distance(params, args.a)
    out = {
        "distance_mm": float(res.distance_mm),
        "dof_far_mm": float(res.far_mm),
        "dof_near_mm": float(res.near_mm),
    }
    _emit(out, args.json)
    return 0


def _emit(out: dict, as_json: bool) -> None:
    if as_json:
        print_json(out)
        return
    for key, value in out.items():
        if isinstance(value, float):
            print(f"{key} = {value:.6f}" if math.isfinite(value) else f"{key} = {value}")
        else:
            print(f"{key} = {value}")
