"""The exact light-field fit: the forward model of a point (or line) source fitted to a
region's pixels, started from a triangulation of the lenslet spots (docs/distance.md).

It locates the source in 3-D; the signed rim-ray heights (y1, y2) follow from the exact trace.
``fast=True`` keeps the triangulation alone. A blur spread over more than
``TRIANGULATION_ENOUGH`` lenslets is always triangulated (to a few 0.01 %): the per-pixel fit
would only re-render a huge patch a hundred times.
"""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np

from lfcam.camera import CameraProfile
from lfcam.measure.base import (
    Measurement,
    line_measurement,
    neighbours,
    point_measurement,
    region_pixels_mask,
)
from lfcam.measure.fastfit import fit_lenslet_line, fit_lenslet_point, region_moments
from lfcam.measure.geometry import Geometry
from lfcam.measure.linefit import fit_line_image
from lfcam.measure.noise import capture_noise
from lfcam.measure.pointfit import (
    DATA_BLUR_PX,
    SpotExtraction,
    _Patch,
    find_spots,
    fit_point,
    fit_point_image,
)
from lfcam.measure.regions import Region
from lfcam.measure.verify import line_trigger, poor_fit_limit
from lfcam.status import RegionStatus

TRIANGULATION_ENOUGH = 300  # lenslets: above this the triangulation alone is used
PIXEL_SIGMA_FLOOR_REL = 1e-3  # added in quadrature to the pixel fit's σ of a distance: the
# model's and the calibration's share, which its noise σ leaves out (bright single sources off
# axis: errors 0.1-0.36 % at a noise σ of 0.02-0.09 %; 0.1 % brings the 108-source grid from
# 101 to 107 within 3σ, the 108th triangulated at 3.1σ; docs/distance.md, "The pixel fit's
# minimum")
LINE_TRIGGER_MISFIT = 0.08  # a point fit worse than this and than twice its noise misfit is also
#                             tried as a line (verify.line_trigger)
LINE_GAIN = 0.7  # ... and becomes a line when the line fit's misfit is below this × the point's
LENSLET_LINE_HINT = 0.8  # ... which a round region tries only when the lenslet fit's line
#                          leaves under this × its point's misfit (lines 2-12 pitches long:
#                          0.07-0.5; points whose line fit ran on scene b: 0.74 or more)
POOR_FIT_MISFIT = 0.25  # neither model explains the pixels: no distance (status "poor-fit"),
#                         unless the region's own noise leaves more (verify.poor_fit_limit)


