"""Compiled inner loops of the measurement (``numba``; compiled once, cached on disk).

Two loops that numpy can only express as chains of frame- or ray-sized temporaries:

* :func:`lenslet_sums`: each lenslet's pixel count, sum and first moments over a label map
  (:func:`lfcam.measure.lenslets.lenslet_stats`): one pass over the frame instead of four
  ``bincount`` and two weighted copies of it (41 Mpx: 1.6 s → 0.1 s).
* :func:`deposit_moments`: the lenslet fit's rays to per-lenslet moments.
  :class:`lfcam.measure.fastfit.LensletModel` traces a point (or line) source's rays through
  the main lens to the MLA plane; each ray then

  1. is shared between the lattice cell it hits and the neighbour across the nearest cell
     border, linearly over the ray's own spacing at the MLA (``share = clip(0.5 −
     gap/spacing, 0, 0.5)``),
  2. lands on the sensor at each cell's centre plus ``f_x`` times its slope,
  3. is spread as a box ``s`` px wide over the pixels it straddles (bilinear shares), and
  4. adds its weight and weighted offsets to the four moments of the lenslet whose
     micro-image holds each pixel: ``Σw``, ``Σw·dx``, ``Σw·dy``, ``Σw·(dx² + dy²)`` with
     ``(dx, dy)`` the pixel centre's offset from the micro-image centre in pitches.

  With numpy this cost ~75 % of a model evaluation. The numpy chain stays in
  :mod:`lfcam.measure.fastfit` as the reference the tests compare this kernel with
  (``tests/test_speed_paths.py``); both give the same sums up to their order.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _nearest_two(ex, ey, inv, b, rect, la, lb):
    """Lattice indices of the nearest and second-nearest node of the point ``(ex, ey)``
    (relative to the lattice origin) and the point's distance to their bisector — the same
    rules and tie-breaking as ``fastfit._two_cells``."""
    u0 = inv[0, 0] * ex + inv[0, 1] * ey
    u1 = inv[1, 0] * ex + inv[1, 1] * ey
    if rect:
        i = np.rint(u0)
        j = np.rint(u1)
        fu = u0 - i
        fv = u1 - j
        gu = (0.5 - abs(fu)) * la
        gv = (0.5 - abs(fv)) * lb
        if gu <= gv:
            return i, j, i + np.sign(fu), j, gu
        return i, j, i, j + np.sign(fv), gv
    fu = math.floor(u0)
    fv = math.floor(u1)
    ru = u0 - fu
    rv = u1 - fv
    best1 = np.inf
    best2 = np.inf
    k1 = 0
    k2 = 0
    for k in range(4):
        di = float(k & 1)
        dj = float(k >> 1)
        gx = b[0, 0] * (ru - di) + b[0, 1] * (rv - dj)
        gy = b[1, 0] * (ru - di) + b[1, 1] * (rv - dj)
        d2 = gx * gx + gy * gy
        if d2 < best1:
            best2, k2 = best1, k1
            best1, k1 = d2, k
        elif d2 < best2:
            best2, k2 = d2, k
    i = fu + float(k1 & 1)
    j = fv + float(k1 >> 1)
    i2 = fu + float(k2 & 1)
    j2 = fv + float(k2 >> 1)
    di = i2 - i
    dj = j2 - j
    sep = math.hypot(b[0, 0] * di + b[0, 1] * dj, b[1, 0] * di + b[1, 1] * dj)
    return i, j, i2, j2, (best2 - best1) / (2.0 * sep)


@njit(cache=True, nogil=True, inline="always")
def _pixel(out, labels, centres_px, inv_pitch, x0, y0, base, col, row, w):
    """Add a pixel share ``w`` at (col, row) of the box to its lenslet's moments."""
    h, wd = labels.shape
    if col < 0 or col >= wd or row < 0 or row >= h:
        return
    k = labels[row, col]
    if k < 0:
        return
    dx = (col + x0 - centres_px[k, 0]) * inv_pitch
    dy = (row + y0 - centres_px[k, 1]) * inv_pitch
    n = base + k
    out[n, 0] += w
    out[n, 1] += w * dx
    out[n, 2] += w * dy
    out[n, 3] += w * (dx * dx + dy * dy)


@njit(cache=True, nogil=True, inline="always")
def _land(out, labels, centres_px, inv_pitch, x0, y0, base, px, py, w, s, inv_s):
    """Spread weight ``w`` landing at box coordinates (px, py) as an ``s`` px box."""
    cx = math.floor(px + 0.5)
    cy = math.floor(py + 0.5)
    tx = px - cx
    ty = py - cy
    ex = min(max((abs(tx) + 0.5 * s - 0.5) * inv_s, 0.0), 0.5)
    ey = min(max((abs(ty) + 0.5 * s - 0.5) * inv_s, 0.0), 0.5)
    nx = cx + np.sign(tx)
    ny = cy + np.sign(ty)
    ic, ir, inx, iny = int(cx), int(cy), int(nx), int(ny)
    _pixel(out, labels, centres_px, inv_pitch, x0, y0, base, ic, ir, w * (1 - ex) * (1 - ey))
    if ex > 0:
        _pixel(out, labels, centres_px, inv_pitch, x0, y0, base, inx, ir, w * ex * (1 - ey))
    if ey > 0:
        _pixel(out, labels, centres_px, inv_pitch, x0, y0, base, ic, iny, w * (1 - ex) * ey)
    if ex > 0 and ey > 0:
        _pixel(out, labels, centres_px, inv_pitch, x0, y0, base, inx, iny, w * ex * ey)


