"""lfcam: metric distance maps from plenoptic 1.0 (microlens-array) camera captures.

The package folders follow the pipeline: ``io`` (load) → ``calibrate`` → ``decode`` →
``measure`` → ``models`` → ``export``; ``optics`` holds the exact thick-lens ray trace and
paraxial helpers every stage shares, ``sim`` the synthetic renderer.
"""

from lfcam.camera import CameraProfile, MainLens, MicrolensArray, Sensor, load_profile
from lfcam.errors import LfcamError

__all__ = [
    "CameraProfile",
    "LfcamError",
    "MainLens",
    "MicrolensArray",
    "Sensor",
    "load_profile",
]
__version__ = "0.1.0"
