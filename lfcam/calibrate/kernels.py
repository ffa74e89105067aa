"""Compiled inner loops of the own-light fit of touching micro-images (``numba``; compiled
once, cached on disk).

:func:`lfcam.calibrate.microimage.own_light_fit` keeps each lens's disc model on its *seam*
pixels (those a neighbour's light can reach) and the sum of all models, the model image
``M``, on a padded flat float32 image. Every fixed-point and polish step reads ``M`` on the
seam pixels of ~230 000 lenses (Illum-size white, ~29 M pixel reads) and writes each lens's
change back. With numpy each such pass was a chain of (lenses × seam pixels) temporaries, a
fancy-indexed gather and a grouped scatter (``M[idx] += Δ`` is only exact when no index
repeats), memory-bound at 9–13 ms per 8 192 lenses; here each is one pass with no
temporaries, and the scatter is a plain loop (repeated indices add up).

The arithmetic is that of the numpy chains it replaced, in float32 where they were float32
(the disc model on the seams), with the per-lens sums accumulated in float64. The callers
still run the model and the sums on threads over chunks of lenses (these functions release
the GIL) and scatter one chunk at a time (:func:`scatter_seams` under a lock).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def seam_models(ks, frac, oxs, oys, sup, inv2w, plane, m_cur, delta):
    """Disc model of the lenses ``ks`` on their seam pixels; store it in ``m_cur`` and its
    change in ``delta``.

    The model of lens ``k`` at seam offset ``(ox, oy)`` from its base pixel is its brightness
    plane times the edge ramp ``clip((sup − |(ox, oy) − frac_k|)·inv2w, 0, 1)``.

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
    plane : (N, ns) float32
        Each lens's brightness plane on its seam pixels.
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
            mk = t * plane[k, j]
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
def gather_rows(flat, bflat, ks, lin, out):
    """``out[k] = flat[bflat[k] + lin]`` for each lens ``k`` in ``ks``: the pixels at the
    offsets ``lin`` from each lens's base pixel (flat indices in the padded image)."""
    for i in range(ks.size):
        k = ks[i]
        b = bflat[k]
        for j in range(lin.size):
            out[k, j] = flat[b + lin[j]]


@njit(cache=True, nogil=True)
def offset_sums(flat, bflat, ks, lin, ox, oy):
    """Σ I·(1, ox, oy) over the offsets ``lin`` (float64 ``ox``, ``oy``) from each lens's
    base pixel, for the lenses ``ks``; (m, 3) float64."""
    out = np.zeros((ks.size, 3))
    for i in range(ks.size):
        b = bflat[ks[i]]
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for j in range(lin.size):
            v = flat[b + lin[j]]
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
def edge_sums(ks, frac, coef, sup, inv2w, total, bflat, lin_s, p_s, plane, oxs, oys, p_o,
              oxo, oyo, cut_row, ins_s, ins_o):
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
            _edge_pixel(oxs[j] - fx, oys[j] - fy, plane[k, j],
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


def warm_up() -> None:
    """Compile (or load from the disk cache) the kernels for the types the fit uses."""
    f32 = np.float32
    ks = np.zeros(1, np.int64)
    frac = np.zeros((1, 2), f32)
    one = np.zeros((1, 1), f32)
    off = np.zeros(1, f32)
    lin = np.zeros(1, np.int64)
    total = np.zeros(4, f32)
    gather_rows(total, lin, ks, lin, one)
    offset_sums(total, lin, ks, lin, off.astype(np.float64), off.astype(np.float64))
    seam_models(ks, frac, off, off, f32(1), f32(1), one, one.copy(), one.copy())
    scatter_seams(total, lin, ks, lin, one)
    own_light_sums(ks, frac, f32(1), one, total, lin, lin, one, off, off, one, off, off)
    edge_sums(ks, frac, np.zeros((1, 3), f32), f32(1), f32(1), total, lin, lin, one, one, off,
              off, one, off, off, np.full(1, -1, np.int64), np.zeros((0, 1), bool),
              np.zeros((0, 1), bool))
