"""Compiled inner loops of the measurement (``numba``; compiled once, cached on disk).

Loops that numpy can only express as chains of frame- or ray-sized temporaries:

* :func:`lenslet_sums`: each lenslet's pixel count, sum and first moments over a label map
  (:func:`lfcam.measure.lenslets.lenslet_stats`): one pass over the frame instead of four
  ``bincount`` and two weighted copies of it (41 Mpx: 1.6 s → 0.1 s).
* :func:`box_moments`: a region's data moments and their noise sums in one pass over its
  box (numpy: ``nonzero``, fancy indexing and four ``bincount``; Illum-size blurs 10 → 2 ms),
  read in place with the other regions' lenslets dropped in the pass.
* :func:`trace_model_rays`: the lenslet fit's rays from point sources through the main lens
  (any :class:`~lfcam.optics.lens.Prescription`: conics, flats, ideal surfaces) to the MLA
  plane, with the rules and arithmetic of :func:`lfcam.optics.raytrace.trace_components`.
  Each surface is one loop over the rays with no branch on the ray (a failed ray only clears
  its flag), so the compiler runs it in SIMD lanes: 10–14 ns a ray against numpy's 70–100
  (singlet; benchmarks/speed_kernels.py).
* :func:`deposit_moments`: the lenslet fit's rays to per-lenslet moments.
  :class:`lfcam.measure.fastfit.LensletModel` traces a point (or line) source's rays through
  the main lens to the MLA plane; each ray then

  1. is shared between the lattice cell it hits and the neighbour across the nearest cell
     border: linearly over the ray's own spacing at the MLA (``share = clip(0.5 −
     gap/spacing, 0, 0.5)``, a box), or, for the ray-sampled models, by the two boxes'
     combination whose second moment is zero (``richardson``:
     :func:`lfcam.measure.sampling.ray_share`),
  2. lands on the sensor at each cell's centre plus ``f_x`` times its slope,
  3. is spread as a box ``s`` px wide over the pixels it straddles (bilinear shares), and
  4. adds its weight and weighted offsets to the four moments of the lenslet whose
     micro-image holds each pixel: ``Σw``, ``Σw·dx``, ``Σw·dy``, ``Σw·(dx² + dy²)`` with
     ``(dx, dy)`` the pixel centre's offset from the micro-image centre in pitches.

  With numpy this cost ~75 % of a model evaluation. Steps 1–3 run a block of rays at a time
  in SIMD lanes, step 4 after them in the rays' order (docs/distance.md, "The deposit's
  arithmetic in SIMD lanes (stop 52)").
* :func:`trace_deposit_moments`: the two above in one pass a point, the ray models' path:
  a point's rays are deposited while they are still in cache, the same sums bit for bit
  (docs/distance.md, "The trace and the deposit in one pass (stop 59)").
* :func:`cell_samples`, :func:`cell_centres`, :func:`deposit_cells`: a point's pupil samples
  fixed on the lenslet cells (n × n a cell), and on a rectangular lattice the cells it lights
  whole, integrated by a 2 × 2 Gauss rule and landed as their cell's linear image on the
  sensor (docs/distance.md, "Samples fixed on the lenslet cells", "Cells integrated whole
  (stop 43)").

The numpy chains stay (:mod:`lfcam.optics.raytrace`, :mod:`lfcam.measure.fastfit` with
``kernel="numpy"``) as the references the tests compare these kernels with
(``tests/test_speed_paths.py``): the same sums up to their order and rounding (1e-12).
"""

from __future__ import annotations

import ctypes
import math
import os

import numpy as np
from numba import njit

from lfcam.measure.sampling import RICHARDSON_ONE, RICHARDSON_TWO


@njit(cache=True, nogil=True, inline="always")
def _nearest_two(ex, ey, inv, b, rect, la, lb, seps):
    """Lattice indices of the nearest and second-nearest node of the point ``(ex, ey)``
    (relative to the lattice origin) and the point's distance to their bisector — the same
    rules and tie-breaking as ``fastfit._two_cells``. ``seps[di + 1, dj + 1]``: the length of
    the lattice vector ``(di, dj)`` (:func:`_separations`)."""
    if rect:
        return _nearest_two_rect(ex, ey, inv[0, 0], inv[0, 1], inv[1, 0], inv[1, 1], la, lb)
    return _nearest_two_hex(ex, ey, inv[0, 0], inv[0, 1], inv[1, 0], inv[1, 1], b[0, 0],
                            b[0, 1], b[1, 0], b[1, 1], seps[2, 1], seps[1, 2], seps[2, 2],
                            seps[2, 0])


# The two lattices' rules below are arithmetic on floats with no branch and no table lookup
# that depends on the point (comparisons become 0/1 factors, integer corner codes are small
# whole floats), on scalars (no array the compiler must reload after each store): inlined
# into a loop over a block of rays they run in SIMD lanes (deposit_moments' first pass).
@njit(cache=True, nogil=True, inline="always")
def _nearest_two_rect(ex, ey, i00, i01, i10, i11, la, lb):
    """:func:`_nearest_two` on a rectangular lattice (``i··``: the inverse basis; cell sides
    ``la``, ``lb``)."""
    u0 = i00 * ex + i01 * ey
    u1 = i10 * ex + i11 * ey
    i = np.rint(u0)
    j = np.rint(u1)
    fu = u0 - i
    fv = u1 - j
    gu = (0.5 - abs(fu)) * la
    gv = (0.5 - abs(fv)) * lb
    # across u or across v, as arithmetic rather than a branch (a coin toss a ray)
    across_u = 1.0 if gu <= gv else 0.0
    su = (1.0 if fu > 0.0 else 0.0) - (1.0 if fu < 0.0 else 0.0)  # np.sign
    sv = (1.0 if fv > 0.0 else 0.0) - (1.0 if fv < 0.0 else 0.0)
    return i, j, i + across_u * su, j + (1.0 - across_u) * sv, min(gu, gv)


@njit(cache=True, nogil=True, inline="always")
def _nearest_two_hex(ex, ey, i00, i01, i10, i11, b00, b01, b10, b11, len_10, len_01, len_11,
                     len_1m1):
    """:func:`_nearest_two` on any other lattice: the two nearest of the four corners of the
    lattice cell that holds the point (``i··``: the inverse basis, ``b··`` the basis,
    ``len_…``: the lengths of the lattice vectors (1, 0), (0, 1), (1, 1), (1, −1))."""
    u0 = i00 * ex + i01 * ey
    u1 = i10 * ex + i11 * ey
    fu = np.floor(u0)
    fv = np.floor(u1)
    ru = u0 - fu
    rv = u1 - fv
    # squared distances to the cell's corners (0, 0), (1, 0), (0, 1), (1, 1): corner code
    # k = du + 2·dv
    gx0 = b00 * ru + b01 * rv
    gy0 = b10 * ru + b11 * rv
    gx1 = gx0 - b00
    gy1 = gy0 - b10
    gx2 = gx0 - b01
    gy2 = gy0 - b11
    gx3 = gx1 - b01
    gy3 = gy1 - b11
    d0 = gx0 * gx0 + gy0 * gy0
    d1 = gx1 * gx1 + gy1 * gy1
    d2 = gx2 * gx2 + gy2 * gy2
    d3 = gx3 * gx3 + gy3 * gy3
    # The two smallest, ties to the lower corner code (as argmin), by min/max and 0/1
    # factors, not branches: which corner is nearest is a coin toss from ray to ray, and the
    # mispredicted branches of a sorting loop cost ~15 ns a ray (the deposit of scene b's
    # blurs 83 → 68 ns a ray; docs/distance.md, "Speed at stop 33").
    c01 = 1.0 if d1 < d0 else 0.0  # pair (0, 1) sorted, then pair (2, 3)
    c23 = 1.0 if d3 < d2 else 0.0
    a_lo, a_hi, ka_lo, ka_hi = min(d0, d1), max(d0, d1), c01, 1.0 - c01
    b_lo, b_hi, kb_lo, kb_hi = min(d2, d3), max(d2, d3), 2.0 + c23, 3.0 - c23
    fb = 1.0 if b_lo < a_lo else 0.0  # the nearest is in the second pair
    best1 = min(a_lo, b_lo)
    k1 = ka_lo + fb * (kb_lo - ka_lo)
    # the second: the other pair's lower or the winning pair's higher (ties: lower code)
    c_lo = max(a_lo, b_lo)
    kc_lo = kb_lo + fb * (ka_lo - kb_lo)
    c_hi = a_hi * (1.0 - fb) + b_hi * fb  # exact: one term is × 0, the other × 1
    kc_hi = ka_hi + fb * (kb_hi - ka_hi)
    s2 = 1.0 if (c_hi < c_lo) | ((c_hi == c_lo) & (fb == 0.0)) else 0.0
    best2 = min(c_lo, c_hi)
    k2 = kc_lo + s2 * (kc_hi - kc_lo)
    h1 = np.floor(0.5 * k1)  # the codes' dv; their du is k − 2·dv
    h2 = np.floor(0.5 * k2)
    di = (k2 - 2.0 * h2) - (k1 - 2.0 * h1)
    dj = h2 - h1
    # |(di, dj)| from the four lengths (a vector and its negative are as long), not a lookup
    # by (di, dj)
    sep = len_01 if di == 0.0 else len_10 if dj == 0.0 else len_11 if di == dj else len_1m1
    i = fu + (k1 - 2.0 * h1)
    j = fv + h1
    return i, j, i + di, j + dj, (best2 - best1) / (2.0 * sep)


@njit(cache=True, nogil=True)
def _separations(b):
    """Lengths of the lattice vectors ``(di, dj)``, ``di, dj ∈ {−1, 0, 1}`` (two corners of a
    lattice cell), as ``[di + 1, dj + 1]``: looked up rather than recomputed for every ray."""
    seps = np.empty((3, 3))
    for a in range(3):
        for c in range(3):
            di = float(a - 1)
            dj = float(c - 1)
            seps[a, c] = math.hypot(b[0, 0] * di + b[0, 1] * dj, b[1, 0] * di + b[1, 1] * dj)
    return seps


@njit(cache=True, nogil=True, inline="always")
def _add_pixel(out, n, k, centres_px, inv_pitch, x0, y0, col, row, w):
    """Add a pixel share ``w`` at (col, row) of the box to row ``n`` of the moments, its
    offsets about lenslet ``k``'s centre."""
    dx = (col + x0 - centres_px[k, 0]) * inv_pitch
    dy = (row + y0 - centres_px[k, 1]) * inv_pitch
    out[n, 0] += w
    out[n, 1] += w * dx
    out[n, 2] += w * dy
    out[n, 3] += w * (dx * dx + dy * dy)


@njit(cache=True, nogil=True, inline="always")
def _pixel_in_box(out, labels, centres_px, inv_pitch, x0, y0, base, col, row, w):
    """Add a pixel share ``w`` at (col, row), a pixel of the box, to its lenslet's moments
    (rows ``base`` + lenslet), with no branch: a dark one (label −1) adds 0 to the lenslet
    at ``base`` (the same sums, bit for bit: x + 0 = x). A cut cell's piece across a label
    border is added this way (docs/distance.md, "A landing across a label border without
    branches (stop 78)")."""
    k = labels[row, col]
    dark = k < 0
    kk = 0 if dark else k
    _add_pixel(out, base + kk, kk, centres_px, inv_pitch, x0, y0, col, row,
               0.0 if dark else w)


@njit(cache=True, nogil=True, inline="always")
def _pixel_or_spare(out, labels, centres_px, inv_pitch, x0, y0, base, spare, col, row, w):
    """:func:`_pixel_in_box` for any pixel, in the box or not: one outside it or dark adds
    its share to the row ``spare`` instead (a row of ``out`` no caller reads), every other's
    sums the same, bit for bit. ``labels`` not empty. A landing's four pixels are added this
    way where they are not one lenslet's: four calls that each branched on the box's bounds
    and the label, coin tosses, cost ~85 ns a landing (docs/distance.md, "A landing across a
    label border without branches (stop 78)")."""
    h, wd = labels.shape
    inside = (col >= 0) & (col < wd) & (row >= 0) & (row < h)
    k = labels[min(max(row, 0), h - 1), min(max(col, 0), wd - 1)]
    valid = inside & (k >= 0)
    kk = k if valid else 0
    _add_pixel(out, base + kk if valid else spare, kk, centres_px, inv_pitch, x0, y0, col,
               row, w)


DEPOSIT_BLOCK = 256  # rays a block of deposit_moments' passes (its scratch stays in cache)
# (a ray's share across a cell border: lfcam.measure.sampling.ray_share, RICHARDSON_*)


@njit(cache=True, nogil=True, error_model="numpy")
def _block_cells(ray, cell, k, origin, inverse, basis, rect, la, lb, seps, richardson):
    """The first ``k`` rays of a block (``ray`` rows: x, y, …, spacing: deposit_moments):
    ``cell`` rows ``i, j`` (the nearest node), ``di, dj`` (to the second nearest) and the
    ray's share in the second: ``clip(0.5 − gap/spacing, 0, 0.5)``, or with ``richardson``
    :func:`lfcam.measure.sampling.ray_share`'s. No branch on the ray: it runs in SIMD lanes."""
    o0, o1 = origin[0], origin[1]
    i00, i01, i10, i11 = inverse[0, 0], inverse[0, 1], inverse[1, 0], inverse[1, 1]
    b00, b01, b10, b11 = basis[0, 0], basis[0, 1], basis[1, 0], basis[1, 1]
    len_10, len_01, len_11, len_1m1 = seps[2, 1], seps[1, 2], seps[2, 2], seps[2, 0]
    for b in range(k):
        # (the lattice's test is the same for every ray: the compiler takes it out of the
        # loop, which runs in SIMD lanes either way)
        if rect:
            i, j, i2, j2, gap = _nearest_two_rect(ray[0, b] - o0, ray[1, b] - o1, i00, i01,
                                                  i10, i11, la, lb)
        else:
            i, j, i2, j2, gap = _nearest_two_hex(ray[0, b] - o0, ray[1, b] - o1, i00, i01,
                                                 i10, i11, b00, b01, b10, b11, len_10, len_01,
                                                 len_11, len_1m1)
        cell[0, b] = i
        cell[1, b] = j
        cell[2, b] = i2 - i
        cell[3, b] = j2 - j
        one = min(max(0.5 - gap / ray[5, b], 0.0), 0.5)
        two = min(max(0.5 - 0.5 * gap / ray[5, b], 0.0), 0.5)
        cell[4, b] = RICHARDSON_ONE * one - RICHARDSON_TWO * two if richardson else one


@njit(cache=True, nogil=True, error_model="numpy")
def _block_landings(ray, cell, land, k, c, origin, basis, inv_pp, ax, ay, x0, y0):
    """Landing ``c`` (0: the ray's own cell, 1: the second nearest) of the first ``k`` rays
    of a block on the sensor: the cell centre plus ``f_x`` × the slope, in box pixels, and
    the ``s`` px box spread over the pixel and the neighbour across its nearer border.
    ``land`` rows: the pixel's column and row, the neighbour's (the pixel's own where the
    box does not reach over: ex = 0), the shares ex, ey beyond, and the landing's weight.
    No branch on the ray: it runs in SIMD lanes."""
    o0, o1 = origin[0], origin[1]
    b00, b01, b10, b11 = basis[0, 0], basis[0, 1], basis[1, 0], basis[1, 1]
    for b in range(k):
        ci = cell[0, b] + c * cell[2, b]
        cj = cell[1, b] + c * cell[3, b]
        share = cell[4, b]
        s = ray[6, b]
        inv_s = 1.0 / s
        # the cell centre plus f_x × the slope: box coordinates of the landing
        px = (o0 + b00 * ci + b01 * cj + ray[2, b]) * inv_pp + ax - x0
        py = (o1 + b10 * ci + b11 * cj + ray[3, b]) * inv_pp + ay - y0
        cx = np.floor(px + 0.5)
        cy = np.floor(py + 0.5)
        tx = px - cx
        ty = py - cy
        ex = min(max((abs(tx) + 0.5 * s - 0.5) * inv_s, 0.0), 0.5)
        ey = min(max((abs(ty) + 0.5 * s - 0.5) * inv_s, 0.0), 0.5)
        sx = (1.0 if tx > 0.0 else 0.0) - (1.0 if tx < 0.0 else 0.0)
        sy = (1.0 if ty > 0.0 else 0.0) - (1.0 if ty < 0.0 else 0.0)
        land[0, b] = cx
        land[1, b] = cy
        land[2, b] = cx + (sx if ex > 0.0 else 0.0)
        land[3, b] = cy + (sy if ey > 0.0 else 0.0)
        land[4, b] = ex
        land[5, b] = ey
        land[6, b] = ray[4, b] * ((1.0 - share) if c == 0 else share)


