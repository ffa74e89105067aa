"""The lenslet geometry of a rendered camera, straight from the renderer (no calibration).

Benchmarks and tests use it to measure a distance method apart from the white-image
calibration: the renderer's own lenslet centres on the MLA plane and its chief-ray
micro-image centres on the sensor.
"""

from __future__ import annotations

import numpy as np

from lfcam.camera import CameraProfile
from lfcam.measure.geometry import Geometry
from lfcam.measure.lenslets import build_lenslet_map
from lfcam.sim.render import Renderer


def truth_geometry(profile: CameraProfile, shape: tuple[int, int]) -> Geometry:
    """:class:`~lfcam.measure.Geometry` from the renderer's exact lenslet centres.

    Parameters
    ----------
    profile : CameraProfile
        The camera as rendered (its d_in).
    shape : tuple of int
        (rows, cols) of the captures.

    Returns
    -------
    Geometry
        Micro-image pitch from the chief-ray magnification ``1 + f_x/(d_in − z_exit pupil)``;
        each micro-image spans 0.54 pitch around its chief-ray centre.
    """
    rend = Renderer(profile)
    mag = 1.0 + profile.mla.focal_length_mm / (profile.d_in_mm
                                              - profile.main_lens.exit_pupil_z_mm)
    pitch_px = profile.mla.pitch_mm / profile.sensor.pixel_pitch_mm * mag
    lmap = build_lenslet_map(rend.predicted_centres_px(), shape, 0.54 * pitch_px)
    return Geometry(lmap, np.stack([rend.lcx, rend.lcy], 1), pitch_px, profile.d_in_mm)
