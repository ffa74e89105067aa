"""Field validation for parsed TOML/JSON mappings (profiles, scenes, calibrations): every
failure names its key and raises the caller's :class:`~lfcam.errors.LfcamError` subclass."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from lfcam.errors import LfcamError

MAX_JSON_DEPTH = 64  # lfcam's own files nest at most 4 deep; json.loads recurses per level
_JSON_STRING = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"')
_BRACKET_STEP = np.zeros(256, dtype=np.int8)
_BRACKET_STEP[[ord("["), ord("{")]] = 1
_BRACKET_STEP[[ord("]"), ord("}")]] = -1


def json_depth(raw: bytes) -> int:
    """Deepest ``[``/``{`` nesting of a JSON text, ignoring brackets inside strings.

    Linear and non-recursive (a numpy cumulative sum), so it is safe on hostile input; an
    unterminated string only makes the estimate larger.
    """
    if raw.count(b"[") + raw.count(b"{") <= 1:
        return raw.count(b"[") + raw.count(b"{")
    body = np.frombuffer(_JSON_STRING.sub(b'""', raw), dtype=np.uint8)
    if body.size == 0:
        return 0
    return int(max(0, np.cumsum(_BRACKET_STEP[body], dtype=np.int32).max()))


def parse_json_bytes(raw: bytes, error: type[LfcamError], where: str,
                     max_depth: int = MAX_JSON_DEPTH) -> Any:
    """Parse JSON bytes: UTF-8, nesting at most ``max_depth``, finite numbers only.

    Raises
    ------
    LfcamError
        ``error`` with one line starting with ``where`` for non-UTF-8 text, nesting deeper
        than ``max_depth``, ``NaN``/``Infinity`` constants or malformed JSON.
    """
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise error(f"{where}: not UTF-8 text") from None
    opened = raw.count(b"[") + raw.count(b"{")
    depth = json_depth(raw) if opened > max_depth else opened
    if depth > max_depth:
        raise error(f"{where}: JSON nested {depth} levels deep (limit {max_depth})")

    def constant(name: str) -> Any:
        raise error(f"{where}: {name} is not a JSON number (use a finite value)")

    try:
        return json.loads(text, parse_constant=constant)
    except RecursionError:  # pragma: no cover - the depth scan refuses these first
        raise error(f"{where}: JSON nested too deeply") from None
    except json.JSONDecodeError as exc:
        raise error(f"{where}: not valid JSON ({exc.msg}, line {exc.lineno})") from None


def read_json(path: str | Path, error: type[LfcamError], what: str,
              max_bytes: int = 64 * 1024 * 1024, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """Parse a JSON file; ``error`` with one line for a missing, oversized, non-UTF-8,
    too deeply nested (> ``max_depth``), non-finite (``NaN``) or malformed file (``what``
    names the kind of file in the message)."""
    p = Path(path)
    if not p.is_file():
        raise error(f"{what} file not found: {p}")
    if p.stat().st_size > max_bytes:
        raise error(f"{p}: {what} file larger than {max_bytes} bytes")
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise error(f"{p}: cannot read {what} file ({exc.strerror or exc})") from None
    return parse_json_bytes(raw, error, str(p), max_depth)


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