# error_model="numpy": no zero test before each division (spacings and s_px are > 0):
# the same sums, 10-17 % less CPU
@njit(cache=True, nogil=True, error_model="numpy")
def deposit_moments(x, y, sx, sy, wt, rows, spacing, group, groups, origin, basis, inverse,
                    rect, la, lb, pp, ax, ay, x0, y0, s_px, labels, centres_px, pitch_px,
                    s_ray, richardson):
    """Moments ``(groups·K, 4)`` of rays hitting the MLA at ``(x, y)`` mm with sensor offsets
    ``(sx, sy)`` mm (``f_x`` × slope) and weights ``wt``, ray ``r`` from source point
    ``rows[r]``, whose rays are ``spacing[rows[r]]`` apart on the MLA and go to group
    ``group[rows[r]]`` (module docstring; per point, so that no ray-sized copy of either is
    made for each call). ``labels`` is the region box's compact lenslet map (−1 none),
    ``(x0, y0)`` the box's corner, ``(ax, ay)`` the sensor axis (px), ``pp`` the pixel pitch
    (mm). Each ray is spread as an ``s_px`` box, or, where ``s_ray`` is not empty, ray ``r``
    as an ``s_ray[r]`` box (samples on the cells, each its own pupil area's: docs/distance.md,
    "The whole cells reach the rim; each sample its own box (stop 44)"). ``richardson``: each
    ray shared across its cell's border by :func:`lfcam.measure.sampling.ray_share`'s two
    boxes (the ray samples) instead of one (the samples on the cells).

    Two passes a block of :data:`DEPOSIT_BLOCK` rays (docs/distance.md, "The deposit's
    arithmetic in SIMD lanes (stop 52)"): the first, with no branch on the ray, finds each
    ray's two cells, its share and its two landings' pixels and box shares
    (:func:`_block_cells`, :func:`_block_landings`); the second adds them to the moments in
    the rays' order, as one pass did (the same sums, bit for bit)."""
    n_k = centres_px.shape[0]
    out = np.zeros((groups * n_k + 1, 4))  # (and _deposit_block's spare row)
    inv_pitch = 1.0 / pitch_px
    inv_pp = 1.0 / pp
    seps = _separations(basis)
    ray = np.empty((7, DEPOSIT_BLOCK))  # x, y, sx, sy, wt, spacing, s
    cell = np.empty((5, DEPOSIT_BLOCK))
    land = np.empty((2, 7, DEPOSIT_BLOCK))
    bases = np.empty(DEPOSIT_BLOCK, dtype=np.int64)
    each = s_ray.size > 0
    for lo in range(0, x.size, DEPOSIT_BLOCK):
        k = min(DEPOSIT_BLOCK, x.size - lo)
        for b in range(k):
            r = lo + b
            ray[0, b] = x[r]
            ray[1, b] = y[r]
            ray[2, b] = sx[r]
            ray[3, b] = sy[r]
            ray[4, b] = wt[r]
            ray[5, b] = spacing[rows[r]]
            ray[6, b] = s_ray[r] if each else s_px
            bases[b] = group[rows[r]] * n_k
        _deposit_block(out, ray, cell, land, bases, k, origin, basis, inverse, rect, la, lb,
                       seps, richardson, inv_pp, ax, ay, x0, y0, labels, centres_px, inv_pitch)
    return out[:-1]


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _deposit_block(out, ray, cell, land, bases, k, origin, basis, inverse, rect, la, lb, seps,
                   richardson, inv_pp, ax, ay, x0, y0, labels, centres_px, inv_pitch):
    """The first ``k`` rays of a block (``ray`` rows as :func:`deposit_moments` fills them;
    ray ``b``'s moments at rows ``bases[b]`` + lenslet of ``out``) added to the moments: the
    passes with no branch on the ray (:func:`_block_cells`, :func:`_block_landings`), then
    the sums in the rays' order. ``out``'s last row is a spare that takes the shares of
    pixels outside the box or dark (:func:`_pixel_or_spare`): its callers do not return it."""
    h, wd = labels.shape
    if h == 0 or wd == 0:
        return  # (nothing lands in an empty box)
    spare = out.shape[0] - 1
    _block_cells(ray, cell, k, origin, inverse, basis, rect, la, lb, seps, richardson)
    for c in range(2):
        _block_landings(ray, cell, land[c], k, c, origin, basis, inv_pp, ax, ay, float(x0),
                        float(y0))
    for b in range(k):
        base = bases[b]
        # the ray's share in its cell, then (share ≠ 0) in the neighbour's
        for c in range(2):
            w = land[c, 6, b]
            if c == 1 and cell[4, b] == 0.0:
                break
            ic = int(land[c, 0, b])
            ir = int(land[c, 1, b])
            inx = int(land[c, 2, b])
            iny = int(land[c, 3, b])
            ex = land[c, 4, b]
            ey = land[c, 5, b]
            # (`&`, not `and`: whether the box reaches over a border is a coin toss from
            # ray to ray, s ~ 0.1-0.5 px; a share of 0 adds 0: the same sums)
            if ((0 <= min(ic, inx)) & (max(ic, inx) < wd) & (0 <= min(ir, iny))
                    & (max(ir, iny) < h)):
                kk = labels[ir, ic]
                if ((kk >= 0) & (labels[ir, inx] == kk) & (labels[iny, ic] == kk)
                        & (labels[iny, inx] == kk)):
                    # the (up to) four pixels belong to one lenslet: one update
                    cxk = centres_px[kk, 0]
                    cyk = centres_px[kk, 1]
                    dx0 = (ic + x0 - cxk) * inv_pitch
                    dx1 = (inx + x0 - cxk) * inv_pitch
                    dy0 = (ir + y0 - cyk) * inv_pitch
                    dy1 = (iny + y0 - cyk) * inv_pitch
                    n = base + kk
                    e1 = w * ((1 - ex) * dx0 + ex * dx1)
                    e2 = w * ((1 - ey) * dy0 + ey * dy1)
                    e3 = w * ((1 - ex) * dx0 * dx0 + ex * dx1 * dx1
                              + (1 - ey) * dy0 * dy0 + ey * dy1 * dy1)
                    out[n, 0] += w
                    out[n, 1] += e1
                    out[n, 2] += e2
                    out[n, 3] += e3
                    continue
                if ((kk < 0) & (labels[ir, inx] < 0) & (labels[iny, ic] < 0)
                        & (labels[iny, inx] < 0)):
                    continue  # every pixel dark: nothing to add
            elif ((max(ic, inx) < 0) | (min(ic, inx) >= wd) | (max(ir, iny) < 0)
                    | (min(ir, iny) >= h)):
                continue  # every pixel outside the box: nothing to add
            # (a landing on dark pixels or outside the box, 28 % of a line's distance
            # scan's and 11 % of a 380 mm line's: the early exits above, 80 -> 29 and
            # 40 -> 28 ns a ray: docs/distance.md, "Landings with nothing to add (stop
            # 52)")
            # (the four pixels, a share of 0 where the box does not reach over: the same
            # sums; those outside the box or dark to the spare row)
            _pixel_or_spare(out, labels, centres_px, inv_pitch, x0, y0, base, spare, ic, ir,
                            w * (1 - ex) * (1 - ey))
            _pixel_or_spare(out, labels, centres_px, inv_pitch, x0, y0, base, spare, inx, ir,
                            w * ex * (1 - ey))
            _pixel_or_spare(out, labels, centres_px, inv_pitch, x0, y0, base, spare, ic, iny,
                            w * (1 - ex) * ey)
            _pixel_or_spare(out, labels, centres_px, inv_pitch, x0, y0, base, spare, inx, iny,
                            w * ex * ey)


# glibc's mallopt parameters (malloc.h) and the values keep_large_buffers sets
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024  # glibc's largest (64-bit): served from the heap below
TRIM_THRESHOLD_BYTES = 256 * 1024 * 1024  # free memory kept at the heap's top, at most
_ALLOCATOR: list[bool] = []


def keep_large_buffers() -> None:
    """Have the C allocator serve blocks of up to :data:`MMAP_THRESHOLD_BYTES` from its heap
    and keep freed memory for reuse (glibc ``mallopt``), once a process.

    A lenslet model's evaluation allocates its samples, rays and moments afresh: 1-16 MB
    arrays. glibc maps each such block from the kernel and unmaps it when freed, so every
    evaluation touches fresh pages, which the kernel faults in and zeroes: 15 % of a large
    line region's CPU (175-182 → 148-150 ms; docs/distance.md, "Speed at stop 42"). From the
    heap the same memory is reused. Called by every
    :class:`~lfcam.measure.fastfit.LensletModel` and by :func:`warm_up`. Nothing to do off
    glibc (no ``mallopt``: macOS, Windows), or with ``LFCAM_MALLOC=default`` in the
    environment.
    """
    if _ALLOCATOR:
        return
    _ALLOCATOR.append(True)
    if os.environ.get("LFCAM_MALLOC", "").strip().lower() == "default":
        return
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the C library the process runs on
    except (OSError, AttributeError, TypeError):  # (Windows cannot open None)
        return
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
    mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)


def warm_up() -> None:
    """Load (or compile, the first time on a machine) the kernels with the argument types
    :class:`~lfcam.measure.fastfit.LensletModel` passes, so that a region worker pays for it
    while the parent is still busy with the geometry; and keep the allocator's large blocks
    (:func:`keep_large_buffers`)."""
    keep_large_buffers()
    one = np.zeros(1)
    eye = np.eye(2)
    # a box's slices of the frame (strided; contiguous where the box spans the frame's width)
    # of its int32 labels and a float32 or float64 image
    for cut in (np.s_[:, :1], np.s_[:1, :]):
        for dtype in (np.float64, np.float32):
            box_moments(np.zeros((2, 2), dtype=np.int32)[cut], np.zeros((2, 2), dtype=dtype)[cut],
                        np.zeros(0, dtype=np.bool_), np.zeros((1, 2)), 0, 0, 1.0, 0.0, 1)
    deposit_moments(one, one, one, one, one, np.zeros(1, dtype=np.int64), np.ones(1),
                    np.zeros(1, dtype=np.int64), 1,
                    np.zeros(2), eye, eye, True, 1.0, 1.0, 1.0, 0.0, 0.0, 0, 0, 0.5,
                    np.zeros((1, 1), dtype=np.int32), np.zeros((1, 2)), 1.0, np.empty(0), True)
    table = np.zeros((1, 8))
    table[0, 3:6] = (1.0, 1.0, 1.0)
    trace_deposit_moments(np.array([[0.0, 0.0, -1.0]]), np.array([[0.0, 0.0, 1.0, 1.0]]),
                          np.array([[1.0, 0.0]]), one, one, table, np.zeros((1, 1)), 0.0, 0.0,
                          1.0, 1.0, 1.0, 1.0, np.zeros(1, dtype=np.int64), 1, np.zeros(2), eye,
                          eye, True, 1.0, 1.0, 1.0, 0.0, 0.0, 0, 0, 0.5,
                          np.zeros((1, 1), dtype=np.int32), np.zeros((1, 2)), 1.0, True,
                          np.empty(0))
    trace_model_rays(np.array([[0.0, 0.0, -1.0]]), np.array([[0.0, 0.0, 1.0, 1.0]]),
                     np.array([[1.0, 0.0]]), one, one,
                     table, np.zeros((1, 1)), 0.0, 0.0, 1.0, 1.0)
    trace_sample_rays(np.array([[0.0, 0.0, -1.0]]), np.array([[0.0, 0.0, 1.0, 1.0]]),
                      np.array([0, 1], dtype=np.int64), one, one,
                      table, np.zeros((1, 1)), 0.0, 0.0, 1.0, 1.0)
    pupil_maps(np.array([[0.0, 0.0, -10.0]]), np.zeros(1), table, np.zeros((1, 1)), 0, 1.0, 1.0,
               0.0, 1.0)
    terms = (MAP_DEGREE + 1) * (MAP_DEGREE + 2) // 2
    poly = np.zeros((1, terms))
    cell_samples(poly, poly, np.zeros((1, 4)), np.zeros((1, 3)), np.zeros(2), eye, eye, 2,
                 np.zeros((1, 5), dtype=np.int64), np.zeros(1, dtype=np.bool_), 1.0, True,
                 1.0, 1.0)
    cell_centres(poly, poly, np.zeros((1, 4)), np.zeros((1, 3)), np.zeros(2), eye, eye, 1.25,
                 np.zeros((2, 2)), np.zeros((4, 2)), np.full(4, 0.25), np.zeros((4, 2)))
    deposit_cells(np.zeros((1, 4)), np.zeros(1, dtype=np.int64), one, one, one, one, one,
                  np.zeros((1, 4)), np.zeros(1, dtype=np.int64), np.zeros(2), eye, 1.0, 0.0, 0.0,
                  0, 0, np.zeros((1, 1), dtype=np.int32), np.zeros((1, 2)), 1.0,
                  np.zeros((0, 3, 2)), 1)
    cell_landings(np.zeros(4, dtype=np.int64), np.ones(4), np.zeros(4), np.zeros(4),
                  np.ones(4), 1, np.zeros((4, 2)))
    moments_summary(np.ones((1, 4)), np.zeros((1, 2)), np.zeros(1, dtype=np.int64), 1.0)
    gram_of(np.zeros((4, 2)))
    jt_of(np.zeros((4, 2)), np.zeros(4))
    sq_of(np.zeros(4))
    scaled_residual(np.ones((1, 4)), np.ones((1, 4)), 1.0)
    jackknife_deltas(np.ones((4, 1)), np.zeros(4), np.ones((1, 1)), 0.95)


def warm_up_frame() -> None:
    """Load (or compile) the frame kernels with the argument types
    :mod:`lfcam.measure.lenslets` passes on large frames (the lenslet map's stamping, the
    per-lenslet sums): what the parent process needs before its geometry."""
    stamp_labels(np.full((1, 1), -1, dtype=np.int32), np.zeros((1, 2)),
                 np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64),
                 np.zeros(1, dtype=np.int64), 1.0, 1)
    lenslet_sums(np.zeros((1, 1), dtype=np.int32), np.zeros((1, 1)), 1)


