"""Compiled inner loops of the white calibration's micro-image fits (``numba``; compiled
once, cached on disk).

:func:`lfcam.calibrate.microimage.own_light_fit` keeps each lens's disc model on its *seam*
pixels (those a neighbour's light can reach) and the sum of all models, the model image
``M``, on a padded flat float32 image. Every fixed-point and polish step reads ``M`` on the
seam pixels of ~230 000 lenses (Illum-size white, ~29 M pixel reads) and writes each lens's
change back. With numpy each such pass was a chain of (lenses × seam pixels) temporaries, a
fancy-indexed gather and a grouped scatter (``M[idx] += Δ`` is only exact when no index
repeats), memory-bound at 9–13 ms per 8 192 lenses; here each is one pass with no
temporaries, and the scatter is a plain loop (repeated indices add up).

The Gauss–Newton fit of overlapping discs (:func:`lfcam.calibrate.microimage.fit_discs`)
has the same two passes a step over whole patches: the model image (:func:`disc_models`)
and each disc's normal-equation sums against it (:func:`disc_step_sums`), each pixel's
terms computed where they are used instead of kept as (lenses × patch) arrays; the
brightness planes' least-squares sums (:func:`core_plane_sums`) likewise. The candidate
search's score takes one pass between its filters (:func:`flat_score`), and the projective
lattice fit's normal equations one pass over the lenses (:func:`projective_normal`).

The arithmetic is that of the numpy chains they replaced, in float32 where they were float32
(the disc models), with the per-lens sums accumulated in float64. The callers still run the
sums on threads over chunks of lenses (these functions release the GIL) and scatter one
chunk at a time (:func:`scatter_seams` under a lock).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _seam_plane(coef, k, ox, oy):
    """Lens ``k``'s brightness plane at offset ``(ox, oy)`` from its base pixel, not below 0
    (float32, in the order ``a + gx·ox + gy·oy``)."""
    return max(coef[k, 0] + coef[k, 1] * ox + coef[k, 2] * oy, np.float32(0.0))


@njit(cache=True, nogil=True)
def seam_models(ks, frac, oxs, oys, sup, inv2w, coef, m_cur, delta):
    """Disc model of the lenses ``ks`` on their seam pixels; store it in ``m_cur`` and its
    change in ``delta``.

    The model of lens ``k`` at seam offset ``(ox, oy)`` from its base pixel is its brightness
    plane there, ``max(a + gx·ox + gy·oy, 0)``, times the edge ramp ``clip((sup − |(ox, oy) −
    frac_k|)·inv2w, 0, 1)``.

    Parameters
    ----------
    ks : (m,) int64
        Lens rows.
    frac : (N, 2) float32
        Disc centre minus base pixel, per lens.
    oxs, oys : (ns,) float32
        Seam offsets from the base pixel.
    sup, inv2w : float32
        Support radius (R + w) and 1 / (2 w), pixels.
    coef : (N, 3) float32
        Each lens's brightness plane (a, gx, gy) about its base pixel.
    m_cur : (N, ns) float32
        Each lens's current model on its seam pixels (updated in place).
    delta : (m, ns) float32
        Output: the change of each lens's model.
    """
    zero = np.float32(0.0)
    one = np.float32(1.0)
    for i in range(ks.size):
        k = ks[i]
        fx = frac[k, 0]
        fy = frac[k, 1]
        for j in range(oxs.size):
            ux = oxs[j] - fx
            uy = oys[j] - fy
            t = (sup - np.sqrt(ux * ux + uy * uy)) * inv2w
            t = min(max(t, zero), one)
            mk = t * _seam_plane(coef, k, oxs[j], oys[j])
            delta[i, j] = mk - m_cur[k, j]
            m_cur[k, j] = mk


@njit(cache=True, nogil=True)
def scatter_seams(total, bflat, ks, lin_s, delta):
    """``total[bflat[k] + lin_s] += delta[i]`` for ``k = ks[i]`` (repeated pixels add)."""
    for i in range(ks.size):
        b = bflat[ks[i]]
        for j in range(lin_s.size):
            total[b + lin_s[j]] += delta[i, j]


@njit(cache=True, nogil=True)
def gather_patch(image, base, ks, ox, oy, out):
    """``out[k, j] = image[base_y + oy[j], base_x + ox[j]]`` for each lens ``k`` in ``ks``
    (its base pixel ``base[k]`` (x, y)), 0 off the image: the pixels at the offsets
    ``ox, oy`` (int) from each lens's base pixel."""
    h, w = image.shape
    for i in range(ks.size):
        k = ks[i]
        bx = base[k, 0]
        by = base[k, 1]
        for j in range(ox.size):
            x = bx + ox[j]
            y = by + oy[j]
            out[k, j] = image[y, x] if 0 <= x < w and 0 <= y < h else np.float32(0.0)


