"""The centroid estimator's bias on touching micro-images, learnt on a model white.

Where a white's micro-images touch or overlap, their own-light centroids
(:func:`lfcam.calibrate.grid._model_centroids`) split the shared seams with a disc model, and
the disc fit's centres sit a few hundredths of a pixel inward of the micro-images' at the
field's rim. The centroids then come out up to 0.03 px inward (system 1 at focus ∞), which the
distance fits read as a lenslet lattice 4e-5 too small (docs/calibration.md, "Own-light
centroids of touching whites at the field's rim (stop 64)"). That error is smooth in the field
radius and depends on the optics and on the estimator, not on the particular white: learnt on
one rendering of a white, it removes the error of another to ~2e-6 of the lattice's scale.

:func:`centroid_bias` renders a noise-free model white of the profile on a strip of the
sensor from the optical axis to the distance of the farthest corner (:class:`lfcam.sim.render.
Renderer`, the same exact backward trace as a rendered white), takes its centroids with the
calibration's own estimator and disc model, and fits their radial error against the
renderer's ray-derived centroids by an odd polynomial in the field radius.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from lfcam.calibrate.grid import _model_centroids
from lfcam.calibrate.microimage import DiscModel
from lfcam.camera import CameraProfile
from lfcam.errors import LfcamError

if TYPE_CHECKING:
    from lfcam.calibrate.model import Calibration

STRIP_PITCHES = 6.0  # the model strip's height, in micro-image pitches
BIAS_TERMS = 5  # odd powers 1 … 9 of the field radius
MIN_LENSES = 20  # fewer measured model lenses: no bias learnt
MAX_RMS_PX = 0.03  # the model lenses' centroids scatter about the fit by more: no bias (the
#                    calibration's disc model does not describe the profile's white; measured
#                    0.004-0.008 px where it does)


@dataclass(frozen=True)
class CentroidBias:
    """Radial error of measured micro-image centroids, ``b(r) = Σ c_k (r/R)^(2k+1)`` px
    outward, ``r`` the distance from the optical axis in px (held at ``R`` beyond it).

    Attributes
    ----------
    coef : tuple of float
        ``c_k`` (px).
    radius_px : float
        ``R``: the radius the model white reached (the sensor's farthest corner).
    axis_xy_px : tuple of float
        The optical axis on the sensor (px).
    rms_px : float
        RMS of the fit's residual over the model lenses (their per-lens scatter).
    lenses : int
        Model lenses fitted.
    """

    coef: tuple[float, ...]
    radius_px: float
    axis_xy_px: tuple[float, float]
    rms_px: float
    lenses: int

    def radial_px(self, r_px: np.ndarray) -> np.ndarray:
        """``b(r)`` (px, outward)."""
        rho = np.clip(np.asarray(r_px, dtype=np.float64), 0.0, self.radius_px) / self.radius_px
        return _powers(rho, len(self.coef)) @ np.asarray(self.coef)

    def correct(self, centres_px: np.ndarray) -> np.ndarray:
        """Measured centroids (N, 2) with the bias taken out (moved by ``−b(r)`` radially)."""
        c = np.asarray(centres_px, dtype=np.float64).reshape(-1, 2)
        d = c - np.asarray(self.axis_xy_px)
        r = np.hypot(d[:, 0], d[:, 1])
        unit = d / np.maximum(r, 1e-12)[:, None]
        return c - self.radial_px(r)[:, None] * unit


def _powers(rho: np.ndarray, terms: int) -> np.ndarray:
    return np.column_stack([rho ** (2 * k + 1) for k in range(terms)])


def centroid_bias(profile: CameraProfile, d_in_mm: float, calibration: Calibration,
                  shape: tuple[int, int]) -> CentroidBias | None:
    """The bias of ``calibration``'s centroids for a sensor of ``shape`` (rows, cols), or
    None where there is none to learn: a white whose neighbouring micro-images' edge ramps
    overlap by less than a ramp's half-width (no seam is split; their centroids match the
    white-offset table to 0.002 px: docs/calibration.md), a calibration that does not state
    its disc model, a profile the renderer cannot render, or a model white whose centroids
    scatter about the fit by over :data:`MAX_RMS_PX` (the calibration's disc model does not
    describe it). The centroids are then used as measured."""
    diag = calibration.diagnostics or {}
    radius, edge = diag.get("disc_radius_px"), diag.get("disc_edge_px")
    if diag.get("centroid_method") != "micro-image model" or radius is None or edge is None:
        return None
    if 2.0 * (float(radius) + float(edge)) - float(calibration.pitch_px) < float(edge):
        return None  # neighbours' edge ramps overlap by less than a half-width: no seam to split
    try:
        return _learn(profile.with_d_in(float(d_in_mm)), (int(shape[0]), int(shape[1])),
                      float(radius), float(edge), float(calibration.pitch_px),
                      calibration.grid, float(calibration.rotation_rad))
    except LfcamError:
        return None


def model_strip(profile: CameraProfile, shape: tuple[int, int],
                pitch_px: float) -> tuple[CameraProfile, tuple[float, float], float]:
    """The model white's sensor for a sensor of ``shape`` (rows, cols): ``profile`` on a strip
    :data:`STRIP_PITCHES` micro-image pitches high, the optical axis one pitch in from its left
    end, reaching along +x past the distance of ``shape``'s farthest corner from its axis.
    Returns the strip's profile, its axis (px) and that distance (px)."""
    h, w = shape
    ax, ay = profile.sensor.axis_xy_px
    reach = max(math.hypot(x - ax, y - ay) for x in (0.0, w - 1.0) for y in (0.0, h - 1.0))
    height = int(math.ceil(STRIP_PITCHES * pitch_px))
    width = int(math.ceil(reach + 3.0 * pitch_px))
    axis = (pitch_px, 0.5 * (height - 1))
    strip = replace(profile, sensor=replace(profile.sensor, width_px=width, height_px=height,
                                            axis_px=axis))
    return strip, axis, reach