@njit(cache=True, nogil=True)
def moments_summary(m, centres_mm, ids, scale):
    """:func:`lfcam.measure.fastfit.summary` of the moments ``m`` (K, 4) of lenslets ``ids``
    (their centres ``centres_mm[ids]``; ``scale``: MLA mm a moment's offset unit): ``(b, x̄,
    ȳ, ρ)`` over the lenslets holding over 5 % of the brightest one's energy, in two passes
    (the numpy form took ~0.1 ms a call, ~4 600 calls on the focus grid's 108 points: 7 % of
    their CPU). All NaN where no energy is positive or any is NaN (as ``np.max``)."""
    out = np.full(4, np.nan)
    k = m.shape[0]
    e_max = -np.inf
    for i in range(k):
        e = m[i, 0]
        if e != e:
            return out
        e_max = max(e_max, e)
    if not e_max > 0.0:
        return out
    lit = 0.05 * e_max
    sw = 0.0
    sx = 0.0
    sy = 0.0
    sox = 0.0
    soy = 0.0
    for i in range(k):
        w = m[i, 0]
        if w > lit:
            j = ids[i]
            sw += w
            sx += centres_mm[j, 0] * w
            sy += centres_mm[j, 1] * w
            sox += scale * m[i, 1]
            soy += scale * m[i, 2]
    cx = sx / sw
    cy = sy / sw
    ox = sox / sw
    oy = soy / sw
    den = 0.0
    num = 0.0
    for i in range(k):
        w = m[i, 0]
        if w > lit:
            j = ids[i]
            dx = centres_mm[j, 0] - cx
            dy = centres_mm[j, 1] - cy
            den += w * (dx * dx + dy * dy)
            num += w * ((scale * m[i, 1] / w - ox) * dx + (scale * m[i, 2] / w - oy) * dy)
    out[0] = num / den if den > 0.0 else 0.0
    out[1] = cx
    out[2] = cy
    out[3] = math.sqrt(den / sw)
    return out


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
def box_moments(labels, image, drop, centres_px, x0, y0, pitch_px, pedestal, n_lenslets):
    """:func:`lfcam.measure.fastfit.data_moments` of a box in one pass: ``labels`` and
    ``image`` are the box's slices (corner ``(x0, y0)``; views of the frame's arrays, any
    layout, the image float32 or float64), ``drop`` a flag per lenslet left out of the box
    (as label −1; empty: none), ``centres_px`` every lenslet's micro-image centre. Returns
    (ids of the lenslets present, in increasing order; the box's labels as compact indices
    into ``ids``, −1 none, ``int32``: the deposits read it for every ray; their moments
    ``(K, 4)``; the noise sums of :func:`lfcam.measure.noise.moment_noise_sums`), summed in a
    row-major pass as ``np.bincount`` does. The slices are read where they lie and the
    lenslets left out are dropped here: no copy of the box, nor a pass over it for the
    exclusion (an Illum-size box of 10⁶ px: 10 → 4 ms, docs/distance.md, "The data's
    moments read in place (stop 75)")."""
    h, w = labels.shape
    present = np.zeros(n_lenslets + 1, dtype=np.int64)
    for row in range(h):
        for col in range(w):
            k = labels[row, col]
            if k >= 0:
                present[k] = 1
    for k in range(min(drop.size, n_lenslets)):
        if drop[k]:
            present[k] = 0
    count = 0
    for k in range(n_lenslets):
        if present[k]:
            present[k] = count + 1  # compact index + 1
            count += 1
    ids = np.empty(count, dtype=np.int64)
    for k in range(n_lenslets):
        if present[k]:
            ids[present[k] - 1] = k
    compact = np.empty((h, w), dtype=np.int32)
    out = np.zeros((count, 4))
    s0 = 0.0
    s1 = 0.0
    for row in range(h):
        for col in range(w):
            k = labels[row, col]
            c = present[k] - 1 if k >= 0 else -1
            compact[row, col] = c
            if c < 0:
                continue
            v = image[row, col] - pedestal
            dx = (col + x0 - centres_px[k, 0]) / pitch_px
            dy = (row + y0 - centres_px[k, 1]) / pitch_px
            r2 = dx * dx + dy * dy
            out[c, 0] += v
            out[c, 1] += v * dx
            out[c, 2] += v * dy
            out[c, 3] += v * r2
            f2 = 1.0 + r2 + r2 * r2
            s0 += f2
            s1 += (v if v > 0.0 else 0.0) * f2  # (no branch: the sign is noise's coin toss)
    return ids, compact, out, s0, s1


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


# ----------------------------------------------------------------------------- lens trace
# Columns of the packed prescription (:func:`pack_prescription`).
_VZ, _C, _K, _SEMI2, _N1, _N2, _IDEAL, _POWER = range(8)
RIM_TOLERANCE = 1e-9  # as lfcam.optics.raytrace.RIM_TOLERANCE
TRACE_BLOCK = 4096  # rays a block of the compiled trace


def pack_prescription(prescription) -> tuple[np.ndarray, np.ndarray]:
    """A :class:`~lfcam.optics.lens.Prescription` as the arrays :func:`trace_model_rays`
    reads: ``(S, 8)`` per surface (vertex z, curvature, conic, clear semi-diameter², index
    before and after, ideal flag, ideal paraxial power) and ``(S, A)`` the ideal surfaces'
    aberration coefficients (zeros elsewhere)."""
    from lfcam.optics import raytrace

    # one rim rule and one aiming rule for both tracers (compiled code freezes these)
    if (raytrace.RIM_TOLERANCE, raytrace.AIM_TOLERANCE_MM) != (RIM_TOLERANCE, AIM_TOLERANCE_MM):
        raise AssertionError("RIM_TOLERANCE or AIM_TOLERANCE_MM differs from "
                             "lfcam.optics.raytrace")
    surfaces = prescription.surfaces
    n_coef = max([len(s.spherical) for s in surfaces if s.is_ideal] + [0])
    table = np.zeros((len(surfaces), 8))
    coef = np.zeros((len(surfaces), max(n_coef, 1)))
    for i, s in enumerate(surfaces):
        table[i] = (prescription.vertex_z_mm[i], s.curvature_per_mm, s.conic,
                    s.semi_diameter_mm * s.semi_diameter_mm, prescription.index_before[i],
                    s.refractive_index, float(s.is_ideal),
                    1.0 / s.focal_length_mm if s.is_ideal else 0.0)
        if s.is_ideal:
            coef[i, :len(s.spherical)] = s.spherical
    return table, coef


@njit(cache=True, nogil=True, error_model="numpy")
def _surface(x, y, z, dx, dy, dz, ok, i, table, coef, clip=True, refract=True) -> None:
    """Carry the rays (component arrays, in place) through surface ``i`` of ``table``: the
    rules and arithmetic of :func:`lfcam.optics.raytrace._run` (forward), written without
    branches on the ray so that the loop runs in SIMD lanes; a ray that fails (misses,
    vignetted, backward, total internal reflection) has ``ok`` cleared and carries on with
    meaningless numbers. ``clip=False``: no clear apertures; ``refract=False``: the ray stops
    on the surface, its direction unchanged (``last_refracts=False``)."""
    vz = table[i, _VZ]
    c = table[i, _C]
    k = table[i, _K]
    semi2 = table[i, _SEMI2] * (1.0 + RIM_TOLERANCE) if clip else np.inf
    n1 = table[i, _N1]
    n2 = table[i, _N2]
    # the first surface may not lie behind the ray, unless it is a flat plane in air
    first = i == 0 and not (c == 0.0 and n1 == 1.0 and n2 == 1.0)
    if not refract:
        n2 = n1
    eta = n1 / n2
    q = (1.0 + k) * c
    lim = 1.0 / q if q != 0.0 else 0.0
    if table[i, _IDEAL] != 0.0 and refract:  # flat, air both sides: s_out = s_in − (x, y)·P(r)
        p0 = table[i, _POWER]
        n_coef = coef.shape[1]
        for r in range(x.size):
            t = (vz - z[r]) / dz[r]
            x1 = x[r] + t * dx[r]
            y1 = y[r] + t * dy[r]
            r2 = x1 * x1 + y1 * y1
            good = not (first and t < 0.0)
            good &= r2 <= semi2
            p = p0
            term = 1.0
            for j in range(n_coef):
                term = term * r2
                p = p + coef[i, j] * term
            sx = dx[r] / dz[r] - x1 * p
            sy = dy[r] / dz[r] - y1 * p
            dz1 = 1.0 / math.sqrt(1.0 + sx * sx + sy * sy)
            x[r] = x1
            y[r] = y1
            z[r] = vz
            dx[r] = sx * dz1
            dy[r] = sy * dz1
            dz[r] = dz1
            ok[r] &= good
    elif c == 0.0:  # flat: only the axial component changes (an ideal one: none here)
        for r in range(x.size):
            t = (vz - z[r]) / dz[r]
            x1 = x[r] + t * dx[r]
            y1 = y[r] + t * dy[r]
            good = not (first and t < 0.0)
            good &= x1 * x1 + y1 * y1 <= semi2
            x[r] = x1
            y[r] = y1
            z[r] = vz
            if n1 != n2:
                cos_i = dz[r]
                kk = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
                good &= kk >= 0.0
                dx[r] = eta * dx[r]
                dy[r] = eta * dy[r]
                dz1 = math.sqrt(max(kk, 0.0))
                good &= dz1 > 0.0
                dz[r] = dz1
            ok[r] &= good
    else:  # a conic (Spencer & Murty: tangent plane, then the vertex-branch root)
        for r in range(x.size):
            ddx = dx[r]
            ddy = dy[r]
            ddz = dz[r]
            t = (vz - z[r]) / ddz
            x0 = x[r] + t * ddx
            y0 = y[r] + t * ddy
            cc = c * (x0 * x0 + y0 * y0)
            b = ddz - c * (x0 * ddx + y0 * ddy)
            a = c if k == 0.0 else c * (1.0 + k * ddz * ddz)
            disc = b * b - a * cc
            good = disc >= 0.0
            step = cc / (b + math.copysign(math.sqrt(max(disc, 0.0)), b))
            x1 = x0 + step * ddx
            y1 = y0 + step * ddy
            zl = step * ddz
            good &= not ((q > 0.0 and zl >= lim) or (q < 0.0 and zl <= lim))
            good &= not (first and t + step < 0.0)
            good &= x1 * x1 + y1 * y1 <= semi2
            x[r] = x1
            y[r] = y1
            z[r] = vz + zl
            if n1 != n2:
                nx = c * x1
                ny = c * y1
                nz = c * (1.0 + k) * zl - 1.0
                if k != 0.0:
                    inv = 1.0 / math.sqrt(nx * nx + ny * ny + nz * nz)
                    nx = nx * inv
                    ny = ny * inv
                    nz = nz * inv
                cos_i = -(nx * ddx + ny * ddy + nz * ddz)
                kk = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
                good &= kk >= 0.0
                g = eta * cos_i - math.sqrt(max(kk, 0.0))
                dz1 = eta * ddz + g * nz
                good &= dz1 > 0.0
                dx[r] = eta * ddx + g * nx
                dy[r] = eta * ddy + g * ny
                dz[r] = dz1
            ok[r] &= good


@njit(cache=True, nogil=True, error_model="numpy")
def trace_model_rays(points, maps, turns, rx, ry, table, coef, front_z, rim_z, z_plane, fx):
    """The lenslet model's rays: every point source ``points`` (M, 3) (lens frame) through
    the aperture points ``(rx, ry)`` (on the plane ``rim_z``; per point mapped by ``maps``
    (M, 4) ``= (cx, cy, sx, sy)`` onto the real stop's image; each point's aperture points
    first turned by ``turns`` (M, 2) ``= (cos, sin)`` of its angle) through the prescription
    (``table``, ``coef`` from :func:`pack_prescription`, front vertex at ``front_z``) to the
    MLA plane ``z_plane``.

    Returns, for the rays that pass, in point-major order: ``x, y`` (mm at the MLA),
    ``sx, sy`` (``fx`` × slope), the cosine³ weight ``wt`` (unmapped aperture point), the
    point index ``row``, the aperture point's index ``ray`` (0 … len(rx) − 1); and ``foot``
    (M,): each point's footprint extent at the MLA (the
    larger of its x and y ranges; 0 when no ray passes). The same quantities
    :class:`~lfcam.measure.fastfit.LensletModel` computes with numpy from
    :func:`lfcam.optics.trace.trace_sources_fast` (to ~1e-15, ``tests/test_speed_paths.py``).
    """
    m = points.shape[0]
    return _trace_ranges(points, maps, turns, rx, ry, np.zeros(m, dtype=np.int64),
                         np.full(m, rx.size, dtype=np.int64), table, coef, front_z, rim_z,
                         z_plane, fx)


@njit(cache=True, nogil=True, error_model="numpy")
def trace_sample_rays(points, maps, cuts, rx, ry, table, coef, front_z, rim_z, z_plane, fx):
    """:func:`trace_model_rays` with each point its own aperture points: point ``p``'s are
    ``rx[cuts[p]:cuts[p + 1]]``, ``ry[...]`` (``cuts`` (M + 1,), non-decreasing), not turned;
    the returned ``ray`` indexes ``rx``. The same rays, sums and order as one
    :func:`trace_model_rays` call a point (the lenslet cells' samples:
    ``LensletModel._simulate_cells``), without a call and a copy a point."""
    m = points.shape[0]
    turns = np.zeros((m, 2))
    turns[:, 0] = 1.0
    return _trace_ranges(points, maps, turns, rx, ry, cuts[:m], cuts[1:] - cuts[:m],
                         table, coef, front_z, rim_z, z_plane, fx)