def measure_lightfield(profile: CameraProfile, geom: Geometry, image: np.ndarray,
                       region: Region, noise: float, fast: bool = False,
                       nearby: tuple[Region, ...] = ()) -> Measurement:
    """Exact forward-model fit of a point-like region (module docstring).

    Parameters
    ----------
    profile : CameraProfile
    geom : Geometry
        Lenslet map and centres (:func:`lfcam.measure.prepare_geometry`).
    image : (H, W) float array
        Linear grey capture.
    region : Region
        One region of :func:`lfcam.measure.find_regions`.
    noise : float
        Pixel noise σ (:func:`lfcam.measure.noise_sigma`).
    fast : bool, optional
        Keep the triangulation of lenslet spots, skip the per-pixel fit.
    nearby : tuple of Region, optional
        Regions whose blur may reach into this one's box
        (:func:`lfcam.measure.regions.nearby_regions`): the pixel fit models their light too
        (their lenslet fits' points, each at its own free intensity).

    Returns
    -------
    Measurement
        Source distance, offset and rim heights; a line measurement (``kind="line"``) when
        the line model explains the pixels clearly better than a point.
    """
    x0, y0, x1, y1 = region.box_px
    sub = image[y0:y1, x0:x1]
    mask = region_pixels_mask(region, geom.lmap) | (geom.lmap.labels[y0:y1, x0:x1] < 0)
    peak = float(sub[mask].max()) if mask.any() else 0.0
    thr = max(6.0 * noise, 0.03 * peak)
    spots, energy = find_spots(sub, mask, thr)
    spots = spots + np.array([x0, y0])
    # the fit simulates its statistic through the same box, mask and threshold
    extraction = SpotExtraction(region.box_px, mask, thr, float(sub[mask].sum()))
    fit = fit_point(profile, geom.d_in_mm, spots, energy, geom.lens_centres_mm, extraction)
    # A blur spread over hundreds of lenslets is triangulated to a few 0.01 % (docs/distance.md);
    # the per-pixel fit would only re-render a huge patch a hundred times.
    triangulated = not fast and fit.ok and fit.spots >= TRIANGULATION_ENOUGH
    pad = int(math.ceil(0.5 * geom.pitch_px))
    h, w = image.shape
    box = (max(0, x0 - pad), max(0, y0 - pad), min(w, x1 + pad), min(h, y1 + pad))
    near = np.unique(np.concatenate([region.lenslets, neighbours(geom, region),
                                     _lenslets_in(geom, box)]))
    floor = 0.0  # of the σ (point_measurement): the pixel fit's alone
    # the lenslet fits' moments (their points start the pixel fits): a cut region's as
    # measure_lenslet reads them, band and neighbours left out (docs/distance.md, "Blurs
    # that overlap without a waist (stop 68)": with the other blur's light in them the parts
    # of two blurs 187 px apart were both poor-fit after ~20 s each); else the box's own
    own = region_moments(geom, image, region, nearby) if region.touching else None
    # the noise a clipped capture cuts at zero: the pixel fits model its floor
    floor_sigma = capture_noise(image, geom.lmap, geom.pitch_px).floor_sigma
    moments = None  # the lenslet fit's point, where it runs
    if fast:
        if not fit.ok:
            return Measurement.failed(fit.reason, geom.d_in_mm)
        source = fit.source_mm
        sigma_d = float(np.sqrt(max(fit.covariance_mm2[2, 2], 0.0)))
        misfit = float("nan")
    elif triangulated:
        # the triangulation assumes a point: whether one explains the pixels is checked by
        # rendering it once (a line behind focus triangulates 30-80 % short, docs/distance.md)
        source = fit.source_mm
        sigma_d = float(np.sqrt(max(fit.covariance_mm2[2, 2], 0.0)))
        misfit = _Patch(profile, geom.d_in_mm, image, box,
                        geom.lens_centres_mm[near], floor_sigma).misfit(source)
    else:
        # start from the lenslet-moment fit (0.1-0.4 s, within ~0.5 %): the triangulation
        # start can lie 3-4 % off in a side basin whose misfit already looks good (system 2,
        # focus ∞, 3500 mm at 80 % of the field: −2.4 %, docs/distance.md)
        start = fit.source_mm if fit.ok else None
        moments = fit_lenslet_point(profile, geom, image, region, mom=own)
        if moments.ok:
            start = moments.source_mm
        elif moments.reason == RegionStatus.NEAR_FOCUS:
            # the distance profile is flat (a blur within 2×2 lenslets): the pixels of the
            # same lenslets carry no more of it (docs/distance.md, "Blurs of a few lenslets")
            return Measurement.failed(RegionStatus.NEAR_FOCUS, geom.d_in_mm)
        others = []
        for other in nearby:
            # a touching blur's light in this box, where its lenslet fit puts it
            fit_other = fit_lenslet_point(profile, geom, image, other, mom=(
                region_moments(geom, image, other, (region,)) if other.touching else None))
            if fit_other.ok:
                others.append(fit_other.source_mm)
        fi = fit_point_image(profile, geom.d_in_mm, image, box, geom.lens_centres_mm[near],
                             start, floor_sigma, others)
        if not fi.ok:
            return Measurement.failed(fi.reason or RegionStatus.NO_SOLUTION, geom.d_in_mm)
        source, sigma_d, misfit = fi.source_mm, fi.sigma_distance_mm, float(fi.misfit)
        floor = PIXEL_SIGMA_FLOOR_REL  # its σ is its noise's only
    noise_mf = float("nan") if fast else _noise_misfit(image, box, geom)
    if not fast:
        # the gate is relative to the noise: a dim far source leaves mostly photon noise
        limit = poor_fit_limit(noise_mf, POOR_FIT_MISFIT)
        # point or line is decided from the pixels, on both sides of focus: the region's
        # elongation only forces the line fit to be tried
        if misfit > line_trigger(noise_mf, LINE_TRIGGER_MISFIT) or region.kind == "line":
            # the lenslet fit's line (~0.1-0.3 s, against the pixel fit's 4-15 s) is one start
            # of the pixel fit's, and says whether it is worth running at all
            if moments is None:
                moments = fit_lenslet_point(profile, geom, image, region, mom=own)
            lens_line = fit_lenslet_line(profile, geom, image, region,
                                         moments if moments.ok else None, mom=own)
            if (region.kind == "line" or not (lens_line.ok and moments.ok)
                    or lens_line.misfit < LENSLET_LINE_HINT * moments.misfit):
                line = measure_line(profile, geom, image, box, near,
                                    lens_line.ends_mm if lens_line.ok else None,
                                    lens_line.sigma_distance_mm if lens_line.ok else None)
                if line.status == RegionStatus.OK and line.misfit < LINE_GAIN * misfit:
                    if line.misfit > limit:
                        return Measurement.failed(RegionStatus.POOR_FIT, geom.d_in_mm,
                                                  kind="line")
                    return replace(line, noise_misfit=noise_mf)
        if not misfit <= limit:
            return Measurement.failed(RegionStatus.POOR_FIT, geom.d_in_mm)
    return point_measurement(profile, geom.d_in_mm, source, sigma_d, floor, misfit=misfit,
                             noise_misfit=noise_mf,
                             source_xy_mm=(float(source[0]), float(source[1])))


