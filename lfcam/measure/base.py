"""What every measurement method shares: the result type and the region helpers."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lfcam.measure.geometry import Geometry
from lfcam.measure.lenslets import LensletMap
from lfcam.measure.regions import Region
from lfcam.optics.trace import forward
from lfcam.robust import mad_sigma
from lfcam.status import RegionStatus


@dataclass(frozen=True)
class Measurement:
    """Blur geometry of one region: signed rim heights at the sensor and their uncertainty."""

    y1_mm: float
    y2_mm: float
    sigma_y_mm: float
    distance_mm: float  # the measurement's own estimate (lightfield: the exact fit), or NaN
    offset_mm: float
    sigma_distance_mm: float
    status: str
    plane_d_in_mm: float  # the d_in at which (y1, y2) are expressed to the models
    kind: str = "spot"
    misfit: float = float("nan")
    endpoints: tuple = ()  # lines: ((y1, y2) of endpoint a, (y1, y2) of endpoint b)
    noise_misfit: float = float("nan")  # the misfit pixel noise alone would give
    source_xy_mm: tuple = ()  # lateral position (x, y) of the fitted source, when known
    model_misfit: float = float("nan")  # the lenslet fit's point models' own disagreement
    #                                     (their ray samples') at the point fit
    fitted_mm: tuple = ()  # the fitted source in the lens frame: a point's (x, y, z), a
    #                        line's two ends; empty when no fit located it
    method: str = ""  # the fit that made it, where a later stage needs to know ("lenslet")

    @classmethod
    def failed(cls, status: str, d_in_mm: float, kind: str = "spot") -> Measurement:
        """A measurement without numbers, with the reason in ``status``."""
        nan = float("nan")
        return cls(nan, nan, nan, nan, nan, nan, status, d_in_mm, kind=kind)


def region_pixels_mask(region: Region, lmap: LensletMap) -> np.ndarray:
    """Pixels of ``region``'s lenslets inside its bounding box (bool, box-shaped)."""
    x0, y0, x1, y1 = region.box_px
    sub = lmap.labels[y0:y1, x0:x1]
    return np.isin(sub, region.lenslets)


def noise_sigma(image: np.ndarray) -> float:
    """Robust pixel noise (normal-scaled MAD) of a subsample of the whole frame (most
    pixels see no source).

    Parameters
    ----------
    image : (H, W) array

    Returns
    -------
    float
        σ of one pixel, in the image's units.
    """
    return mad_sigma(frame_sample(image))