@njit(cache=True, nogil=True, error_model="numpy")
def _trace_ranges(points, maps, turns, rx, ry, first, n_rays, table, coef, front_z, rim_z,
                  z_plane, fx):
    """The body of :func:`trace_model_rays`: point ``p`` through the aperture points
    ``first[p]`` … ``first[p] + n_rays[p] − 1``."""
    m = points.shape[0]
    size = 0
    widest = 1
    for p in range(m):
        size += n_rays[p]
        widest = max(widest, n_rays[p])
    block = min(TRACE_BLOCK, widest)
    # one block of rays at a time through every surface: scratch arrays that stay in cache
    scratch = np.empty((7, block))
    ok = np.empty(block, dtype=np.uint8)
    res = np.empty((1, 7, size))  # the passing rays: x, y, sx, sy, wt (_land's layout)
    rows = np.empty(size, dtype=np.int64)
    rays = np.empty(size, dtype=np.int64)
    extent = np.empty(4)
    foot = np.zeros(m)
    count = 0
    for p in range(m):
        extent[:] = (np.inf, -np.inf, np.inf, -np.inf)
        end = first[p] + n_rays[p]
        for lo in range(first[p], end, block):
            start = count
            count = _trace_block(points, maps, turns, rx, ry, p, lo, min(block, end - lo),
                                 scratch, ok, table, coef, front_z, rim_z, z_plane, fx, res,
                                 count, rays, extent)
            rows[start:count] = p
        if extent[1] >= extent[0]:
            foot[p] = max(extent[1] - extent[0], extent[3] - extent[2])
    return (res[0, 0, :count], res[0, 1, :count], res[0, 2, :count], res[0, 3, :count],
            res[0, 4, :count], rows[:count], rays[:count], foot)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _trace_block(points, maps, turns, rx, ry, p, lo, k, scratch, ok, table, coef, front_z,
                 rim_z, z_plane, fx, dest, count, rays, extent) -> int:
    """Point ``p``'s rays toward the aperture points ``lo`` … ``lo + k − 1`` through every
    surface (:func:`_launch`, :func:`_surface` a surface) to the MLA plane ``z_plane``, those
    that pass appended to ``dest`` (:func:`_land`); returns the new count."""
    x, y, z, dx, dy, dz = scratch[0], scratch[1], scratch[2], scratch[3], scratch[4], scratch[5]
    _launch(points, maps, turns, rx, ry, p, lo, k, scratch, ok, front_z, rim_z)
    for i in range(table.shape[0]):
        _surface(x[:k], y[:k], z[:k], dx[:k], dy[:k], dz[:k], ok[:k], i, table, coef)
    return _land(scratch, ok, k, z_plane - front_z, fx, dest, count, rays, lo, extent)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _launch(points, maps, turns, rx, ry, p, lo, k, scratch, ok, front_z, rim_z) -> None:
    """The first ``k`` rays of a trace block (``scratch`` rows x, y, z, dx, dy, dz, wt): from
    point ``p`` toward the aperture points ``lo`` … ``lo + k − 1`` (turned by ``turns[p]``,
    mapped by ``maps[p]``), at the source, with their cosine³ weights."""
    px = points[p, 0]
    py = points[p, 1]
    pz = points[p, 2]
    along = rim_z - pz
    a2 = along * along
    tc = turns[p, 0]
    ts = turns[p, 1]
    for b in range(k):
        j = lo + b
        ax = tc * rx[j] - ts * ry[j]  # (1, 0): rx, ry unchanged, bit for bit
        ay = ts * rx[j] + tc * ry[j]
        ex = maps[p, 0] + maps[p, 2] * ax - px
        ey = maps[p, 1] + maps[p, 3] * ay - py
        norm = 1.0 / math.sqrt(ex * ex + ey * ey + along * along)
        scratch[0, b] = px
        scratch[1, b] = py
        scratch[2, b] = pz - front_z
        scratch[3, b] = ex * norm
        scratch[4, b] = ey * norm
        scratch[5, b] = along * norm
        ok[b] = along * norm > 0.0
        ux = ax - px
        uy = ay - py
        cos2 = a2 / (ux * ux + uy * uy + a2)
        scratch[6, b] = cos2 * math.sqrt(cos2)  # (cos² θ)^1.5, without pow


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _land(scratch, ok, k, zp, fx, dest, count, rays, lo, extent) -> int:
    """The first ``k`` rays of a traced block on the plane ``zp`` (lens frame): those that
    pass appended from the ``count``-th on to ``dest`` (B, 7, W): ray ``c`` at
    ``dest[c // W, :5, c % W]`` (x, y, ``fx`` × slopes, weight; rows 5 and 6 untouched), their
    aperture point's index to ``rays`` (``lo`` + their place in the block; none where
    ``rays`` is empty); ``extent`` (x and y: least, most) widened. Returns the new count."""
    width = dest.shape[2]
    i = count // width  # (once a block: no division a ray)
    j = count - i * width
    keep = rays.size > 0
    for b in range(k):
        dz = scratch[5, b]
        t = (zp - scratch[2, b]) / dz
        xr = scratch[0, b] + t * scratch[3, b]
        yr = scratch[1, b] + t * scratch[4, b]
        if not (ok[b] and math.isfinite(xr) and math.isfinite(yr) and math.isfinite(dz)):
            continue
        dest[i, 0, j] = xr
        dest[i, 1, j] = yr
        dest[i, 2, j] = fx * scratch[3, b] / dz
        dest[i, 3, j] = fx * scratch[4, b] / dz
        dest[i, 4, j] = scratch[6, b]
        if keep:
            rays[count] = lo + b
        count += 1
        j += 1
        if j == width:
            i += 1
            j = 0
        extent[0] = min(extent[0], xr)
        extent[1] = max(extent[1], xr)
        extent[2] = min(extent[2], yr)
        extent[3] = max(extent[3], yr)
    return count


@njit(cache=True, nogil=True, error_model="numpy")
def trace_deposit_moments(points, maps, turns, rx, ry, table, coef, front_z, rim_z, z_plane,
                          fx, spacing_scale, pupil_mm, group, groups, origin, basis, inverse,
                          rect, la, lb, pp, ax, ay, x0, y0, s_px, labels, centres_px,
                          pitch_px, richardson, second):
    """:func:`trace_model_rays` and :func:`deposit_moments` in one pass a point: the moments
    ``(groups·K, 4)`` of the rays from ``points`` through the aperture points ``(rx, ry)``
    (arguments up to ``fx`` as :func:`trace_model_rays`'), point ``p``'s rays
    ``max(spacing_scale · foot_p / pupil_mm, 1e-12)`` apart on the MLA (``foot_p`` its
    footprint's extent) and spread as ``s_px`` boxes into group ``group[p]`` (the rest as
    :func:`deposit_moments`' arguments). ``second`` (a weight a point, or empty): the
    moments ``(2·groups·K, 4)``, the groups' sums and then each group's sum with point ``p``'s
    moments times ``second[p]`` (a line's Jacobian weights its points by their place along
    it: docs/distance.md, "A line's weighted sums in the deposit (stop 75)"); the first rows'
    sums are those without it, bit for bit. The weighted sums are not a second scatter-add a
    landing: after each point the group's running sums, times the difference of its weight
    and the next point's, are added to them (Abel's summation by parts; points of a group
    in runs, a run's first point taking off its weight times the sums before it): one pass
    over the group's rows a point, ~3 % of a fine line model's deposit instead of ~30 %
    (docs/distance.md, "A line's weighted sums by parts (stop 78)"). The same sums as the
    two calls, bit for bit; a point's traced rays land straight in the deposit's blocks and
    are deposited while they are still in cache, and no ray-sized array of the whole call is
    made (the two calls wrote and read back ~56 bytes a ray: 44 → 35 ns a ray on system 1's
    far lines, docs/distance.md, "The trace and the deposit in one pass (stop 59)")."""
    m = points.shape[0]
    n_k = centres_px.shape[0]
    weighted = second.size > 0
    out = np.zeros(((2 if weighted else 1) * groups * n_k + 1, 4))  # (and a spare row)
    block = min(TRACE_BLOCK, max(rx.size, 1))
    scratch = np.empty((7, block))
    ok = np.empty(block, dtype=np.uint8)
    # one point's passing rays, landed straight into the deposit's blocks (rows x, y, sx, sy,
    # wt, spacing, s: deposit_moments' `ray`)
    blocks = np.empty((max((rx.size + DEPOSIT_BLOCK - 1) // DEPOSIT_BLOCK, 1), 7,
                       DEPOSIT_BLOCK))
    blocks[:, 6, :] = s_px
    no_index = np.empty(0, dtype=np.int64)
    extent = np.empty(4)
    inv_pitch = 1.0 / pitch_px
    inv_pp = 1.0 / pp
    seps = _separations(basis)
    cell = np.empty((5, DEPOSIT_BLOCK))
    land = np.empty((2, 7, DEPOSIT_BLOCK))
    bases = np.empty(DEPOSIT_BLOCK, dtype=np.int64)
    for p in range(m):
        g = group[p]
        if weighted and (p == 0 or group[p - 1] != g):
            # a run of the group's points begins: − w · (the group's sums so far)
            _add_scaled(out, (groups + g) * n_k, g * n_k, n_k, -second[p])
        extent[:] = (np.inf, -np.inf, np.inf, -np.inf)
        count = 0
        for lo in range(0, rx.size, block):
            count = _trace_block(points, maps, turns, rx, ry, p, lo, min(block, rx.size - lo),
                                 scratch, ok, table, coef, front_z, rim_z, z_plane, fx, blocks,
                                 count, no_index, extent)
        if count > 0:
            spacing = max(spacing_scale * max(extent[1] - extent[0], extent[3] - extent[2])
                          / pupil_mm, 1e-12)
            bases[:] = g * n_k
            for lo in range(0, count, DEPOSIT_BLOCK):
                ray = blocks[lo // DEPOSIT_BLOCK]
                ray[5, :] = spacing
                _deposit_block(out, ray, cell, land, bases, min(DEPOSIT_BLOCK, count - lo),
                               origin, basis, inverse, rect, la, lb, seps, richardson, inv_pp,
                               ax, ay, x0, y0, labels, centres_px, inv_pitch)
        if weighted:
            # Abel's summation: Σ wₚ·(Sₚ − Sₚ₋₁) over a run = Σ (wₚ − wₚ₊₁)·Sₚ, the run's last
            # point taking its whole w (Sₚ: the group's sums once point p is in)
            c = second[p]
            if p + 1 < m and group[p + 1] == g:
                c -= second[p + 1]
            _add_scaled(out, (groups + g) * n_k, g * n_k, n_k, c)
    return out[:-1]


@njit(cache=True, nogil=True, inline="always")
def _add_scaled(out, to, frm, n, c) -> None:
    """``out[to:to + n] += c · out[frm:frm + n]`` (rows of four moments); nothing for c = 0."""
    if c == 0.0:
        return
    for k in range(n):
        for j in range(4):
            out[to + k, j] += c * out[frm + k, j]


# ----------------------------------------------------------------------------- ray aiming
AIM_TOLERANCE_MM = 1e-11  # as lfcam.optics.raytrace.AIM_TOLERANCE_MM
AIM_ITERATIONS = 30  # as lfcam.optics.raytrace.aim_rays' max_iterations
_EDGES = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])  # pupil_map's stop edges


@njit(cache=True, nogil=True, error_model="numpy")
def _stop_miss(ax, ay, sx, sy, sz, z_ref, tx, ty, table, coef, stop, buf, ok):
    """Where the ray from the source ``(sx, sy, sz)`` toward ``(ax, ay, z_ref)`` meets the
    stop surface, minus the target ``(tx, ty)`` (NaN where it cannot): ``aim_rays``' miss,
    traced unclipped through the surfaces up to the stop (no refraction there)."""
    dx = ax - sx
    dy = ay - sy
    dz = z_ref - sz
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)  # rays_for: d / |d|
    dx = dx / norm
    dy = dy / norm
    dz = dz / norm
    inv = 1.0 / math.sqrt(dx * dx + dy * dy + dz * dz)  # _prepare: d · (1 / |d|)
    buf[0, 0] = sx
    buf[1, 0] = sy
    buf[2, 0] = sz
    buf[3, 0] = dx * inv
    buf[4, 0] = dy * inv
    buf[5, 0] = dz * inv
    ok[0] = 1  # (no check of the direction's sense, as _stop_hits)
    for i in range(stop + 1):
        _surface(buf[0], buf[1], buf[2], buf[3], buf[4], buf[5], ok, i, table, coef, False,
                 i != stop)
    if not ok[0]:
        return np.nan, np.nan
    return buf[0, 0] - tx, buf[1, 0] - ty


@njit(cache=True, nogil=True, error_model="numpy")
def pupil_maps(points, z_refs, table, coef, stop, stop_sd, r_ep, z_ap, half):
    """:func:`lfcam.optics.trace.pupil_map` of each point source ``points`` (M, 3) (prescription
    frame), with ``z_refs`` (M,) the aiming plane of each (``aim_rays``' paraxial entrance
    pupil, moved where it passes through the source): the four stop-edge rays aimed by the
    same damped Newton iteration as :func:`lfcam.optics.raytrace.aim_rays`, each on its own.
    Returns (M, 4) ``(cx, cy, sx, sy)``; the identity ``(0, 0, 1, 1)`` where an edge ray
    cannot be aimed."""
    m = points.shape[0]
    out = np.empty((m, 4))
    buf = np.empty((6, 1))  # one ray's scratch for _stop_miss, reused
    ok = np.empty(1, dtype=np.uint8)
    h = 1e-6 * max(r_ep, 1e-3)
    scale = max(stop_sd, 1.0)
    tol = AIM_TOLERANCE_MM * scale
    hx = np.empty(4)
    hy = np.empty(4)
    for p in range(m):
        sx = points[p, 0]
        sy = points[p, 1]
        sz = points[p, 2]
        z_ref = z_refs[p]
        aimed = True
        for e in range(4):
            tx = _EDGES[e, 0] * stop_sd
            ty = _EDGES[e, 1] * stop_sd
            ax = _EDGES[e, 0] * r_ep
            ay = _EDGES[e, 1] * r_ep
            f0, f1 = _stop_miss(ax, ay, sx, sy, sz, z_ref, tx, ty, table, coef, stop, buf, ok)
            for _ in range(AIM_ITERATIONS):
                if math.hypot(f0, f1) <= tol:
                    break
                if math.isnan(f0) or math.isnan(f1):
                    # a guess that misses a surface: pull it toward the axis and retry
                    ax *= 0.5
                    ay *= 0.5
                    f0, f1 = _stop_miss(ax, ay, sx, sy, sz, z_ref, tx, ty, table, coef, stop,
                                        buf, ok)
                    continue
                gx0, gx1 = _stop_miss(ax + h, ay, sx, sy, sz, z_ref, tx, ty, table, coef,
                                      stop, buf, ok)
                gy0, gy1 = _stop_miss(ax, ay + h, sx, sy, sz, z_ref, tx, ty, table, coef,
                                      stop, buf, ok)
                j11 = (gx0 - f0) / h
                j21 = (gx1 - f1) / h
                j12 = (gy0 - f0) / h
                j22 = (gy1 - f1) / h
                det = j11 * j22 - j12 * j21
                step_x = -(j22 * f0 - j12 * f1) / det
                step_y = -(-j21 * f0 + j11 * f1) / det
                if not math.isfinite(step_x):
                    step_x = 0.0
                if not math.isfinite(step_y):
                    step_y = 0.0
                old = math.hypot(f0, f1)
                lam = 1.0
                cx = ax
                cy = ay
                c0 = f0
                c1 = f1
                for _ in range(8):  # damping: halve the step while the miss grows or is NaN
                    cx = ax + lam * step_x
                    cy = ay + lam * step_y
                    c0, c1 = _stop_miss(cx, cy, sx, sy, sz, z_ref, tx, ty, table, coef, stop,
                                        buf, ok)
                    if math.hypot(c0, c1) <= max(old, tol):
                        break
                    lam *= 0.5
                ax = cx
                ay = cy
                f0 = c0
                f1 = c1
            if not math.hypot(f0, f1) <= tol:
                aimed = False
                break
            # the aimed object-space ray's crossing of the aperture plane
            dx = ax - sx
            dy = ay - sy
            dz = z_ref - sz
            norm = math.sqrt(dx * dx + dy * dy + dz * dz)
            t = (z_ap - sz) / (dz / norm)
            hx[e] = sx + t * (dx / norm)
            hy[e] = sy + t * (dy / norm)
        if aimed:
            out[p, 0] = 0.5 * (hx[0] + hx[1])
            out[p, 1] = 0.5 * (hy[2] + hy[3])
            out[p, 2] = 0.5 * (hx[0] - hx[1]) / half
            out[p, 3] = 0.5 * (hy[2] - hy[3]) / half
        else:
            out[p, 0] = 0.0
            out[p, 1] = 0.0
            out[p, 2] = 1.0
            out[p, 3] = 1.0
    return out


# ----------------------------------------------------------------------------- cell samples
CELL_NEWTON = 8  # Newton iterations of the pupil map's inverse, at most (from its linear part:
#                 5-6 on system 2's large blurs behind focus)
CELL_NEWTON_REACH = 1.5  # ... until every sample whose iterate is within this pupil radius
#                          has converged (one beyond it lies past the rim)
CELL_START_REACH2 = 16.0  # a lattice point whose preimage by the map's linear part lies beyond
#                           this squared pupil radius is not inverted: past the rim however
#                           strong the aberration (system 2 behind a 1 m focus: the rim's
#                           cells at pupil radius 0.88-1 have linear preimages at 1.5-1.9)
CELL_NEWTON_STEP = 1e-4  # Newton ends on a step under this (pupil radii): the root is then
#                          within ~1e-8 of it, ~1e-6 pitch on the MLA


MAP_DEGREE = 5  # the pupil → MLA map's polynomial degree (cubic: 0.015 pitch RMS off the exact
#                trace on a large system-2 blur, 0.08 at most; quintic: 0.0005 and 0.003);
#                _poly5 is written out for it


