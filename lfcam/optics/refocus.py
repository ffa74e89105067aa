"""Exact metric refocus: the shift-and-sum shift that images a point at a distance sharpest.

The decoder's refocus (:mod:`lfcam.decode.refocus`) sums views with the shift ``a`` (Hahne's
convention: lenslets of spatial shift per pixel of angular coordinate). A ray of a point source
crosses the MLA at ``x`` (``s = x / p_m`` lenslets) with slope ``σ``; behind its lenslet it lands
``i = f_s·(σ − x/d_A)/p_p`` pixels from the micro-image centre (the chief ray from the exit-pupil
centre through the lenslet centre, ``d_A`` = exit pupil → MLA). The refocused image of the
point is the distribution of ``s + a·i`` over the rays, with each ray's weight its share of the
pupil. Its mean square about the centroid is a quadratic in ``a``; its minimum,

    a* = −cov(s, i) / var(i),

is the shift of least RMS blur. The rays come from the exact trace (any main lens, real stop,
aberrations included), so a point at D refocused with ``a*(D)`` is sharper than at any other
shift, which Hahne's paraxial closed form does not guarantee at large apertures.
"""

from __future__ import annotations

import math

import numpy as np

from lfcam.camera import CameraProfile
from lfcam.errors import OpticsError
from lfcam.optics.raytrace import pupil_pattern
from lfcam.optics.trace import trace_source_fast

PUPIL_RAYS = 2048
FAR_MM = 1e8  # "infinity" for the trace (a plane 100 km away is in focus with infinity)


def _shift_one(profile: CameraProfile, d_in: float, distance_mm: float, pattern) -> float:
    lens = profile.main_lens
    fs, pm, pp = profile.mla.focal_length_mm, profile.mla.pitch_mm, profile.sensor.pixel_pitch_mm
    d_a = d_in - lens.exit_pupil_z_mm
    half = 0.5 * lens.pupil_diameter_mm
    src = (0.0, 0.0, lens.front_vertex_z_mm - min(float(distance_mm), FAR_MM))
    tr = trace_source_fast(lens, src, half * pattern[:, 0], half * pattern[:, 1], d_in)
    ok = tr.ok
    if ok.sum() < 8:
        raise OpticsError(f"no light from {distance_mm} mm reaches the MLA")
    x = np.concatenate([tr.x[ok], tr.y[ok]])
    slope = np.concatenate([tr.dx[ok] / tr.dz[ok], tr.dy[ok] / tr.dz[ok]])
    s = x / pm
    i = fs * (slope - x / d_a) / pp
    s = s - s.mean()
    i = i - i.mean()
    return float(-(s * i).sum() / (i * i).sum())


def exact_shift_for_distance(
    profile: CameraProfile, distance_mm, d_in_mm: float | None = None, n_rays: int = PUPIL_RAYS
):
    """Shift ``a`` of least RMS blur for an axial point ``distance_mm`` before the front vertex.

    Parameters
    ----------
    profile : CameraProfile
    distance_mm : array_like
        Object distance(s) from the front vertex; ``inf`` allowed.
    d_in_mm : float, optional
        MLA position (default the profile's).
    n_rays : int
        Pupil samples (Vogel spiral over the real pupil).

    Raises
    ------
    OpticsError
        A non-positive distance, or one from which no light reaches the MLA.
    """
    d = np.asarray(distance_mm, dtype=np.float64)
    if np.any(~(d > 0)):
        raise OpticsError(f"refocus distance must be positive, got {distance_mm}")
    d_in = profile.d_in_mm if d_in_mm is None else float(d_in_mm)
    pattern = pupil_pattern(n_rays, "fibonacci")
    out = np.array([_shift_one(profile, d_in, v, pattern) for v in d.ravel()])
    return out.reshape(d.shape) if d.ndim else float(out[0])


def exact_distance_for_shift(
    profile: CameraProfile, shift, d_in_mm: float | None = None, n_rays: int = PUPIL_RAYS
):
    """Inverse of :func:`exact_shift_for_distance` (Brent on the object vergence 1/D).

    Returns NaN for a shift no object in front of the lens produces (beyond the shift of
    infinity, or of a plane at 1.002 × the front focal distance).
    """
    from scipy.optimize import brentq  # lazily: scipy.optimize costs every command ~0.2 s

    a = np.asarray(shift, dtype=np.float64)
    d_in = profile.d_in_mm if d_in_mm is None else float(d_in_mm)
    lens = profile.main_lens
    pattern = pupil_pattern(n_rays, "fibonacci")
    near = 1.002 * max(-lens.as_prescription.paraxial.front_focal_z_mm, 1e-3)

    def g(v: float, target: float) -> float:
        return _shift_one(profile, d_in, 1.0 / v if v > 0 else math.inf, pattern) - target

    v_hi = 1.0 / near
    out = np.full(a.size, np.nan)
    lo_val = g(1.0 / FAR_MM, 0.0)
    hi_val = g(v_hi, 0.0)
    for k, target in enumerate(a.ravel()):
        if not math.isfinite(target):
            continue
        if (lo_val - target) * (hi_val - target) > 0:
            continue
        v = brentq(g, 1.0 / FAR_MM, v_hi, args=(float(target),), xtol=1e-15, rtol=1e-12)
        out[k] = 1.0 / v
    return out.reshape(a.shape) if a.ndim else float(out[0])
