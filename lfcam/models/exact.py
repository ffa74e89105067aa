"""``exact``: numerical inversion of the exact stop-edge ray trace (no model error), any lens.

Each y1/y2 ray passes a fixed point (the upper or lower edge of the real stop; the seed
singlet: its front rim), so its sensor height is a function of one number only, its slope
``t`` just before the stop surface (the singlet: the object-side slope): ``y = g±(t)``,
smooth and strictly monotonic over every slope the lens passes. Inverting the two edges
independently gives two rays; traced back into object space (nothing to trace for a stop on
the front surface) they are lines ``y = a± + s±·(z − z_ref)`` with ``z_ref`` the aperture
plane (:attr:`MainLens.rim_z_mm`), and their intersection is the source:

    L = (a1 − a2) / (s1 − s2)         (source → aperture plane, along the axis)
    distance_mm = L − rim_sag
    offset_mm   = a1 − s1·L

For the singlet a± = ±D/2 and s± = t±, the seed's ``L = D/(t1 − t2)``,
``offset = −(D/2)(t1 + t2)/(t1 − t2)``.

The signs of y1, y2 are kept (no diameter is formed), so sources on either side of the focused
plane, and on it, are resolved. The solve per rim is: linear interpolation in a dense table of
``(g(t), t)`` for the start (error ~1e-8), one quasi-Newton step with the table's slope, then
secant steps on the exact trace until the height residual is at rounding level; everything is
vectorised over regions and processed in cache-sized chunks.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from lfcam.camera import CameraProfile, MainLens
from lfcam.models.base import Inversion, Status, as_heights, finish
from lfcam.optics.raytrace import stop_edge_object_rays
from lfcam.optics.trace import meridional_rim_heights

TABLE_SIZE = 8193
MAX_ANGLE_RAD = np.deg2rad(75.0)
CHUNK = 1 << 15
SECANT_STEPS = 1
RESIDUAL_TOL_MM = 1e-11  # final |y(t) − y| accepted as converged (rounding is ~1e-14 mm)


@lru_cache(maxsize=64)
def _rim_table(lens: MainLens, rim_sign: float, z_plane_mm: float):
    """Monotone table (y, t, dt/dy) of one rim ray's sensor height versus its slope."""
    lo_a, hi_a = -MAX_ANGLE_RAD, MAX_ANGLE_RAD
    if not lens.is_singlet:  # a stop inside the lens passes a narrow fan: find it first
        coarse = np.linspace(lo_a, hi_a, 2049)
        _, ok_c = meridional_rim_heights(lens, rim_sign, np.tan(coarse), z_plane_mm)
        if ok_c.any():
            idx = np.nonzero(ok_c)[0]
            c = 1024 if ok_c[1024] else idx[np.argmin(np.abs(idx - 1024))]
            a, b = c, c
            while a > 0 and ok_c[a - 1]:
                a -= 1
            while b < coarse.size - 1 and ok_c[b + 1]:
                b += 1
            lo_a, hi_a = coarse[max(a - 1, 0)], coarse[min(b + 1, coarse.size - 1)]
    angles = np.linspace(lo_a, hi_a, TABLE_SIZE)
    t = np.tan(angles)
    y, ok = meridional_rim_heights(lens, rim_sign, t, z_plane_mm)
    dy = np.diff(y)
    sign = np.sign(np.nanmedian(dy[ok[1:] & ok[:-1]]))
    good_step = ok[1:] & ok[:-1] & (dy * sign > 0)
    # largest contiguous run of valid, strictly monotone samples containing slope 0
    centre = int(np.argmin(np.abs(angles)))
    if not (ok[centre] and ok.any()):
        centre = int(np.nonzero(ok)[0][np.argmin(np.abs(np.nonzero(ok)[0] - centre))]) if (
            ok.any()) else centre
    lo = centre
    while lo > 0 and good_step[lo - 1]:
        lo -= 1
    hi = centre
    while hi < TABLE_SIZE - 1 and good_step[hi]:
        hi += 1
    t, y = t[lo : hi + 1], y[lo : hi + 1]
    if sign < 0:
        t, y = t[::-1], y[::-1]
    slope = np.gradient(t, y)
    for arr in (t, y, slope):
        arr.setflags(write=False)
    return y, t, slope