@njit(cache=True, nogil=True, inline="always", fastmath={"contract"})
def _map2(c_x, c_y, u, v):
    """Values and partial derivatives of the two polynomials ``c_x``, ``c_y`` of degree
    :data:`MAP_DEGREE` at the pupil point (u, v) (terms ``u^i v^(k−i)``, k = 0 … degree,
    i = 0 … k, in that order: :func:`lfcam.measure.fastfit._map_basis`): x, y, ∂x/∂u, ∂x/∂v,
    ∂y/∂u, ∂y/∂v."""
    fx, j11, j12 = _poly5(c_x, u, v)
    fy, j21, j22 = _poly5(c_y, u, v)
    return fx, fy, j11, j12, j21, j22


@njit(cache=True, nogil=True, inline="always", fastmath={"contract"})
def _poly5(c, u, v):
    """One polynomial of :func:`_map2` (``c`` (21,)) and its two partial derivatives, in
    Horner's form: ``f = Σᵢ uⁱ Pᵢ(v)`` (the term ``uⁱ vʲ`` is ``c[k(k+1)/2 + i]``, k = i + j),
    each ``Pᵢ`` and the sums over i nested: half the multiplications of the written-out
    powers (with the fused multiply-adds, :func:`cell_samples` takes 26-34 % less CPU)."""
    p0 = c[0] + v * (c[1] + v * (c[3] + v * (c[6] + v * (c[10] + v * c[15]))))
    p1 = c[2] + v * (c[4] + v * (c[7] + v * (c[11] + v * c[16])))
    p2 = c[5] + v * (c[8] + v * (c[12] + v * c[17]))
    p3 = c[9] + v * (c[13] + v * c[18])
    p4 = c[14] + v * c[19]
    p5 = c[20]
    f = p0 + u * (p1 + u * (p2 + u * (p3 + u * (p4 + u * p5))))
    fu = p1 + u * (2.0 * p2 + u * (3.0 * p3 + u * (4.0 * p4 + u * 5.0 * p5)))
    d0 = c[1] + v * (2.0 * c[3] + v * (3.0 * c[6] + v * (4.0 * c[10] + v * 5.0 * c[15])))
    d1 = c[4] + v * (2.0 * c[7] + v * (3.0 * c[11] + v * 4.0 * c[16]))
    d2 = c[8] + v * (2.0 * c[12] + v * 3.0 * c[17])
    d3 = c[13] + v * 2.0 * c[18]
    fv = d0 + u * (d1 + u * (d2 + u * (d3 + u * c[19])))
    return f, fu, fv


@njit(cache=True, nogil=True, inline="always", fastmath={"contract"})
def _poly5_value(c, u, v):
    """:func:`_poly5`'s polynomial's value alone."""
    p0 = c[0] + v * (c[1] + v * (c[3] + v * (c[6] + v * (c[10] + v * c[15]))))
    p1 = c[2] + v * (c[4] + v * (c[7] + v * (c[11] + v * c[16])))
    p2 = c[5] + v * (c[8] + v * (c[12] + v * c[17]))
    p3 = c[9] + v * (c[13] + v * c[18])
    p4 = c[14] + v * c[19]
    return p0 + u * (p1 + u * (p2 + u * (p3 + u * (p4 + u * c[20]))))


@njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def _newton_pass(c_x, c_y, gx, gy, u, v, det, step, count):
    """One Newton step of the inverse of the map ``(c_x, c_y)`` (:func:`_map2`) at each of the
    first ``count`` points: ``(u, v)`` moves toward the preimage of ``(gx, gy)``; ``det`` is
    the map's Jacobian determinant where the step was taken, ``step`` the step's length
    (|Δu| + |Δv|; not finite where ``det`` is 0 or the point is not finite, which never
    passes the convergence test). No branch: SIMD."""
    for k in range(count):
        fx, fy, j11, j12, j21, j22 = _map2(c_x, c_y, u[k], v[k])
        d = j11 * j22 - j12 * j21
        rx = gx[k] - fx
        ry = gy[k] - fy
        su = (j22 * rx - j12 * ry) / d
        sv = (-j21 * rx + j11 * ry) / d
        u[k] += su
        v[k] += sv
        det[k] = d
        step[k] = abs(su) + abs(sv)


@njit(cache=True, nogil=True, inline="always")
def _newton_until(c_x, c_y, gx, gy, u, v, det, step, count, reach2):
    """Newton passes (:func:`_newton_pass`), at most :data:`CELL_NEWTON`, until every point
    whose iterate lies within ``reach2`` (squared pupil radii) has a step under
    :data:`CELL_NEWTON_STEP`."""
    for _ in range(CELL_NEWTON):
        _newton_pass(c_x, c_y, gx, gy, u, v, det, step, count)
        left = 0
        for k in range(count):
            left += (not (step[k] < CELL_NEWTON_STEP)) & (u[k] * u[k] + v[k] * v[k] < reach2)
        if left == 0:
            break


@njit(cache=True, nogil=True, inline="always")
def _in_reach(gx, gy, x_lo, x_hi, y_lo, y_hi, cx, cy, r2):
    """Whether the MLA point (gx, gy) lies in a point's footprint box and its reach disc
    (centre (cx, cy), squared radius r2)."""
    ox = gx - cx
    oy = gy - cy
    return not (gx < x_lo or gx > x_hi or gy < y_lo or gy > y_hi or ox * ox + oy * oy > r2)


@njit(cache=True, nogil=True, inline="always")
def _linear_start(gx, gy, x0, y0, a11, a12, a21, a22, det0):
    """The preimage (u, v) of the MLA point (gx, gy) under a map's linear part (constant
    (x0, y0), matrix ``[[a11, a12], [a21, a22]]``, determinant det0): Newton's start, and
    whether it lies within :data:`CELL_START_REACH2` (one beyond it is past the rim)."""
    ex = gx - x0
    ey = gy - y0
    u = (a22 * ex - a12 * ey) / det0
    v = (-a21 * ex + a11 * ey) / det0
    return not (u * u + v * v > CELL_START_REACH2), u, v


@njit(cache=True, nogil=True, inline="always")
def _candidate(gx, gy, c_x, c_y, a11, a12, a21, a22, det0, gxs, gys, cu, cv, nc):
    """Put the MLA point ``(gx, gy)`` and its Newton start (:func:`_linear_start`) at ``nc`` of
    the candidates' arrays, if the start is near enough to be one; whether it was."""
    near, u, v = _linear_start(gx, gy, c_x[0], c_y[0], a11, a12, a21, a22, det0)
    if near:
        gxs[nc] = gx
        gys[nc] = gy
        cu[nc] = u
        cv[nc] = v
    return near


@njit(cache=True, nogil=True, inline="always")
def _lattice_bounds(x_lo, x_hi, y_lo, y_hi, origin, inverse):
    """The lattice coordinates' ranges (s lo, s hi, t lo, t hi) over an MLA box's corners."""
    s_lo = math.inf
    s_hi = -math.inf
    t_lo = math.inf
    t_hi = -math.inf
    for cxr in (x_lo, x_hi):
        for cyr in (y_lo, y_hi):
            ex = cxr - origin[0]
            ey = cyr - origin[1]
            s = inverse[0, 0] * ex + inverse[0, 1] * ey
            t = inverse[1, 0] * ex + inverse[1, 1] * ey
            s_lo = min(s_lo, s)
            s_hi = max(s_hi, s)
            t_lo = min(t_lo, t)
            t_hi = max(t_hi, t)
    return s_lo, s_hi, t_lo, t_hi


@njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def cell_samples(cx, cy, boxes, reach, origin, basis, inverse, n, skip_grid, skip,
                 share_spacing, rect, la, lb):
    """Pupil samples of each point source whose images on the MLA form a fixed sub-grid of
    every lattice cell: the centres of the n × n sub-cells of the cell about each node, the
    points ``(i + (a + o)/n, j + (b + o)/n)`` in lattice coordinates (``a, b = 0 … n−1``: n²
    a cell, wherever the cell's border runs; ``o`` = ½ for even n, 0 for odd: (a + ½)/n − ½
    modulo 1; docs/distance.md, "Samples fixed on the lenslet cells", on why no other offset),
    each mapped back to the unit pupil disc through the inverse of
    the point's polynomial pupil → MLA map ``(cx[p], cy[p])`` (M, terms) (:func:`_map2`) by
    Newton, started from the map's linear part: each Newton iteration is one pass over all of
    a point's sub-grid points (:func:`_newton_pass`, straight-line code the compiler runs in
    SIMD lanes), until every one within :data:`CELL_NEWTON_REACH` of the pupil's centre has
    converged, and one more pass takes the area element at the roots. Walking each row
    instead, each sample started from the three before it, took one iteration a sample but
    each waited for the one before: 62-67 ns a sample against 30-40 (docs/distance.md,
    "Speed at stop 42").

    ``boxes`` (M, 4): each point's footprint box on the MLA (x lo, x hi, y lo, y hi, mm);
    ``reach`` (M, 3): a disc (centre x, y, radius, mm) that holds each footprint.
    Returns ``u, v`` (pupil, unit disc), ``w`` (the sample's pupil area, ``|∂u/∂X|`` × the
    sub-cell's area, times its share of the pupil's rim: linear over its own spacing there),
    ``rows`` (point index) and ``du`` (M,): each point's mean pupil spacing of its samples.

    ``skip_grid`` (M, 5) and ``skip``: the cells left out (integrated whole by
    :func:`cell_centres`): point ``p``'s nodes ``(i, j)``, ``i0 ≤ i < i0 + ni``, ``j0 ≤ j <
    j0 + nj``, rows ``(i0, j0, ni, nj, offset)``, are left out where ``skip[offset + (i −
    i0)·nj + (j − j0)]`` is set. On a rectangular lattice a sub-grid point's cell is its
    nearest node's, and no sample lies across a border. On a hexagonal one a sample belongs
    to its nearest node's cell and is shared with the next nearest's as the deposit shares
    it (linearly over ``share_spacing`` across their border: :func:`deposit_moments`).
    Where one of the two cells is whole and the other not, the sample keeps only the other's
    share (its weight × that share) and lands there alone: ``tx, ty`` (that node's MLA
    position, for the deposit; NaN for a sample shared as usual; both empty where no sample
    is moved). So every cell that is not whole keeps the light its samples gave it, and a
    whole cell gets none of theirs.

    ``rect, la, lb``: whether the lattice's cells are rectangles and its basis vectors'
    lengths (``fastfit._cell_shape``, as :func:`deposit_moments` takes them).

    Returns ``u, v, w, rows, du, tx, ty``.
    """
    m = cx.shape[0]
    area = abs(basis[0, 0] * basis[1, 1] - basis[0, 1] * basis[1, 0]) / (n * n)
    o = 0.5 * ((n + 1) % 2)
    reach2 = CELL_NEWTON_REACH * CELL_NEWTON_REACH
    cap = 1024
    us = np.empty(cap)
    vs = np.empty(cap)
    ws = np.empty(cap)
    rows = np.empty(cap, dtype=np.int64)
    du_mean = np.zeros(m)
    count = 0
    # one point's sub-grid points (its candidates) and their Newton state
    ccap = 1024
    gxs = np.empty(ccap)
    gys = np.empty(ccap)
    cu = np.empty(ccap)
    cv = np.empty(ccap)
    cdet = np.empty(ccap)
    cstep = np.empty(ccap)
    conv = np.empty(ccap, dtype=np.bool_)
    qa = basis[0, 1] * basis[0, 1] + basis[1, 1] * basis[1, 1]
    seps = _separations(basis)
    half = 0.5 if rect else 0.0  # (the row's cells, below)
    # (samples moved to a neighbour's node: only on a hexagonal lattice with whole cells;
    # otherwise tx, ty are empty)
    moves = (not rect) and skip_grid.shape[0] > 0 and skip_grid[:, 2].max() > 0
    txs = np.empty(cap if moves else 0)
    tys = np.empty(cap if moves else 0)
    cfac = np.empty(ccap)
    ctx = np.empty(ccap)
    cty = np.empty(ccap)
    blocks = np.zeros(64, dtype=np.int64)
    for p in range(m):
        c_x = cx[p]
        c_y = cy[p]
        # the linear terms (order 1, v then u: see _map2): the Newton start
        a11, a12, a21, a22 = c_x[2], c_x[1], c_y[2], c_y[1]
        det0 = a11 * a22 - a12 * a21
        if det0 == 0.0 or not math.isfinite(det0):
            continue
        x_lo, x_hi, y_lo, y_hi = boxes[p, 0], boxes[p, 1], boxes[p, 2], boxes[p, 3]
        if x_lo > x_hi:
            continue  # (an empty box: nothing left to sample)
        # the box's corners in lattice coordinates bound the cells to visit
        s_lo, s_hi, t_lo, t_hi = _lattice_bounds(x_lo, x_hi, y_lo, y_hi, origin, inverse)
        r2 = reach[p, 2] * reach[p, 2]
        nc = 0
        hex_skip = (not rect) and skip_grid[p, 2] > 0
        if hex_skip:
            # each lattice cell [i, i + 1] × [j, j + 1] of the point's grid: how many of its
            # four corners are whole
            nbk = skip_grid[p, 2] * skip_grid[p, 3]
            if nbk > blocks.size:
                blocks = np.zeros(2 * nbk, dtype=np.int64)
            gn = skip_grid[p, 3]
            at = skip_grid[p, 4]
            for a in range(skip_grid[p, 2]):
                for b in range(gn):
                    c = int(skip[at + a * gn + b])
                    if b + 1 < gn:
                        c += int(skip[at + a * gn + b + 1])
                    if a + 1 < skip_grid[p, 2]:
                        c += int(skip[at + (a + 1) * gn + b])
                        if b + 1 < gn:
                            c += int(skip[at + (a + 1) * gn + b + 1])
                    blocks[a * gn + b] = c
        # the sub-grid is a finer lattice: row by row (fixed s index), the points of the row
        # inside the reach disc (an interval of t) and the box
        row_lo = (int(math.floor(t_lo)) - 1) * n
        row_hi = (int(math.ceil(t_hi)) + 1) * n
        for fi in range((int(math.floor(s_lo)) - 1) * n, (int(math.ceil(s_hi)) + 1) * n):
            s = (fi + o) / n
            # the row's points g(t) = p0 + t·b2 inside the reach disc: a quadratic in t
            px0 = origin[0] + basis[0, 0] * s - reach[p, 0]
            py0 = origin[1] + basis[1, 0] * s - reach[p, 1]
            qb = px0 * basis[0, 1] + py0 * basis[1, 1]
            qc = px0 * px0 + py0 * py0 - r2
            disc = qb * qb - qa * qc
            if disc <= 0.0:
                continue
            root = math.sqrt(disc)
            j_lo = max(int(math.floor(((-qb - root) / qa) * n - o)), row_lo)
            j_hi = min(int(math.ceil(((-qb + root) / qa) * n - o)) + 1, row_hi)
            if nc + j_hi - j_lo > ccap:
                while nc + j_hi - j_lo > ccap:
                    ccap *= 2
                gxs = _grow(gxs, ccap)
                gys = _grow(gys, ccap)
                cu = _grow(cu, ccap)
                cv = _grow(cv, ccap)
                cdet = np.empty(ccap)
                cstep = np.empty(ccap)
                conv = np.empty(ccap, dtype=np.bool_)
                cfac = _grow(cfac, ccap)
                ctx = _grow(ctx, ccap)
                cty = _grow(cty, ccap)
            # the row's points cell by cell (a rectangular lattice's cell about node J holds
            # the points J − ½ ≤ t < J + ½; a hexagonal one's points are matched with the
            # parallelogram T ≤ t < T + 1 whose corners hold their nearest two nodes): a
            # cell left out whole is skipped at once
            bi = int(math.floor(s + half)) - skip_grid[p, 0]
            for tb in range(int(math.floor((j_lo + o) / n + half)),
                            int(math.floor((j_hi - 1 + o) / n + half)) + 1):
                bj = tb - skip_grid[p, 1]
                inside = 0 <= bi < skip_grid[p, 2] and 0 <= bj < skip_grid[p, 3]
                corners_whole = 0
                if inside and hex_skip:
                    corners_whole = blocks[bi * skip_grid[p, 3] + bj]
                    if corners_whole == 4:
                        continue
                elif inside and skip[skip_grid[p, 4] + bi * skip_grid[p, 3] + bj]:
                    continue
                for fj in range(max(j_lo, int(math.ceil((tb - half) * n - o))),
                                min(j_hi, int(math.ceil((tb + 1 - half) * n - o)))):
                    t = (fj + o) / n
                    gx = origin[0] + basis[0, 0] * s + basis[0, 1] * t
                    gy = origin[1] + basis[1, 0] * s + basis[1, 1] * t
                    if not _in_reach(gx, gy, x_lo, x_hi, y_lo, y_hi, reach[p, 0], reach[p, 1],
                                     r2):
                        continue
                    fac = 1.0
                    tgx = math.nan
                    tgy = math.nan
                    if corners_whole > 0:
                        i1, j1, i2, j2, gap = _nearest_two(gx - origin[0], gy - origin[1],
                                                           inverse, basis, rect, la, lb, seps)
                        share = min(max(0.5 - gap / share_spacing, 0.0), 0.5)
                        w1 = _is_whole(skip_grid, skip, p, i1, j1)
                        w2 = share > 0.0 and _is_whole(skip_grid, skip, p, i2, j2)
                        if w1 and (share == 0.0 or w2):
                            continue
                        if w1:  # only its share in the neighbour, which is not whole
                            fac = share
                            tgx = origin[0] + basis[0, 0] * i2 + basis[0, 1] * j2
                            tgy = origin[1] + basis[1, 0] * i2 + basis[1, 1] * j2
                        elif w2:  # only its own share (the neighbour is whole)
                            fac = 1.0 - share
                            tgx = origin[0] + basis[0, 0] * i1 + basis[0, 1] * j1
                            tgy = origin[1] + basis[1, 0] * i1 + basis[1, 1] * j1
                    if not _candidate(gx, gy, c_x, c_y, a11, a12, a21, a22, det0, gxs, gys,
                                      cu, cv, nc):
                        continue
                    if hex_skip:
                        cfac[nc] = fac
                        ctx[nc] = tgx
                        cty[nc] = tgy
                    nc += 1
        if nc == 0:
            continue
        # Newton, one pass over all the candidates an iteration, until each within the reach
        # has a step under CELL_NEWTON_STEP (the root then within ~step² of it); those beyond
        # it lie past the pupil's rim (dropped below, converged or not)
        _newton_until(c_x, c_y, gxs, gys, cu, cv, cdet, cstep, nc, reach2)
        for k in range(nc):
            conv[k] = ((cstep[k] < CELL_NEWTON_STEP)
                       & (cu[k] * cu[k] + cv[k] * cv[k] <= CELL_START_REACH2))
        # the area element at the roots: one more pass (it moves them by ~1e-8)
        _newton_pass(c_x, c_y, gxs, gys, cu, cv, cdet, cstep, nc)
        if count + nc > cap:
            while count + nc > cap:
                cap *= 2
            us = _grow(us, cap)
            vs = _grow(vs, cap)
            ws = _grow(ws, cap)
            rows = _grow_int(rows, cap)
            if moves:
                txs = _grow(txs, cap)
                tys = _grow(tys, cap)
        n_du = 0.0
        n_kept = 0
        for k in range(nc):
            u = cu[k]
            v = cv[k]
            d_area = area / abs(cdet[k])
            spacing = math.sqrt(d_area)
            r = math.sqrt(u * u + v * v)
            if not (conv[k] and d_area < math.inf and r < 1.0 + 0.5 * spacing):
                continue
            # its share of the pupil's rim: linear over its own spacing there; a sample beyond
            # the rim (its share there) is traced on the rim
            rim = min(max(0.5 + (1.0 - r) / spacing, 0.0), 1.0)
            scale = min(1.0, 1.0 / r)
            us[count] = u * scale
            vs[count] = v * scale
            if hex_skip:
                ws[count] = d_area * rim * cfac[k]
                txs[count] = ctx[k]
                tys[count] = cty[k]
            else:
                ws[count] = d_area * rim
                if moves:
                    txs[count] = math.nan
                    tys[count] = math.nan
            rows[count] = p
            count += 1
            n_du += spacing
            n_kept += 1
        if n_kept:
            du_mean[p] = n_du / n_kept
    return (us[:count], vs[:count], ws[:count], rows[:count], du_mean,
            txs[:count if moves else 0], tys[:count if moves else 0])


