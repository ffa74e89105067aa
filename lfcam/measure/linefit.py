"""Light-field measurement of a line-like source: the exact forward model fitted to the pixels.

A straight line source in a plane perpendicular to the axis is fixed by its distance and its
two lateral endpoints (5 numbers). The model renders it as ``LINE_POINTS`` equally bright
points along the segment, each traced through the exact main lens and the ideal lenslets
(:class:`lfcam.measure.pointfit._Patch`), and is matched to the region's pixels with the
intensity scale in closed form.

Start: the footprint of a uniform segment of image length ``Lᵢ`` blurred by a disc of
diameter ``B`` has second moments ``Lᵢ²/12 + B²/16`` along and ``B²/16`` across its axis, which
give ``Lᵢ``; a distance scan then maps the image segment back to the object through the chief-
ray gain (lateral centre matched to the light's centroid through the exact render); the
caller's line (the lenslet fit's, whose axis does not depend on the footprint's moments) is a
start beside the scan's best. A trust-region least-squares refinement with physically sized
finite-difference steps finishes. Each point's rays sample the pupil quasi-randomly (Vogel):
a regular grid, the same for every point, aliased with the pixels (docs/distance.md, "Short
lines behind focus").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lfcam.camera import CameraProfile
from lfcam.measure.pointfit import (
    PhysicalJacobian,
    _centroid_px,
    _match_centroid,
    _Patch,
    chief_ray_offset,
    pupil_pattern,
)
from lfcam.measure.sampling import segment_points, vogel_disc
from lfcam.status import RegionStatus

LINE_POINTS = 24
LINE_PUPIL = 110  # per side of the pupil grid for each line point (~9.5 k rays; 64 left a line
#                   60 % off axis far behind focus on a ripple of the sample, −2.5 % at 40 σ:
#                   docs/distance.md, "Lines off axis")
SIGMA_STEPS_LOG = (5e-3, 2e-2, 5e-2)  # steps of the σ parabola in log distance, tried in turn


@dataclass(frozen=True)
class LineFit:
    """Line source found by matching the exact forward model to a region's pixels."""

    start_mm: np.ndarray  # (3,) endpoint a
    end_mm: np.ndarray  # (3,) endpoint b
    misfit: float
    sigma_distance_mm: float
    evaluations: int
    ok: bool
    reason: str = ""

    @property
    def length_mm(self) -> float:
        """Length of the fitted segment."""
        return float(np.linalg.norm(self.end_mm - self.start_mm))


def _moments(img: np.ndarray):
    """Centroid and principal second moments (variances, unit axis) of an image."""
    tot = img.sum()
    yy, xx = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    cx, cy = (xx * img).sum() / tot, (yy * img).sum() / tot
    dx, dy = xx - cx, yy - cy
    cov = np.array([[(dx * dx * img).sum(), (dx * dy * img).sum()],
                    [(dx * dy * img).sum(), (dy * dy * img).sum()]]) / tot
    evals, evecs = np.linalg.eigh(cov)
    return np.array([cx, cy]), evals, evecs[:, 1]


