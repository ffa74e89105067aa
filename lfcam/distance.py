"""The product: a raw capture in, a per-region metric distance map out.

Stages: load (``lfcam.io``) → calibration grid and lenslet geometry (``lfcam.measure.geometry``)
→ regions on the lenslet lattice (``lfcam.measure.regions``) → per-region blur measurement →
distance model (``lfcam.models``) → outputs (``lfcam.export``).

Measurement methods (``method``):

* ``lightfield`` (default) — the exact forward model of a point source fitted to the region's
  pixels (``lfcam.measure.pointfit``), started from a triangulation of the lenslet spots. It
  locates the source in 3-D; the signed rim-ray heights (y1, y2) follow from the exact trace.
  ``fast=True`` keeps the triangulation alone.
* ``diameter`` — the seed's measurement: the blur footprint's diameter on the MLA plane
  (equivalent-area disc from per-lenslet energies, sub-lenslet), its sign (front or back of
  focus) from the slope field of the micro-image spots, its centre from the energy centroid.

Models (``model``): ``exact``, ``offaxis``, ``onaxis``, ``thin`` map (y1, y2) to a distance;
``auto`` picks per region the cheapest whose predicted error (model error table ⊕ measurement
uncertainty) meets ``tolerance_pct`` (default: best available, i.e. ``exact``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from lfcam.camera import CameraProfile
from lfcam.decode.grid import MAX_CALIBRATION_BYTES, GridSpec, grid_from_dict
from lfcam.errors import CalibrationError, InputFileError, LfcamError
from lfcam.export import RegionResult, write_distance_png, write_distance_tiff, write_regions_csv
from lfcam.measure.geometry import lenslet_centres_mm, regularise_to_lattice
from lfcam.measure.lenslets import LensletMap, build_lenslet_map, lenslet_stats
from lfcam.measure.linefit import fit_line_image
from lfcam.measure.pointfit import (
    SpotExtraction,
    assign_spots,
    find_spots,
    fit_point,
    fit_point_image,
)
from lfcam.measure.regions import Region, find_regions
from lfcam.models import auto
from lfcam.models.base import Status
from lfcam.optics.trace import forward
from lfcam.validate import read_json

MODELS = ("auto", "exact", "offaxis", "onaxis", "thin", "refocus")
TRIANGULATION_ENOUGH = 300  # lenslets: above this the triangulation alone is used
LINE_TRIGGER_MISFIT = 0.08  # a point fit worse than this is also tried as a line
LINE_GAIN = 0.7  # ... and becomes a line when the line fit's misfit is below this × the point's
METHODS = ("lightfield", "diameter")
DIAMETER_SIGMA_PITCH = 0.1  # 1-σ error of footprint edges, in lenslet pitches (heuristic)


@dataclass(frozen=True)
class Calibration:
    """What the distance stage needs from a calibration file (CONTRACT §3 keys)."""

    grid: GridSpec
    d_in_mm: float | None = None
    source: str = ""


def load_calibration(path: str | Path) -> Calibration:
    """Read a calibration JSON (grid keys of CONTRACT §3, optional ``d_in_mm``).

    Raises
    ------
    CalibrationError
        Missing or unreadable file, invalid JSON, or invalid grid values.
    """
    p = Path(path)
    data = read_json(p, CalibrationError, "calibration", MAX_CALIBRATION_BYTES)
    grid = grid_from_dict(data)
    d_in = data.get("d_in_mm") if isinstance(data, dict) else None
    valid = isinstance(d_in, (int, float)) and math.isfinite(d_in) and d_in > 0
    if d_in is not None and not valid:
        raise CalibrationError(f"{p}: d_in_mm must be a positive number, got {d_in!r}")
    return Calibration(grid=grid, d_in_mm=None if d_in is None else float(d_in), source=str(p))


@dataclass(frozen=True)
class Geometry:
    """Per-calibration data reused for every capture."""

    lmap: LensletMap
    lens_centres_mm: np.ndarray  # (N, 2) on the MLA plane
    pitch_px: float
    d_in_mm: float


def prepare_geometry(profile: CameraProfile, calibration: Calibration,
                     shape: tuple[int, int]) -> Geometry:
    """Lenslet map and lenslet centres for one calibration and sensor size."""
    grid = calibration.grid
    if grid.centres_px is not None and len(grid.centres_px):
        centres = np.asarray(grid.centres_px, dtype=np.float64)
    else:
        lc = grid.lens_centres(shape)
        centres = np.column_stack([np.ravel(lc.x), np.ravel(lc.y)])
        centres = centres[np.isfinite(centres).all(axis=1)]
    d_in = calibration.d_in_mm if calibration.d_in_mm is not None else profile.d_in_mm
    lmap = build_lenslet_map(centres, shape, 0.5 * grid.pitch_px * 1.08)
    lens_mm = lenslet_centres_mm(profile, d_in, centres)
    lens_mm, _ = regularise_to_lattice(lens_mm, profile.mla.pitch_mm, grid.grid,
                                       grid.rotation_rad)
    return Geometry(lmap, lens_mm, float(grid.pitch_px), d_in)


@dataclass(frozen=True)
class Measurement:
    """Blur geometry of one region: signed rim heights at the sensor and their uncertainty."""

    y1_mm: float
    y2_mm: float
    sigma_y_mm: float
    distance_mm: float  # the measurement's own estimate (lightfield: the exact fit), or NaN
    offset_mm: float
    sigma_distance_mm: float
    status: str
    plane_d_in_mm: float  # the d_in at which (y1, y2) are expressed to the models
    kind: str = "spot"
    misfit: float = float("nan")
    endpoints: tuple = ()  # lines: ((y1, y2) of endpoint a, (y1, y2) of endpoint b)


def _region_pixels_mask(region: Region, lmap: LensletMap) -> np.ndarray:
    x0, y0, x1, y1 = region.box_px
    sub = lmap.labels[y0:y1, x0:x1]
    return np.isin(sub, region.lenslets)


def _noise_sigma(image: np.ndarray, lmap: LensletMap) -> float:
    """Robust pixel noise from the whole frame (most pixels see no source)."""
    sample = image[:: max(1, image.shape[0] // 256), :: max(1, image.shape[1] // 256)]
    med = float(np.median(sample))
    return float(np.median(np.abs(sample - med))) * 1.4826


def measure_lightfield(profile, geom: Geometry, image, region: Region, noise: float,
                       fast: bool) -> Measurement:
    """Exact forward-model fit of a point-like region (module docstring)."""
    x0, y0, x1, y1 = region.box_px
    sub = image[y0:y1, x0:x1]
    mask = _region_pixels_mask(region, geom.lmap) | (geom.lmap.labels[y0:y1, x0:x1] < 0)
    peak = float(sub[mask].max()) if mask.any() else 0.0
    thr = max(6.0 * noise, 0.03 * peak)
    spots, energy = find_spots(sub, mask, thr)
    spots = spots + np.array([x0, y0])
    # the fit simulates its statistic through the same box, mask and threshold
    extraction = SpotExtraction(region.box_px, mask, thr, float(sub[mask].sum()))
    fit = fit_point(profile, geom.d_in_mm, spots, energy, geom.lens_centres_mm, extraction)
    nan = float("nan")
    # A blur spread over hundreds of lenslets is triangulated to a few 0.01 % (docs/distance.md);
    # the per-pixel fit would only re-render a huge patch a hundred times.
    if not fast and fit.ok and fit.spots >= TRIANGULATION_ENOUGH:
        fast = True
    if fast:
        if not fit.ok:
            return Measurement(nan, nan, nan, nan, nan, nan, fit.reason, geom.d_in_mm)
        source = fit.source_mm
        sigma_d = float(np.sqrt(max(fit.covariance_mm2[2, 2], 0.0)))
    else:
        near = np.unique(np.concatenate([region.lenslets, _neighbours(geom, region)]))
        pad = int(math.ceil(0.5 * geom.pitch_px))
        h, w = image.shape
        box = (max(0, x0 - pad), max(0, y0 - pad), min(w, x1 + pad), min(h, y1 + pad))
        fi = fit_point_image(profile, geom.d_in_mm, image, box, geom.lens_centres_mm[near],
                             fit.source_mm if fit.ok else None)
        if not fi.ok:
            return Measurement(nan, nan, nan, nan, nan, nan, fi.reason or "no-solution",
                               geom.d_in_mm)
        source, sigma_d = fi.source_mm, fi.sigma_distance_mm
        if fi.misfit > LINE_TRIGGER_MISFIT or region.kind == "line":
            line = measure_line(profile, geom, image, region, box, near)
            if line.status == "ok" and line.misfit < LINE_GAIN * fi.misfit:
                return line
    distance = profile.main_lens.front_vertex_z_mm - float(source[2])
    offset = float(np.hypot(source[0], source[1]))
    fw = forward(profile, geom.d_in_mm, distance, offset)
    if fw.status != 0:
        return Measurement(nan, nan, nan, distance, offset, sigma_d, "out-of-domain",
                           geom.d_in_mm)
    y1, y2 = float(fw.y1_mm), float(fw.y2_mm)
    # height uncertainty equivalent to the distance uncertainty (for model selection)
    fw2 = forward(profile, geom.d_in_mm, distance * 1.001, offset)
    dy = abs(float(fw2.y1_mm - fw2.y2_mm) - (y1 - y2)) / (0.001 * distance)
    sigma_y = sigma_d * dy if np.isfinite(sigma_d) else nan
    misfit = float("nan") if fast else float(fi.misfit)
    return Measurement(y1, y2, sigma_y, distance, offset, sigma_d, "ok", geom.d_in_mm,
                       misfit=misfit)


def measure_line(profile, geom: Geometry, image, region: Region, box, near) -> Measurement:
    """Exact forward-model fit of a line source (``lfcam.measure.linefit``)."""
    nan = float("nan")
    lf = fit_line_image(profile, geom.d_in_mm, image, box, geom.lens_centres_mm[near])
    if not lf.ok:
        return Measurement(nan, nan, nan, nan, nan, nan, lf.reason or "no-solution",
                           geom.d_in_mm, kind="line")
    z_front = profile.main_lens.front_vertex_z_mm
    distance = z_front - float(lf.start_mm[2])
    ends = []
    for pt in (lf.start_mm, lf.end_mm):
        fw = forward(profile, geom.d_in_mm, distance, float(np.hypot(pt[0], pt[1])))
        ends.append((float(fw.y1_mm), float(fw.y2_mm)))
    mid = 0.5 * (lf.start_mm + lf.end_mm)
    y1 = 0.5 * (ends[0][0] + ends[1][0])
    y2 = 0.5 * (ends[0][1] + ends[1][1])
    return Measurement(y1, y2, nan, distance, float(np.hypot(mid[0], mid[1])),
                       lf.sigma_distance_mm, "ok", geom.d_in_mm, kind="line",
                       misfit=lf.misfit, endpoints=tuple(ends))


def measure_refocus(profile, geom: Geometry, image, region: Region) -> tuple[float, float, str]:
    """Hahne et al.'s depth from refocus (the seed's baseline [14]): (distance, σ, status).

    Shift-and-sum maps a sample of lenslet ``j`` (lattice units) at angular offset ``u`` (pixels
    from its micro-image centre) to ``j + a·u``; the refocused spot is sharpest where its
    spatial spread is least, i.e. where ``u`` is linear in ``j`` with slope ``−1/a``; the
    continuous sweep's optimum is the regression ``a* = −Var(j)/Cov(j, u)`` (both axes pooled,
    intensity-weighted),
    and Hahne's model maps ``a*`` to a distance (``lfcam.models.hahne``).
    """
    from lfcam.models import hahne

    x0, y0, x1, y1 = region.box_px
    labels = geom.lmap.labels[y0:y1, x0:x1]
    mask = np.isin(labels, region.lenslets)
    w = np.clip(image[y0:y1, x0:x1][mask], 0.0, None)
    if w.sum() <= 0:
        return float("nan"), float("nan"), "near-focus"
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
        return float("nan"), float("nan"), "near-focus"
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
    status = "ok" if np.isfinite(d) and d > 0 else "out-of-domain"
    return d, sigma_d, status


def _neighbours(geom: Geometry, region: Region) -> np.ndarray:
    from scipy.spatial import cKDTree

    tree = cKDTree(geom.lmap.centres_px)
    lists = tree.query_ball_point(geom.lmap.centres_px[region.lenslets], 3.0 * geom.pitch_px)
    return np.unique(np.concatenate([np.asarray(v, dtype=np.int64) for v in lists]))


def measure_diameter(profile, geom: Geometry, image, stats, region: Region,
                     noise: float) -> Measurement:
    """The seed's measurement: signed footprint diameter on the MLA plane (module docstring)."""
    nan = float("nan")
    e = stats.energy[region.lenslets]
    plateau = float(np.percentile(e, 90))
    if plateau <= 0 or len(e) < 3:
        return Measurement(nan, nan, nan, nan, nan, nan, "near-focus", geom.d_in_mm)
    pitch = profile.mla.pitch_mm
    cell = pitch * pitch * (math.sqrt(3) / 2 if geom_is_hex(profile) else 1.0)
    area = float(_covered_fraction(geom, stats, region).sum()) * cell
    diameter = 2.0 * math.sqrt(area / math.pi)
    c = geom.lens_centres_mm[region.lenslets]
    centre = (c * e[:, None]).sum(0) / e.sum()
    radial = float(np.hypot(*centre))
    # sign from the slope field of the spots: converging bundle (dσ/ds < 0) → y1 > y2
    x0, y0, x1, y1_ = region.box_px
    sub = image[y0:y1_, x0:x1]
    mask = _region_pixels_mask(region, geom.lmap) | (geom.lmap.labels[y0:y1_, x0:x1] < 0)
    peak = float(sub[mask].max()) if mask.any() else 0.0
    spots, energy = find_spots(sub, mask, max(6.0 * noise, 0.03 * peak))
    if len(spots) < 3:
        return Measurement(nan, nan, nan, nan, nan, nan, "near-focus", geom.d_in_mm)
    spots = spots + np.array([x0, y0])
    pp = profile.sensor.pixel_pitch_mm
    ax, ay = profile.sensor.axis_xy_px
    spots_mm = np.column_stack([(spots[:, 0] - ax) * pp, (spots[:, 1] - ay) * pp])
    fx = profile.mla.focal_length_mm
    mag = 1.0 + fx / (geom.d_in_mm - profile.main_lens.exit_pupil_z_mm)
    k = assign_spots(spots_mm, energy, geom.lens_centres_mm, pitch, mag)
    good = k >= 0
    cc = geom.lens_centres_mm[k[good]]
    off = spots_mm[good] - cc
    a = np.column_stack([np.ones(good.sum()), cc])
    sol, *_ = np.linalg.lstsq(a * np.sqrt(energy[good])[:, None],
                              off * np.sqrt(energy[good])[:, None], rcond=None)
    divergence = float(sol[1, 0] + sol[2, 1])  # trace of dσ·f_x/ds
    sign = -1.0 if divergence > 0 else 1.0
    y1 = radial + sign * 0.5 * diameter
    y2 = radial - sign * 0.5 * diameter
    return Measurement(y1, y2, DIAMETER_SIGMA_PITCH * pitch, nan, nan, nan, "ok",
                       geom.d_in_mm - fx)


