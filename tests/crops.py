"""Off-axis sensor crops of a shipped camera and the sources placed in them, shared by the
tests: a small ``size``² sensor whose optical axis lies off the crop, so that a few hundred
pixels stand for a patch far out in the field."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from lfcam import distance
from lfcam.camera import load_profile
from lfcam.measure import find_regions, lenslet_stats
from lfcam.measure.noise import capture_noise
from lfcam.measure.pointfit import chief_ray_offset
from lfcam.sim.capture import apply_overrides, simulate
from lfcam.sim.geometry import truth_geometry
from lfcam.sim.scene import scene_from_dict

ILLUM_LIKE = Path(__file__).resolve().parents[1] / "benchmarks" / "profiles" / "illum_like.toml"
SENSOR_NOISE = {"photon_noise": True, "full_well_e": 20000.0, "read_noise_e": 3.0}


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


def illum_crop_capture(width_px: int, height_px: int, axis_px: list[float], objects: list[dict],
                       seed: int, rays_per_source: int) -> tuple:
    """``objects`` rendered on a ``width_px`` × ``height_px`` crop of the Illum-like profile's
    sensor (``benchmarks/profiles/illum_like.toml``, the many-source scene (b)'s camera) whose
    optical axis lies at ``axis_px``, with sensor noise (:data:`SENSOR_NOISE`, the full well
    stated in the profile), its noise model registered as ``lfcam distance`` does: (profile,
    geometry, image, the capture's one region, pixel noise σ)."""
    base = load_profile(ILLUM_LIKE)
    camera = {"sensor": {"width_px": width_px, "height_px": height_px, "axis_px": axis_px}}
    prof = apply_overrides(base, camera)
    prof = replace(prof, sensor=replace(prof.sensor, full_well_e=SENSOR_NOISE["full_well_e"]))
    scene = {"seed": seed, "rays_per_source": rays_per_source, "camera": camera,
             "sensor": SENSOR_NOISE, "exposure": {"peak": 0.8}, "objects": objects}
    raw, used, _ = simulate(base, scene_from_dict(scene))
    image = raw.astype(np.float64) - used.sensor.black_level
    geom = truth_geometry(prof, image.shape)
    stats = lenslet_stats(image, geom.lmap)
    white = float(used.sensor.white_level - used.sensor.black_level)
    capture_noise(image, geom.lmap, geom.pitch_px, stats,
                  sensor_gain=distance.sensor_gain(prof, white))
    (region,) = find_regions(stats, geom.lmap, geom.pitch_px)
    return prof, geom, image, region, distance.noise_sigma(image)