@njit(cache=True, nogil=True, inline="always")
def _is_whole(skip_grid, skip, p, i, j):
    """Whether point ``p``'s cell at node ``(i, j)`` is whole (:func:`cell_samples`)."""
    a = int(i) - skip_grid[p, 0]
    b = int(j) - skip_grid[p, 1]
    return ((0 <= a) & (a < skip_grid[p, 2]) & (0 <= b) & (b < skip_grid[p, 3])
            and skip[skip_grid[p, 4] + a * skip_grid[p, 3] + b])


@njit(cache=True, nogil=True)
def _grow(a, cap):
    out = np.empty(cap)
    out[: a.size] = a
    return out


@njit(cache=True, nogil=True)
def _grow_int(a, cap):
    out = np.empty(cap, dtype=np.int64)
    out[: a.size] = a
    return out


# ----------------------------------------------------------------------------- whole cells
CELL_WHOLE_MARGIN = 1.25  # a cell is integrated whole where its pupil patch (its corners'
#                           preimages by the map's linear part at its centre), this much
#                           wider, lies inside the pupil (docs/distance.md, "Cells
#                           integrated whole (stop 43)")
CELL_WHOLE_MAX_PATCH = 0.1  # ... and whose patch reaches at most this far (pupil radii): the
#                             2 × 2 Gauss rule leaves 1.4 % of a cell's light on patches of
#                             0.25 (a small blur: 5 whole cells)
CELL_SPLIT = 3  # a whole hexagonal cell's landing across lenslets' pixels: cut into this²
#                 (4 until stop 47: as many moments, a piece's pixels 3.3e-3 off a dense
#                 sample's where 3 × 3 leave 7.2e-4, 16 pieces for 9; docs/distance.md,
#                 "Cheaper kernels (stop 47)")
RIM_SPLIT = 2  # ... and a rim's cut cell's rectangle (_rim_cut) into this² (4: the same
#                moments within 2e-5 of their norm, 20 % more deposit_cells CPU)
CELL_GAUSS_2 = 0.5 / math.sqrt(3.0)  # the 2 × 2 Gauss rule's points: ± this × a cell's sides


@njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def cell_centres(cx, cy, boxes, reach, origin, basis, inverse, margin, corners, rule, rule_w,
                 polygon):
    """The lattice cells each point source lights whole, and the pupil points of each one's
    quadrature rule: the cell about a node is the polygon whose corners are ``±corners`` (C,
    2; offsets from the node, MLA mm), the rule's points ``node + rule[q]`` (K, 2), weights
    ``rule_w[q]`` (K,: shares of the cell's area, summing to 1). On a rectangular lattice
    the cell is the parallelogram ``node + [−½, ½]·b₁ + [−½, ½]·b₂`` and the rule the 2 × 2
    Gauss rule; on a hexagonal one the hexagon and a ring of six
    (:func:`lfcam.measure.fastfit.cell_rule`).

    Each node inside the point's box and reach (as :func:`cell_samples`) is mapped back to the
    unit pupil disc through the inverse of the point's polynomial pupil → MLA map ``(cx[p],
    cy[p])`` by Newton (:func:`_newton_pass`). Where the preimages of the cell's corners by
    the map's linear part there reach within ``1 − r`` of the pupil's centre with ``margin``
    to spare (``r`` the node's pupil radius), the whole cell is lit. Its light is then
    integrated by the rule (its points each mapped back by Newton from the linear part's
    preimage): both rules are exact for a density and a landing cubic across the cell, where
    the midpoint rule leaves the density's curvature (1.8e-3 of a lenslet's light at the
    centre of a large blur behind focus; docs/distance.md, "Cells integrated whole (stop
    43)" and "Whole hexagonal cells (stop 45)").

    ``polygon`` (V, 2: the cell's corners in order about the node, or empty): the cells the
    pupil's rim cuts are integrated too, each over its part inside the rim (the rim's image
    a line across the cell: :func:`_rim_cut`) by the 4-point rule of that polygon's second
    moments (:func:`_moment_rule`), and the cells wholly past the rim left out; neither is
    then sampled (docs/distance.md, "Rim cells cut by the rim's line (stop 46)").

    Returns ``rows`` (point), ``ci, cj`` (the cell's lattice indices), ``u, v`` (n, K: the
    rule's pupil points, in its order), ``w`` (n, K: each one's pupil area, ``|cell| ·
    rule_w[q] / |det ∂X/∂u|``), ``skip_grid``, ``skip`` (:func:`cell_samples`'s: these
    cells left out of its samples), and the rim cells' ``rows, ci, cj, u, v, w`` (n, 4:
    the moment rule's points ``+e₁, −e₁, +e₂, −e₂``; all empty without ``polygon``), and
    ``unresolved`` (M,): how many of each point's nodes its samples must still cover
    (0: none; with ``polygon`` a point without any needs no :func:`cell_samples`).
    """
    m = cx.shape[0]
    nq = rule.shape[0]
    cell_area = abs(basis[0, 0] * basis[1, 1] - basis[0, 1] * basis[1, 0])
    grid = np.zeros((m, 5), dtype=np.int64)
    cap = 1024
    rows = np.empty(cap, dtype=np.int64)
    ci = np.empty(cap)
    cj = np.empty(cap)
    us = np.empty((cap, nq))
    vs = np.empty((cap, nq))
    ws = np.empty((cap, nq))
    skip = np.zeros(1024, dtype=np.bool_)
    count = 0
    moff = 0
    rim = polygon.shape[0] > 0
    # each point's cells its samples must still cover (nodes neither whole, cut nor dark)
    unresolved = np.zeros(m, dtype=np.int64)
    rcap = 256
    r_rows = np.empty(rcap, dtype=np.int64)
    r_ci = np.empty(rcap)
    r_cj = np.empty(rcap)
    r_us = np.empty((rcap, 4))
    r_vs = np.empty((rcap, 4))
    r_ws = np.empty((rcap, 4))
    r_count = 0
    # one point's rim cells: node (a, b), the rule's MLA points and their Newton state
    rim_a = np.empty(rcap, dtype=np.int64)
    rim_b = np.empty(rcap, dtype=np.int64)
    rim_w = np.empty(rcap)
    rgx = np.empty(4 * rcap)
    rgy = np.empty(4 * rcap)
    rcu = np.empty(4 * rcap)
    rcv = np.empty(4 * rcap)
    rdet = np.empty(4 * rcap)
    rstep = np.empty(4 * rcap)
    cut = np.empty((polygon.shape[0] + 2, 2))
    ccap = 256
    gxs = np.empty(ccap)
    gys = np.empty(ccap)
    cu = np.empty(ccap)
    cv = np.empty(ccap)
    cdet = np.empty(ccap)
    cstep = np.empty(ccap)
    ni_ = np.empty(ccap, dtype=np.int64)
    nj_ = np.empty(ccap, dtype=np.int64)
    for p in range(m):
        c_x = cx[p]
        c_y = cy[p]
        a11, a12, a21, a22 = c_x[2], c_x[1], c_y[2], c_y[1]
        det0 = a11 * a22 - a12 * a21
        unresolved[p] = 1  # (until its nodes are resolved, below)
        if det0 == 0.0 or not math.isfinite(det0):
            continue
        x_lo, x_hi, y_lo, y_hi = boxes[p, 0], boxes[p, 1], boxes[p, 2], boxes[p, 3]
        s_lo, s_hi, t_lo, t_hi = _lattice_bounds(x_lo, x_hi, y_lo, y_hi, origin, inverse)
        i0 = int(math.floor(s_lo)) - 1
        j0 = int(math.floor(t_lo)) - 1
        ni = int(math.ceil(s_hi)) + 2 - i0
        nj = int(math.ceil(t_hi)) + 2 - j0
        grid[p, 0] = i0
        grid[p, 1] = j0
        grid[p, 2] = ni
        grid[p, 3] = nj
        grid[p, 4] = moff
        if moff + ni * nj > skip.size:
            big = skip.size
            while moff + ni * nj > big:
                big *= 2
            grown = np.zeros(big, dtype=np.bool_)
            grown[:moff] = skip[:moff]
            skip = grown
        skip[moff:moff + ni * nj] = False
        moff += ni * nj
        if (1 + nq) * ni * nj > ccap:
            while (1 + nq) * ni * nj > ccap:
                ccap *= 2
            gxs = np.empty(ccap)
            gys = np.empty(ccap)
            cu = np.empty(ccap)
            cv = np.empty(ccap)
            cdet = np.empty(ccap)
            cstep = np.empty(ccap)
            ni_ = np.empty(ccap, dtype=np.int64)
            nj_ = np.empty(ccap, dtype=np.int64)
        r2 = reach[p, 2] * reach[p, 2]
        nc = 0
        far = 0  # nodes past CELL_NEWTON_REACH (or whose linear start is): dark on a large blur
        for a in range(ni):
            for b in range(nj):
                i = float(i0 + a)
                j = float(j0 + b)
                gx = origin[0] + basis[0, 0] * i + basis[0, 1] * j
                gy = origin[1] + basis[1, 0] * i + basis[1, 1] * j
                if not _in_reach(gx, gy, x_lo, x_hi, y_lo, y_hi, reach[p, 0], reach[p, 1], r2):
                    continue
                if not _candidate(gx, gy, c_x, c_y, a11, a12, a21, a22, det0, gxs, gys, cu, cv,
                                  nc):
                    far += 1
                    continue
                ni_[nc] = a
                nj_[nc] = b
                nc += 1
        if nc == 0:
            continue
        # (until those within CELL_NEWTON_REACH have converged: a node beyond it is past the
        # rim, its cell not lit whole)
        _newton_until(c_x, c_y, gxs, gys, cu, cv, cdet, cstep, nc,
                      CELL_NEWTON_REACH * CELL_NEWTON_REACH)
        # the whole cells, and their Gauss points' starts (appended after the nodes)
        nw = 0
        nr = 0
        left = 0
        resolved = 0
        for k in range(nc):
            if not (cstep[k] < CELL_NEWTON_STEP):
                if cu[k] * cu[k] + cv[k] * cv[k] < CELL_NEWTON_REACH * CELL_NEWTON_REACH:
                    left += 1
                else:
                    far += 1
                continue
            u = cu[k]
            v = cv[k]
            _, _, j11, j12, j21, j22 = _map2(c_x, c_y, u, v)
            d = j11 * j22 - j12 * j21
            if d == 0.0 or not math.isfinite(d):
                left += 1
                continue
            ia = j22 / d
            ib = -j12 / d
            ic = -j21 / d
            ie = j11 / d
            # the cell's reach in the pupil: its farthest corner's linear image (squared
            # lengths, one root: math.hypot a corner cost ~10 % of this kernel)
            patch2 = 0.0
            for q in range(corners.shape[0]):
                du = ia * corners[q, 0] + ib * corners[q, 1]
                dv = ic * corners[q, 0] + ie * corners[q, 1]
                patch2 = max(patch2, du * du + dv * dv)
            patch = math.sqrt(patch2)
            if patch > CELL_WHOLE_MAX_PATCH:
                left += 1
                continue
            resolved += 1
            rr = math.sqrt(u * u + v * v)
            if rr + margin * patch >= 1.0:
                if not rim:
                    left += 1
                    continue
                at_skip = grid[p, 4] + ni_[k] * nj + nj_[k]
                if rr - margin * patch > 1.0:
                    skip[at_skip] = True  # wholly past the rim: no light
                    continue
                # cut by the rim: its part inside, and that part's moment rule
                area_in = _rim_cut(c_x, c_y, gxs[k], gys[k], u, v, ia, ib, ic, ie, polygon,
                                   polygon.shape[0], cut, rgx, rgy, 4 * nr, cell_area)
                if area_in <= 0.0:
                    skip[at_skip] = True
                    continue
                if area_in < (1.0 - 1e-9) * cell_area:
                    skip[at_skip] = True
                    for q in range(4):
                        ox = rgx[4 * nr + q]
                        oy = rgy[4 * nr + q]
                        rgx[4 * nr + q] = gxs[k] + ox
                        rgy[4 * nr + q] = gys[k] + oy
                        rcu[4 * nr + q] = u + ia * ox + ib * oy
                        rcv[4 * nr + q] = v + ic * ox + ie * oy
                    rim_a[nr] = ni_[k]
                    rim_b[nr] = nj_[k]
                    rim_w[nr] = area_in
                    nr += 1
                    if nr == rcap:
                        rcap *= 2
                        rim_a = _grow_int(rim_a, rcap)
                        rim_b = _grow_int(rim_b, rcap)
                        rim_w = _grow(rim_w, rcap)
                        rgx = _grow(rgx, 4 * rcap)
                        rgy = _grow(rgy, 4 * rcap)
                        rcu = _grow(rcu, 4 * rcap)
                        rcv = _grow(rcv, 4 * rcap)
                        rdet = np.empty(4 * rcap)
                        rstep = np.empty(4 * rcap)
                    continue
                # (not cut after all: the whole cell's rule, below)
            ni_[nw] = ni_[k]
            nj_[nw] = nj_[k]
            for q in range(nq):
                ox = rule[q, 0]
                oy = rule[q, 1]
                at = nc + nq * nw + q
                gxs[at] = gxs[k] + ox
                gys[at] = gys[k] + oy
                cu[at] = u + ia * ox + ib * oy
                cv[at] = v + ic * ox + ie * oy
            nw += 1
        if nr:
            # the rim cells' rule points: Newton from the node's linear part, and one more
            # pass for the area element; a point the rim's curve leaves just outside the
            # pupil is traced on its rim (as a sample there: cell_samples)
            _newton_until(c_x, c_y, rgx, rgy, rcu, rcv, rdet, rstep, 4 * nr, math.inf)
            _newton_pass(c_x, c_y, rgx, rgy, rcu, rcv, rdet, rstep, 4 * nr)
            r_rows, r_ci, r_cj, r_us, r_vs, r_ws = _grow_cells(r_rows, r_ci, r_cj, r_us, r_vs,
                                                               r_ws, r_count + nr)
            for k in range(nr):
                ok = True
                for q in range(4):
                    at = 4 * k + q
                    ok &= (rstep[at] < CELL_NEWTON_STEP) & (rdet[at] != 0.0)
                if not ok:
                    # (left to the samples)
                    skip[grid[p, 4] + rim_a[k] * nj + rim_b[k]] = False
                    left += 1
                    continue
                r_rows[r_count] = p
                r_ci[r_count] = float(i0 + rim_a[k])
                r_cj[r_count] = float(j0 + rim_b[k])
                for q in range(4):
                    at = 4 * k + q
                    uq = rcu[at]
                    vq = rcv[at]
                    sc = min(1.0, 1.0 / math.sqrt(uq * uq + vq * vq))
                    r_us[r_count, q] = uq * sc
                    r_vs[r_count, q] = vq * sc
                    r_ws[r_count, q] = 0.25 * rim_w[k] / abs(rdet[at])
                r_count += 1
        # a node past the pupil's reach is dark where every node resolved has a patch under
        # CELL_WHOLE_MAX_PATCH (its cell then reaches at most that far in)
        unresolved[p] = left + (far if resolved == 0 else 0)
        if nw == 0:
            continue
        # Newton on the Gauss points (from the linear part: 2-3 passes), and one more pass
        # for the area element at the roots
        gx4 = gxs[nc:nc + nq * nw]
        gy4 = gys[nc:nc + nq * nw]
        u4 = cu[nc:nc + nq * nw]
        v4 = cv[nc:nc + nq * nw]
        det4 = cdet[nc:nc + nq * nw]
        step4 = cstep[nc:nc + nq * nw]
        _newton_until(c_x, c_y, gx4, gy4, u4, v4, det4, step4, nq * nw, math.inf)
        _newton_pass(c_x, c_y, gx4, gy4, u4, v4, det4, step4, nq * nw)
        rows, ci, cj, us, vs, ws = _grow_cells(rows, ci, cj, us, vs, ws, count + nw)
        for k in range(nw):
            ok = True
            for q in range(nq):
                at = nq * k + q
                ok &= (step4[at] < CELL_NEWTON_STEP) & (det4[at] != 0.0)
                ok &= u4[at] * u4[at] + v4[at] * v4[at] < 1.0
            if not ok:
                unresolved[p] += 1
                continue  # (left to the samples)
            rows[count] = p
            ci[count] = float(i0 + ni_[k])
            cj[count] = float(j0 + nj_[k])
            for q in range(nq):
                at = nq * k + q
                us[count, q] = u4[at]
                vs[count, q] = v4[at]
                ws[count, q] = rule_w[q] * cell_area / abs(det4[at])
            skip[grid[p, 4] + ni_[k] * nj + nj_[k]] = True
            count += 1
    return (rows[:count], ci[:count], cj[:count], us[:count], vs[:count], ws[:count], grid,
            skip[:max(moff, 1)], r_rows[:r_count], r_ci[:r_count], r_cj[:r_count],
            r_us[:r_count], r_vs[:r_count], r_ws[:r_count], unresolved)