def fit_line_image(
    profile: CameraProfile,
    d_in_mm: float,
    image: np.ndarray,
    box: tuple[int, int, int, int],
    lens_centres_mm: np.ndarray,
    start_mm: tuple[np.ndarray, np.ndarray] | None = None,
    floor_sigma: float = 0.0,
) -> LineFit:
    """Fit (distance, endpoint a, endpoint b) of a line source to the pixels in ``box``.

    ``start_mm``: endpoints (two (3,) points, lens frame) of a line found another way (the
    lenslet fit's), a start beside those of the distance scan. ``floor_sigma``: as
    :func:`lfcam.measure.pointfit.fit_point_image`'s.
    """
    from scipy.optimize import least_squares  # lazily (import cost, as in pointfit)

    lens = profile.main_lens
    z_front = lens.front_vertex_z_mm
    patch = _Patch(profile, d_in_mm, image, box, lens_centres_mm, floor_sigma)
    # a quasi-random (Vogel) pupil sample, as the point fit's: a regular grid, the same for
    # every point of the line, aliases with the pixels
    pattern = vogel_disc(len(pupil_pattern(LINE_PUPIL)[0]))
    nan3 = np.full(3, np.nan)
    if patch.norm <= 0:
        return LineFit(nan3, nan3, 1.0, np.nan, 0, False, RegionStatus.EMPTY)
    _, var, axis = _moments(np.clip(patch.data, 0, None))
    image_len_px = float(np.sqrt(max(12.0 * (var[1] - var[0]), 0.0)))
    pp = profile.sensor.pixel_pitch_mm
    mag = 1.0 + profile.mla.focal_length_mm / (d_in_mm - lens.exit_pupil_z_mm)
    cen_px = _centroid_px(patch.data)
    ax, ay = profile.sensor.axis_xy_px
    target = np.array([(cen_px[0] + box[0] - ax) * pp, (cen_px[1] + box[1] - ay) * pp]) / mag
    def points(q):
        xy = segment_points(q[1:3], q[3:5], LINE_POINTS)
        return np.column_stack([xy, np.full(LINE_POINTS, z_front - np.exp(q[0]))])

    model = PhysicalJacobian(lambda q: patch.residual(points(q), pattern))
    fun, jac = model.fun, model.jac

    def start_at(d):
        centre = _match_centroid(patch, profile, d_in_mm, d, target, z_front)
        gain = chief_ray_offset(profile, d_in_mm, d, np.array([1.0, 0.0]))[0]  # src mm / MLA mm
        half = 0.5 * image_len_px * pp / mag * abs(gain)
        return np.array([np.log(d), *(centre - half * axis), *(centre + half * axis)])

    f = lens.focal_length_mm
    scored = []
    for d in np.geomspace(1.1 * f, 2e4, 24):
        q = start_at(d)
        scored.append((float(np.sqrt((fun(q) ** 2).sum())), q))
    scored.sort(key=lambda s: s[0])
    fine = []
    for _, q0 in scored[:2]:
        for d in np.exp(q0[0]) * np.linspace(0.9, 1.1, 7):
            q = start_at(d)
            fine.append((float(np.sqrt((fun(q) ** 2).sum())), q))
    if start_mm is not None and all(np.isfinite(p).all() for p in start_mm):
        # the lenslet fit's line: its axis and length come from the light's distribution over
        # every lenslet, where the footprint's second moments above only see noise for a line
        # a few pitches long inside a wide blur (docs/distance.md, "Short lines behind focus")
        a, b = start_mm
        if a[2] < z_front - 1.05 * lens.focal_length_mm:
            q = np.array([np.log(z_front - a[2]), a[0], a[1], b[0], b[1]])
            fine.append((float(np.sqrt((fun(q) ** 2).sum())), q))
    scored = sorted(fine + scored, key=lambda s: s[0])

    best = None
    for _, q0 in scored[:2]:
        res = least_squares(fun, q0, jac=jac, method="trf", x_scale="jac", max_nfev=20)
        val = float(np.sqrt((res.fun**2).sum()))
        if best is None or val < best[0]:
            best = (val, res.x)
    # along the line of sight (every point scaled about the entrance-pupil centre) distance
    # and lateral size trade off: scan ±15 %, restart from a better point, refine again
    def scaled(q, sc):
        """Parameters of the line scaled by ``sc`` about the pupil centre (0, 0, z_rim)."""
        z = lens.rim_z_mm + sc * ((z_front - np.exp(q[0])) - lens.rim_z_mm)
        return np.r_[np.log(z_front - z), sc * q[1:]]

    for _ in range(2):
        f0, q = best
        vals = [(float(np.sqrt((fun(scaled(q, sc)) ** 2).sum())), sc)
                for sc in np.linspace(0.85, 1.15, 13)]
        v, sc = min(vals)
        if v < f0 and abs(sc - 1.0) > 1e-9:
            res = least_squares(fun, scaled(q, sc), jac=jac, method="trf", x_scale="jac",
                                max_nfev=20)
            val = float(np.sqrt((res.fun**2).sum()))
            if val < f0:
                best = (val, res.x)
                continue
        break
    f0, q = best
    # σ of the distance from the curvature of the misfit in log-distance (lateral held). The
    # misfit is rough on the scale of a few 0.1 % (a finite pupil sample binned into pixels):
    # where ±0.5 % sees no positive curvature (2 of 21 lines behind a 1 m focus: σ = ∞ with an
    # `ok` status), the step widens
    npix = max(int((patch.data > 0.05 * patch.data.max()).sum()), 1)
    sigma_log = np.inf
    for h in SIGMA_STEPS_LOG:
        fp = float(np.sqrt((fun(q + [h, 0, 0, 0, 0]) ** 2).sum()))
        fm = float(np.sqrt((fun(q - [h, 0, 0, 0, 0]) ** 2).sum()))
        curv = (fp - 2 * f0 + fm) / h**2
        if curv > 0:
            sigma_log = np.sqrt(2 * f0 / np.sqrt(npix) / curv)
            break
    d = float(np.exp(q[0]))
    pts = points(q)
    a = np.array([q[1], q[2], pts[0, 2]])
    b = np.array([q[3], q[4], pts[0, 2]])
    return LineFit(a, b, f0, d * float(sigma_log), patch.evaluations, True)