@njit(cache=True, nogil=True)
def patch_sums(image, base, ks, ox, oy):
    """Σ I·(1, ox, oy) over the on-image pixels at the offsets ``ox, oy`` (int) from each
    lens's base pixel, for the lenses ``ks``; (m, 3) float64."""
    h, w = image.shape
    out = np.zeros((ks.size, 3))
    for i in range(ks.size):
        k = ks[i]
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for j in range(ox.size):
            x = base[k, 0] + ox[j]
            y = base[k, 1] + oy[j]
            if 0 <= x < w and 0 <= y < h:
                v = np.float64(image[y, x])
                s0 += v
                s1 += v * ox[j]
                s2 += v * oy[j]
        out[i, 0] = s0
        out[i, 1] = s1
        out[i, 2] = s2
    return out


@njit(cache=True, nogil=True)
def own_light_sums(ks, frac, sup, m_cur, total, bflat, lin_s, p_s, oxs, oys, p_o, oxo, oyo):
    """Σ I·(1, x, y) of the light attributed to the lenses ``ks`` outside their inner disc.

    Seam pixels: the data times the lens's share of the model, ``m_k / max(M, m_k)``
    (``M ≥ 1e-30``). Outer pixels (no neighbour reaches them): the data where the pixel is
    inside the lens's support. Offsets are from the base pixel.

    Returns
    -------
    (m, 3) float64
    """
    out = np.zeros((ks.size, 3))
    tiny = np.float32(1e-30)
    sup2 = sup * sup
    for i in range(ks.size):
        k = ks[i]
        b = bflat[k]
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for j in range(lin_s.size):
            mk = m_cur[k, j]
            big = max(max(total[b + lin_s[j]], mk), tiny)
            q = p_s[k, j] * mk / big
            s0 += q
            s1 += q * oxs[j]
            s2 += q * oys[j]
        fx = frac[k, 0]
        fy = frac[k, 1]
        for j in range(oxo.size):
            ux = oxo[j] - fx
            uy = oyo[j] - fy
            if ux * ux + uy * uy < sup2:
                v = p_o[k, j]
                s0 += v
                s1 += v * oxo[j]
                s2 += v * oyo[j]
        out[i, 0] = s0
        out[i, 1] = s1
        out[i, 2] = s2
    return out


@njit(cache=True, nogil=True, inline="always")
def _edge_pixel(ux, uy, b, pix_r, own_model, cf1, cf2, sup, inv2w, on, acc):
    """One ring pixel's Gauss–Newton terms: ``acc += (jx², jy², jx·jy, jx·r, jy·r)``.

    ``b``: the lens's brightness there; ``pix_r``: the residual (seams: the data minus
    ``M``), or with ``own_model`` the data, from which the lens's model is taken here (outer
    pixels); ``on``: 0 for an off-sensor pixel of a cut disc, else 1."""
    d = np.sqrt(ux * ux + uy * uy)
    t = (sup - d) * inv2w  # coverage before clipping
    gsc = np.float32(0.0)
    if t > 0.0 and t < 1.0:
        gsc = b / max(d, np.float32(1e-6)) * inv2w * on  # |∂m/∂d| on the edge ramp, over d
    t = min(max(t, np.float32(0.0)), np.float32(1.0))
    r = pix_r - b * t if own_model else pix_r
    t *= on
    jx = gsc * ux - cf1 * t
    jy = gsc * uy - cf2 * t
    acc[0] += jx * jx
    acc[1] += jy * jy
    acc[2] += jx * jy
    acc[3] += jx * r
    acc[4] += jy * r


