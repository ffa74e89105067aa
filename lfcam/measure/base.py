"""What every measurement method shares: the result type and the region helpers."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import median_abs_deviation

from lfcam.measure.geometry import Geometry
from lfcam.measure.lenslets import LensletMap
from lfcam.measure.regions import Region


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
    sample = image[:: max(1, image.shape[0] // 256), :: max(1, image.shape[1] // 256)]
    return float(median_abs_deviation(sample, axis=None, scale="normal"))


def neighbours(geom: Geometry, region: Region) -> np.ndarray:
    """Lenslets within three pitches of any of ``region``'s lenslets."""
    tree = cKDTree(geom.lmap.centres_px)
    lists = tree.query_ball_point(geom.lmap.centres_px[region.lenslets], 3.0 * geom.pitch_px)
    return np.unique(np.concatenate([np.asarray(v, dtype=np.int64) for v in lists]))
