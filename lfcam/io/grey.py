"""Linear grey image from a raw mosaic: the one demosaic-and-normalise step of the pipeline."""

from __future__ import annotations

import math

import cv2
import numpy as np

from lfcam.camera import BAYER_PATTERNS
from lfcam.errors import InputFileError

GREY_WHITE = 1.0  # the value of the sensor's white level in to_grey's images (black: 0)

# OpenCV names a Bayer pattern after the second row's 2nd/3rd pixels; these map our
# pattern (colours of pixels (0,0), (0,1), (1,0), (1,1)) to the code giving BGR output.
_CV_BAYER = {
    "RGGB": cv2.COLOR_BayerBG2BGR,
    "BGGR": cv2.COLOR_BayerRG2BGR,
    "GRBG": cv2.COLOR_BayerGB2BGR,
    "GBRG": cv2.COLOR_BayerGR2BGR,
}

def to_grey(raw: np.ndarray, bayer: str = "none", black_level: float = 0.0,
            white_level: float | None = None) -> np.ndarray:
    """Linear grey float32 image from a raw mosaic: demosaic (OpenCV) and level-normalise.

    Parameters
    ----------
    raw : 2-D array
    bayer : str
        ``"none"`` or a CFA pattern (docs/profiles.md).
    black_level, white_level : float
        Raw value of no light and of saturation (``None``: the dtype maximum, or 1 for floats).

    Returns
    -------
    (H, W) float32 array
        0 at the black level, 1 at the white level.

    Raises
    ------
    InputFileError
        Not 2-D, unknown pattern, levels in the wrong order, or non-finite values.
    """
    if raw.ndim != 2 or raw.shape[0] < 2 or raw.shape[1] < 2:
        raise InputFileError(f"raw image must be 2-D and at least 2×2, got shape {raw.shape}")
    if bayer not in BAYER_PATTERNS:
        raise InputFileError(f"unknown Bayer pattern {bayer!r} (expected one of {BAYER_PATTERNS})")
    if white_level is None:
        white_level = float(np.iinfo(raw.dtype).max) if raw.dtype.kind in "ui" else 1.0
    span = float(white_level) - float(black_level)
    if not math.isfinite(span) or span <= 0:
        raise InputFileError(f"white level {white_level} must exceed black level {black_level}")
    if bayer != "none":
        src = raw
        if src.dtype not in (np.uint8, np.uint16):
            src = np.clip(raw, 0, 65535).astype(np.uint16)
        bgr = cv2.cvtColor(np.ascontiguousarray(src), _CV_BAYER[bayer])
        grey = cv2.cvtColor(bgr.astype(np.float32), cv2.COLOR_BGR2GRAY)
    else:
        grey = raw.astype(np.float32, copy=True)
    if raw.dtype.kind not in "ui" and not np.all(np.isfinite(grey)):  # integers always are
        raise InputFileError("raw image contains NaN or infinite values")
    grey -= np.float32(black_level)
    grey *= np.float32(GREY_WHITE / span)
    return grey