@njit(cache=True, nogil=True, inline="always")
def _rim_line(c_x, c_y, gx0, gy0, nx, ny):
    """The tangent to the rim's image on the MLA at the rim point ``(nx, ny)`` (unit): its
    outward unit normal ``(vx, vy)`` and its offset ``h`` from the node ``(gx0, gy0)`` along
    it (the inside: ``v · x ≤ h``)."""
    fx, fy, j11, j12, j21, j22 = _map2(c_x, c_y, nx, ny)
    tx = j11 * -ny + j12 * nx
    ty = j21 * -ny + j22 * nx
    vx = ty
    vy = -tx
    if vx * (j11 * nx + j12 * ny) + vy * (j21 * nx + j22 * ny) < 0.0:
        vx = -vx
        vy = -vy
    norm = math.hypot(vx, vy)
    vx /= norm
    vy /= norm
    return vx, vy, vx * (fx - gx0) + vy * (fy - gy0)


@njit(cache=True, nogil=True, inline="always")
def _clip(poly, nv, vx, vy, h, out):
    """The convex polygon ``poly[:nv]`` cut to ``v · x ≤ h`` (Sutherland–Hodgman, one line),
    into ``out``: its vertex count, and the two points where the line crosses its border
    (NaN where it does not)."""
    m = 0
    ex0 = ey0 = ex1 = ey1 = math.nan
    crossings = 0
    for i in range(nv):
        ax = poly[i, 0]
        ay = poly[i, 1]
        bx = poly[(i + 1) % nv, 0]
        by = poly[(i + 1) % nv, 1]
        da = vx * ax + vy * ay - h
        db = vx * bx + vy * by - h
        if da <= 0.0:
            out[m, 0] = ax
            out[m, 1] = ay
            m += 1
        if (da < 0.0 < db) or (db < 0.0 < da):
            t = da / (da - db)
            out[m, 0] = ax + t * (bx - ax)
            out[m, 1] = ay + t * (by - ay)
            if crossings == 0:
                ex0, ey0 = out[m, 0], out[m, 1]
            else:
                ex1, ey1 = out[m, 0], out[m, 1]
            crossings += 1
            m += 1
    return m, ex0, ey0, ex1, ey1


@njit(cache=True, nogil=True, inline="always")
def _cos_sin(x):
    """cos and sin of an angle: by their series where it is small (under 0.2 rad: within
    1e-7 and 3e-9), which a cell's angle along the rim is."""
    if abs(x) > 0.2:
        return math.cos(x), math.sin(x)
    x2 = x * x
    return 1.0 - x2 * (0.5 - x2 * (1.0 / 24.0 - x2 / 720.0)), x * (1.0 - x2 * (
        1.0 / 6.0 - x2 * (1.0 / 120.0 - x2 / 5040.0)))


@njit(cache=True, nogil=True)
def _rim_cut(c_x, c_y, gx0, gy0, u, v, ia, ib, ic, ie, poly, nv, cut, ox, oy, at,
             cell_area):
    """The part of the cell ``poly[:nv]`` (corners about its node ``(gx0, gy0)``, MLA mm, in
    counter-clockwise order) inside the pupil's rim: its area (MLA mm²), and the 4-point
    rule of its second moments at ``ox, oy[at : at + 4]`` (offsets from the node:
    :func:`_moment_rule`). ``(u, v)``: the node's pupil point, ``[[ia, ib], [ic, ie]]`` the
    inverse of the map's Jacobian there. A cell the first pass finds uncut (wholly inside)
    gets ``cell_area`` (its area) and no rule: the caller integrates it whole.

    The rim's image is taken as a line across the cell: first the rim seen through the
    node's linear map, which finds the chord the rim cuts; then the tangent to the rim's
    exact image at the chord's middle, moved inward by a third of the rim curve's depth at
    the chord's ends (the exact map there), so that the cut keeps the area a parabola would
    (the curve's depth over a chord of 0.05 pupil radii is ~3e-4 of the pupil radius)."""
    rr = math.sqrt(u * u + v * v)
    nx = u / rr
    ny = v / rr
    # the rim n · p = 1 with p = (u, v) + A·x: the line (Aᵀn) · x = 1 − rr; along it the rim's
    # angle from n is (Aᵀτ) · x, τ = (−n_y, n_x)
    wx = ia * nx + ic * ny
    wy = ib * nx + ie * ny
    norm = math.hypot(wx, wy)
    m, ex0, ey0, ex1, ey1 = _clip(poly, nv, wx / norm, wy / norm, (1.0 - rr) / norm, cut)
    if not math.isfinite(ex1):
        if m == nv:  # not cut: the whole cell, whose rule the caller takes (not this one)
            return cell_area
        return _moment_rule(cut, m, ox, oy, at) if m >= 3 else 0.0
    tax = ia * -ny + ic * nx
    tay = ib * -ny + ie * nx
    s0 = tax * ex0 + tay * ey0
    s1 = tax * ex1 + tay * ey1
    cm, sn = _cos_sin(0.5 * (s0 + s1))
    mx = nx * cm - ny * sn
    my = ny * cm + nx * sn
    vx, vy, h = _rim_line(c_x, c_y, gx0, gy0, mx, my)
    c2, s2 = _cos_sin(0.5 * abs(s1 - s0))
    depth = 0.0
    for sg in (-1.0, 1.0):
        pu = mx * c2 - sg * my * s2
        pv = my * c2 + sg * mx * s2
        depth += 0.5 * (vx * (_poly5_value(c_x, pu, pv) - gx0)
                        + vy * (_poly5_value(c_y, pu, pv) - gy0) - h)
    m = _clip(poly, nv, vx, vy, h + depth / 3.0, cut)[0]
    if m < 3:
        return 0.0
    return _moment_rule(cut, m, ox, oy, at)


@njit(cache=True, nogil=True, inline="always")
def _moment_rule(poly, m, ox, oy, at):
    """The area of the polygon ``poly[:m]`` (counter-clockwise), and at ``ox, oy[at : at +
    4]`` the 4-point rule of equal weights with its area's mean and second moments, ``c ±
    √(2λ₁)·e₁``, ``c ± √(2λ₂)·e₂`` (λ, e: the covariance's eigenvalues and vectors): exact
    for polynomials up to degree 2. A uniform rectangle of that covariance has sides
    ``√(12λ)·e``: √6/2 × the differences across its pairs (:data:`RIM_SIDES`)."""
    a2 = 0.0
    sx = 0.0
    sy = 0.0
    sxx = 0.0
    syy = 0.0
    sxy = 0.0
    for i in range(m):
        x0 = poly[i, 0]
        y0 = poly[i, 1]
        x1 = poly[(i + 1) % m, 0]
        y1 = poly[(i + 1) % m, 1]
        cr = x0 * y1 - x1 * y0
        a2 += cr
        sx += (x0 + x1) * cr
        sy += (y0 + y1) * cr
        sxx += (x0 * x0 + x0 * x1 + x1 * x1) * cr
        syy += (y0 * y0 + y0 * y1 + y1 * y1) * cr
        sxy += (x0 * y1 + 2.0 * x0 * y0 + 2.0 * x1 * y1 + x1 * y0) * cr
    area = 0.5 * a2
    if not area > 0.0:
        return 0.0
    cx = sx / (6.0 * area)
    cy = sy / (6.0 * area)
    vxx = sxx / (12.0 * area) - cx * cx
    vyy = syy / (12.0 * area) - cy * cy
    vxy = sxy / (24.0 * area) - cx * cy
    half = 0.5 * (vxx + vyy)
    rad = math.sqrt(max(0.25 * (vxx - vyy) ** 2 + vxy * vxy, 0.0))
    l1 = half + rad
    l2 = max(half - rad, 0.0)
    # the first eigenvector, from whichever row of (C − λ₁I) is the longer (any axis where
    # the moments are isotropic)
    ax_ = l1 - vyy
    ay_ = vxy
    bx_ = vxy
    by_ = l1 - vxx
    if ax_ * ax_ + ay_ * ay_ >= bx_ * bx_ + by_ * by_:
        e1x, e1y = ax_, ay_
    else:
        e1x, e1y = bx_, by_
    en = math.hypot(e1x, e1y)
    if en > 0.0:
        e1x /= en
        e1y /= en
    else:
        e1x, e1y = 1.0, 0.0
    a1 = math.sqrt(2.0 * l1)
    b1 = math.sqrt(2.0 * l2)
    ox[at] = cx + a1 * e1x
    oy[at] = cy + a1 * e1y
    ox[at + 1] = cx - a1 * e1x
    oy[at + 1] = cy - a1 * e1y
    ox[at + 2] = cx - b1 * e1y
    oy[at + 2] = cy + b1 * e1x
    ox[at + 3] = cx + b1 * e1y
    oy[at + 3] = cy - b1 * e1x
    return area


RIM_SIDES = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]]) * (
    0.5 * math.sqrt(6.0))  # the rim rule's points' coefficients in its rectangle's sides
RIM_PIECE = np.array([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]])  # (deposit_cells: one piece, cut)


@njit(cache=True, nogil=True)
def _grow_cells(rows, ci, cj, us, vs, ws, need):
    """:func:`cell_centres`' output arrays, doubled until they hold ``need`` cells."""
    cap = rows.size
    if need <= cap:
        return rows, ci, cj, us, vs, ws
    while need > cap:
        cap *= 2
    return (_grow_int(rows, cap), _grow(ci, cap), _grow(cj, cap), _grow2(us, cap),
            _grow2(vs, cap), _grow2(ws, cap))


@njit(cache=True, nogil=True)
def _grow2(a, cap):
    out = np.empty((cap, a.shape[1]))
    out[: a.shape[0]] = a
    return out


