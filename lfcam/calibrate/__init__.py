"""Calibration: microlens centres from white images, lattice model, d_in from a reference plane.

See docs/calibration.md.
"""

from __future__ import annotations

from pathlib import Path

from lfcam.calibrate.grid import GridFit, find_centres
from lfcam.calibrate.image import prepare_white, read_raster
from lfcam.calibrate.model import (
    Calibration,
    calibration_from_fit,
    load_calibration,
    save_calibration,
    sha256_file,
)

__all__ = [
    "Calibration", "GridFit", "calibrate_white", "calibrate_white_file", "find_centres",
    "load_calibration", "prepare_white", "read_raster", "save_calibration",
]


def calibrate_white(white, dark=None, bayer: str = "none", pitch_hint_px: float | None = None,
                    progress=None, white_sha256: str | None = None,
                    dark_sha256: str | None = None) -> Calibration:
    """Calibrate from in-memory arrays (see :func:`lfcam.calibrate.grid.find_centres`)."""
    img, n_hot = prepare_white(white, dark, bayer)
    kwargs = {} if progress is None else {"progress": progress}
    fit = find_centres(img, pitch_hint_px=pitch_hint_px, **kwargs)
    cal = calibration_from_fit(fit, (img.shape[1], img.shape[0]), white_sha256, dark_sha256)
    cal.diagnostics["hot_pixels_replaced"] = n_hot
    return cal


def calibrate_white_file(white_path, dark=None, profile=None, output=None,
                         progress=None) -> Calibration:
    """Read WHITE (and DARK), calibrate, optionally save atomically to ``output``."""
    bayer, hint = "none", None
    if profile is not None:
        from lfcam.camera import load_profile

        prof = load_profile(profile)
        bayer = prof.sensor.bayer
        hint = prof.mla.pitch_mm / prof.sensor.pixel_pitch_mm
    white = read_raster(white_path)
    dark_img = None if dark is None else read_raster(dark)
    cal = calibrate_white(white, dark_img, bayer, hint, progress,
                          sha256_file(white_path), None if dark is None else sha256_file(dark))
    if output is not None:
        save_calibration(cal, Path(output))
    return cal
