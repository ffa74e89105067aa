"""``offaxis``: the seed paper's single-point-light-source model, §2.2, eqs. 1–17, as written.

Per rim ray i (1 = upper rim, 2 = lower rim), in a frame mirrored so that ray i's rim is up
(the paper's ``sgn(i)``; the in-frame sensor height is ``v = y1`` for ray 1 and ``v = −y2``
for ray 2):

1. eq. 14 (the approximation): the emerging ray is taken to leave the lens-centre plane at
   height D/2, so its slope magnitude is ``m = (D/2 − v)/(f_x + d_in)``;
2. eqs. 8–9: the exit point (p, q) is where the line through the sensor point with slope m
   meets the back surface ``(R − T/2 + p)² + q² = R²`` (the root nearest the back vertex);
3. eq. 15: ``ω = arctan(|q − v|/(f_x + d_in − p)) + arcsin(|q|/R)``;
4. eq. 16: ``ψ = arcsin(D/2R) + arcsin(|q|/R) − arcsin(sin ω / n)``;
5. eq. 17: ``φ = arcsin(n sin ψ) − arcsin(D/2R)``.

Then eq. 3 gives ``Δh = D(tan φ2 − tan φ1) / (2(tan φ2 + tan φ1))`` and two estimates of
d'out, one per ray. Substituting Δh shows the two are algebraically identical:
``(D/2 ∓ Δh)/tan φ_i = D/(tan φ1 + tan φ2)``. We return that common value in this symmetric
form, because the per-ray forms divide two small numbers when a source nears a rim
(Δh → ±D/2, tan φ_i → 0) while the symmetric form never cancels. ``distance_mm = d'out − T/2``.
"""

from __future__ import annotations

import numpy as np

from lfcam.camera import CameraProfile
from lfcam.models.base import Inversion, Status, as_heights, finish


def rim_angles(profile: CameraProfile, d_in_mm: float | None, v_mm: np.ndarray) -> np.ndarray:
    """tan φ of a rim ray from its in-frame sensor height ``v_mm`` (eqs. 8–9, 14–17).

    NaN where the chain leaves the real domain of an arcsin or the line misses the surface,
    and everywhere for a main lens that is not the seed's singlet: the derivation (eqs. 8–17)
    needs its two equal spheres and the stop on the front rim, so ``offaxis``, ``onaxis`` and
    ``line`` answer ``out-of-domain`` on a general prescription (docs/models.md).
    """
    lens = profile.main_lens
    if not lens.is_singlet:
        return np.full(np.shape(v_mm), np.nan)
    r, t, n, d = lens.radius_mm, lens.thickness_mm, lens.refractive_index, lens.pupil_diameter_mm
    d_in = profile.d_in_mm if d_in_mm is None else float(d_in_mm)
    l_s = profile.mla.focal_length_mm + d_in
    theta = np.arcsin(d / (2.0 * r))
    m = (0.5 * d - v_mm) / l_s  # eq. 14
    # eqs. 8–9: q = a − m p on the circle (p − c)² + q² = R², c = T/2 − R
    c = 0.5 * t - r
    a = v_mm + m * l_s
    bq = c + a * m
    one_m2 = 1.0 + m * m
    disc = bq * bq - one_m2 * (c * c + a * a - r * r)
    p = (bq + np.sqrt(disc)) / one_m2
    q = a - m * p
    normal = np.arcsin(np.abs(q) / r)  # eq. 7, shared by eqs. 15 and 16
    omega = np.arctan(np.abs(q - v_mm) / (l_s - p)) + normal  # eq. 15
    psi = theta + normal - np.arcsin(np.sin(omega) / n)  # eq. 16
    phi = np.arcsin(n * np.sin(psi)) - theta  # eq. 17
    return np.tan(phi)


def from_angles(profile: CameraProfile, tan1: np.ndarray, tan2: np.ndarray):
    """Eq. 3: (distance_mm, offset_mm) from the two rim-ray tangents."""
    lens = profile.main_lens
    total = tan1 + tan2
    if not lens.is_singlet:  # out of the derivation's domain (tan φ are NaN already)
        nan = np.full(np.shape(total), np.nan)
        return nan, nan.copy(), total
    r, t, d = lens.radius_mm, lens.thickness_mm, lens.pupil_diameter_mm
    offset = d * (tan2 - tan1) / (2.0 * total)
    d_out = d / total + np.sqrt(r * r - 0.25 * d * d) - r + 0.5 * t
    return d_out - 0.5 * t, offset, total


def classify(distance, tan1, tan2, total) -> np.ndarray:
    """Status of a closed-form answer: NaNs are out-of-domain, a non-positive sum no-solution."""
    status = np.full(distance.shape, Status.OK, dtype=np.uint8)
    status[~(np.isfinite(tan1) & np.isfinite(tan2))] = Status.OUT_OF_DOMAIN
    status[(status == Status.OK) & ~(total > 0.0)] = Status.NO_SOLUTION
    status[(status == Status.OK) & ~(distance > 0.0)] = Status.OUT_OF_DOMAIN
    return status


def invert(profile: CameraProfile, d_in_mm: float | None, y1_mm, y2_mm) -> Inversion:
    """Distance and offset from rim-ray heights with the seed's closed form (eqs. 1–17).

    Parameters
    ----------
    profile : CameraProfile
    d_in_mm : float or None
    y1_mm, y2_mm : array_like
        Signed sensor heights of the upper- and lower-rim rays.

    Returns
    -------
    Inversion
    """
    y1, y2, shape = as_heights(y1_mm, y2_mm)
    with np.errstate(invalid="ignore", divide="ignore"):
        tan1 = rim_angles(profile, d_in_mm, y1)
        tan2 = rim_angles(profile, d_in_mm, -y2)
        distance, offset, total = from_angles(profile, tan1, tan2)
    status = classify(distance, tan1, tan2, total)
    status[~(np.isfinite(y1) & np.isfinite(y2))] = Status.INVALID_INPUT
    return finish(distance, offset, status, shape)
