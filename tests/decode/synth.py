"""Test-only light-field → raw encoder, written independently of ``lfcam.decode``.

Each sensor pixel belongs to its nearest lens centre (k-d tree, no lattice inversion); its
value is ``f(du, dv, s, t)`` with ``(du, dv)`` its offset from that centre in the lattice's
(rotated) axes, in pixels, and ``(s, t)`` the lens's lattice coordinates in lenslets (rect
coordinates: for hex rows, ``s`` carries the half-pitch shift of odd rows and ``t`` is in
units of the row spacing times √3/2, i.e. in lenslets too).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree


def lattice(grid, pitch, rot, off, rows, cols):
    """Lens centres (x, y) and their lattice position (s, t) in lenslets, explicit formula."""
    t, s = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    s_pos = s + (0.5 * (t % 2) if grid == "hex" else 0.0)
    t_pos = t * (math.sqrt(3) / 2 if grid == "hex" else 1.0)
    a, b = s_pos * pitch, t_pos * pitch
    x = off[0] + math.cos(rot) * a - math.sin(rot) * b
    y = off[1] + math.sin(rot) * a + math.cos(rot) * b
    return x.ravel(), y.ravel(), s_pos.ravel(), t_pos.ravel()


def encode(f, shape, cx, cy, s_pos, t_pos, rot, radius):
    """Raw image of ``shape``: pixel = f(du, dv, s, t) of its nearest lens, 0 beyond ``radius``."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    pts = np.column_stack([xx.ravel(), yy.ravel()]).astype(np.float64)
    _, idx = cKDTree(np.column_stack([cx, cy])).query(pts)
    dx, dy = pts[:, 0] - cx[idx], pts[:, 1] - cy[idx]
    du = math.cos(rot) * dx + math.sin(rot) * dy
    dv = -math.sin(rot) * dx + math.cos(rot) * dy
    val = f(du, dv, s_pos[idx], t_pos[idx])
    val = np.where(np.hypot(du, dv) <= radius, val, 0.0)
    return val.reshape(h, w)
