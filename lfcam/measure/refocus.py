"""Hahne et al.'s depth from refocus, the seed paper's baseline, measured per region."""

from __future__ import annotations

import numpy as np

from lfcam.camera import CameraProfile
from lfcam.measure.geometry import Geometry
from lfcam.measure.regions import Region
from lfcam.models import hahne
from lfcam.status import RegionStatus


def measure_refocus(profile: CameraProfile, geom: Geometry, image: np.ndarray,
                    region: Region) -> tuple[float, float, str]:
    """Hahne et al.'s depth from refocus (the seed's baseline [14]): (distance, σ, status).

    Shift-and-sum maps a sample of lenslet ``j`` (lattice units) at angular offset ``u`` (pixels
    from its micro-image centre) to ``j + a·u``; the refocused spot is sharpest where its
    spatial spread is least, i.e. where ``u`` is linear in ``j`` with slope ``−1/a``; the
    continuous sweep's optimum is the regression ``a* = −Var(j)/Cov(j, u)`` (both axes pooled,
    intensity-weighted),
    and Hahne's model maps ``a*`` to a distance (``lfcam.models.hahne``).

    Parameters
    ----------
    profile : CameraProfile
    geom : Geometry
    image : (H, W) float array
    region : Region

    Returns
    -------
    distance_mm, sigma_mm : float
    status : str
        ``ok``, ``near-focus`` (no defocus to measure) or ``out-of-domain``.
    """
    x0, y0, x1, y1 = region.box_px
    labels = geom.lmap.labels[y0:y1, x0:x1]
    mask = np.isin(labels, region.lenslets)
    w = np.clip(image[y0:y1, x0:x1][mask], 0.0, None)
    if w.sum() <= 0:
        return float("nan"), float("nan"), RegionStatus.NEAR_FOCUS
    ys, xs = np.nonzero(mask)
    k = labels[mask]
    centre = geom.lmap.centres_px[k]
    u = np.column_stack([xs + x0 - centre[:, 0], ys + y0 - centre[:, 1]])
    j = centre / geom.pitch_px  # lenslet positions in lattice units
    wn = w / w.sum()
    jm, um = wn @ j, wn @ u
    cov = float((wn * ((j - jm) * (u - um)).sum(axis=1)).sum())
    var_j = float((wn * ((j - jm) ** 2).sum(axis=1)).sum())
    if cov == 0.0 or var_j <= 0:
        return float("nan"), float("nan"), RegionStatus.NEAR_FOCUS
    # regress u on j, not j on u: a sample's true crossing differs from its lenslet centre by
    # up to half a pitch, an error correlated with u (which is set by the crossing) but not
    # with j — the j-on-u regression would be diluted toward zero shift
    a_star = -var_j / cov
    params = hahne.parameters_for(profile, geom.d_in_mm)
    offset = hahne.mla_to_front_vertex_mm(profile, geom.d_in_mm)
    d = float(hahne.refocus_distance(params, a_star).distance_mm) - offset
    # σ of a* from the weighted regression's residual, mapped through the model
    resid = (u - um) + (j - jm) / a_star
    n_eff = 1.0 / float((wn * wn).sum())
    slope_sigma = float(np.sqrt((wn * (resid**2).sum(axis=1)).sum() / max(n_eff - 1, 1) / var_j))
    sigma_a = a_star * a_star * slope_sigma  # a = −1/slope
    d2 = float(hahne.refocus_distance(params, a_star + 1e-3).distance_mm) - offset
    sigma_d = abs(d2 - d) / 1e-3 * sigma_a
    status = RegionStatus.OK if np.isfinite(d) and d > 0 else RegionStatus.OUT_OF_DOMAIN
    return d, sigma_d, status
