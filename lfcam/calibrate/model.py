"""The calibration file: a frozen :class:`Calibration`, atomic save, validating load.

JSON layout (CONTRACT §3 keys first; every other key documented in docs/calibration.md)::

    {
      "format": "lfcam-calibration", "version": 1,
      "grid": "rect" | "hex",
      "pitch_px": float, "rotation_rad": float, "offset_px": [x, y],
      "centres_px": [[x, y], ...],            # measured intensity centroids, accepted lenses
      "indices": [[i, j], ...],               # lattice index of each centre
      "residual_rms_px": float,               # |centre - model(index)| RMS
      "model": "similarity" | "affine" | "projective",
      "lattice_matrix": 3x3,                  # (x, y, 1) ∝ M @ (i, j, 1) for the chosen model
      "centre_definition": "intensity-centroid",
      "image_size_px": [width, height],
      "white_sha256": hex | null, "dark_sha256": hex | null,
      "rejected": {"reason": count, ...}, "rejected_px": [[x, y, reason], ...],
      "d_in_mm": float | null, "d_in_method": str | null,
      "diagnostics": {...}
    }
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lfcam.calibrate.grid import RADIAL_NORM_PX, REJECT_REASONS, GridFit, predict_lattice
from lfcam.errors import CalibrationError
from lfcam.validate import read_json

FORMAT = "lfcam-calibration"
VERSION = 1
MAX_LENSES = 5_000_000
MAX_FILE_BYTES = 2_000_000_000


@dataclass(frozen=True)
class Calibration:
    """Microlens grid of one camera (one white image), plus d_in when known.

    Attributes
    ----------
    grid : str
    pitch_px, rotation_rad : float
    offset_px : tuple of float
        (x, y) of lattice index (0, 0) under the similarity model.
    centres_px : (N, 2) float array
        Measured micro-image intensity centroids (x, y) of the accepted lenses.
    indices : (N, 2) int array
    residual_rms_px : float
    model : str
        ``similarity``, ``affine``, ``projective`` or ``projective+radial``.
    lattice_matrix : (3, 3) array
    image_size_px : tuple of int
        (width, height) of the white image.
    white_sha256, dark_sha256 : str or None
    rejected : dict
        Count of rejected candidates per reason.
    rejected_px : tuple
        (x, y, reason) of each rejected candidate.
    d_in_mm : float or None
    d_in_method : str or None
    centre_definition : str
    diagnostics : dict
    lattice_radial : tuple or None
        (cx, cy, k1, k2) of the radial term of ``projective+radial`` (ρ in units of 1000 px).
    """

    grid: str
    pitch_px: float
    rotation_rad: float
    offset_px: tuple[float, float]
    centres_px: np.ndarray
    indices: np.ndarray
    residual_rms_px: float
    model: str
    lattice_matrix: np.ndarray
    image_size_px: tuple[int, int]
    white_sha256: str | None = None
    dark_sha256: str | None = None
    rejected: dict = field(default_factory=dict)
    rejected_px: tuple = ()
    d_in_mm: float | None = None
    d_in_method: str | None = None
    centre_definition: str = "intensity-centroid"
    diagnostics: dict = field(default_factory=dict)
    lattice_radial: tuple | None = None

    def __post_init__(self) -> None:
        for name in ("centres_px", "indices", "lattice_matrix"):
            arr = getattr(self, name)
            arr.setflags(write=False)

    @property
    def n_lenses(self) -> int:
        """Number of accepted lenses."""
        return int(len(self.centres_px))

    def predict(self, indices: np.ndarray) -> np.ndarray:
        """Model position (x, y) of lattice indices."""
        return predict_lattice(self.lattice_matrix, self.lattice_radial, indices)

    @property
    def residuals_px(self) -> np.ndarray:
        """Per-lens residual vectors (measured − model)."""
        return self.centres_px - self.predict(self.indices)

    def with_d_in(self, d_in_mm: float, method: str) -> Calibration:
        """Copy with the reference-plane d_in stored."""
        from dataclasses import replace

        if not (math.isfinite(d_in_mm) and d_in_mm > 0):
            raise CalibrationError(f"d_in must be a positive finite length, got {d_in_mm}")
        return replace(self, d_in_mm=float(d_in_mm), d_in_method=str(method))


def sha256_file(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def calibration_from_fit(
    fit: GridFit,
    image_size_px: tuple[int, int],
    white_sha256: str | None = None,
    dark_sha256: str | None = None,
) -> Calibration:
    """Wrap a :class:`GridFit` as a :class:`Calibration`."""
    counts: dict[str, int] = {}
    for r in fit.rejected_reason:
        counts[r] = counts.get(r, 0) + 1
    rej = tuple(
        (float(x), float(y), r)
        for (x, y), r in zip(fit.rejected_px, fit.rejected_reason, strict=True)
    )
    return Calibration(
        grid=fit.grid,
        pitch_px=float(fit.pitch_px),
        rotation_rad=float(fit.rotation_rad),
        offset_px=(float(fit.offset_px[0]), float(fit.offset_px[1])),
        centres_px=np.array(fit.centres_px, dtype=np.float64),
        indices=np.array(fit.indices, dtype=np.int64),
        residual_rms_px=float(fit.residual_rms_px),
        model=fit.model,
        lattice_matrix=np.array(fit.matrix, dtype=np.float64),
        image_size_px=(int(image_size_px[0]), int(image_size_px[1])),
        white_sha256=white_sha256,
        dark_sha256=dark_sha256,
        rejected=counts,
        rejected_px=rej,
        diagnostics={k: _plain(v) for k, v in fit.diagnostics.items()},
        lattice_radial=None if fit.radial is None else tuple(float(v) for v in fit.radial),
    )


def _plain(v: Any) -> Any:
    if isinstance(v, (np.floating, float)):
        return float(v)
    if isinstance(v, (np.integer, int)):
        return int(v)
    return v


def to_json_dict(cal: Calibration) -> dict:
    """The JSON-ready mapping of a calibration (centres rounded to 1e-5 px)."""
    return {
        "format": FORMAT,
        "version": VERSION,
        "grid": cal.grid,
        "pitch_px": cal.pitch_px,
        "rotation_rad": cal.rotation_rad,
        "offset_px": list(cal.offset_px),
        "residual_rms_px": cal.residual_rms_px,
        "model": cal.model,
        "lattice_matrix": cal.lattice_matrix.tolist(),
        "lattice_radial": None if cal.lattice_radial is None else {
            "centre_px": list(cal.lattice_radial[:2]), "k1": cal.lattice_radial[2],
            "k2": cal.lattice_radial[3], "rho_unit_px": RADIAL_NORM_PX},
        "centre_definition": cal.centre_definition,
        "image_size_px": list(cal.image_size_px),
        "white_sha256": cal.white_sha256,
        "dark_sha256": cal.dark_sha256,
        "d_in_mm": cal.d_in_mm,
        "d_in_method": cal.d_in_method,
        "n_lenses": cal.n_lenses,
        "rejected": dict(cal.rejected),
        "rejected_px": [[round(x, 4), round(y, 4), r] for x, y, r in cal.rejected_px],
        "diagnostics": cal.diagnostics,
        "centres_px": np.round(cal.centres_px, 5).tolist(),
        "indices": cal.indices.tolist(),
    }


def save_calibration(cal: Calibration, path: str | Path) -> Path:
    """Write ``cal`` as JSON atomically (temp file in the same folder, then ``os.replace``)."""
    out = Path(path)
    folder = out.parent if str(out.parent) else Path(".")
    if not folder.is_dir():
        raise CalibrationError(f"output folder does not exist: {folder}")
    text = json.dumps(to_json_dict(cal), separators=(",", ":"), allow_nan=False)
    fd, tmp = tempfile.mkstemp(prefix=out.name + ".", suffix=".tmp", dir=folder)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.chmod(tmp, 0o644)
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return out


def _num(d: dict, key: str, positive: bool = False, optional: bool = False) -> float | None:
    if key not in d:
        if optional:
            return None
        raise CalibrationError(f"calibration file: missing key {key!r}")
    v = d[key]
    if v is None and optional:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise CalibrationError(f"calibration file: {key} must be a finite number, got {v!r}")
    if positive and v <= 0:
        raise CalibrationError(f"calibration file: {key} must be positive, got {v!r}")
    return float(v)


def _array(d: dict, key: str, cols: int, dtype: type) -> np.ndarray:
    if key not in d:
        raise CalibrationError(f"calibration file: missing key {key!r}")
    v = d[key]
    if not isinstance(v, list):
        raise CalibrationError(f"calibration file: {key} must be a list of [{cols} numbers]")
    if len(v) > MAX_LENSES:
        raise CalibrationError(f"calibration file: {key} has {len(v)} rows (limit {MAX_LENSES})")
    try:
        arr = np.array(v, dtype=dtype)
    except (TypeError, ValueError):
        raise CalibrationError(f"calibration file: {key} holds non-numeric entries") from None
    if len(v) == 0:
        arr = arr.reshape(0, cols)
    if arr.ndim != 2 or arr.shape[1] != cols:
        raise CalibrationError(f"calibration file: {key} must be N×{cols}, got {arr.shape}")
    if dtype is float and not np.isfinite(arr).all():
        raise CalibrationError(f"calibration file: {key} contains non-finite values")
    return arr


def calibration_from_dict(d: Any) -> Calibration:
    """Validate a parsed calibration mapping and build a :class:`Calibration`."""
    if not isinstance(d, dict):
        raise CalibrationError("calibration file: top level must be a JSON object")
    if d.get("format") != FORMAT:
        raise CalibrationError(f"calibration file: 'format' must be {FORMAT!r}")
    if d.get("version") != VERSION:
        raise CalibrationError(f"calibration file: unsupported version {d.get('version')!r}")
    grid = d.get("grid")
    if grid not in ("rect", "hex"):
        raise CalibrationError(f"calibration file: grid must be 'rect' or 'hex', got {grid!r}")
    model = d.get("model")
    if model not in ("similarity", "affine", "projective", "projective+radial"):
        raise CalibrationError(f"calibration file: unknown model {model!r}")
    radial = _radial_from_dict(d.get("lattice_radial"))
    if (radial is not None) != (model == "projective+radial"):
        raise CalibrationError("calibration file: lattice_radial goes with (only) the "
                               "projective+radial model")
    pitch = _num(d, "pitch_px", positive=True)
    rot = _num(d, "rotation_rad")
    rms = _num(d, "residual_rms_px")
    off = d.get("offset_px")
    if not (isinstance(off, list) and len(off) == 2):
        raise CalibrationError("calibration file: offset_px must be [x, y]")
    offset = (_num({"x": off[0]}, "x"), _num({"y": off[1]}, "y"))
    centres = _array(d, "centres_px", 2, float)
    indices = _array(d, "indices", 2, np.int64)
    if len(centres) != len(indices):
        raise CalibrationError(
            f"calibration file: {len(centres)} centres but {len(indices)} indices"
        )
    if len(centres) == 0:
        raise CalibrationError("calibration file: no lens centres")
    mat = _array(d, "lattice_matrix", 3, float)
    if mat.shape != (3, 3):
        raise CalibrationError("calibration file: lattice_matrix must be 3×3")
    size = d.get("image_size_px")
    if not (isinstance(size, list) and len(size) == 2
            and all(isinstance(s, int) and not isinstance(s, bool) and s > 0 for s in size)):
        raise CalibrationError("calibration file: image_size_px must be [width, height] > 0")
    d_in = _num(d, "d_in_mm", positive=True, optional=True)
    for key in ("white_sha256", "dark_sha256"):
        v = d.get(key)
        if v is not None and not (isinstance(v, str) and len(v) == 64
                                  and all(c in "0123456789abcdef" for c in v)):
            raise CalibrationError(f"calibration file: {key} must be a 64-digit hex string")
    rejected = d.get("rejected", {})
    if not isinstance(rejected, dict) or any(
        k not in REJECT_REASONS or not isinstance(v, int) for k, v in rejected.items()
    ):
        raise CalibrationError("calibration file: rejected must map reasons to counts")
    rej_px = d.get("rejected_px", [])
    if not isinstance(rej_px, list) or any(
        not (isinstance(r, list) and len(r) == 3 and r[2] in REJECT_REASONS) for r in rej_px
    ):
        raise CalibrationError("calibration file: rejected_px must be [[x, y, reason], ...]")
    return Calibration(
        grid=grid,
        pitch_px=pitch,
        rotation_rad=rot,
        offset_px=offset,
        centres_px=centres,
        indices=indices,
        residual_rms_px=rms,
        model=model,
        lattice_matrix=mat,
        image_size_px=(size[0], size[1]),
        white_sha256=d.get("white_sha256"),
        dark_sha256=d.get("dark_sha256"),
        rejected=dict(rejected),
        rejected_px=tuple((float(x), float(y), str(r)) for x, y, r in rej_px),
        d_in_mm=d_in,
        d_in_method=d.get("d_in_method"),
        centre_definition=str(d.get("centre_definition", "intensity-centroid")),
        diagnostics=d.get("diagnostics", {}) if isinstance(d.get("diagnostics"), dict) else {},
        lattice_radial=radial,
    )


def _radial_from_dict(r: Any) -> tuple | None:
    """Validate the ``lattice_radial`` entry (None or {centre_px, k1, k2, rho_unit_px})."""
    if r is None:
        return None
    if not isinstance(r, dict):
        raise CalibrationError("calibration file: lattice_radial must be an object or null")
    c = r.get("centre_px")
    if not (isinstance(c, list) and len(c) == 2):
        raise CalibrationError("calibration file: lattice_radial.centre_px must be [x, y]")
    if _num(r, "rho_unit_px", positive=True) != RADIAL_NORM_PX:
        raise CalibrationError(f"calibration file: lattice_radial.rho_unit_px must be "
                               f"{RADIAL_NORM_PX}")
    return (_num({"x": c[0]}, "x"), _num({"y": c[1]}, "y"), _num(r, "k1"), _num(r, "k2"))


def load_calibration(path: str | Path) -> Calibration:
    """Read and validate a calibration JSON file.

    Raises
    ------
    CalibrationError
        Missing file, not JSON, or any invalid field (named in the message).
    """
    return calibration_from_dict(read_json(path, CalibrationError, "calibration",
                                           MAX_FILE_BYTES))