@lru_cache(maxsize=8)
def _learn(profile: CameraProfile, shape: tuple[int, int], radius_px: float, edge_px: float,
           pitch_px: float, grid: str, rotation_rad: float) -> CentroidBias | None:
    """:func:`centroid_bias`'s model white and fit (cached per camera and calibration)."""
    from lfcam.sim.render import Renderer
    from lfcam.sim.scene import Scene, WhiteScene

    strip, axis, reach = model_strip(profile, shape, pitch_px)
    rend = Renderer(strip)
    res = rend.render(Scene(objects=(WhiteScene(),), seed=0))
    cand = np.rint(rend.predicted_centres_px())
    on = ((cand[:, 0] >= 0) & (cand[:, 0] < strip.sensor.width_px) & (cand[:, 1] >= 0)
          & (cand[:, 1] < strip.sensor.height_px))
    centres, _, conv, at_edge = _model_centroids(
        res.signal, cand[on], DiscModel(radius_px, edge_px, 0.0), pitch_px, grid, rotation_rad,
        lambda *a: None)
    got = centres[conv & ~at_edge]
    true = res.lens_centroid_px[res.lens_complete & np.isfinite(res.lens_centroid_px).all(1)]
    if len(got) < MIN_LENSES or len(true) < MIN_LENSES:
        return None
    dist, k = cKDTree(true).query(got)
    keep = dist < 0.5 * pitch_px
    got, true = got[keep], true[k[keep]]
    d = true - np.asarray(axis)
    r = np.hypot(d[:, 0], d[:, 1])
    radial = ((got - true) * d / np.maximum(r, 1e-12)[:, None]).sum(axis=1)
    a = _powers(np.minimum(r, reach) / reach, BIAS_TERMS)
    coef, *_ = np.linalg.lstsq(a, radial, rcond=None)
    rms = float(np.sqrt(np.mean((a @ coef - radial) ** 2)))
    if not rms <= MAX_RMS_PX:
        return None
    return CentroidBias(tuple(float(c) for c in coef), float(reach),
                        tuple(float(v) for v in profile.sensor.axis_xy_px), rms, int(len(got)))