def _covered_fraction(geom: Geometry, stats, region: Region) -> np.ndarray:
    """Share of each lenslet's cell inside the footprint: 1 for interior lenslets (every
    neighbour lit), else its energy over its brightest lit neighbour's (partial edge cells)."""
    from scipy.spatial import cKDTree

    members = region.lenslets
    centres = geom.lmap.centres_px
    tree = cKDTree(centres)
    lit = np.zeros(len(centres), bool)
    lit[members] = True
    frac = np.ones(len(members))
    for i, nb in enumerate(tree.query_ball_point(centres[members], 1.5 * geom.pitch_px)):
        nb = [j for j in nb if j != members[i]]
        if all(lit[j] for j in nb):
            continue
        ref = max((stats.energy[j] for j in nb if lit[j]), default=0.0)
        frac[i] = min(1.0, stats.energy[members[i]] / ref) if ref > 0 else 0.0
    return frac


def geom_is_hex(profile: CameraProfile) -> bool:
    """Whether the profile's MLA is hexagonal."""
    return profile.mla.grid == "hex"


def _apply_line_model(profile, meas: Measurement, model: str):
    """Lines: ``exact``/``auto`` keep the exact fit; the closed-form choices run the seed's
    line model (eqs. 18–20) on the endpoints' rim-ray heights."""
    if model in ("exact", "auto"):
        return "exact", meas.distance_mm, meas.offset_mm, meas.sigma_distance_mm, "ok"
    from lfcam.models import line as line_model

    (a1, a2), (b1, b2) = meas.endpoints
    inv = line_model.invert(profile, meas.plane_d_in_mm, a1, a2, b1, b2)
    status = Status(int(inv.status)).label
    d = float(inv.distance_mm)
    table = auto.error_table(profile, meas.plane_d_in_mm)
    model_err = float("nan")
    if status == "ok":
        model_err = float(table.predict("offaxis", d, meas.offset_mm)) * d
    return "line", d, abs(float(inv.offset_mm)), model_err, status


