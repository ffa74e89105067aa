"""Per-lenslet statistics of a raw capture: energy and micro-image centroid of every lenslet.

Every pixel belongs to the micro-image whose (calibrated) centre is nearest, if it lies within
``radius_px`` of it; pixels further out (seams between micro-images, where neighbours overlap
in fast systems, docs/calibration.md) are ignored. The assignment is computed once per calibration
(a k-d tree query over the pixel grid) and reused for every capture.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lfcam.errors import CalibrationError


@dataclass(frozen=True)
class LensletMap:
    """Pixel → lenslet assignment for one sensor size and one set of micro-image centres."""

    centres_px: np.ndarray  # (N, 2) x, y
    labels: np.ndarray  # (H, W) int32, −1 = unassigned
    radius_px: float

    @property
    def count(self) -> int:
        """Number of lenslets."""
        return int(self.centres_px.shape[0])


def build_lenslet_map(
    centres_px: np.ndarray, shape: tuple[int, int], radius_px: float
) -> LensletMap:
    """Assign every pixel of an ``(H, W)`` sensor to its nearest micro-image centre.

    Raises
    ------
    CalibrationError
        If there are no centres or the radius is not positive.
    """
    centres = np.asarray(centres_px, dtype=np.float64).reshape(-1, 2)
    if centres.shape[0] == 0:
        raise CalibrationError("no micro-image centres in the calibration")
    if not radius_px > 0:
        raise CalibrationError(f"micro-image radius must be positive, got {radius_px}")
    h, w = shape
    tree = cKDTree(centres)
    labels = np.full(h * w, -1, dtype=np.int32)
    cols = np.arange(w, dtype=np.float64)
    rows_per_chunk = max(1, 1_000_000 // w)
    for r0 in range(0, h, rows_per_chunk):
        r1 = min(h, r0 + rows_per_chunk)
        yy, xx = np.meshgrid(np.arange(r0, r1, dtype=np.float64), cols, indexing="ij")
        dist, idx = tree.query(np.column_stack([xx.ravel(), yy.ravel()]),
                               distance_upper_bound=radius_px)
        chunk = np.where(np.isfinite(dist), idx, -1).astype(np.int32)
        labels[r0 * w : r1 * w] = chunk
    return LensletMap(centres, labels.reshape(h, w), float(radius_px))


@dataclass(frozen=True)
class LensletStats:
    """Energy and intensity centroid of each micro-image of one capture."""

    energy: np.ndarray  # (N,) summed signal
    centroid_px: np.ndarray  # (N, 2) x, y; NaN where the energy is not positive
    pixels: np.ndarray  # (N,) number of pixels assigned


def lenslet_stats(image: np.ndarray, lmap: LensletMap) -> LensletStats:
    """Sum and first moments of ``image`` over each lenslet's pixels (vectorised bincount).

    Parameters
    ----------
    image : (H, W) array
        Linear signal, black level already removed (negative values allowed: noise).
    lmap : LensletMap

    Returns
    -------
    LensletStats
        Energy and intensity centroid of every lenslet.

    Raises
    ------
    CalibrationError
        The image and the lenslet map differ in size.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.shape != lmap.labels.shape:
        raise CalibrationError(
            f"capture is {img.shape[1]}×{img.shape[0]} px but the calibration is for "
            f"{lmap.labels.shape[1]}×{lmap.labels.shape[0]} px"
        )
    lab = lmap.labels.ravel()
    keep = lab >= 0
    lab = lab[keep]
    val = img.ravel()[keep]
    h, w = img.shape
    yy, xx = np.divmod(np.flatnonzero(keep), w)
    n = lmap.count
    energy = np.bincount(lab, weights=val, minlength=n)
    mx = np.bincount(lab, weights=val * xx, minlength=n)
    my = np.bincount(lab, weights=val * yy, minlength=n)
    pixels = np.bincount(lab, minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        centroid = np.column_stack([mx / energy, my / energy])
    centroid[~(energy > 0)] = np.nan
    return LensletStats(energy, centroid, pixels)
