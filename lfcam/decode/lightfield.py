"""Decode a raw plenoptic 1.0 capture into a 4-D light field ``L[v, u, t, s]``.

Indexing (see ``docs/decoding.md``):

* ``s`` (column) and ``t`` (row) are spatial: one sample per microlens, on a rectangular grid
  (hex grids are resampled, see below). Sample spacing in sensor pixels is
  ``LightField.spacing_px`` = (pitch, pitch) for rect, (pitch, pitch·√3/2) for hex.
* ``u`` (column) and ``v`` (row) are angular: the sample of view ``(v, u)`` sits at
  ``centre + R(θ)·(u − uc, v − vc)`` pixels from its lens centre (``uc = vc = (n − 1)/2``), i.e.
  one sensor pixel per angular step, along the lattice axes.

Every sample is read at its sub-pixel position with bilinear interpolation (``cv2.remap``),
one view at a time (the raw is the only full-size buffer). Devignetting divides by the white
image resampled at the same positions; ``weight`` is the white image's relative value there
(1 without a white image), and 0 where it is below ``white_threshold``, where the sample leaves
the raw, and for views outside the lens disk (radius pitch/2 − ½ px: they would see the
neighbouring micro-image; those views are skipped entirely).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from lfcam.calibrate.model import Calibration
from lfcam.errors import InputFileError
from lfcam.io.grey import to_grey  # noqa: F401 - part of the decode API

MAX_VIEWS = 64
MAX_SAMPLES = 400_000_000  # nv·nu·T·S: ~1.6 GB per float32 array


@dataclass(frozen=True)
class LightField:
    """A decoded light field.

    Attributes
    ----------
    data : numpy.ndarray
        float32 ``(nv, nu, T, S)``: devignetted radiance (white-normalised when a white image
        was given, else black/white-level normalised raw), 0 where ``weight`` is 0.
    weight : numpy.ndarray
        float32 ``(nv, nu, T, S)`` in [0, 1]: relative vignetting; 0 = invalid sample.
    grid : Calibration
        The microlens calibration it was decoded with.
    spacing_px : tuple of float
        (x, y) sensor-pixel distance between neighbouring spatial samples (s, t).
    first_t, first_s : int
        Lattice index of spatial sample (0, 0).
    """

    data: np.ndarray
    weight: np.ndarray
    grid: Calibration
    spacing_px: tuple[float, float]
    first_t: int = 0
    first_s: int = 0

    @property
    def n_views(self) -> tuple[int, int]:
        """(nv, nu)."""
        return int(self.data.shape[0]), int(self.data.shape[1])

    @property
    def angular_centre(self) -> tuple[float, float]:
        """(vc, uc): the angular index of the micro-image centre."""
        nv, nu = self.n_views
        return 0.5 * (nv - 1), 0.5 * (nu - 1)


def default_n_views(pitch_px: float) -> int:
    """Odd number of one-pixel angular samples spanning a micro-image: 2·⌊pitch/2⌋ + 1.

    Parameters
    ----------
    pitch_px : float
        Micro-image pitch.

    Returns
    -------
    int
    """
    return 2 * int(math.floor(pitch_px / 2.0)) + 1


def decode(raw: np.ndarray, grid: Calibration, white: np.ndarray | None = None,
           n_views: int | None = None, hex_to_rect: bool = True,
           white_threshold: float = 0.1) -> LightField:
    """Decode a (grey, level-normalised) raw into a light field.

    Parameters
    ----------
    raw : 2-D float array
        Linear sensor image (see :func:`to_grey` for Bayer / levels).
    grid : Calibration
        Microlens grid: every lens on the sensor sits at its measured centre, else where the
        calibration's fitted lattice model puts it (:meth:`Calibration.lens_centres`).
    white : 2-D array, optional
        White (flat-field) image of the same size, already linear (see :func:`to_grey`).
    n_views : int, optional
        Angular samples per axis (odd recommended); default :func:`default_n_views`.
    hex_to_rect : bool
        For hex grids, shift odd lens rows by half a pitch (linear interpolation along the row)
        so every spatial sample of a column is at the same x.
    white_threshold : float
        Samples whose white value is below this fraction of the white image's maximum are
        invalid (weight 0).

    Returns
    -------
    LightField
    """
    raw = np.asarray(raw)
    if raw.ndim != 2:
        raise InputFileError(f"raw image must be 2-D, got shape {raw.shape}")
    raw32 = np.ascontiguousarray(raw, dtype=np.float32)
    h, w = raw32.shape
    n = default_n_views(grid.pitch_px) if n_views is None else int(n_views)
    if not 1 <= n <= MAX_VIEWS:
        raise InputFileError(f"n_views must be in [1, {MAX_VIEWS}], got {n}")
    if white is not None:
        white = np.asarray(white)
        if white.shape != raw32.shape:
            raise InputFileError(f"white image {white.shape} and raw {raw32.shape} differ in size")
        white32 = np.ascontiguousarray(white, dtype=np.float32)
        wmax = float(np.max(white32))
        if not math.isfinite(wmax) or wmax <= 0 or not np.all(np.isfinite(white32)):
            raise InputFileError("white image is black or not finite")
    grid.check_image((h, w))
    lens = grid.lens_centres((h, w))
    t_count, s_count = lens.x.shape
    if n * n * t_count * s_count > MAX_SAMPLES:
        raise InputFileError(
            f"light field of {n}×{n}×{t_count}×{s_count} samples exceeds {MAX_SAMPLES}"
        )
    cx = lens.x.astype(np.float32)
    cy = lens.y.astype(np.float32)
    cos_r, sin_r = math.cos(grid.rotation_rad), math.sin(grid.rotation_rad)
    centre = 0.5 * (n - 1)
    radius = 0.5 * grid.pitch_px - 0.5
    data = np.zeros((n, n, t_count, s_count), np.float32)
    weight = np.zeros_like(data)
    odd_rows = None
    if grid.grid == "hex" and hex_to_rect:
        odd_rows = np.flatnonzero((np.arange(t_count) + lens.first_t) % 2 == 1)
    inv_wmax = np.float32(1.0 / wmax) if white is not None else None
    for v in range(n):
        for u in range(n):
            du, dv = u - centre, v - centre
            if math.hypot(du, dv) > radius:
                continue  # outside the lens disk: it sees the neighbour's micro-image
            map_x = cx + np.float32(cos_r * du - sin_r * dv)
            map_y = cy + np.float32(sin_r * du + cos_r * dv)
            wt = ((map_x >= 0) & (map_x <= w - 1) & (map_y >= 0) & (map_y <= h - 1)).view(np.uint8)
            wt = wt.astype(np.float32)
            val = cv2.remap(raw32, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            if white is None:
                np.multiply(val, wt, out=data[v, u])
            else:
                wv = cv2.remap(white32, map_x, map_y, cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_REPLICATE)
                _, rel = cv2.threshold(wv * inv_wmax, white_threshold, 0, cv2.THRESH_TOZERO)
                np.minimum(rel, 1.0, out=rel)
                wt *= rel
                np.divide(val, wv, out=data[v, u], where=wt > 0)
            weight[v, u] = wt
            if odd_rows is not None and odd_rows.size:
                _hex_rows_to_rect(data[v, u], weight[v, u], odd_rows)
    spacing = (float(grid.pitch_px), float(grid.row_spacing_px))
    return LightField(data=data, weight=weight, grid=grid, spacing_px=spacing,
                      first_t=lens.first_t, first_s=lens.first_s)


def _hex_rows_to_rect(data: np.ndarray, weight: np.ndarray, odd: np.ndarray) -> None:
    """In place, one view (T, S): resample odd lattice rows onto the even rows' columns.

    Odd row sample ``s`` sits at x = (s + ½)·pitch; the rect value at x = s·pitch is the
    weighted mean of odd samples ``s − 1`` and ``s`` (linear interpolation, weights carried).
    """
    wt = weight[odd]
    d = data[odd] * wt
    d_new = 0.5 * d
    w_new = 0.5 * wt
    d_new[:, 1:] += 0.5 * d[:, :-1]
    w_new[:, 1:] += 0.5 * wt[:, :-1]
    w_new[:, 0] = 0.0  # no left neighbour: the first rect sample of an odd row is unknown
    good = w_new > 0
    data[odd] = np.where(good, d_new / np.where(good, w_new, 1.0), 0.0)
    weight[odd] = w_new

