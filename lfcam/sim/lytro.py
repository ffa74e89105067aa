"""Rendered captures written as Lytro containers, with the metadata a Lytro camera writes.

A rendered raw (``lfcam.sim.capture.simulate``) becomes an ``.lfr``/``.lfp`` file through
:func:`lfcam.io.write_lfp`: 10-bit sensors get the Illum layout, 12-bit sensors the F01
layout. The frame metadata describes the camera the way a Lytro camera does, in metres:
``devices.lens`` (focal length, f-number, exit pupil → MLA distance, zoom and focus steps),
``devices.mla`` (hex tiling, pitch, rotation, ``sensorOffset``), ``devices.sensor``
(pixel pitch) and the raw format (black/white levels, Bayer mosaic). The lens prescription
is not written: a reader learns the lens only as a real camera's owner would.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from lfcam.camera import CameraProfile
from lfcam.errors import SceneError

# Lytro's "exit pupil at infinity" sentinel (metres), written when the exit pupil is at infinity
EXIT_PUPIL_INFINITY_M = 10000.0
# mosaic.tile of both Lytro cameras; upperLeftPixel picks the pattern (lytro_meta.bayer_from_mosaic)
_TILE = "r,gr:gb,b"
_UPPER_LEFT = {"RGGB": "r", "GRBG": "gr", "GBRG": "gb", "BGGR": "b"}
_PACKING = {10: "10bit", 12: "12bit"}


def lytro_metadata(profile: CameraProfile, model: str = "ILLUM", zoom_step: int = 0,
                   focus_step: int = 0) -> dict:
    """Lytro frame metadata (metres, radians) describing a rendered camera.

    Parameters
    ----------
    profile : CameraProfile
        The camera used for rendering, MLA position resolved (``d_in_mm`` known).
    model : str
        ``camera.model`` (``"ILLUM"`` or ``"F01"``).
    zoom_step, focus_step : int
        ``devices.lens.zoomStep`` / ``focusStep`` (identify the lens state; not optics).

    Returns
    -------
    dict
        Frame metadata; :func:`lfcam.io.write_lfp` adds the packing keys.

    Raises
    ------
    SceneError
        A sensor the Lytro layouts cannot hold (Bayer pattern, bit depth) or an MLA grid that
        is not hexagonal (both Lytro cameras have hex MLAs).
    """
    s, mla, lens = profile.sensor, profile.mla, profile.main_lens
    if s.bit_depth not in _PACKING:
        raise SceneError(f"Lytro containers hold 10- or 12-bit raws, not {s.bit_depth}-bit")
    if mla.grid != "hex":
        raise SceneError("Lytro cameras have hexagonal MLAs: set mla.grid = \"hex\"")
    pupil_to_mla_mm = profile.mla_z_mm - lens.exit_pupil_z_mm
    epo_m = pupil_to_mla_mm * 1e-3 if math.isfinite(pupil_to_mla_mm) else EXIT_PUPIL_INFINITY_M
    mosaic = ({"tile": "monochrome", "upperLeftPixel": "gr"} if s.bayer == "none"
              else {"tile": _TILE, "upperLeftPixel": _UPPER_LEFT[s.bayer]})
    fmt = {"black": {c: s.black_level for c in ("r", "gr", "gb", "b")},
           "white": {c: s.white_level for c in ("r", "gr", "gb", "b")},
           "rightShift": 0}
    image: dict = {"mosaic": mosaic, "pixelFormat": fmt}
    if s.bit_depth == 12:  # the F01 layout keeps the raw format under image.rawDetails
        image = {"rawDetails": image}
    return {
        "type": "lightField",
        "camera": {"make": "Lytro, Inc.", "model": model, "firmware": "lfcam-sim"},
        "image": image,
        "devices": {
            "sensor": {"pixelPitch": s.pixel_pitch_mm * 1e-3, "bitsPerPixel": s.bit_depth,
                       "mosaic": mosaic},
            "lens": {
                "focalLength": lens.focal_length_mm * 1e-3,
                "fNumber": lens.f_number,
                "exitPupilOffset": {"z": epo_m},
                "zoomStep": int(zoom_step),
                "focusStep": int(focus_step),
            },
            "mla": {
                "tiling": "hexUniformRowMajor",
                "lensPitch": mla.pitch_mm * 1e-3,
                "rotation": mla.rotation_rad,
                "scaleFactor": {"x": 1.0, "y": 1.0},
                "sensorOffset": {"x": mla.offset_mm[0] * 1e-3, "y": mla.offset_mm[1] * 1e-3,
                                 "z": mla.focal_length_mm * 1e-3},
            },
        },
    }


def write_lytro_capture(path: str | Path, raw: np.ndarray, profile: CameraProfile,
                        model: str = "ILLUM", zoom_step: int = 0, focus_step: int = 0,
                        serial: str = "LFCAM-SIM-0001") -> Path:
    """Write a rendered raw as a Lytro container (atomically).

    Parameters
    ----------
    path : str or Path
        ``.lfr`` / ``.lfp`` output.
    raw : (H, W) uint16 array
        The rendered raw (``simulate`` output), within the sensor's bit depth.
    profile : CameraProfile
        The profile used for rendering.
    model, zoom_step, focus_step :
        As :func:`lytro_metadata`.
    serial : str
        ``camera.serialNumber`` in the private metadata.

    Returns
    -------
    Path
    """
    from lfcam.io.lfp import write_lfp

    meta = lytro_metadata(profile, model=model, zoom_step=zoom_step, focus_step=focus_step)
    return write_lfp(path, raw, meta, packing=_PACKING[profile.sensor.bit_depth],
                     private_metadata={"camera": {"serialNumber": serial}})