def frame_sample(image: np.ndarray) -> np.ndarray:
    """About 256 × 256 pixels spread over the whole frame (every k-th row and column)."""
    return image[:: max(1, image.shape[0] // 256), :: max(1, image.shape[1] // 256)]


def neighbours(geom: Geometry, region: Region) -> np.ndarray:
    """Lenslets within three pitches of any of ``region``'s lenslets."""
    tree = cKDTree(geom.lmap.centres_px)
    lists = tree.query_ball_point(geom.lmap.centres_px[region.lenslets], 3.0 * geom.pitch_px)
    return np.unique(np.concatenate([np.asarray(v, dtype=np.int64) for v in lists]))


LINE_SIGMA_FLOOR_REL = 1e-3  # added in quadrature to a line's σ of a distance, either
# method's: behind focus the line fits come out long by 0.1-0.4 % on the independent renderer's
# captures (system 2, through the centre +0.17 % mean, at 60 % of the half-field +0.25 %) at a
# statistical σ of 0.04-0.06 %, whatever the centres (calibrated or true) or the model's
# sampling (twice the points, 3x the rays; about 0.07 % of it is that renderer's line
# sampling, the rest as on lfcam.sim's captures); with it 334 of 336 measured lines fall within
# 3σ (docs/distance.md, "Lines on the independent renderer")


def point_measurement(profile, d_in_mm: float, source_mm: np.ndarray, sigma_distance_mm: float,
                      sigma_floor_rel: float = 0.0, **extra) -> Measurement:
    """The measurement of a fitted point source: distance from the front vertex, offset, and
    the exact rim-ray heights at the sensor with the height uncertainty equivalent to
    ``sigma_distance_mm`` (for the models' error propagation), after ``sigma_floor_rel`` of
    the distance is added to it in quadrature (a fit's floor for the model's and the
    calibration's share, which its noise σ leaves out).

    Parameters
    ----------
    profile : CameraProfile
    d_in_mm : float
    source_mm : (3,) array
        Fitted source position (lens frame).
    sigma_distance_mm : float
    sigma_floor_rel : float, optional
    **extra
        Further :class:`Measurement` fields (``misfit``, ``noise_misfit``, …).

    Returns
    -------
    Measurement
        ``out-of-domain`` when the rim rays of that source do not reach the sensor.
    """
    nan = float("nan")
    distance = profile.main_lens.front_vertex_z_mm - float(source_mm[2])
    offset = float(np.hypot(source_mm[0], source_mm[1]))
    if sigma_floor_rel:
        sigma_distance_mm = math.hypot(sigma_distance_mm, sigma_floor_rel * distance)
    # the source and one 0.1 % further, in one trace
    fw = forward(profile, d_in_mm, np.array([distance, distance * 1.001]), offset)
    if fw.status[0] != 0:
        return Measurement(nan, nan, nan, distance, offset, sigma_distance_mm,
                           RegionStatus.OUT_OF_DOMAIN, d_in_mm)
    y1, y2 = float(fw.y1_mm[0]), float(fw.y2_mm[0])
    dy = abs(float(fw.y1_mm[1] - fw.y2_mm[1]) - (y1 - y2)) / (0.001 * distance)
    sigma_y = sigma_distance_mm * dy if np.isfinite(sigma_distance_mm) else nan
    fitted = (tuple(float(v) for v in source_mm),)
    return Measurement(y1, y2, sigma_y, distance, offset, sigma_distance_mm, RegionStatus.OK,
                       d_in_mm, fitted_mm=fitted, **extra)


def line_measurement(profile, d_in_mm: float, ends_mm, sigma_distance_mm: float,
                     **extra) -> Measurement:
    """The measurement of a fitted line source (``kind="line"``): distance from the front
    vertex, the offset of its midpoint, the exact rim-ray heights at the sensor of both
    endpoints (``endpoints``) and their mean, and ``sigma_distance_mm`` with
    :data:`LINE_SIGMA_FLOOR_REL` of the distance added in quadrature.

    Parameters
    ----------
    profile : CameraProfile
    d_in_mm : float
    ends_mm : pair of (3,) arrays
        The line's endpoints (lens frame), both at the line's z.
    sigma_distance_mm : float
    **extra
        Further :class:`Measurement` fields (``misfit``, ``noise_misfit``, …).

    Returns
    -------
    Measurement
    """
    distance = profile.main_lens.front_vertex_z_mm - float(ends_mm[0][2])
    fw = forward(profile, d_in_mm, distance,  # both ends in one trace
                 np.array([float(np.hypot(pt[0], pt[1])) for pt in ends_mm]))
    ends = tuple((float(fw.y1_mm[k]), float(fw.y2_mm[k])) for k in range(2))
    mid = 0.5 * (np.asarray(ends_mm[0], dtype=float) + np.asarray(ends_mm[1], dtype=float))
    return Measurement(0.5 * (ends[0][0] + ends[1][0]), 0.5 * (ends[0][1] + ends[1][1]),
                       float("nan"), distance, float(np.hypot(mid[0], mid[1])),
                       math.hypot(sigma_distance_mm, LINE_SIGMA_FLOOR_REL * distance),
                       RegionStatus.OK, d_in_mm, kind="line", endpoints=ends,
                       fitted_mm=tuple(tuple(float(v) for v in pt) for pt in ends_mm), **extra)
