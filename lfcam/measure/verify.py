"""``ok`` is earned per region: the fit must explain the pixels, the footprint and be alone.

After every region has been measured, :func:`verify_regions` checks each ``ok`` region
(docs/distance.md, "Region gates"; limits measured with ``python benchmarks/region_gates.py``):

(a) **poor-fit** — the per-pixel fit's relative misfit exceeds what noise and the renderer's
    own model floor allow: ``misfit > max(MISFIT_FLOOR, NOISE_FACTOR · noise_misfit)``, where
    ``noise_misfit`` is the misfit the region's own read and photon noise alone would give
    (:class:`lfcam.measure.noise.NoiseModel`, measured from the capture).
(b) **unexplained-footprint** — less than ``MIN_EXPLAINED`` of the region's energy falls on
    lenslets within ``MARGIN_PITCH`` lenslet pitch of those the fitted source lights in the
    exact forward model (traced through the main lens: aberrations, coma and vignetting
    included).
(c) **fragment-of-N** — two ``ok`` regions of which one's predicted footprint reaches the
    other's light centroid, or whose sources coincide within their uncertainties, are one blur
    cut in two: the one with less energy is marked a fragment of the other.
(d) **poor-fit**, wrong side of focus — near focus a blur has the same diameter on both sides;
    what tells them apart is the slope field: how the spots move in their micro-images across
    the footprint (:func:`slope_divergence`). When the data's slope and the fitted source's
    (exact forward model) have opposite signs, both beyond ``SIDE_SIGMAS`` standard errors of
    the data's, the fit sits on the wrong side of focus.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lfcam.measure.pointfit import pupil_pattern, simulate_lenslets
from lfcam.status import RegionStatus, fragment_of

MISFIT_FLOOR = 0.12
NOISE_FACTOR = 3.0
LINE_NOISE_FACTOR = 2.0  # a point fit within this × its noise misfit: no line is tried ...
LINE_NOISE_GAIN = 0.7  # a line at or under the noise misfit wins from this × the point's
LINE_TRIGGER_CAP = 0.1  # ... unless its misfit is over this (a point fit that poor is tried as a
#                         line whatever the noise bound says; lines fitted as points: 0.11-0.69)
MIN_EXPLAINED = 0.8
MARGIN_PITCH = 1.0
COINCIDE_SIGMAS = 3.0
PUPIL_SAMPLES = 48  # pupil grid of the footprint prediction (about 1 800 rays)
LIT_FRACTION = 1e-3
SIDE_SIGMAS = 5.0


@dataclass(frozen=True)
class RegionCheck:
    """Per-region figures of the gates (NaN where not computed)."""

    misfit: float
    noise_misfit: float
    explained: float
    predicted_lenslets: int
    status: str


def poor_fit_limit(noise_misfit_: float, floor: float = MISFIT_FLOOR) -> float:
    """The largest relative misfit a region may leave and stay ``ok``: ``floor`` (the forward
    model's own mismatch on bright regions) or ``NOISE_FACTOR`` times the misfit the region's
    own noise leaves (:class:`lfcam.measure.noise.NoiseModel`), whichever is larger."""
    nm = noise_misfit_ if math.isfinite(noise_misfit_) else 0.0
    return max(floor, NOISE_FACTOR * nm)


def line_beats(point_misfit: float, noise_misfit_: float, gain: float) -> float:
    """The misfit a line fit must stay under to be the answer instead of a point fit that
    leaves ``point_misfit``: ``gain`` × that (two more parameters cannot cut a misfit that is
    noise by that much), or — when the line reaches the region's noise misfit — no more than
    ``LINE_NOISE_GAIN`` × the point's. A line 2 pitches long inside a blur of ~900 lenslets
    (system 2, 2900 mm behind a 1 m focus) leaves 0.8 × its noise misfit as a line and 1.6 × as
    a point, a ratio of 0.50: the line explains all there is, the point does not
    (docs/distance.md, "Short lines behind focus")."""
    nm = noise_misfit_ if math.isfinite(noise_misfit_) else 0.0
    return max(gain * point_misfit, min(nm, LINE_NOISE_GAIN * point_misfit))


def line_trigger(noise_misfit_: float, floor: float,
                 factor: float = LINE_NOISE_FACTOR) -> float:
    """The point misfit above which a region is also fitted as a line: ``floor`` (the point
    model's own sampling noise) or ``factor`` (default ``LINE_NOISE_FACTOR``; the lenslet fit
    passes its own, ``fastfit.LINE_NOISE_FACTOR``) times the misfit the region's noise alone
    leaves, whichever is larger — but never above ``LINE_TRIGGER_CAP``. A point fit that
    already explains the data to within its noise leaves nothing for the line's two extra
    parameters to explain (on the Illum-size scene of docs/distance.md point fits leave
    0.3–1.5× and lines fitted as points 15–18× their noise misfit), and the line fit costs 2–5×
    the point fit. The cap: the noise misfit is an upper bound (scatter between neighbouring
    lenslets counts as photon noise), and inside a large blur with structure it reaches
    0.1–0.15 on noise-free data, above the misfit a line leaves as a point."""
    nm = noise_misfit_ if math.isfinite(noise_misfit_) else 0.0
    return max(floor, min(factor * nm, LINE_TRIGGER_CAP))


def predicted_lit(profile, d_in_mm: float, distance_mm: float, source_xy_mm, tree: cKDTree,
                  centres_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lenslets the fitted source lights, by the exact forward model
    (:func:`lfcam.measure.pointfit.simulate_lenslets`, ``PUPIL_SAMPLES``² pupil points).

    Returns
    -------
    lit_mm : (L, 2) array
        Centres (mm) of every lenslet receiving more than ``LIT_FRACTION`` of the brightest
        one's energy.
    energy : (N,) array
        Predicted energy of every lenslet (empty when the source sends no light).
    landing_mm : (N, 2) array
        Predicted mean landing point on the sensor (mm from the axis) under each lenslet.
    """
    z = profile.main_lens.front_vertex_z_mm - float(distance_mm)
    source = np.array([float(source_xy_mm[0]), float(source_xy_mm[1]), z])
    e, landing = simulate_lenslets(profile, d_in_mm, source, tree, centres_mm,
                                   pupil_pattern(PUPIL_SAMPLES))
    if not (e.size and np.isfinite(e).all() and e.max() > 0):
        return np.zeros((0, 2)), np.zeros(0), np.zeros((0, 2))
    return centres_mm[e > LIT_FRACTION * e.max()], e, landing


def slope_divergence(positions_px: np.ndarray, offsets_px: np.ndarray,
                     weights: np.ndarray) -> tuple[float, float]:
    """How the spots' offsets in their micro-images grow across a footprint: the trace of the
    weighted least-squares slope d(offset)/d(position), and its standard error.

    Negative for a converging bundle (source nearer than the focused plane), positive for a
    diverging one, for an ideal lens; aberrations can change that near focus, so the gate
    compares the data with the exact forward model, not with a sign. NaN with fewer than four
    spots.
    """
    ok = np.isfinite(offsets_px).all(axis=1) & np.isfinite(positions_px).all(axis=1) & (
        weights > 0)
    if ok.sum() < 4:
        return float("nan"), float("nan")
    pos = positions_px[ok] - positions_px[ok].mean(axis=0)
    a = np.column_stack([np.ones(ok.sum()), pos]) * np.sqrt(weights[ok])[:, None]
    b = offsets_px[ok] * np.sqrt(weights[ok])[:, None]
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    resid = b - a @ sol
    try:
        cov = np.linalg.inv(a.T @ a)
    except np.linalg.LinAlgError:
        return float(sol[1, 0] + sol[2, 1]), float("nan")
    s2 = (resid * resid).sum(axis=0) / max(ok.sum() - 3, 1)
    return float(sol[1, 0] + sol[2, 1]), float(math.sqrt(s2[0] * cov[1, 1] + s2[1] * cov[2, 2]))


def side_contradicted(profile, geom, stats, reg, energy: np.ndarray,
                      landing_mm: np.ndarray) -> bool:
    """Gate (d): do the region's spots diverge where the fitted source's converge (or the
    reverse), both by more than ``SIDE_SIGMAS`` standard errors of the data's slope?"""
    if energy.size == 0:
        return False
    idx = reg.lenslets
    w = np.clip(stats.energy[idx], 0.0, None)
    centres = geom.lmap.centres_px[idx]
    measured, sigma = slope_divergence(centres, stats.centroid_px[idx] - centres, w)
    pp = profile.sensor.pixel_pitch_mm
    ax, ay = profile.sensor.axis_xy_px
    pred_px = np.column_stack([landing_mm[idx, 0] / pp + ax, landing_mm[idx, 1] / pp + ay])
    predicted, _ = slope_divergence(centres, pred_px - centres,
                                    np.where(energy[idx] > 0, w, 0.0))
    if not (math.isfinite(measured) and math.isfinite(sigma) and math.isfinite(predicted)):
        return False
    limit = SIDE_SIGMAS * sigma
    return measured * predicted < 0 and abs(measured) > limit and abs(predicted) > limit


def verify_regions(profile, geom, stats, regions, measured) -> list[RegionCheck]:
    """Gate every region (module docstring).

    Parameters
    ----------
    profile : CameraProfile
    geom : Geometry
    stats : LensletStats
    regions : list of Region
    measured : list of (status, Measurement or None, source_xy_mm or None, sigma_mm)
        What the measurement gave for each region; only ``ok`` entries are checked.

    Returns
    -------
    list of RegionCheck
        One per region; ``status`` is the region's final status.
    """
    lens = geom.lens_centres_mm
    pitch_mm = float(profile.mla.pitch_mm)
    reach = MARGIN_PITCH * pitch_mm
    nan = float("nan")
    tree = None
    checks: list[RegionCheck] = []
    lit: dict[int, cKDTree | None] = {}
    for k, (reg, (status, meas, xy, _sig)) in enumerate(zip(regions, measured, strict=True)):
        if status != RegionStatus.OK or meas is None or xy is None:
            checks.append(RegionCheck(nan, nan, nan, 0, status))
            continue
        if tree is None:
            tree = cKDTree(lens)
        mf = float(meas.misfit)
        nm = float(getattr(meas, "noise_misfit", nan))
        pred, pred_e, landing = predicted_lit(profile, geom.d_in_mm, meas.distance_mm, xy,
                                              tree, lens)
        lit[k] = cKDTree(pred) if len(pred) else None
        e = np.clip(stats.energy[reg.lenslets], 0.0, None)
        if lit[k] is None or e.sum() <= 0:
            explained = 0.0
        else:
            dist, _ = lit[k].query(lens[reg.lenslets])
            explained = float(e[dist <= reach].sum() / e.sum())
        limit = poor_fit_limit(nm)
        if math.isfinite(mf) and mf > limit:
            status = RegionStatus.POOR_FIT
        elif explained < MIN_EXPLAINED:
            status = RegionStatus.UNEXPLAINED_FOOTPRINT
        elif meas.kind != "line" and side_contradicted(profile, geom, stats, reg, pred_e,
                                                       landing):
            status = RegionStatus.POOR_FIT
        checks.append(RegionCheck(mf, nm, explained, len(pred), status))
    # (c) fragments: among the regions still ok, the weaker of two that are one blur
    ok = [k for k, c in enumerate(checks) if c.status == RegionStatus.OK]
    centroid = {k: _centroid_mm(geom, stats, regions[k]) for k in ok}
    order = sorted(ok, key=lambda k: -float(regions[k].energy))
    for pos, a in enumerate(order):
        if checks[a].status != RegionStatus.OK:
            continue
        for b in order[pos + 1:]:
            if checks[b].status != RegionStatus.OK:
                continue
            if _same_blur(lit[a], lit[b], centroid[a], centroid[b], measured[a], measured[b],
                          reach):
                c = checks[b]
                checks[b] = RegionCheck(c.misfit, c.noise_misfit, c.explained,
                                        c.predicted_lenslets,
                                        fragment_of(regions[a].region_id))
    return checks


def _centroid_mm(geom, stats, reg) -> np.ndarray:
    e = np.clip(stats.energy[reg.lenslets], 0.0, None)
    xy = geom.lens_centres_mm[reg.lenslets]
    return (xy * e[:, None]).sum(axis=0) / e.sum() if e.sum() > 0 else xy.mean(axis=0)


def _same_blur(lit_a, lit_b, pa, pb, ma, mb, reach: float) -> bool:
    """Does one region's predicted blur reach the other's light centroid, or do their sources
    coincide within their uncertainties?"""
    for lit, p in ((lit_a, pb), (lit_b, pa)):
        if lit is not None and lit.query(np.asarray(p, dtype=np.float64))[0] <= reach:
            return True
    (_, m1, xy1, s1), (_, m2, xy2, s2) = ma, mb
    sig = math.hypot(s1, s2) if math.isfinite(s1) and math.isfinite(s2) else 0.0
    if sig > 0 and abs(m1.distance_mm - m2.distance_mm) <= COINCIDE_SIGMAS * sig:
        # the same distance: the same source only if also at the same place (lateral σ
        # taken as the distance σ scaled by the field angle, plus one lenslet pitch)
        lateral = math.hypot(xy1[0] - xy2[0], xy1[1] - xy2[1])
        return lateral <= COINCIDE_SIGMAS * sig * lateral_per_distance(m1) + reach
    return False


def lateral_per_distance(meas) -> float:
    """Rough lateral-position uncertainty per unit of distance uncertainty (offset/distance)."""
    d = float(meas.distance_mm)
    return abs(float(meas.offset_mm)) / d if d > 0 else 0.0
