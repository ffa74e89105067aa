"""The seed paper's measurement: the blur footprint's diameter on the MLA plane.

The diameter is that of the equivalent-area disc from per-lenslet energies (sub-lenslet: edge
cells count by their energy against their brightest lit neighbour); its sign (in front of or
behind focus) comes from the slope field of the micro-image spots, its centre from the energy
centroid. ``DIAMETER_SIGMA_PITCH`` is the assumed 1-σ error of the footprint edges.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from lfcam.camera import CameraProfile
from lfcam.measure.base import Measurement, region_pixels_mask
from lfcam.measure.geometry import Geometry
from lfcam.measure.lenslets import LensletStats
from lfcam.measure.pointfit import assign_spots, find_spots
from lfcam.measure.regions import Region
from lfcam.status import RegionStatus

DIAMETER_SIGMA_PITCH = 0.1  # 1-σ error of footprint edges, in lenslet pitches (heuristic)


def measure_diameter(profile: CameraProfile, geom: Geometry, image: np.ndarray,
                     stats: LensletStats, region: Region, noise: float) -> Measurement:
    """The seed's measurement: signed footprint diameter on the MLA plane (module docstring).

    Parameters
    ----------
    profile : CameraProfile
    geom : Geometry
    image : (H, W) float array
    stats : LensletStats
        Per-lenslet energies of the capture (:func:`lfcam.measure.lenslet_stats`).
    region : Region
    noise : float
        Pixel noise σ.

    Returns
    -------
    Measurement
        Rim heights on the MLA plane (``plane_d_in_mm`` = d_in − f_x), no distance of its own.
    """
    nan = float("nan")
    e = stats.energy[region.lenslets]
    plateau = float(np.percentile(e, 90))
    if plateau <= 0 or len(e) < 3:
        return Measurement.failed(RegionStatus.NEAR_FOCUS, geom.d_in_mm)
    pitch = profile.mla.pitch_mm
    cell = pitch * pitch * (math.sqrt(3) / 2 if profile.mla.grid == "hex" else 1.0)
    area = float(_covered_fraction(geom, stats, region).sum()) * cell
    diameter = 2.0 * math.sqrt(area / math.pi)
    c = geom.lens_centres_mm[region.lenslets]
    centre = (c * e[:, None]).sum(0) / e.sum()
    radial = float(np.hypot(*centre))
    # sign from the slope field of the spots: converging bundle (dσ/ds < 0) → y1 > y2
    x0, y0, x1, y1_ = region.box_px
    sub = image[y0:y1_, x0:x1]
    mask = region_pixels_mask(region, geom.lmap) | (geom.lmap.labels[y0:y1_, x0:x1] < 0)
    peak = float(sub[mask].max()) if mask.any() else 0.0
    spots, energy = find_spots(sub, mask, max(6.0 * noise, 0.03 * peak))
    if len(spots) < 3:
        return Measurement.failed(RegionStatus.NEAR_FOCUS, geom.d_in_mm)
    spots = spots + np.array([x0, y0])
    pp = profile.sensor.pixel_pitch_mm
    ax, ay = profile.sensor.axis_xy_px
    spots_mm = np.column_stack([(spots[:, 0] - ax) * pp, (spots[:, 1] - ay) * pp])
    fx = profile.mla.focal_length_mm
    mag = 1.0 + fx / (geom.d_in_mm - profile.main_lens.exit_pupil_z_mm)
    k = assign_spots(spots_mm, energy, geom.lens_centres_mm, pitch, mag)
    good = k >= 0
    cc = geom.lens_centres_mm[k[good]]
    off = spots_mm[good] - cc
    a = np.column_stack([np.ones(good.sum()), cc])
    sol, *_ = np.linalg.lstsq(a * np.sqrt(energy[good])[:, None],
                              off * np.sqrt(energy[good])[:, None], rcond=None)
    divergence = float(sol[1, 0] + sol[2, 1])  # trace of dσ·f_x/ds
    sign = -1.0 if divergence > 0 else 1.0
    y1 = radial + sign * 0.5 * diameter
    y2 = radial - sign * 0.5 * diameter
    return Measurement(y1, y2, DIAMETER_SIGMA_PITCH * pitch, nan, nan, nan, RegionStatus.OK,
                       geom.d_in_mm - fx)


def _covered_fraction(geom: Geometry, stats, region: Region) -> np.ndarray:
    """Share of each lenslet's cell inside the footprint: 1 for interior lenslets (every
    neighbour lit), else its energy over its brightest lit neighbour's (partial edge cells)."""
    members = region.lenslets
    centres = geom.lmap.centres_px
    tree = cKDTree(centres)
    lit = np.zeros(len(centres), bool)
    lit[members] = True
    frac = np.ones(len(members))
    for i, nb in enumerate(tree.query_ball_point(centres[members], 1.5 * geom.pitch_px)):
        nb = [j for j in nb if j != members[i]]
        if all(lit[j] for j in nb):
            continue
        ref = max((stats.energy[j] for j in nb if lit[j]), default=0.0)
        frac[i] = min(1.0, stats.energy[members[i]] / ref) if ref > 0 else 0.0
    return frac