@dataclass(frozen=True)
class DistanceRun:
    """Everything a distance run produced."""

    regions: list[RegionResult]
    distance_map: np.ndarray
    timings_s: dict = field(default_factory=dict)


def _apply_model(profile, meas: Measurement, model: str, tolerance_pct: float | None):
    """(model name, distance, offset, sigma, status) for one measured region."""
    nan = float("nan")
    if meas.status != "ok":
        return model, nan, nan, nan, meas.status
    if meas.kind == "line":
        return _apply_line_model(profile, meas, model)
    if model == "auto":
        names, inv, sigma = auto.choose(profile, meas.plane_d_in_mm, meas.y1_mm, meas.y2_mm,
                                        meas.sigma_y_mm, meas.sigma_y_mm, tolerance_pct)
        name = str(names[0])
    else:
        name = model
        inv, sigma = auto.propagate(model, profile, meas.plane_d_in_mm, np.array([meas.y1_mm]),
                                    np.array([meas.y2_mm]), meas.sigma_y_mm, meas.sigma_y_mm)
        if model != "exact":
            table = auto.error_table(profile, meas.plane_d_in_mm)
            model_err = table.predict(model, inv.distance_mm, inv.offset_mm) * inv.distance_mm
            sigma = np.hypot(sigma, model_err)
    status = Status(int(inv.status[0])).label
    d = float(inv.distance_mm[0])
    s = float(sigma[0])
    if name == "exact" and np.isfinite(meas.distance_mm) and status == "ok":
        # the lightfield fit already located the source exactly: use its own uncertainty
        d, s = meas.distance_mm, meas.sigma_distance_mm
    return name, d, abs(float(inv.offset_mm[0])), s, status


