"""Helpers shared by the sub-commands: profiles, CSV batch input, JSON output."""

from __future__ import annotations

import argparse
import csv
import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lfcam.camera import CameraProfile, load_profile
from lfcam.errors import InputFileError

MAX_CSV_ROWS = 50_000_000


def add_profile_args(p: argparse.ArgumentParser, focus: bool = True) -> None:
    """``--profile`` and, optionally, the ``--d-in | --focus`` pair."""
    p.add_argument("--profile", required=True, help="profile name (system1, system2) or TOML path")
    if focus:
        g = p.add_mutually_exclusive_group()
        g.add_argument("--d-in", type=float, help="main-lens centre → MLA distance, mm")
        g.add_argument("--focus", type=float, help="object distance in focus, mm (inf allowed)")


def profile_from_args(args: argparse.Namespace) -> CameraProfile:
    """Load ``--profile`` and apply ``--d-in`` / ``--focus`` when given."""
    profile = load_profile(args.profile)
    if getattr(args, "d_in", None) is not None:
        profile = profile.with_d_in(args.d_in)
    elif getattr(args, "focus", None) is not None:
        profile = profile.with_focus(args.focus)
    return profile


def read_csv_columns(path: str | Path, columns: Sequence[str]) -> dict[str, np.ndarray]:
    """Read numeric ``columns`` of a CSV with a header row.

    Raises
    ------
    InputFileError
        Missing file, missing column, non-numeric cell (with its row number), or no rows.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"input CSV not found: {path}")
    values: dict[str, list[float]] = {c: [] for c in columns}
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            missing = [c for c in columns if c not in (reader.fieldnames or [])]
            if missing:
                raise InputFileError(f"{path}: missing column(s) {', '.join(missing)}")
            for row_no, row in enumerate(reader, start=2):
                if row_no > MAX_CSV_ROWS:
                    raise InputFileError(f"{path}: more than {MAX_CSV_ROWS} rows")
                for c in columns:
                    cell = (row.get(c) or "").strip()
                    try:
                        values[c].append(float(cell))
                    except ValueError:
                        raise InputFileError(
                            f"{path}: row {row_no}, column {c}: not a number: {cell!r}"
                        ) from None
    except UnicodeDecodeError:
        raise InputFileError(f"{path}: not UTF-8 text") from None
    if not values[columns[0]]:
        raise InputFileError(f"{path}: no data rows")
    return {c: np.asarray(v, dtype=np.float64) for c, v in values.items()}


def json_value(value: object) -> object:
    """JSON-safe scalar: NaN → null, inf → "inf", numpy → Python."""
    if isinstance(value, (float, np.floating)):
        v = float(value)
        if math.isnan(v):
            return None
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return v
    if isinstance(value, np.integer):
        return int(value)
    return value


def print_json(obj: dict) -> None:
    """Print one JSON object."""
    print(json.dumps({k: json_value(v) for k, v in obj.items()}))
