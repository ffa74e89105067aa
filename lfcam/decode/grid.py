"""Microlens grid as the decoder needs it: lattice model + optional measured centres.

A :class:`GridSpec` holds exactly the keys of a calibration file (CONTRACT §3): ``grid``
(``"rect"`` | ``"hex"``), ``pitch_px``, ``rotation_rad``, ``offset_px`` ([x, y] of one lens
centre) and, optionally, ``centres_px`` (N×2, x then y).

Lattice (lens row ``t``, column ``s``, both integers, ``(0, 0)`` = the lens at ``offset_px``)::

    rect:  p(t, s) = offset + R(θ)·(s·pitch,                     t·pitch)
    hex:   p(t, s) = offset + R(θ)·((s + (t mod 2)/2)·pitch,      t·pitch·√3/2)

``R(θ)`` rotates by ``rotation_rad`` (rows run along the rotated x axis). Odd hex rows sit
half a pitch to the right of even ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lfcam.camera import GRIDS
from lfcam.errors import CalibrationError
from lfcam.validate import read_json

MAX_PITCH_PX = 1000.0
MAX_CALIBRATION_BYTES = 256 * 1024 * 1024
SNAP_TOLERANCE = 0.3  # a measured centre replaces the lattice one if within 0.3 pitch


@dataclass(frozen=True)
class GridSpec:
    """Microlens grid on the sensor (pixels, CONTRACT §1 pixel frame).

    Parameters
    ----------
    grid : str
        ``"rect"`` or ``"hex"``.
    pitch_px : float
        Lens-centre spacing along a row, in sensor pixels.
    rotation_rad : float
        Rotation of the rows against the sensor x axis.
    offset_px : tuple of float
        (x, y) of one lens centre, the lattice origin.
    centres_px : numpy.ndarray or None
        Measured lens centres (N×2, x then y); they override the lattice where they fit it.
    """

    grid: str
    pitch_px: float
    rotation_rad: float = 0.0
    offset_px: tuple[float, float] = (0.0, 0.0)
    centres_px: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.grid not in GRIDS:
            raise CalibrationError(f"grid: must be one of {GRIDS}, got {self.grid!r}")
        p = self.pitch_px
        if not (isinstance(p, (int, float)) and math.isfinite(p) and 2.0 <= p <= MAX_PITCH_PX):
            raise CalibrationError(f"pitch_px: must be a number in [2, {MAX_PITCH_PX}], got {p!r}")
        if not math.isfinite(self.rotation_rad) or abs(self.rotation_rad) > math.pi:
            raise CalibrationError(
                f"rotation_rad: must be finite, |θ| ≤ π, got {self.rotation_rad}"
            )
        if len(self.offset_px) != 2 or not all(math.isfinite(v) for v in self.offset_px):
            raise CalibrationError(f"offset_px: expected finite [x, y], got {self.offset_px!r}")
        if self.centres_px is not None:
            c = self.centres_px
            if c.ndim != 2 or c.shape[1] != 2 or not np.all(np.isfinite(c)):
                raise CalibrationError("centres_px: expected a finite N×2 array (x, y)")

    @property
    def row_spacing_px(self) -> float:
        """Distance between lens rows: pitch (rect) or pitch·√3/2 (hex)."""
        return self.pitch_px * (math.sqrt(3.0) / 2.0 if self.grid == "hex" else 1.0)

    def lattice_xy(self, t: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Model centre (x_px, y_px) of lens row ``t``, column ``s`` (integer arrays)."""
        t = np.asarray(t, dtype=np.float64)
        s = np.asarray(s, dtype=np.float64)
        a = s * self.pitch_px
        if self.grid == "hex":
            a = a + 0.5 * self.pitch_px * np.mod(t, 2.0)
        b = t * self.row_spacing_px
        c, sn = math.cos(self.rotation_rad), math.sin(self.rotation_rad)
        return self.offset_px[0] + c * a - sn * b, self.offset_px[1] + sn * a + c * b

    def lattice_coords(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Continuous (t, s) of sensor points (inverse of :meth:`lattice_xy`)."""
        dx = np.asarray(x, dtype=np.float64) - self.offset_px[0]
        dy = np.asarray(y, dtype=np.float64) - self.offset_px[1]
        c, sn = math.cos(self.rotation_rad), math.sin(self.rotation_rad)
        a, b = c * dx + sn * dy, -sn * dx + c * dy
        t = b / self.row_spacing_px
        s = a / self.pitch_px
        if self.grid == "hex":
            s = s - 0.5 * np.mod(np.round(t), 2.0)
        return t, s

    def lens_centres(self, shape: tuple[int, int]) -> LensCentres:
        """Centres of every lens whose model centre lies on a sensor of ``shape`` (rows, cols).

        Returns
        -------
        LensCentres
            ``x``, ``y`` of shape (T, S) and the absolute index of the first row / column.
        """
        h, w = int(shape[0]), int(shape[1])
        cx, cy = np.array([0, w - 1, 0, w - 1]), np.array([0, 0, h - 1, h - 1])
        t, s = self.lattice_coords(cx, cy)
        t0, t1 = int(math.floor(t.min())) - 1, int(math.ceil(t.max())) + 1
        s0, s1 = int(math.floor(s.min())) - 1, int(math.ceil(s.max())) + 1
        tt, ss = np.meshgrid(np.arange(t0, t1 + 1), np.arange(s0, s1 + 1), indexing="ij")
        x, y = self.lattice_xy(tt, ss)
        inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
        rows = np.flatnonzero(inside.any(axis=1))
        cols = np.flatnonzero(inside.any(axis=0))
        if rows.size == 0 or cols.size == 0:
            raise CalibrationError("no microlens centre of the calibration lies on the raw image")
        rs = slice(rows[0], rows[-1] + 1)
        cs = slice(cols[0], cols[-1] + 1)
        x, y = x[rs, cs].copy(), y[rs, cs].copy()
        first_t, first_s = t0 + rows[0], s0 + cols[0]
        if self.centres_px is not None and len(self.centres_px):
            mt, ms = self.lattice_coords(self.centres_px[:, 0], self.centres_px[:, 1])
            it, js = np.round(mt), np.round(ms)
            near = (np.abs(mt - it) < SNAP_TOLERANCE) & (np.abs(ms - js) < SNAP_TOLERANCE)
            r = it.astype(np.int64) - first_t
            q = js.astype(np.int64) - first_s
            ok = near & (r >= 0) & (r < x.shape[0]) & (q >= 0) & (q < x.shape[1])
            x[r[ok], q[ok]] = self.centres_px[ok, 0]
            y[r[ok], q[ok]] = self.centres_px[ok, 1]
        return LensCentres(x=x, y=y, first_t=int(first_t), first_s=int(first_s))


@dataclass(frozen=True)
class LensCentres:
    """Lens centres arranged by lattice row/column (arrays of shape (T, S), pixels)."""

    x: np.ndarray
    y: np.ndarray
    first_t: int
    first_s: int


def _num(data: dict, key: str, default: Any = None) -> float:
    v = data.get(key, default)
    if v is None:
        raise CalibrationError(f"calibration: missing key {key!r}")
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise CalibrationError(f"calibration: {key} must be a number, got {v!r}")
    return float(v)


def grid_from_dict(data: Any) -> GridSpec:
    """Build a :class:`GridSpec` from a parsed calibration mapping (CONTRACT §3 keys).

    Raises
    ------
    CalibrationError
        Missing, mistyped or out-of-range key.
    """
    if not isinstance(data, dict):
        raise CalibrationError("calibration: expected a JSON object")
    grid = data.get("grid")
    if grid not in GRIDS:
        raise CalibrationError(f"calibration: grid must be one of {GRIDS}, got {grid!r}")
    off = data.get("offset_px")
    if not isinstance(off, (list, tuple)) or len(off) != 2 or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in off
    ):
        raise CalibrationError(f"calibration: offset_px must be [x, y], got {off!r}")
    centres = data.get("centres_px")
    arr = None
    if centres is not None:
        try:
            arr = np.asarray(centres, dtype=np.float64)
        except (TypeError, ValueError):
            raise CalibrationError(
                "calibration: centres_px must be an N×2 list of numbers"
            ) from None
        if arr.size == 0:
            arr = None
    return GridSpec(
        grid=grid,
        pitch_px=_num(data, "pitch_px"),
        rotation_rad=_num(data, "rotation_rad", 0.0),
        offset_px=(float(off[0]), float(off[1])),
        centres_px=arr,
    )


def load_grid(path: str | Path) -> GridSpec:
    """Read a calibration JSON file (CONTRACT §3) into a :class:`GridSpec`."""
    return grid_from_dict(read_json(path, CalibrationError, "calibration",
                                    MAX_CALIBRATION_BYTES))
