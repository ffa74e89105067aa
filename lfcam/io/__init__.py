"""Capture loaders: Lytro LFP/LFR containers and packed raws, camera raws, PNG/TIFF rasters.

Entry point: :func:`load_capture`. See ``docs/loaders.md``.
"""

from lfcam.io.capture import Capture, load_capture, sniff_kind
from lfcam.io.lfp import LfpContainer, read_lfp, write_lfp
from lfcam.io.lytro_meta import LytroCamera, LytroOptics, lytro_camera, raw_format
from lfcam.io.profiles import profile_for_capture, profile_from_lytro
from lfcam.io.whiteimage import find_white_image, white_image_for

__all__ = [
    "Capture",
    "LfpContainer",
    "LytroCamera",
    "LytroOptics",
    "find_white_image",
    "load_capture",
    "lytro_camera",
    "profile_for_capture",
    "profile_from_lytro",
    "raw_format",
    "read_lfp",
    "sniff_kind",
    "white_image_for",
    "write_lfp",
]
