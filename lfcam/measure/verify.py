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
MIN_EXPLAINED = 0.8
MARGIN_PITCH = 1.0
COINCIDE_SIGMAS = 3.0
PUPIL_SAMPLES = 48  # pupil grid of the footprint prediction (about 1 800 rays)
LIT_FRACTION = 1e-3


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


def predicted_lit(profile, d_in_mm: float, distance_mm: float, source_xy_mm, tree: cKDTree,
                  centres_mm: np.ndarray) -> np.ndarray:
    """Centres (mm) of the lenslets the fitted source lights, by the exact forward model
    (:func:`lfcam.measure.pointfit.simulate_lenslets`, ``PUPIL_SAMPLES``² pupil points):
    every lenslet receiving more than ``LIT_FRACTION`` of the brightest one's energy."""
    z = profile.main_lens.front_vertex_z_mm - float(distance_mm)
    source = np.array([float(source_xy_mm[0]), float(source_xy_mm[1]), z])
    e, _ = simulate_lenslets(profile, d_in_mm, source, tree, centres_mm,
                             pupil_pattern(PUPIL_SAMPLES))
    if not (e.size and np.isfinite(e).all() and e.max() > 0):
        return np.zeros((0, 2))
    return centres_mm[e > LIT_FRACTION * e.max()]


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
        pred = predicted_lit(profile, geom.d_in_mm, meas.distance_mm, xy, tree, lens)
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
