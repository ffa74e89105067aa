"""Helpers shared by the sub-commands: profiles, CSV batch input, JSON output."""

from __future__ import annotations

import argparse
import csv
import json
import math
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lfcam.camera import CameraProfile, load_profile
from lfcam.errors import InputFileError

MAX_CSV_ROWS = 50_000_000


class ArgumentParser(argparse.ArgumentParser):
    """argparse with negative numbers as values everywhere: ``--y1 -1e-12``, ``--a -.5``,
    ``--offset -inf`` are values, not unknown flags (argparse's own pattern only knows
    ``-12`` and ``-1.5``). lfcam has no option that looks like a number, so this is safe."""

    NEGATIVE_NUMBER = re.compile(
        r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$|^-(inf|infinity|nan)$", re.IGNORECASE)

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = self.NEGATIVE_NUMBER


def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None


def finite_float(text: str) -> float:
    """argparse type: a finite number (no nan/inf)."""
    v = _number(text)
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return v


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    v = finite_float(text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text!r}")
    return v


def positive_or_inf(text: str) -> float:
    """argparse type: a number > 0, ``inf`` allowed (focus at infinity), nan refused."""
    v = _number(text)
    if math.isnan(v) or v <= 0:
        raise argparse.ArgumentTypeError(f"must be positive (inf allowed), got {text!r}")
    return v


def nonneg_float(text: str) -> float:
    """argparse type: a finite number ≥ 0."""
    v = finite_float(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must not be negative, got {text!r}")
    return v


def positive_int(text: str) -> int:
    """argparse type: an integer ≥ 1."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {n}")
    return n


def nonneg_int(text: str) -> int:
    """argparse type: an integer ≥ 0."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if n < 0:
        raise argparse.ArgumentTypeError(f"must not be negative, got {n}")
    return n


def add_quiet(p: argparse.ArgumentParser) -> None:
    """``--quiet``: no progress line (it is only drawn when stderr is a terminal anyway)."""
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress line on stderr (shown only on a terminal)")


def add_tolerance(p: argparse.ArgumentParser) -> None:
    """``--tolerance PCT`` of the distance pipeline (``lfcam distance``, ``lfcam batch``)."""
    p.add_argument("--tolerance", type=positive_float, metavar="PCT",
                   help="allowed distance error in percent: --model auto and --method auto "
                   "pick the cheapest that meets it; with --method lenslet or auto a fit "
                   "stops where its answer's σ meets it (a point's polish, a line's refit, a "
                   "large line's last iterations are skipped there) (default: best)")


def add_no_verify(p: argparse.ArgumentParser) -> None:
    """``--no-verify`` for commands that load captures (LFP sha1 checks)."""
    p.add_argument("--no-verify", action="store_true",
                   help="warn instead of failing on LFP sha1 mismatches")


def verify_mode(args: argparse.Namespace) -> str:
    """``verify=`` for :func:`lfcam.io.load_capture` from ``--no-verify``."""
    return "warn" if getattr(args, "no_verify", False) else "error"


def profile_file(name: str | Path | None) -> Path | None:
    """The TOML file ``--profile`` names (shipped names resolved), for overwrite checks."""
    if name is None:
        return None
    path = Path(name)
    if not path.suffix and not path.exists():
        from lfcam.camera import shipped_profile_dir

        return shipped_profile_dir() / f"{name}.toml"
    return path


def capture_files(path: str | Path | None) -> list[Path]:
    """A capture and the metadata sidecar a bare ``.raw`` is read with."""
    if path is None:
        return []
    from lfcam.io.capture import find_sidecar

    p = Path(path)
    side = find_sidecar(p) if p.suffix.lower() == ".raw" else None
    return [p] if side is None else [p, side]


def add_profile_args(p: argparse.ArgumentParser, focus: bool = True) -> None:
    """``--profile`` and, optionally, the ``--d-in | --focus`` pair."""
    p.add_argument("--profile", required=True, help="profile name (system1, system2) or TOML path")
    if focus:
        g = p.add_mutually_exclusive_group()
        g.add_argument("--d-in", type=positive_float, help="main-lens centre → MLA distance, mm")
        g.add_argument("--focus", type=positive_or_inf,
                       help="object distance in focus, mm (inf allowed)")


def profile_from_args(args: argparse.Namespace) -> CameraProfile:
    """Load ``--profile`` and apply ``--d-in`` / ``--focus`` when given. A black-box main
    lens is used through its seed ideal lens, and a note on stderr says so."""
    profile = load_profile(args.profile)
    if profile.main_lens.is_black_box:
        import sys

        print(f"lfcam: note: profile {profile.name!r} gives its main lens as a black box; "
              "using its seed ideal lens (learn the real one with lfcam calibrate --targets)",
              file=sys.stderr)
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