def run_distance(
    image: np.ndarray,
    profile: CameraProfile,
    calibration: Calibration,
    model: str = "auto",
    method: str = "lightfield",
    tolerance_pct: float | None = None,
    fast: bool = False,
    progress: Callable[[int, int], None] | None = None,
    geometry: Geometry | None = None,
) -> DistanceRun:
    """Detect regions in a linear grey image and estimate a distance for each.

    Parameters
    ----------
    image : (H, W) array
        Linear signal (black level removed), e.g. from ``lfcam.decode.lightfield.to_grey``.
    profile : CameraProfile
    calibration : Calibration
    model, method, tolerance_pct, fast
        See the module docstring.
    progress : callable, optional
        Called as ``progress(done, total)`` after each region.
    geometry : Geometry, optional
        Reuse a prepared geometry (batches).
    """
    if model not in MODELS:
        raise LfcamError(f"unknown model {model!r} (choose from {', '.join(MODELS)})")
    if method not in METHODS:
        raise LfcamError(f"unknown method {method!r} (choose from {', '.join(METHODS)})")
    t0 = time.perf_counter()
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise InputFileError(f"expected a 2-D image, got shape {img.shape}")
    expected = (profile.sensor.height_px, profile.sensor.width_px)
    if img.shape != expected:
        raise InputFileError(
            f"capture is {img.shape[1]}×{img.shape[0]} px but profile {profile.name!r} "
            f"describes a {expected[1]}×{expected[0]} px sensor"
        )
    geom = geometry or prepare_geometry(profile, calibration, img.shape)
    t1 = time.perf_counter()
    stats = lenslet_stats(img, geom.lmap)
    regions = find_regions(stats, geom.lmap, geom.pitch_px)
    noise = _noise_sigma(img, geom.lmap)
    t2 = time.perf_counter()
    results = []
    dmap = np.full(img.shape, np.nan, dtype=np.float32)
    for i, reg in enumerate(regions):
        nan = float("nan")
        if reg.kind in ("spot", "line") and model == "refocus":
            d, sig, status = measure_refocus(profile, geom, img, reg)
            name, off, diameter, kind = "refocus", float("nan"), float("nan"), reg.kind
        elif reg.kind in ("spot", "line"):
            if method == "lightfield":
                meas = measure_lightfield(profile, geom, img, reg, noise, fast)
            else:
                meas = measure_diameter(profile, geom, img, stats, reg, noise)
            name, d, off, sig, status = _apply_model(profile, meas, model, tolerance_pct)
            diameter = abs(meas.y1_mm - meas.y2_mm)
            kind = meas.kind
        else:
            name, d, off, sig, diameter = model, nan, nan, nan, nan
            status = f"unsupported-{reg.kind}"
            kind = reg.kind
        if status != "ok" or not np.isfinite(d):
            # no estimate: no numbers (CONTRACT §3), whatever the model computed on the way
            status = status if status != "ok" else "out-of-domain"
            d = off = sig = float("nan")
        results.append(RegionResult(
            region_id=reg.region_id, x_px=reg.centroid_px[0], y_px=reg.centroid_px[1],
            kind=kind, model=name, distance_mm=d, offset_mm=off, diameter_mm=diameter,
            uncertainty_mm=sig, status=status, bbox_px=reg.box_px,
        ))
        if status == "ok" and np.isfinite(d):
            x0, y0, x1, y1 = reg.box_px
            m = _region_pixels_mask(reg, geom.lmap).astype(np.uint8)
            k = max(3, int(geom.pitch_px) | 1)
            m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, np.ones((k, k), np.uint8)).astype(bool)
            dmap[y0:y1, x0:x1][m] = d
        if progress:
            progress(i + 1, len(regions))
    t3 = time.perf_counter()
    return DistanceRun(results, dmap, {"geometry": t1 - t0, "regions": t2 - t1,
                                       "measure": t3 - t2})


def write_outputs(outdir: str | Path, run: DistanceRun) -> None:
    """``regions.csv``, ``distance.tiff``, ``distance.png`` (CONTRACT §3), atomically."""
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    write_regions_csv(out / "regions.csv", run.regions)
    write_distance_tiff(out / "distance.tiff", run.distance_map)
    write_distance_png(out / "distance.png", run.distance_map, run.regions)
