"""``thin``: paraxial (Gaussian) defocus through the thick lens's principal planes.

The aperture stop is the front rim (at ``z_rim``), not a principal plane, and that matters at
the percent level: the rim ray of a source a distance ``L = distance_mm + rim_sag`` before the
rim plane has slope ``t± = (±D/2 − Δh)/L`` and reaches the object-side principal plane H1,
``e = z_H1 − z_rim`` further on, at height ``h± = ±D/2 + e·t±``. Paraxially it leaves H2 at the
same height and heads for the image point ``(s', −Δh·s'/s)``, with ``s = L + e`` (source → H1)
and ``1/s' = 1/f − 1/s``. At the sensor, ``g = d_in + f_x − z_H2`` behind H2:

    y± = h±·(1 − g/s') − Δh·g/s

Forward and inverse are closed form; with ``Δy = y1 − y2`` and ``Σ = y1 + y2``:

    s  = (D·g + Δy·e) / (Δy − D(1 − g/f))
    Δh = −Σ / (2·[e(1 − g/f + g/s)/L + g/s])

The cheapest model. Its error is the main lens's spherical aberration, which at F/2 moves the
rim rays' crossing far from the paraxial focus (see docs/models.md).
"""

from __future__ import annotations

import numpy as np

from lfcam.camera import CameraProfile
from lfcam.models.base import Inversion, Status, as_heights, finish


def _geometry(profile: CameraProfile, d_in_mm: float | None) -> tuple[float, float, float, float]:
    lens = profile.main_lens
    d_in = profile.d_in_mm if d_in_mm is None else float(d_in_mm)
    gap = d_in + profile.mla.focal_length_mm - lens.back_principal_z_mm
    stop_to_h1 = lens.front_principal_z_mm - lens.rim_z_mm
    return lens.pupil_diameter_mm, lens.focal_length_mm, gap, stop_to_h1


def forward(profile: CameraProfile, d_in_mm: float | None, distance_mm, offset_mm=0.0):
    """Paraxial rim-ray sensor heights ``(y1_mm, y2_mm)``."""
    d, f, g, e = _geometry(profile, d_in_mm)
    along = np.asarray(distance_mm, dtype=np.float64) + profile.main_lens.rim_sag_mm
    off = np.asarray(offset_mm, dtype=np.float64)
    s = along + e
    keep = 1.0 - g / f + g / s  # 1 − g/s'
    shift = -off * g / s
    h1 = 0.5 * d + e * (0.5 * d - off) / along
    h2 = -0.5 * d + e * (-0.5 * d - off) / along
    return h1 * keep + shift, h2 * keep + shift


def invert(profile: CameraProfile, d_in_mm: float | None, y1_mm, y2_mm) -> Inversion:
    """Distance and offset from rim-ray heights in the paraxial model (closed form)."""
    d, f, g, e = _geometry(profile, d_in_mm)
    y1, y2, shape = as_heights(y1_mm, y2_mm)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        dy, sigma = y1 - y2, y1 + y2
        s = (d * g + dy * e) / (dy - d * (1.0 - g / f))
        along = s - e
        offset = -sigma / (2.0 * (e * (1.0 - g / f + g / s) / along + g / s))
    distance = along - profile.main_lens.rim_sag_mm
    status = np.full(y1.shape, Status.OK, dtype=np.uint8)
    status[~(np.isfinite(s) & (s > 0.0))] = Status.NO_SOLUTION
    status[(status == Status.OK) & ~(distance > 0.0)] = Status.OUT_OF_DOMAIN
    status[~(np.isfinite(y1) & np.isfinite(y2))] = Status.INVALID_INPUT
    return finish(distance, offset, status, shape)