@njit(cache=True, nogil=True, inline="always")
def _sum_of_uniforms_cdf(t, a, b):
    """CDF at ``t`` of the sum of two uniform variables on [−a, a] and [−b, b], a ≥ b ≥ 0
    (the trapezoid's integral: piecewise quadratic)."""
    if a <= 0.0:
        return 1.0 if t >= 0.0 else 0.0
    at = abs(t)
    if at >= a + b:
        g = 0.5
    elif at <= a - b:
        g = at / (2.0 * a)
    else:
        lo = a - b
        g = lo / (2.0 * a) + ((a + b) * (at - lo) - 0.5 * (at * at - lo * lo)) / (4.0 * a * b)
    return 0.5 + g if t >= 0.0 else 0.5 - g


@njit(cache=True, nogil=True, inline="always")
def _pixel_span(p, ha, hb):
    """The pixels ``lo … hi`` (along one axis) that the sum of two uniform offsets of
    half-widths ``ha ≥ hb`` about ``p`` (pixel coordinates) reaches."""
    return int(math.floor(p - ha - hb + 0.5)), int(math.floor(p + ha + hb + 0.5))


@njit(cache=True, nogil=True, inline="always")
def _pixel_shares(p, ha, hb, lo, hi, out):
    """Each pixel's share ``out[i − lo]``, ``i = lo … hi`` (:func:`_pixel_span`), of the sum of
    two uniform offsets about ``p`` (:func:`_sum_of_uniforms_cdf`)."""
    f0 = _sum_of_uniforms_cdf(lo - 0.5 - p, ha, hb)
    for i in range(lo, hi + 1):
        f1 = _sum_of_uniforms_cdf(i + 0.5 - p, ha, hb)
        out[i - lo] = f1 - f0
        f0 = f1


@njit(cache=True, nogil=True, inline="always")
def _share_moments(shares, lo, hi, origin_px, centre_px, inv_pitch):
    """First and second moments, in lenslet pitches about ``centre_px``, of the pixel shares
    ``shares[i − lo]`` of pixels ``i = lo … hi`` along one axis (box offset ``origin_px``)."""
    m1 = 0.0
    m2 = 0.0
    for i in range(lo, hi + 1):
        d = (i + origin_px - centre_px) * inv_pitch
        m1 += shares[i - lo] * d
        m2 += shares[i - lo] * d * d
    return m1, m2


@njit(cache=True, nogil=True, error_model="numpy")
def cell_landings(ray, wt, sx, sy, w4, n_cells, side_coef):
    """Each whole cell's light from its K rule points' traced rays (:func:`cell_centres`'
    order): ray ``k`` is rule point ``ray[k]`` (cell ``ray[k] // K``, point ``ray[k] % K``),
    with transmitted weight ``wt[k]`` and sensor offsets ``(sx[k], sy[k])``; ``w4`` the rule
    points' pupil areas, flat. Returns ``(every cell has its K rays, weight, lx, ly,
    sides)``: each cell's light, its weighted mean landing and the two sides (n_cells, 4: the
    first's x, y, then the second's) of the parallelogram its landing spreads it over, each
    ``Σ_q side_coef[q, i] · (sx, sy)_q`` (K, 2: on a rectangular lattice the landing's linear
    image of the cell's sides b₁, b₂; :func:`lfcam.measure.fastfit.cell_rule`): the sums
    :func:`deposit_cells` takes, in the order numpy's ``bincount`` would add them (the same
    sums bit for bit, at a fraction of the dozen array passes)."""
    nq = side_coef.shape[0]
    weight = np.zeros(n_cells)
    lx = np.zeros(n_cells)
    ly = np.zeros(n_cells)
    sides = np.zeros((n_cells, 4))
    count = np.zeros(n_cells, dtype=np.int64)
    for k in range(ray.size):
        c = ray[k] // nq
        q = ray[k] % nq
        wq = wt[k] * w4[ray[k]]
        weight[c] += wq
        lx[c] += wq * sx[k]
        ly[c] += wq * sy[k]
        s1 = side_coef[q, 0]
        s2 = side_coef[q, 1]
        sides[c, 0] += s1 * sx[k]
        sides[c, 1] += s1 * sy[k]
        sides[c, 2] += s2 * sx[k]
        sides[c, 3] += s2 * sy[k]
        count[c] += 1
    whole = True
    for c in range(n_cells):
        whole &= count[c] == nq
        lx[c] = lx[c] / weight[c]
        ly[c] = ly[c] / weight[c]
    return whole, weight, lx, ly, sides


@njit(cache=True, nogil=True, error_model="numpy")
def deposit_cells(out, rows, ci, cj, sx, sy, wt, e, group, origin, basis, pp, ax, ay, x0, y0,
                  labels, centres_px, pitch_px, pieces, split):
    """Add whole cells' light (:func:`cell_centres`) to the moments ``out`` (groups·K, 4), as
    :func:`deposit_moments` would in the limit of infinitely many samples a cell: cell ``c``
    of point ``rows[c]`` (group ``group[rows[c]]``), lattice node ``(ci, cj)``, weight
    ``wt``, lands as a uniform parallelogram of sides ``e[c, 0:2]``, ``e[c, 2:4]`` (sensor
    mm) about the node plus ``(sx, sy)``. Each pixel's share is the parallelogram's area in
    it: along x the sum of two uniform offsets (a trapezoid), along y the same. Where the
    pixels it covers are one lenslet's, the moments need only these two marginals. Where they
    are not (a cell whose light lands on its micro-image's rim), each pixel takes the product
    of its column's and its row's shares: exact for an upright rectangle, and off for a
    sheared parallelogram by a share of the pixel that shrinks with its size. A hexagonal
    cell's pieces (below) are sheared, and cut into ``split``² smaller ones there
    (:data:`CELL_SPLIT`; a rim's cut cell :data:`RIM_SPLIT`; 1: not cut) (a
    rim cell's piece across a label's border: 66.6 % in its own micro-image whole, 70.5 %
    cut 4 × 4, 70.7 % by a dense sample; docs/distance.md, "Whole hexagonal cells (stop
    45)"; 3 × 3 since stop 47); a rectangular cell's image is nearly upright (cut, 27
    regions' answers moved by at most 5e-6 of their distance, at 20 % more CPU here)."""
    n_k = centres_px.shape[0]
    inv_pitch = 1.0 / pitch_px
    inv_pp = 1.0 / pp
    h, wd = labels.shape
    wxs = np.empty(64)
    wys = np.empty(64)
    for c in range(rows.size):
        w = wt[c]
        base = group[rows[c]] * n_k
        px = (origin[0] + basis[0, 0] * ci[c] + basis[0, 1] * cj[c] + sx[c]) * inv_pp + ax - x0
        py = (origin[1] + basis[1, 0] * ci[c] + basis[1, 1] * cj[c] + sy[c]) * inv_pp + ay - y0
        n_q = max(pieces.shape[0], 1)
        for q in range(n_q):
            if pieces.shape[0] == 0:
                pxq, pyq, wq = px, py, w
                e0, e1, e2, e3 = e[c, 0], e[c, 1], e[c, 2], e[c, 3]
            else:
                mx_, my_ = pieces[q, 0, 0], pieces[q, 0, 1]
                pxq = px + (mx_ * e[c, 0] + my_ * e[c, 2]) * inv_pp
                pyq = py + (mx_ * e[c, 1] + my_ * e[c, 3]) * inv_pp
                wq = w / n_q
                e0 = pieces[q, 1, 0] * e[c, 0] + pieces[q, 1, 1] * e[c, 2]
                e1 = pieces[q, 1, 0] * e[c, 1] + pieces[q, 1, 1] * e[c, 3]
                e2 = pieces[q, 2, 0] * e[c, 0] + pieces[q, 2, 1] * e[c, 2]
                e3 = pieces[q, 2, 0] * e[c, 1] + pieces[q, 2, 1] * e[c, 3]
            ax1 = 0.5 * abs(e0) * inv_pp
            ax2 = 0.5 * abs(e2) * inv_pp
            ay1 = 0.5 * abs(e1) * inv_pp
            ay2 = 0.5 * abs(e3) * inv_pp
            hxa = max(ax1, ax2)
            hxb = min(ax1, ax2)
            hya = max(ay1, ay2)
            hyb = min(ay1, ay2)
            c_lo, c_hi = _pixel_span(pxq, hxa, hxb)
            r_lo, r_hi = _pixel_span(pyq, hya, hyb)
            if c_hi - c_lo >= wxs.size or r_hi - r_lo >= wys.size:
                wxs = np.empty(2 * max(c_hi - c_lo, r_hi - r_lo) + 2)
                wys = np.empty(wxs.size)
            _pixel_shares(pxq, hxa, hxb, c_lo, c_hi, wxs)
            _pixel_shares(pyq, hya, hyb, r_lo, r_hi, wys)
            one = (c_lo >= 0) & (c_hi < wd) & (r_lo >= 0) & (r_hi < h)
            k = -1
            if one:
                k = labels[r_lo, c_lo]
                one = k >= 0
                for row in range(r_lo, r_hi + 1):
                    for col in range(c_lo, c_hi + 1):
                        one &= labels[row, col] == k
            if one:
                mx, mxx = _share_moments(wxs, c_lo, c_hi, x0, centres_px[k, 0], inv_pitch)
                my, myy = _share_moments(wys, r_lo, r_hi, y0, centres_px[k, 1], inv_pitch)
                n = base + k
                out[n, 0] += wq
                out[n, 1] += wq * mx
                out[n, 2] += wq * my
                out[n, 3] += wq * (mxx + myy)
                continue
            ws = wq / (split * split)
            sxa = hxa / split
            sxb = hxb / split
            sya = hya / split
            syb = hyb / split
            for a in range(split):
                ta = (a + 0.5) / split - 0.5
                for b in range(split):
                    tb = (b + 0.5) / split - 0.5
                    qx = pxq + (ta * e0 + tb * e2) * inv_pp
                    qy = pyq + (ta * e1 + tb * e3) * inv_pp
                    q_lo, q_hi = _pixel_span(qx, sxa, sxb)
                    s_lo, s_hi = _pixel_span(qy, sya, syb)
                    _pixel_shares(qx, sxa, sxb, q_lo, q_hi, wxs)
                    _pixel_shares(qy, sya, syb, s_lo, s_hi, wys)
                    for row in range(max(s_lo, 0), min(s_hi + 1, h)):
                        for col in range(max(q_lo, 0), min(q_hi + 1, wd)):
                            _pixel_in_box(out, labels, centres_px, inv_pitch, x0, y0, base,
                                          col, row, ws * wxs[col - q_lo] * wys[row - s_lo])
    return out


# ----------------------------------------------------------------------- least-squares sums
# A fit's reductions over its residuals (~10⁴: four moments a lenslet of a region's box) in
# four interleaved partial sums, added in a fixed order: einsum's generic loop for JᵀJ of a
# tall, thin Jacobian cost 105-420 µs a call (5-8 × these), and BLAS is not used for them
# (its threads woke for each: docs/distance.md, "Threaded BLAS"; "The fit's sums compiled
# (stop 79)").


@njit(cache=True, nogil=True, inline="always")
def _dot4(x, y):
    """``Σ x·y`` of two vectors (any stride) in four interleaved partial sums, added in a
    fixed order."""
    n = x.size
    m = n - n % 4
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    for k in range(0, m, 4):
        s0 += x[k] * y[k]
        s1 += x[k + 1] * y[k + 1]
        s2 += x[k + 2] * y[k + 2]
        s3 += x[k + 3] * y[k + 3]
    for k in range(m, n):
        s0 += x[k] * y[k]
    return (s0 + s1) + (s2 + s3)


@njit(cache=True, nogil=True)
def gram_of(a):
    """``aᵀa`` of a tall ``(n, p)`` array."""
    p = a.shape[1]
    out = np.empty((p, p))
    for i in range(p):
        for j in range(i, p):
            out[i, j] = out[j, i] = _dot4(a[:, i], a[:, j])
    return out


@njit(cache=True, nogil=True)
def jt_of(a, r):
    """``aᵀr`` of a tall ``(n, p)`` array and ``(n,)`` vector."""
    p = a.shape[1]
    out = np.empty(p)
    for i in range(p):
        out[i] = _dot4(a[:, i], r)
    return out


@njit(cache=True, nogil=True)
def sq_of(r):
    """``Σ r²`` of a vector."""
    return _dot4(r, r)


@njit(cache=True, nogil=True)
def scaled_residual(m, data, norm):
    """``(data − a·m) / norm`` raveled (``(K, 4)`` C-ordered moments each), ``a = Σ m·data /
    Σ m²`` the best scale of the model (0 where ``Σ m² = 0``):
    :meth:`lfcam.measure.fastfit.LensletModel.residual_of`."""
    mv = m.reshape(m.size)
    dv = data.reshape(data.size)
    s_mm = _dot4(mv, mv)
    a = _dot4(mv, dv) / s_mm if s_mm > 0 else 0.0
    out = np.empty(mv.size)
    for k in range(mv.size):
        out[k] = (dv[k] - a * mv[k]) / norm
    return out


@njit(cache=True, nogil=True)
def jackknife_deltas(jac, r, inv, cap):
    """:func:`lfcam.measure.solve.jackknife_variance`'s parameter changes ``δ_k`` of the
    lenslets whose leverage ``H_k`` has a trace under ``cap`` (``(I − H_k)⁻¹ r_k`` by a 4 × 4
    Cholesky solve: ``I − H_k`` is positive definite there), as rows of ``(K, p)``; and a flag
    for each lenslet left to the caller (its row 0): those whose eigenvalues may need the cap.
    ``jac`` ``(4K, p)``, ``r`` ``(4K,)``, ``inv`` ``(JᵀJ)⁻¹``."""
    n, p = jac.shape
    k_n = n // 4
    d = np.zeros((k_n, p))
    capped = np.zeros(k_n, dtype=np.bool_)
    a = np.empty((4, p))
    m = np.empty((4, 4))
    x = np.empty(4)
    t = np.empty(p)
    for k in range(k_n):
        o = 4 * k
        for i in range(4):  # A = J_k (JᵀJ)⁻¹
            for j in range(p):
                s = 0.0
                for q in range(p):
                    s += jac[o + i, q] * inv[q, j]
                a[i, j] = s
        trace = 0.0
        for i in range(4):  # I − H_k, H_k = A J_kᵀ (lower triangle)
            for j in range(i + 1):
                s = 0.0
                for q in range(p):
                    s += a[i, q] * jac[o + j, q]
                m[i, j] = (1.0 if i == j else 0.0) - s
            trace += 1.0 - m[i, i]
        if not trace < cap:
            capped[k] = True
            continue
        for j in range(4):  # Cholesky, in place (lower)
            s = m[j, j]
            for q in range(j):
                s -= m[j, q] * m[j, q]
            m[j, j] = math.sqrt(s)
            for i in range(j + 1, 4):
                s = m[i, j]
                for q in range(j):
                    s -= m[i, q] * m[j, q]
                m[i, j] = s / m[j, j]
        for i in range(4):  # forward, then back substitution
            s = r[o + i]
            for q in range(i):
                s -= m[i, q] * x[q]
            x[i] = s / m[i, i]
        for i in range(3, -1, -1):
            s = x[i]
            for q in range(i + 1, 4):
                s -= m[q, i] * x[q]
            x[i] = s / m[i, i]
        for j in range(p):  # δ_k = (J_kᵀ x) (JᵀJ)⁻¹
            s = 0.0
            for i in range(4):
                s += jac[o + i, j] * x[i]
            t[j] = s
        for j in range(p):
            s = 0.0
            for q in range(p):
                s += t[q] * inv[q, j]
            d[k, j] = s
    return d, capped
