"""Paraxial (Gaussian) optics of the thick main lens, through its principal planes."""

from __future__ import annotations

import math

import numpy as np

from lfcam.camera import MainLens
from lfcam.errors import OpticsError


def image_distance_mm(lens: MainLens, distance_mm: np.ndarray | float) -> np.ndarray | float:
    """Paraxial image distance behind H2 for an object ``distance_mm`` before the front vertex.

    Infinite distances give f. Objects at or inside the front focal plane give ``inf`` or a
    negative (virtual) image distance.
    """
    f = lens.focal_length_mm
    s = np.asarray(distance_mm, dtype=np.float64) + lens.principal_depth_mm
    with np.errstate(divide="ignore"):
        inv = 1.0 / f - 1.0 / s
        out = 1.0 / inv
    return out if out.ndim else float(out)


def d_in_for_focus(lens: MainLens, focus_mm: float) -> float:
    """MLA distance d_in (main-lens centre → MLA) that focuses an object at ``focus_mm``.

    Parameters
    ----------
    lens : MainLens
    focus_mm : float
        Object distance from the front vertex; ``math.inf`` for infinity focus.

    Raises
    ------
    OpticsError
        If the object is at or inside the front focal point (no real image).
    """
    focus = float(focus_mm)
    if math.isnan(focus) or focus <= 0:
        raise OpticsError(f"focus distance must be positive, got {focus_mm}")
    s_img = image_distance_mm(lens, focus)
    if not math.isfinite(s_img) or s_img <= 0:
        raise OpticsError(
            f"focus {focus} mm is at or inside the front focal point "
            f"(f = {lens.focal_length_mm:.3f} mm): no real image to put the MLA at"
        )
    return lens.back_principal_z_mm + s_img


def focus_for_d_in(lens: MainLens, d_in_mm: float) -> float:
    """Object distance (from the front vertex) in paraxial focus on an MLA at ``d_in_mm``.

    Returns ``inf`` when the MLA sits at the back focal plane or closer.
    """
    s_img = float(d_in_mm) - lens.back_principal_z_mm
    f = lens.focal_length_mm
    if s_img <= f:
        return math.inf
    s_obj = 1.0 / (1.0 / f - 1.0 / s_img)
    return s_obj - lens.principal_depth_mm
