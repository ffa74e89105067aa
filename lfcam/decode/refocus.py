"""Shift-and-sum refocusing of a decoded light field, by shift or by metric distance.

Shift convention (the same ``a`` as Hahne et al.'s refocusing model, :mod:`lfcam.models.hahne`):
the refocused image is

    E(t, s) = Σ_{v,u} w·L[v, u, t − a·(v − vc)·k_y, s − a·(u − uc)] / Σ_{v,u} w

with ``u − uc`` in sensor pixels from the micro-image centre and ``s`` in lenslets;
``k_y = spacing_x / spacing_y`` (1 for rect grids, 2/√3 for hex rows). So ``−a`` is the
slope of a scene point's trace in the light field, in lenslets of spatial shift per pixel of
angular coordinate, and any real ``a`` is allowed (bilinear interpolation).

Why this is Hahne's ``a`` (derivation in ``docs/decoding.md``): a pixel ``i`` pixels from its
micro-image centre sees, through its lenslet centre, the point ``h = −i·p_p·d_A/f_s`` of the
exit pupil. The chief ray from there to an image point a distance Δ behind the MLA crosses the
MLA at ``x = h·Δ/(d_A + Δ)``, i.e. at ``−i·a`` lenslets with
``a = Δ·p_p·d_A / (f_s·p_m·(d_A + Δ))`` — exactly Hahne's closed form
(:func:`lfcam.models.hahne.shift_for_distance`), whose refocused pixel pairs pixel ``i`` with
lenslet ``−a·i``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from lfcam.camera import CameraProfile
from lfcam.decode.lightfield import LightField
from lfcam.errors import OpticsError
from lfcam.optics.refocus import exact_distance_for_shift, exact_shift_for_distance

WARP_FLAGS = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
MAX_ABS_SHIFT = 100.0  # lenslets per angular pixel; beyond this nothing overlaps anyway


@dataclass(frozen=True)
class Refocused:
    """A refocused image and the total weight behind each pixel (0 = no valid sample)."""

    image: np.ndarray  # float32 (T, S)
    weight: np.ndarray  # float32 (T, S)
    shift: float


def shift_for_distance(profile: CameraProfile, distance_mm, d_in_mm: float | None = None):
    """Shift ``a`` that refocuses onto the plane ``distance_mm`` from the front vertex: the
    shift of least RMS blur of a point there, from the exact trace through the main lens
    (:func:`lfcam.optics.refocus.exact_shift_for_distance`; Hahne's paraxial closed form is
    :func:`lfcam.models.hahne.shift_for_distance`).

    Parameters
    ----------
    profile : CameraProfile
    distance_mm : array_like
        Object distance from the main lens's front vertex (docs/conventions.md); ``inf`` allowed.
    d_in_mm : float, optional
        MLA distance (default the profile's).

    Raises
    ------
    OpticsError
        Distance not positive, or a plane that the main lens images to infinity.
    """
    d = np.asarray(distance_mm, dtype=np.float64)
    if np.any(~(d > 0)):
        raise OpticsError(f"refocus distance must be positive, got {distance_mm}")
    try:
        a = exact_shift_for_distance(profile, d, d_in_mm)
    except OpticsError:
        a = np.nan
    if not np.all(np.isfinite(a)):
        raise OpticsError(f"distance {distance_mm} mm cannot be refocused (at or inside f)")
    return a


def distance_for_shift(profile: CameraProfile, shift, d_in_mm: float | None = None):
    """Inverse of :func:`shift_for_distance` (mm from the front vertex; NaN where no object
    in front of the lens refocuses to ``shift``)."""
    return exact_distance_for_shift(profile, shift, d_in_mm)


def _check_shift(a: float) -> float:
    a = float(a)
    if not math.isfinite(a) or abs(a) > MAX_ABS_SHIFT:
        raise OpticsError(f"refocus shift must be finite with |a| ≤ {MAX_ABS_SHIFT}, got {a}")
    return a


def focal_stack(lf: LightField, shifts) -> list[Refocused]:
    """Refocus at every shift in ``shifts`` (one pass over the views).

    Parameters
    ----------
    lf : LightField
    shifts : sequence of float
        Hahne shifts ``a`` (see the module docstring for the convention).

    Returns
    -------
    list of Refocused
    """
    shifts = [_check_shift(a) for a in np.atleast_1d(np.asarray(shifts, dtype=np.float64))]
    nv, nu, t_count, s_count = lf.data.shape
    vc, uc = lf.angular_centre
    ky = lf.spacing_px[0] / lf.spacing_px[1]
    num = np.zeros((len(shifts), t_count, s_count), np.float32)
    den = np.zeros_like(num)
    size = (s_count, t_count)
    m = np.eye(2, 3, dtype=np.float64)
    for v in range(nv):
        for u in range(nu):
            w = lf.weight[v, u]
            if not w.any():
                continue
            lw = lf.data[v, u] * w
            du, dv = u - uc, v - vc
            for k, a in enumerate(shifts):
                m[0, 2], m[1, 2] = -a * du, -a * dv * ky
                cv2.add(num[k], cv2.warpAffine(lw, m, size, flags=WARP_FLAGS), dst=num[k])
                cv2.add(den[k], cv2.warpAffine(w, m, size, flags=WARP_FLAGS), dst=den[k])
    out = []
    for k, a in enumerate(shifts):
        good = den[k] > 1e-6
        img = np.zeros((t_count, s_count), np.float32)
        np.divide(num[k], den[k], out=img, where=good)
        out.append(Refocused(image=img, weight=den[k], shift=a))
    return out


def refocus(lf: LightField, shift: float) -> Refocused:
    """Shift-and-sum refocus at Hahne shift ``shift`` (any real value)."""
    return focal_stack(lf, [shift])[0]


def refocus_distance(lf: LightField, profile: CameraProfile, distance_mm: float,
                     d_in_mm: float | None = None) -> Refocused:
    """Refocus onto the plane ``distance_mm`` from the front vertex (via Hahne's geometry)."""
    return refocus(lf, float(shift_for_distance(profile, distance_mm, d_in_mm)))