@njit(cache=True, nogil=True)
def deposit_moments(x, y, sx, sy, wt, spacing, tag, groups, origin, basis, inverse, rect,
                    la, lb, pp, ax, ay, x0, y0, s_px, labels, centres_px, pitch_px):
    """Moments ``(groups·K, 4)`` of rays hitting the MLA at ``(x, y)`` mm with sensor offsets
    ``(sx, sy)`` mm (``f_x`` × slope), weights ``wt``, MLA-plane spacing ``spacing`` and
    group ``tag`` (module docstring). ``labels`` is the region box's compact lenslet map
    (−1 none), ``(x0, y0)`` the box's corner, ``(ax, ay)`` the sensor axis (px), ``pp`` the
    pixel pitch (mm)."""
    n_k = centres_px.shape[0]
    out = np.zeros((groups * n_k, 4))
    inv_pitch = 1.0 / pitch_px
    inv_pp = 1.0 / pp
    inv_s = 1.0 / s_px
    for r in range(x.size):
        i, j, i2, j2, gap = _nearest_two(x[r] - origin[0], y[r] - origin[1], inverse, basis,
                                         rect, la, lb)
        share = min(max(0.5 - gap / spacing[r], 0.0), 0.5)
        base = tag[r] * n_k
        c1x = origin[0] + basis[0, 0] * i + basis[0, 1] * j
        c1y = origin[1] + basis[1, 0] * i + basis[1, 1] * j
        _land(out, labels, centres_px, inv_pitch, x0, y0, base,
              (c1x + sx[r]) * inv_pp + ax - x0, (c1y + sy[r]) * inv_pp + ay - y0,
              wt[r] * (1.0 - share), s_px, inv_s)
        if share > 0:
            c2x = origin[0] + basis[0, 0] * i2 + basis[0, 1] * j2
            c2y = origin[1] + basis[1, 0] * i2 + basis[1, 1] * j2
            _land(out, labels, centres_px, inv_pitch, x0, y0, base,
                  (c2x + sx[r]) * inv_pp + ax - x0, (c2y + sy[r]) * inv_pp + ay - y0,
                  wt[r] * share, s_px, inv_s)
    return out


def warm_up() -> None:
    """Load (or compile, the first time on a machine) the kernel with the argument types
    :class:`~lfcam.measure.fastfit.LensletModel` passes, so that a region worker pays for it
    while the parent is still busy with the geometry."""
    one = np.zeros(1)
    eye = np.eye(2)
    deposit_moments(one, one, one, one, one, np.ones(1), np.zeros(1, dtype=np.int64), 1,
                    np.zeros(2), eye, eye, True, 1.0, 1.0, 1.0, 0.0, 0.0, 0, 0, 0.5,
                    np.zeros((1, 1), dtype=np.int64), np.zeros((1, 2)), 1.0)


@njit(cache=True, nogil=True)
def lenslet_sums(labels, image, n):
    """Per lenslet ``0 … n−1``: pixel count, Σv, Σv·x, Σv·y over the pixels ``labels``
    assigns to it (−1: none), in the order of a row-major pass (as ``np.bincount``)."""
    pixels = np.zeros(n, dtype=np.int64)
    energy = np.zeros(n)
    mx = np.zeros(n)
    my = np.zeros(n)
    h, w = labels.shape
    for row in range(h):
        for col in range(w):
            k = labels[row, col]
            if k < 0:
                continue
            v = image[row, col]
            pixels[k] += 1
            energy[k] += v
            mx[k] += v * col
            my[k] += v * row
    return pixels, energy, mx, my


@njit(cache=True, nogil=True)
def stamp_labels(labels, centres, ids, ox, oy, r2, band):
    """:func:`lfcam.measure.lenslets.build_lenslet_map`'s stamping in one compiled pass: every
    centre ``ids[i]`` (in that order) claims the pixels of its disc (stencil offsets ``ox, oy``
    from its rounded position, squared radius ``r2``) that no earlier centre holds nearer; a tie
    goes to the later centre. Bands of ``band`` rows bound the distance buffer."""
    h, w = labels.shape
    cy_sorted = centres[ids, 1]
    reach = 0
    for j in range(ox.size):
        reach = max(reach, abs(ox[j]), abs(oy[j]))
    best = np.empty(band * w)
    for r0 in range(0, h, band):
        r1 = min(h, r0 + band)
        lo = np.searchsorted(cy_sorted, r0 - reach, side="left")
        hi = np.searchsorted(cy_sorted, r1 - 1 + reach, side="right")
        best[:] = np.inf
        for i in range(lo, hi):
            k = ids[i]
            cx = centres[k, 0]
            cy = centres[k, 1]
            bx = np.rint(cx)
            by = np.rint(cy)
            fx = bx - cx
            fy = by - cy
            ibx = int(bx)
            iby = int(by)
            for j in range(ox.size):
                py = iby + oy[j]
                px = ibx + ox[j]
                if py < r0 or py >= r1 or px < 0 or px >= w:
                    continue
                d2 = (ox[j] + fx) ** 2 + (oy[j] + fy) ** 2
                if d2 > r2:
                    continue
                at = (py - r0) * w + px
                if d2 <= best[at]:
                    best[at] = d2
                    labels[py, px] = k
