"""Field validation for parsed TOML/JSON mappings (profiles, scenes, calibrations): every
failure names its key and raises the caller's :class:`~lfcam.errors.LfcamError` subclass."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from lfcam.errors import LfcamError


def read_json(path: str | Path, error: type[LfcamError], what: str,
              max_bytes: int = 64 * 1024 * 1024) -> Any:
    """Parse a JSON file; ``error`` with one line for a missing, oversized, non-UTF-8 or
    malformed file (``what`` names the kind of file in the message)."""
    p = Path(path)
    if not p.is_file():
        raise error(f"{what} file not found: {p}")
    if p.stat().st_size > max_bytes:
        raise error(f"{p}: {what} file larger than {max_bytes} bytes")
    try:
        return json.loads(p.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise error(f"{p}: not UTF-8 text") from None
    except json.JSONDecodeError as exc:
        raise error(f"{p}: not valid JSON ({exc.msg}, line {exc.lineno})") from None


class Fields:
    """Validators raising ``error`` (e.g. ``ProfileError``) with the offending key."""

    def __init__(self, error: type[LfcamError]):
        self.error = error

    def number(self, key: str, value: Any, positive: bool = False,
               nonneg: bool = False) -> float:
        """A finite number (optionally > 0 or ≥ 0); booleans are not numbers."""
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.error(f"{key}: expected a number, got {value!r}")
        v = float(value)
        if not math.isfinite(v):
            raise self.error(f"{key}: must be finite, got {value!r}")
        if positive and v <= 0.0:
            raise self.error(f"{key}: must be positive, got {value!r}")
        if nonneg and v < 0.0:
            raise self.error(f"{key}: must not be negative, got {value!r}")
        return v

    def integer(self, key: str, value: Any, lo: int, hi: int) -> int:
        """An integer in ``[lo, hi]``."""
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(f"{key}: expected an integer, got {value!r}")
        if not lo <= value <= hi:
            raise self.error(f"{key}: must be in [{lo}, {hi}], got {value}")
        return int(value)

    def pair(self, key: str, value: Any) -> tuple[float, float]:
        """``[x, y]`` of finite numbers."""
        if not isinstance(value, (list, tuple)) or len(value) != 2:
            raise self.error(f"{key}: expected [x, y], got {value!r}")
        return (self.number(f"{key}[0]", value[0]), self.number(f"{key}[1]", value[1]))

    def known_keys(self, table: dict, where: str, allowed: set[str]) -> None:
        """Reject keys outside ``allowed`` (typos must not be ignored silently)."""
        extra = sorted(set(table) - allowed)
        if extra:
            known = ", ".join(sorted(allowed))
            raise self.error(f"unknown key {where}.{extra[0]} (allowed: {known})")
