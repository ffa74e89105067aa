"""Off-axis sensor crops of a shipped camera and the sources placed in them, shared by the
tests: a small ``size``² sensor whose optical axis lies off the crop, so that a few hundred
pixels stand for a patch far out in the field."""

from __future__ import annotations

import math

import numpy as np

from lfcam.camera import load_profile
from lfcam.measure.pointfit import chief_ray_offset
from lfcam.sim.capture import apply_overrides


def crop_camera(focus_mm: float, centre_mm: np.ndarray, size: int,
                system: str = "system1") -> tuple[dict, object]:
    """Scene overrides for a ``size``² crop centred at ``centre_mm`` (sensor, from the axis),
    and the profile they make."""
    pitch = load_profile(system).sensor.pixel_pitch_mm
    axis = (0.5 * (size - 1) - centre_mm[0] / pitch, 0.5 * (size - 1) - centre_mm[1] / pitch)
    cam = {"mla": {"focus_mm": "inf" if math.isinf(focus_mm) else focus_mm},
           "sensor": {"width_px": size, "height_px": size, "axis_px": list(axis)}}
    used = apply_overrides(load_profile(system), cam)
    return cam, used.with_d_in(used.d_in_mm)


def source_at(prof, distance_mm: float, sensor_mm: np.ndarray) -> list[float]:
    """Lateral position whose chief ray lands at ``sensor_mm`` on the sensor."""
    mag = 1 + prof.mla.focal_length_mm / (prof.d_in_mm - prof.main_lens.exit_pupil_z_mm)
    xy = chief_ray_offset(prof, prof.d_in_mm, distance_mm, sensor_mm / mag)
    return [float(xy[0]), float(xy[1])]
