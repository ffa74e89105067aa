"""``onaxis``: the on-axis model the seed extends (its ref. [15]): offset fixed at 0.

An on-axis source puts its rim rays symmetrically, ``y2 = −y1``. Given measured heights we use
their half-difference ``v = (y1 − y2)/2`` (the signed blur radius; the mean ``(y1 + y2)/2`` is
ignored, which is exactly the model's assumption) for both rays of the §2.2 chain, so that
``tan φ1 = tan φ2`` and eq. 3 reduces to ``d'out = (D/2)/tan φ + √(R² − D²/4) − R + T/2``.
"""

from __future__ import annotations

import numpy as np

from lfcam.camera import CameraProfile
from lfcam.models.base import Inversion, Status, as_heights, finish
from lfcam.models.offaxis import classify, from_angles, rim_angles


def invert(profile: CameraProfile, d_in_mm: float | None, y1_mm, y2_mm) -> Inversion:
    """Distance from the signed blur radius, assuming the source is on the axis.

    Returns
    -------
    Inversion
        ``offset_mm`` is 0 wherever the status is ok.
    """
    y1, y2, shape = as_heights(y1_mm, y2_mm)
    with np.errstate(invalid="ignore", divide="ignore"):
        tan = rim_angles(profile, d_in_mm, 0.5 * (y1 - y2))
        distance, offset, total = from_angles(profile, tan, tan)
    status = classify(distance, tan, tan, total)
    status[~(np.isfinite(y1) & np.isfinite(y2))] = Status.INVALID_INPUT
    return finish(distance, np.zeros_like(distance), status, shape)