def _lenslets_in(geom: Geometry, box: tuple[int, int, int, int]) -> np.ndarray:
    """Lenslets whose micro-image reaches into ``box`` (centre within a pitch of it): the
    model must know every lenslet of the pixels it is compared with, or the rays that land on
    one are dropped while the data keep their light (a region's bounding box reaches past
    three pitches from its lenslets where the region is not convex)."""
    x0, y0, x1, y1 = box
    c = geom.lmap.centres_px
    r = geom.pitch_px
    return np.flatnonzero((c[:, 0] > x0 - r) & (c[:, 0] < x1 + r) & (c[:, 1] > y0 - r)
                          & (c[:, 1] < y1 + r))


def _noise_misfit(image: np.ndarray, box: tuple[int, int, int, int], geom: Geometry) -> float:
    """The relative misfit the capture's read and photon noise alone give on the fitted patch
    (same blur as the fit; :mod:`lfcam.measure.noise`)."""
    x0, y0, x1, y1 = box
    sub = np.asarray(image[y0:y1, x0:x1], np.float64)
    data = cv2.GaussianBlur(sub, (0, 0), DATA_BLUR_PX)
    model = capture_noise(image, geom.lmap, geom.pitch_px)
    return model.misfit(sub, DATA_BLUR_PX, float(np.sqrt((data * data).sum())))


def measure_line(profile: CameraProfile, geom: Geometry, image: np.ndarray,
                 box: tuple[int, int, int, int], near: np.ndarray,
                 start_mm: tuple[np.ndarray, np.ndarray] | None = None,
                 sigma_floor_mm: float | None = None) -> Measurement:
    """Exact forward-model fit of a line source (:mod:`lfcam.measure.linefit`).

    Its σ is the larger of the pixel fit's (the curvature of its misfit: noise only) and
    ``sigma_floor_mm``, the lenslet line fit's (a jackknife over lenslets, which sees the
    model's mismatch): off axis the pixel σ alone fell to 0.03 % while the fits missed by
    0.2–1.1 %, up to 46σ (docs/distance.md, "Lines across the field's stretch"); and
    :data:`lfcam.measure.base.LINE_SIGMA_FLOOR_REL` of the distance in quadrature, the line
    model's share.

    Parameters
    ----------
    profile : CameraProfile
    geom : Geometry
    image : (H, W) float array
    box : tuple of int
        (x0, y0, x1, y1) pixel box to fit.
    near : (K,) int array
        Lenslets (indices into ``geom``) whose light may fall in the box.
    start_mm : pair of (3,) arrays, optional
        Endpoints of a line to start from (the lenslet fit's).
    sigma_floor_mm : float, optional
        The least σ of the distance (the lenslet line fit's).

    Returns
    -------
    Measurement
        ``kind="line"``, with the rim heights of both endpoints in ``endpoints``.
    """
    lf = fit_line_image(profile, geom.d_in_mm, image, box, geom.lens_centres_mm[near],
                        start_mm, capture_noise(image, geom.lmap, geom.pitch_px).floor_sigma)
    if not lf.ok:
        return Measurement.failed(lf.reason or RegionStatus.NO_SOLUTION, geom.d_in_mm, kind="line")
    sigma = float(lf.sigma_distance_mm)
    if sigma_floor_mm is not None and np.isfinite(sigma_floor_mm):
        sigma = max(sigma, float(sigma_floor_mm))
    return line_measurement(profile, geom.d_in_mm, (lf.start_mm, lf.end_mm), sigma,
                            misfit=lf.misfit)
