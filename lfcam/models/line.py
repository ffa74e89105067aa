"""``line``: the seed's line-source model, §2.3, eqs. 18–20, from the line's two endpoints.

Every point i of a line in one object plane satisfies eq. 1 for its upper-rim ray:
``D/2 − Δh_i = d·tan φ_i1``, where d is the axial distance from the object plane to the rim
plane (eq. 1's denominator; the paper's eq. 18 prints this with sign slips, we use the form
that agrees with eq. 1). Differencing the two endpoints a and b (eq. 20):

    d = (Δh_a − Δh_b) / (tan φ_b1 − tan φ_a1),   distance_mm = d − rim_sag

with each endpoint's Δh and tan φ_1 from the §2.2 chain. The difference in the denominator
cancels when the endpoints' tangents nearly coincide (short lines, lines seen end-on): we
report ``ill-conditioned`` when the relative error amplification
``(|tan φ_a1| + |tan φ_b1|)/|tan φ_b1 − tan φ_a1|`` exceeds ``max_amplification``.
``offset_mm`` is the midpoint's offset ``(Δh_a + Δh_b)/2``.
"""

from __future__ import annotations

import numpy as np

from lfcam.camera import CameraProfile
from lfcam.models.base import Inversion, Status, as_heights, finish
from lfcam.models.offaxis import from_angles, rim_angles

DEFAULT_MAX_AMPLIFICATION = 1e4


def amplification(tan_a: np.ndarray, tan_b: np.ndarray) -> np.ndarray:
    """Relative error amplification of eq. 20's denominator."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return (np.abs(tan_a) + np.abs(tan_b)) / np.abs(tan_b - tan_a)


def invert(
    profile: CameraProfile,
    d_in_mm: float | None,
    y1a_mm,
    y2a_mm,
    y1b_mm,
    y2b_mm,
    max_amplification: float = DEFAULT_MAX_AMPLIFICATION,
) -> Inversion:
    """Distance of a line source from its endpoints' rim-ray heights (eqs. 18–20).

    Parameters
    ----------
    profile : CameraProfile
    d_in_mm : float or None
    y1a_mm, y2a_mm : array_like
        Rim-ray sensor heights of endpoint a (upper rim, lower rim).
    y1b_mm, y2b_mm : array_like
        The same for endpoint b.
    max_amplification : float
        Threshold of the cancellation flag (see module docstring).

    Returns
    -------
    Inversion
    """
    lens = profile.main_lens
    y1a, y2a, shape = as_heights(y1a_mm, y2a_mm)
    y1b, y2b, _ = as_heights(y1b_mm, y2b_mm)
    with np.errstate(invalid="ignore", divide="ignore"):
        tan1a = rim_angles(profile, d_in_mm, y1a)
        tan2a = rim_angles(profile, d_in_mm, -y2a)
        tan1b = rim_angles(profile, d_in_mm, y1b)
        tan2b = rim_angles(profile, d_in_mm, -y2b)
        _, dh_a, _ = from_angles(profile, tan1a, tan2a)
        _, dh_b, _ = from_angles(profile, tan1b, tan2b)
        along = (dh_a - dh_b) / (tan1b - tan1a)
        amp = amplification(tan1a, tan1b)
    distance = along - lens.rim_sag_mm
    offset = 0.5 * (dh_a + dh_b)
    status = np.full(y1a.shape, Status.OK, dtype=np.uint8)
    finite = np.isfinite(tan1a) & np.isfinite(tan2a) & np.isfinite(tan1b) & np.isfinite(tan2b)
    status[~finite] = Status.OUT_OF_DOMAIN
    status[(status == Status.OK) & ~(amp <= max_amplification)] = Status.ILL_CONDITIONED
    status[(status == Status.OK) & ~(distance > 0.0)] = Status.NO_SOLUTION
    inputs = np.isfinite(y1a) & np.isfinite(y2a) & np.isfinite(y1b) & np.isfinite(y2b)
    status[~inputs] = Status.INVALID_INPUT
    return finish(distance, offset, status, shape)
