"""Ray sampling shared by the measurement's forward models: the pupil sample, the sensor's
pixel binning and the share of a ray across a lenslet cell's border.

:func:`vogel_disc` is the quasi-random pupil sample of both the image model
(:mod:`lfcam.measure.pointfit`) and the lenslet model (:mod:`lfcam.measure.fastfit`);
:func:`pixel_boxes` bins rays into pixels as a sensor integrates them, each ray a small box so
that a model stays continuous in the source position; :func:`ray_share` shares a ray between
the two lenslet cells it lies between, for the same reason. :func:`segment_points` samples a
line source as equally bright points (the lenslet, pixel and light models of a line).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


@lru_cache(maxsize=64)
def vogel_disc(n: int, phase: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` quasi-random points of the unit disc, equal area each (Vogel's sunflower spiral),
    turned by ``phase`` radians. Cached (every model of every region draws the same few
    samples); the arrays are read-only."""
    i = np.arange(n, dtype=np.float64)
    r = np.sqrt((i + 0.5) / n)
    t = i * GOLDEN_ANGLE + phase
    x, y = r * np.cos(t), r * np.sin(t)
    # in the spiral's order, successive points lie on opposite sides of the disc, and so do
    # their rays' landings on the MLA and sensor: every deposit then misses the cache on a
    # large blur. Ordered along rows of the disc instead (bands about √n points long, the
    # direction alternating), successive rays land side by side
    bands = max(1, int(round(math.sqrt(n) / 2.0)))
    band = np.minimum(((y + 1.0) * 0.5 * bands).astype(np.int64), bands - 1)
    # (one key, the band and the signed x in (−1, 1) inside it: the order of a lexsort on
    # the two, in half its time — a sample is drawn for each model of each region)
    order = np.argsort(4.0 * band + np.where(band % 2 == 0, x, -x), kind="stable")
    x, y = x[order], y[order]
    x.flags.writeable = False
    y.flags.writeable = False
    return x, y


def pixel_boxes(px: np.ndarray, py: np.ndarray, w: np.ndarray, s: float,
                 with_source: bool = False):
    """Bin rays at sensor positions (px, py) into pixels, each ray a box ``s`` px wide:
    (cols, rows, weights[, index of the ray each share came from]); ``s → 0`` is
    nearest-pixel binning (the sensor's integration)."""
    cx, cy = np.floor(px + 0.5), np.floor(py + 0.5)
    tx, ty = px - cx, py - cy  # offset from the pixel centre, [−0.5, 0.5)
    ex = np.clip((np.abs(tx) + 0.5 * s - 0.5) / s, 0.0, 0.5)  # share beyond the near edge
    ey = np.clip((np.abs(ty) + 0.5 * s - 0.5) / s, 0.0, 0.5)
    nx = cx + np.sign(tx)
    ny = cy + np.sign(ty)
    sx, sy = ex > 0, ey > 0
    sxy = sx & sy
    cols = np.concatenate([cx, nx[sx], cx[sy], nx[sxy]]).astype(np.int64)
    rows = np.concatenate([cy, cy[sx], ny[sy], ny[sxy]]).astype(np.int64)
    wts = np.concatenate([w * (1 - ex) * (1 - ey), (w * ex * (1 - ey))[sx],
                          (w * (1 - ex) * ey)[sy], (w * ex * ey)[sxy]])
    if not with_source:
        return cols, rows, wts
    src = np.concatenate([np.arange(px.size), np.flatnonzero(sx), np.flatnonzero(sy),
                          np.flatnonzero(sxy)])
    return cols, rows, wts, src


# A ray's share across a cell border as a combination of two boxes, the ray's spacing g and
# 2g wide: 4/3 × the first's share − 1/3 × the second's. Each box alone shares as a
# convolution of the MLA light with it would, which widens every footprint by the box's
# variance (g²/12 a direction) and biased the fine line model's distance by −0.38 % far
# behind focus; the combination's variance is 4/3 · g²/12 − 1/3 · 4g²/12 = 0 (docs/distance.md,
# "Ray shares without the box's variance (stop 53)").
RICHARDSON_ONE = 4.0 / 3.0
RICHARDSON_TWO = 1.0 / 3.0


def ray_share(gap: np.ndarray, spacing: np.ndarray | float,
              richardson: bool = True) -> np.ndarray:
    """A ray's share in the neighbour across the nearest cell border at distance ``gap``
    (MLA mm), the rays ``spacing`` apart there: the box's ``clip(0.5 − gap/spacing, 0, 0.5)``,
    or with ``richardson`` the two boxes' combination with no second moment (negative from
    ``spacing/2`` to ``spacing``, where the ray gives the neighbour back part of its light).
    The numpy form of :func:`lfcam.measure.kernels._block_cells`' rule (the same
    arithmetic)."""
    one = np.clip(0.5 - gap / spacing, 0.0, 0.5)
    if not richardson:
        return one
    two = np.clip(0.5 - 0.5 * gap / spacing, 0.0, 0.5)
    return RICHARDSON_ONE * one - RICHARDSON_TWO * two


def segment_points(a: np.ndarray, b: np.ndarray, count: int) -> np.ndarray:
    """(count, len(a)) the middles of ``count`` equal parts of the segment ``a`` → ``b``: a
    line source's equally bright points."""
    t = (np.arange(count) + 0.5) / count
    return a[None, :] + t[:, None] * (b - a)[None, :]
