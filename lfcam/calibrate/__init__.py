"""Calibration: microlens centres from white images, lattice model, d_in from a reference plane.

See docs/calibration.md.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lfcam.atomic import sha256_file
from lfcam.calibrate.grid import GridFit, find_centres
from lfcam.calibrate.image import prepare_white
from lfcam.calibrate.model import (
    Calibration,
    calibration_from_fit,
    load_calibration,
    save_calibration,
)

__all__ = [
    "Calibration", "GridFit", "calibrate_reference", "calibrate_reference_file",
    "calibrate_white", "calibrate_white_file", "find_centres",
    "load_calibration", "prepare_white", "save_calibration", "with_quality",
]


def calibrate_white(white, dark=None, bayer: str = "none", pitch_hint_px: float | None = None,
                    progress=None, white_sha256: str | None = None,
                    dark_sha256: str | None = None) -> Calibration:
    """Calibrate from in-memory arrays (see :func:`lfcam.calibrate.grid.find_centres`).

    Parameters
    ----------
    white : (H, W) array
        White image, linear, black level removed.
    dark : (H, W) array, optional
        Dark frame subtracted first.
    bayer : str
        Colour filter pattern (its planes are equalised), ``"none"`` for grey.
    pitch_hint_px : float, optional
        Expected micro-image pitch.
    progress : lfcam.progress.Progress, optional
    white_sha256, dark_sha256 : str, optional
        Recorded in the calibration.

    Returns
    -------
    Calibration
        With its quality block (:func:`with_quality`).
    """
    img, n_hot = prepare_white(white, dark, bayer)
    kwargs = {} if progress is None else {"progress": progress}
    fit = find_centres(img, pitch_hint_px=pitch_hint_px, **kwargs)
    cal = calibration_from_fit(fit, (img.shape[1], img.shape[0]), white_sha256, dark_sha256)
    cal.diagnostics["hot_pixels_replaced"] = n_hot
    return with_quality(cal)


def with_quality(cal: Calibration, accepted_poor: bool = False) -> Calibration:
    """Copy of ``cal`` with its quality block (:func:`lfcam.calibrate.quality.assess`).

    Parameters
    ----------
    cal : Calibration
    accepted_poor : bool
        Record that the user accepted a ``poor`` verdict.

    Returns
    -------
    Calibration
    """
    from dataclasses import replace

    from lfcam.calibrate.quality import assess

    return replace(cal, quality=assess(cal).to_dict(accepted_poor))


def calibrate_white_file(white_path, dark=None, profile=None, output=None,
                         progress=None, accept_poor: bool = False) -> Calibration:
    """Read WHITE (and DARK), calibrate, optionally save atomically to ``output``.

    WHITE and DARK may be anything :func:`lfcam.io.load_capture` reads (Lytro ``.lfp``/``.lfr``
    containers and bare packed raws, camera raws, PNG/TIFF rasters). The capture's black
    level is removed (when no dark frame is given) and its Bayer pattern, or else the
    profile's, is equalised. The result carries its quality block; a ``poor`` calibration
    is not written to ``output`` (:class:`~lfcam.errors.CalibrationQualityError`) unless
    ``accept_poor`` (then it is marked ``accepted_poor``).

    Parameters
    ----------
    white_path : str or Path
    dark : str or Path, optional
    profile : str, Path or CameraProfile, optional
        Pitch hint and Bayer pattern when the file does not state one.
    output : str or Path, optional
        Where to save the calibration JSON.
    progress : lfcam.progress.Progress, optional
    accept_poor : bool

    Returns
    -------
    Calibration
    """
    from lfcam.camera import load_profile
    from lfcam.io import load_capture

    prof = None if profile is None else load_profile(profile)
    hint = None if prof is None else prof.mla.pitch_mm / prof.sensor.pixel_pitch_mm
    cap = load_capture(white_path, prof)
    white = np.asarray(cap.raw, dtype=np.float32)
    bayer = cap.bayer if cap.bayer != "none" or prof is None else prof.sensor.bayer
    if dark is None:
        white = white - np.float32(cap.black_level)
        dark_img = None
    else:
        dark_img = np.asarray(load_capture(dark, prof).raw, dtype=np.float32)
    cal = calibrate_white(white, dark_img, bayer, hint, progress,
                          sha256_file(white_path), None if dark is None else sha256_file(dark))
    if accept_poor and cal.is_poor:
        cal = with_quality(cal, accepted_poor=True)
    elif cal.is_poor and output is not None:
        from lfcam.errors import CalibrationQualityError

        raise CalibrationQualityError(
            f"{white_path}: poor calibration, not written: {'; '.join(cal.quality['reasons'])}"
            " (pass --accept-poor to write it anyway)")
    if output is not None:
        save_calibration(cal, Path(output))
    return cal


def calibrate_reference(cal: Calibration, capture, profile, distance_mm: float,
                        **kwargs):
    """Calibrate d_in from a dot-target capture; returns (calibration with d_in, DinResult).

    ``profile`` is a :class:`~lfcam.camera.CameraProfile`; its d_in is only the solver's
    start. The white calibration supplies the micro-image centroids, pitch and rotation
    (see :func:`lfcam.calibrate.reference.measure_d_in`).

    Parameters
    ----------
    cal : Calibration
    capture : (H, W) array
        Raw grey capture of the dot target.
    profile : CameraProfile
    distance_mm : float
        Dot plane → front vertex.
    **kwargs
        Passed to :func:`lfcam.calibrate.reference.measure_d_in`.
    """
    from lfcam.calibrate.reference import METHOD, measure_d_in

    cal.check_image(capture.shape)
    kwargs.setdefault("pitch_px", cal.pitch_px)
    kwargs.setdefault("rotation_rad", cal.rotation_rad)
    kwargs.setdefault("indices", cal.indices)
    res = measure_d_in(capture, cal.centres_px, profile, distance_mm, **kwargs)
    import math
    from dataclasses import replace

    def finite(v: float) -> float | None:
        return float(v) if math.isfinite(v) else None

    out = cal.with_d_in(res.d_in_mm, METHOD)
    diagnostics = dict(cal.diagnostics)
    diagnostics.update({
        "d_in_sigma_mm": finite(res.sigma_mm), "d_in_paraxial_mm": finite(res.d_in_paraxial_mm),
        "reference_distance_mm": res.distance_mm, "reference_dots": res.n_dots,
    })
    return replace(out, diagnostics=diagnostics), res


def calibrate_reference_file(cal: Calibration, capture_path, profile, distance_mm: float):
    """Read a grey dot-target capture (:func:`lfcam.io.load_capture`, values as stored) and
    run :func:`calibrate_reference`.

    Parameters
    ----------
    cal : Calibration
    capture_path : str or Path
    profile : str, Path or CameraProfile
    distance_mm : float

    Returns
    -------
    (Calibration, DinResult)
    """
    from lfcam.camera import load_profile
    from lfcam.errors import CalibrationError
    from lfcam.io import load_capture

    prof = load_profile(profile) if not hasattr(profile, "main_lens") else profile
    if prof.sensor.bayer != "none":
        raise CalibrationError(
            f"profile {prof.name!r} has a {prof.sensor.bayer} colour filter: the reference "
            "route needs a grey (un-mosaicked) capture")
    raw = np.asarray(load_capture(capture_path, prof).raw, dtype=np.float32)
    return calibrate_reference(cal, raw, prof, distance_mm)
