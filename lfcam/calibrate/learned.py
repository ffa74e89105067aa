"""The ``learned_lens`` block of a calibration file: its schema and its checks.

A main lens learned from captures at known distances (:mod:`lfcam.calibrate.lensfit`) is
stored in the calibration as an ideal-surface prescription with its parameters, their σ and
covariance. Reading a calibration file checks that block here, without the measurement
modules the learning itself needs (so the calibration model does not import them).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from lfcam.errors import CalibrationError, LfcamError, OpticsError
from lfcam.optics.lens import Prescription

PARAMS = ("focal_length_mm", "principal_mm", "d_in_mm")
MAX_SOURCES = 1000
# The measurement method the lens is learned with, and the distance stage's default with it:
# the learned aberration terms stand in for the real lens's as that method sees them. On the
# Cooke triplet at ∞ the image fit (``lightfield``) read every hidden source 1.7–1.9 % far
# with the lens learned by the lenslet fit, which read them within 1 % (docs/calibration.md).
LEARNED_METHOD = "lenslet"


def surfaces_to_json(rows: list[dict]) -> list[dict]:
    """Surface tables for JSON: a flat surface's infinite radius is written as null."""
    return [{k: (None if k == "radius_mm" and math.isinf(v) else v) for k, v in r.items()}
            for r in rows]


def surfaces_from_json(rows: Any) -> Prescription:
    """The prescription of a JSON ``surfaces`` list (null radius = flat)."""
    from lfcam.optics.zmx import prescription_from_toml_dict

    if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
        raise CalibrationError("learned_lens.surfaces must be a list of tables")
    rows = [{k: (math.inf if k == "radius_mm" and v is None else v) for k, v in r.items()}
            for r in rows]
    return prescription_from_toml_dict({"surfaces": rows})


def validate_learned(block: Any, where: str) -> dict:
    """Check a calibration file's ``learned_lens`` block (sizes, numbers, plausibility)."""
    if not isinstance(block, dict):
        raise CalibrationError(f"{where}: learned_lens must be an object")
    for key in ("surfaces", "d_in_mm", "parameters", "sigma", "covariance"):
        if key not in block:
            raise CalibrationError(f"{where}: learned_lens.{key} missing")
    surfaces = block["surfaces"]
    if not isinstance(surfaces, list) or not 1 <= len(surfaces) <= 64:
        raise CalibrationError(f"{where}: learned_lens.surfaces must list 1–64 surfaces")
    try:
        rx = surfaces_from_json(surfaces)
        efl = rx.paraxial.efl_mm
    except (LfcamError, TypeError, ValueError) as exc:
        raise CalibrationError(f"{where}: learned_lens.surfaces: {exc}") from None
    except OpticsError as exc:  # pragma: no cover - LfcamError above
        raise CalibrationError(f"{where}: learned_lens: {exc}") from None
    d_in = block["d_in_mm"]
    if isinstance(d_in, bool) or not isinstance(d_in, (int, float)) or not (
            math.isfinite(d_in) and 0 < d_in < 1e5):
        raise CalibrationError(f"{where}: learned_lens.d_in_mm must be a positive length")
    if not (0 < efl < 1e5) or d_in <= rx.paraxial.back_principal_z_mm:
        raise CalibrationError(f"{where}: learned_lens: implausible lens (EFL {efl:.4g} mm, "
                               f"d_in {d_in:.4g} mm)")
    params, sigma = block["parameters"], block["sigma"]
    for name, table in (("parameters", params), ("sigma", sigma)):
        if not isinstance(table, dict) or set(table) != set(PARAMS) or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                for v in table.values()):
            raise CalibrationError(
                f"{where}: learned_lens.{name} must give {', '.join(PARAMS)} as numbers")
    cov = np.asarray(block["covariance"], dtype=np.float64) if isinstance(
        block["covariance"], list) else None
    if cov is None or cov.shape != (3, 3) or not np.isfinite(cov).all():
        raise CalibrationError(f"{where}: learned_lens.covariance must be a 3×3 numeric matrix")
    res = block.get("residuals", [])
    if not isinstance(res, list) or len(res) > MAX_SOURCES:
        raise CalibrationError(f"{where}: learned_lens.residuals must be a list of at most "
                               f"{MAX_SOURCES}")
    method = block.get("measured_with", LEARNED_METHOD)
    if method not in ("lenslet", "lightfield"):
        raise CalibrationError(f"{where}: learned_lens.measured_with must be lenslet or "
                               f"lightfield, got {method!r}")
    out = dict(block)
    out["covariance"] = cov.tolist()
    return out