@njit(cache=True, nogil=True)
def edge_sums(ks, frac, coef, sup, inv2w, total, bflat, lin_s, p_s, oxs, oys, p_o, oxo, oyo,
              cut_row, ins_s, ins_o):
    """Normal-equation sums of the Gauss–Newton step of the disc centres ``ks`` on their
    seam and outer pixels: Σ jx², jy², jx·jy, jx·r, jy·r.

    The residual is the data minus all models (seams: minus ``M``, which holds the lens's own
    model; outer pixels: minus the lens's model, no neighbour reaching them). The Jacobian of
    the lens's model with respect to its centre is the edge ramp's plus the brightness plane
    sliding with the disc (``−(gx, gy)·coverage``). For a cut disc (``cut_row[k] ≥ 0``) only
    its on-sensor pixels count (``ins_s``, ``ins_o``, rows ``cut_row[k]``).

    Parameters
    ----------
    coef : (N, 3) float32
        Brightness planes (a, gx, gy) about each lens's base pixel.

    Returns
    -------
    (m, 5) float64
    """
    out = np.zeros((ks.size, 5))
    acc = np.zeros(5)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for i in range(ks.size):
        k = ks[i]
        b0 = bflat[k]
        fx = frac[k, 0]
        fy = frac[k, 1]
        cf0 = coef[k, 0]
        cf1 = coef[k, 1]
        cf2 = coef[k, 2]
        cr = cut_row[k]
        acc[:] = 0.0
        for j in range(lin_s.size):
            on = one if cr < 0 or ins_s[cr, j] else zero
            _edge_pixel(oxs[j] - fx, oys[j] - fy, _seam_plane(coef, k, oxs[j], oys[j]),
                        p_s[k, j] - total[b0 + lin_s[j]], False, cf1, cf2, sup, inv2w, on,
                        acc)
        for j in range(oxo.size):
            on = one if cr < 0 or ins_o[cr, j] else zero
            b = max(cf1 * oxo[j] + cf2 * oyo[j] + cf0, zero)
            _edge_pixel(oxo[j] - fx, oyo[j] - fy, b, p_o[k, j], True, cf1, cf2, sup, inv2w,
                        on, acc)
        for m in range(5):
            out[i, m] = acc[m]
    return out


@njit(cache=True, nogil=True)
def core_plane_sums(h, w, centres, half, core_px, image):
    """Sums of each micro-image's brightness-plane fit over the on-sensor pixels of its
    ``(2·half + 1)²`` patch (about its rounded centre) within ``core_px`` of its centre:
    Σ 1, dx, dy, dx², dx·dy, dy² and Σ I·(1, dx, dy), with ``(dx, dy)`` the pixel's offset
    from the centre (float64). ``image``: flat (h·w,) float64.

    Returns
    -------
    (N, 9) float64
    """
    out = np.zeros((centres.shape[0], 9))
    for k in range(centres.shape[0]):
        cx = centres[k, 0]
        cy = centres[k, 1]
        bx = int(np.rint(cx))
        by = int(np.rint(cy))
        for y in range(max(by - half, 0), min(by + half + 1, h)):  # the on-sensor patch
            dy = y - cy
            if not abs(dy) < core_px:
                continue
            for x in range(max(bx - half, 0), min(bx + half + 1, w)):
                dx = x - cx
                if not (abs(dx) < core_px and math.hypot(dx, dy) < core_px):
                    continue
                v = image[y * w + x]
                out[k, 0] += 1.0
                out[k, 1] += dx
                out[k, 2] += dy
                out[k, 3] += dx * dx
                out[k, 4] += dx * dy
                out[k, 5] += dy * dy
                out[k, 6] += v
                out[k, 7] += v * dx
                out[k, 8] += v * dy
    return out


@njit(cache=True, nogil=True, inline="always")
def _disc_base(centres, k):
    """Disc ``k``'s base pixel (its centre rounded, half to even as ``np.round``) and the
    centre's offset from it (float32)."""
    bx = int(np.rint(centres[k, 0]))
    by = int(np.rint(centres[k, 1]))
    return bx, by, np.float32(centres[k, 0] - bx), np.float32(centres[k, 1] - by)