def _solve_rim(lens: MainLens, rim_sign: float, z_plane: float, y: np.ndarray):
    """Object-side slope of the rim ray that lands at height ``y``; (t, ok)."""
    table_y, table_t, table_slope = _rim_table(lens, rim_sign, z_plane)
    inside = (y >= table_y[0]) & (y <= table_y[-1])
    t = np.interp(y, table_y, table_t)
    y_t, _ = meridional_rim_heights(lens, rim_sign, t, z_plane)
    t_new = t + (y - y_t) * np.interp(y, table_y, table_slope)
    for _ in range(SECANT_STEPS):
        y_new, _ = meridional_rim_heights(lens, rim_sign, t_new, z_plane)
        dy = y_new - y_t
        with np.errstate(divide="ignore", invalid="ignore"):
            secant = np.where(dy != 0.0, (t_new - t) / dy, 0.0)
        t, y_t = t_new, y_new
        t_new = t + (y - y_t) * secant
    y_final, ok = meridional_rim_heights(lens, rim_sign, t_new, z_plane)
    converged = np.abs(y_final - y) <= RESIDUAL_TOL_MM + 1e-14 * np.abs(y)
    return t_new, inside & ok & converged


def invert_slopes(
    profile: CameraProfile, d_in_mm: float | None, y1_mm, y2_mm
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, ...]]:
    """Object-side slopes (t1, t2) of the two rim rays for sensor heights (y1, y2).

    Returns flat ``t1, t2, ok`` and the broadcast input shape.
    """
    lens = profile.main_lens
    d_in = profile.d_in_mm if d_in_mm is None else float(d_in_mm)
    z_plane = d_in + profile.mla.focal_length_mm
    y1, y2, shape = as_heights(y1_mm, y2_mm)
    t1 = np.empty_like(y1)
    t2 = np.empty_like(y2)
    ok = np.empty(y1.shape, dtype=bool)
    finite = np.isfinite(y1) & np.isfinite(y2)
    y1 = np.where(finite, y1, 0.0)
    y2 = np.where(finite, y2, 0.0)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        for start in range(0, y1.size, CHUNK):
            sl = slice(start, start + CHUNK)
            a, ok_a = _solve_rim(lens, 1.0, z_plane, y1[sl])
            b, ok_b = _solve_rim(lens, -1.0, z_plane, y2[sl])
            t1[sl], t2[sl], ok[sl] = a, b, ok_a & ok_b
    return t1, t2, ok & finite, shape


def invert(profile: CameraProfile, d_in_mm: float | None, y1_mm, y2_mm) -> Inversion:
    """Distance and offset of a point source from its rim-ray sensor heights, exactly.

    Parameters
    ----------
    profile : CameraProfile
    d_in_mm : float or None
        MLA distance (``None``: the profile's).
    y1_mm, y2_mm : array_like
        Signed sensor heights of the upper- and lower-rim rays (docs/conventions.md).

    Returns
    -------
    Inversion
        ``status`` is ``out-of-domain`` where a height is beyond what the lens can produce,
        ``no-solution`` where the two recovered rays do not meet in front of the lens.
    """
    lens = profile.main_lens
    y1, y2, shape = as_heights(y1_mm, y2_mm)
    t1, t2, ok, _ = invert_slopes(profile, d_in_mm, y1, y2)
    z_ref = lens.rim_z_mm - lens.front_vertex_z_mm  # aperture plane, prescription frame
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        a1, s1, ok1 = stop_edge_object_rays(lens.as_prescription, 1.0, t1, z_ref)
        a2, s2, ok2 = stop_edge_object_rays(lens.as_prescription, -1.0, t2, z_ref)
    ok = ok & ok1 & ok2
    spread = s1 - s2
    status = np.full(y1.shape, Status.OK, dtype=np.uint8)
    status[~ok] = Status.OUT_OF_DOMAIN
    status[~(np.isfinite(y1) & np.isfinite(y2))] = Status.INVALID_INPUT
    with np.errstate(divide="ignore", invalid="ignore"):
        if lens.as_prescription.stop_index == 0:  # the seed's closed form, exactly
            half_d = 0.5 * lens.pupil_diameter_mm
            along = lens.pupil_diameter_mm / spread
            offset = -half_d * (t1 + t2) / spread
        else:
            along = (a1 - a2) / spread
            offset = a1 - s1 * along
        distance = along - lens.rim_sag_mm
    status[(status == Status.OK) & ~(spread > 0.0)] = Status.NO_SOLUTION
    status[(status == Status.OK) & ~(distance > 0.0)] = Status.OUT_OF_DOMAIN
    status[(status == Status.OK) & ~np.isfinite(distance)] = Status.ILL_CONDITIONED
    return finish(distance, offset, status, shape)
