"""``ok`` is earned per region: the fit must explain the pixels, the footprint and be alone.

After every region has been measured, :func:`verify_regions` checks each ``ok`` region
(docs/distance.md, "Region gates"; limits measured with ``python benchmarks/region_gates.py``):

(a) **poor-fit** — the per-pixel fit's relative misfit exceeds what noise and the renderer's
    own model floor allow: ``misfit > max(MISFIT_FLOOR, NOISE_FACTOR · noise_misfit)``, where
    ``noise_misfit`` is the misfit white pixel noise alone would give (σ of the blurred patch ×
    √pixels / ‖patch‖).
(b) **unexplained-footprint** — less than ``MIN_EXPLAINED`` of the region's energy falls on
    lenslets inside the blur that the fitted source predicts on the MLA plane (exact rim rays,
    plus ``MARGIN_PITCH`` lenslet pitches for aberration halos and the lenslets' own width).
(c) **fragment-of-N** — two ``ok`` regions whose predicted blurs contain each other's
    centroid, or whose sources coincide within their uncertainties, are one blur cut in two:
    the one with less energy is marked a fragment of the other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lfcam.optics.trace import forward

MISFIT_FLOOR = 0.12
NOISE_FACTOR = 3.0
MIN_EXPLAINED = 0.8
MARGIN_PITCH = 1.0
COINCIDE_SIGMAS = 3.0


@dataclass(frozen=True)
class RegionCheck:
    """Per-region figures of the gates (NaN where not computed)."""

    misfit: float
    noise_misfit: float
    explained: float
    centre_mm: tuple[float, float]
    radius_mm: float
    status: str


def noise_misfit(noise: float, blur_px: float, npix: int, norm: float) -> float:
    """Relative misfit that white pixel noise ``noise`` alone gives on a patch blurred by a
    Gaussian of σ ``blur_px`` (per-pixel σ shrinks by 2√π·σ_b), of ``npix`` pixels and norm
    ``norm``."""
    if not (norm > 0 and npix > 0 and blur_px > 0):
        return float("nan")
    return noise / (2.0 * math.sqrt(math.pi) * blur_px) * math.sqrt(npix) / norm


def predicted_blur(profile, d_in_mm: float, distance_mm: float, source_xy_mm) -> tuple:
    """(centre (x, y) mm, radius mm) of the blur the source makes on the MLA plane."""
    sx, sy = float(source_xy_mm[0]), float(source_xy_mm[1])
    off = math.hypot(sx, sy)
    fw = forward(profile, d_in_mm, distance_mm, off, z_plane_mm=d_in_mm)
    y1, y2 = float(fw.y1_mm), float(fw.y2_mm)
    if not (math.isfinite(y1) and math.isfinite(y2)):
        return (float("nan"), float("nan")), float("nan")
    ux, uy = (sx / off, sy / off) if off > 0 else (0.0, 0.0)
    mid = 0.5 * (y1 + y2)
    return (ux * mid, uy * mid), 0.5 * abs(y1 - y2)


def verify_regions(profile, geom, stats, regions, measured) -> list[RegionCheck]:
    """Gate every region (module docstring).

    Parameters
    ----------
    profile : CameraProfile
    geom : Geometry
    stats : LensletStats
    regions : list of Region
    measured : list of (status, Measurement or None, source_xy_mm or None, sigma_mm)
        What the measurement gave for each region.

    Returns
    -------
    list of RegionCheck
        One per region; ``status`` is the region's final status.
    """
    lens = geom.lens_centres_mm
    pitch_mm = float(profile.mla.pitch_mm)
    nan = float("nan")
    checks: list[RegionCheck] = []
    for reg, (status, meas, xy, _sig) in zip(regions, measured, strict=True):
        if status != "ok" or meas is None or xy is None:
            checks.append(RegionCheck(nan, nan, nan, (nan, nan), nan, status))
            continue
        mf = float(meas.misfit)
        nm = float(getattr(meas, "noise_misfit", nan))
        centre, radius = predicted_blur(profile, geom.d_in_mm, meas.distance_mm, xy)
        e = np.clip(stats.energy[reg.lenslets], 0.0, None)
        d = np.hypot(lens[reg.lenslets, 0] - centre[0], lens[reg.lenslets, 1] - centre[1])
        inside = d <= radius + MARGIN_PITCH * pitch_mm
        explained = float(e[inside].sum() / e.sum()) if e.sum() > 0 else nan
        if math.isfinite(mf) and mf > max(MISFIT_FLOOR, NOISE_FACTOR * (nm if math.isfinite(nm)
                                                                        else 0.0)):
            status = "poor-fit"
        elif not (explained >= MIN_EXPLAINED):
            status = "unexplained-footprint"
        checks.append(RegionCheck(mf, nm, explained, centre, radius, status))
    # (c) fragments: among the regions still ok, the weaker of two overlapping blurs
    ok = [k for k, c in enumerate(checks) if c.status == "ok"]
    centroid = {k: _centroid_mm(geom, stats, regions[k]) for k in ok}
    order = sorted(ok, key=lambda k: -float(regions[k].energy))
    for a_pos, a in enumerate(order):
        if checks[a].status != "ok":
            continue
        for b in order[a_pos + 1:]:
            if checks[b].status != "ok":
                continue
            if _same_blur(checks[a], checks[b], centroid[a], centroid[b], measured[a],
                          measured[b], pitch_mm):
                c = checks[b]
                checks[b] = RegionCheck(c.misfit, c.noise_misfit, c.explained, c.centre_mm,
                                        c.radius_mm, f"fragment-of-{regions[a].region_id}")
    return checks


def _centroid_mm(geom, stats, reg) -> np.ndarray:
    e = np.clip(stats.energy[reg.lenslets], 0.0, None)
    xy = geom.lens_centres_mm[reg.lenslets]
    return (xy * e[:, None]).sum(axis=0) / e.sum() if e.sum() > 0 else xy.mean(axis=0)


def _same_blur(ca: RegionCheck, cb: RegionCheck, pa, pb, ma, mb, pitch_mm: float) -> bool:
    """Do two regions' predicted blurs reach each other's light, or their sources coincide?"""
    for c, p in ((ca, pb), (cb, pa)):
        if math.hypot(p[0] - c.centre_mm[0], p[1] - c.centre_mm[1]) <= c.radius_mm + pitch_mm:
            return True
    (_, m1, xy1, s1), (_, m2, xy2, s2) = ma, mb
    sig = math.hypot(s1, s2) if math.isfinite(s1) and math.isfinite(s2) else 0.0
    if sig > 0 and abs(m1.distance_mm - m2.distance_mm) <= COINCIDE_SIGMAS * sig:
        # same distance within the uncertainty: the same source only if also laterally close
        lateral = math.hypot(xy1[0] - xy2[0], xy1[1] - xy2[1])
        return lateral <= COINCIDE_SIGMAS * sig * lateral_per_distance(m1) + pitch_mm
    return False


def lateral_per_distance(meas) -> float:
    """Rough lateral-position uncertainty per unit of distance uncertainty (offset/distance)."""
    d = float(meas.distance_mm)
    return abs(float(meas.offset_mm)) / d if d > 0 else 0.0