@njit(cache=True, nogil=True, inline="always")
def _disc_pixel(ox, oy, fx, fy, cf0, cf1, cf2, sup, inv2w):
    """A disc's terms at a patch pixel ``(ox, oy)`` from its base pixel (float32): offsets
    from the disc centre, distance, coverage before clipping, brightness plane."""
    dx = ox - fx
    dy = oy - fy
    d = np.sqrt(dx * dx + dy * dy)
    return dx, dy, d, (sup - d) * inv2w, cf0 + cf1 * dx + cf2 * dy


@njit(cache=True, nogil=True)
def disc_models(h, w, centres, coef, half, sup, inv2w, total):
    """``total[y·w + x] += max(b, 0)·clip(t, 0, 1)`` over the on-sensor pixels of each disc's
    ``(2·half + 1)²`` patch about its rounded centre: the model image of
    :func:`lfcam.calibrate.microimage.model_image` (float32 terms, float64 sums).

    Parameters
    ----------
    centres : (N, 2) float64
    coef : (N, 3) float32
        Brightness planes (a, gx, gy) about each disc centre.
    sup, inv2w : float32
        Support radius R + w and 1 / (2 w).
    total : (h·w,) float64
        Added to.
    """
    zero = np.float32(0.0)
    one = np.float32(1.0)
    for k in range(centres.shape[0]):
        bx, by, fx, fy = _disc_base(centres, k)
        for y in range(max(by - half, 0), min(by + half + 1, h)):  # the on-sensor patch
            oy = y - by
            for x in range(max(bx - half, 0), min(bx + half + 1, w)):
                ox = x - bx
                _, _, _, t, b = _disc_pixel(np.float32(ox), np.float32(oy), fx, fy,
                                            coef[k, 0], coef[k, 1], coef[k, 2], sup, inv2w)
                total[y * w + x] += max(b, zero) * min(max(t, zero), one)


@njit(cache=True, nogil=True)
def disc_step_sums(h, w, centres, coef, half, sup, inv2w, image, total, ks):
    """Normal-equation sums of each disc's Gauss–Newton step (:func:`lfcam.calibrate.
    microimage.fit_discs`) on its patch's on-sensor pixels: Σ jx², jy², jx·jy, jx·r, jy·r
    with ``r`` the data minus the model image ``total`` (float32) and ``j`` the derivative of
    the disc's model with respect to its centre (the edge ramp's, plus the brightness plane
    sliding with the disc). ``image``, ``total``: flat (h·w,) float64. Rows ``ks``.

    Returns
    -------
    (len(ks), 5) float64
    """
    out = np.zeros((ks.size, 5))
    zero = np.float32(0.0)
    one = np.float32(1.0)
    two_w = one / inv2w  # 2 w
    for i in range(ks.size):
        k = ks[i]
        bx, by, fx, fy = _disc_base(centres, k)
        cf1 = coef[k, 1]
        cf2 = coef[k, 2]
        axx = 0.0
        ayy = 0.0
        axy = 0.0
        sbx = 0.0
        sby = 0.0
        for y in range(max(by - half, 0), min(by + half + 1, h)):  # the on-sensor patch
            oy = y - by
            for x in range(max(bx - half, 0), min(bx + half + 1, w)):
                ox = x - bx
                dx, dy, d, t, b = _disc_pixel(np.float32(ox), np.float32(oy), fx, fy,
                                              coef[k, 0], cf1, cf2, sup, inv2w)
                inv = zero
                if t > zero and t < one:
                    inv = b / (two_w * (d if d > zero else one))
                cov = min(max(t, zero), one)
                jx = np.float64(-cf1 * cov + dx * inv)
                jy = np.float64(-cf2 * cov + dy * inv)
                at = y * w + x
                r = np.float64(np.float32(image[at] - total[at]))
                axx += jx * jx
                ayy += jy * jy
                axy += jx * jy
                sbx += jx * r
                sby += jy * r
        out[i, 0] = axx
        out[i, 1] = ayy
        out[i, 2] = axy
        out[i, 3] = sbx
        out[i, 4] = sby
    return out


@njit(cache=True, nogil=True)
def flat_score(mean, mean_sq):
    """``mean − 2·sqrt(max(mean_sq − mean², 0))`` in place of ``mean`` (2-D float32): the
    candidate score of :func:`lfcam.calibrate.grid.find_candidates` from the local mean and
    mean square, in one pass (float32, in numpy's order of operations)."""
    zero = np.float32(0.0)
    two = np.float32(2.0)
    for i in range(mean.shape[0]):
        for j in range(mean.shape[1]):
            m = mean[i, j]
            v = mean_sq[i, j] - m * m
            mean[i, j] = m - np.sqrt(max(v, zero)) * two


@njit(cache=True, nogil=True)
def projective_normal(ij, pts, wts, h):
    """The weighted normal equations of one Gauss–Newton step of a projective lattice fit:
    ``Σ w·JᵀJ`` (8, 8) and ``Σ w·Jᵀr`` (8,) over the points ``pts`` (N, 2) at lattice
    indices ``ij`` (N, 2, float), ``r`` each point less its image through the homography
    ``h`` (3 × 3, ``h[2, 2]`` = 1), ``J`` that image's derivatives in ``h``'s first eight
    entries (row-major). One pass, no (2N × 8) Jacobian
    (:func:`lfcam.calibrate.grid.fit_projective`)."""
    a = np.zeros((8, 8))
    b = np.zeros(8)
    jx = np.zeros(8)
    jy = np.zeros(8)
    for n in range(ij.shape[0]):
        w = wts[n]
        if w == 0.0:
            continue
        i = ij[n, 0]
        j = ij[n, 1]
        iz = 1.0 / (h[2, 0] * i + h[2, 1] * j + h[2, 2])
        x = (h[0, 0] * i + h[0, 1] * j + h[0, 2]) * iz
        y = (h[1, 0] * i + h[1, 1] * j + h[1, 2]) * iz
        jx[0] = i * iz
        jx[1] = j * iz
        jx[2] = iz
        jx[6] = -x * i * iz
        jx[7] = -x * j * iz
        jy[3] = jx[0]
        jy[4] = jx[1]
        jy[5] = iz
        jy[6] = -y * i * iz
        jy[7] = -y * j * iz
        rx = w * (pts[n, 0] - x)
        ry = w * (pts[n, 1] - y)
        for p in range(8):
            b[p] += jx[p] * rx + jy[p] * ry
            wx = w * jx[p]
            wy = w * jy[p]
            for q in range(p, 8):
                a[p, q] += wx * jx[q] + wy * jy[q]
    for p in range(8):
        for q in range(p):
            a[p, q] = a[q, p]
    return a, b


def warm_up() -> None:
    """Compile (or load from the disk cache) the kernels for the types the fit uses."""
    f32 = np.float32
    ks = np.zeros(1, np.int64)
    frac = np.zeros((1, 2), f32)
    one = np.zeros((1, 1), f32)
    off = np.zeros(1, f32)
    lin = np.zeros(1, np.int64)
    total = np.zeros(4, f32)
    coef = np.zeros((1, 3), f32)
    base = np.zeros((1, 2), np.int64)
    gather_patch(np.zeros((2, 2), f32), base, ks, lin, lin, one)
    patch_sums(np.zeros((2, 2), f32), base, ks, lin, lin)
    seam_models(ks, frac, off, off, f32(1), f32(1), coef, one.copy(), one.copy())
    scatter_seams(total, lin, ks, lin, one)
    own_light_sums(ks, frac, f32(1), one, total, lin, lin, one, off, off, one, off, off)
    edge_sums(ks, frac, coef, f32(1), f32(1), total, lin, lin, one, off, off, one, off, off,
              np.full(1, -1, np.int64), np.zeros((0, 1), bool), np.zeros((0, 1), bool))
    cen = np.zeros((1, 2))
    flat = np.zeros(4)
    disc_models(2, 2, cen, coef, 1, f32(1), f32(1), flat)
    disc_step_sums(2, 2, cen, coef, 1, f32(1), f32(1), flat, flat, ks)
    core_plane_sums(2, 2, cen, 1, 1.0, flat)
    flat_score(np.zeros((2, 2), f32), np.zeros((2, 2), f32))
    projective_normal(np.zeros((1, 2)), np.zeros((1, 2)), np.ones(1), np.eye(3))
