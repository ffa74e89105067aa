"""The product: a raw capture in, a per-region metric distance map out (docs/distance.md).

The pipeline, once per capture: the calibration's lenslet geometry
(:func:`lfcam.measure.prepare_geometry`, reusable across captures) → per-lenslet energies and
regions on the lenslet lattice → per region a blur measurement (:mod:`lfcam.measure`, one
``method``) → a distance model (:mod:`lfcam.models`, one ``model``) → the outputs
(:mod:`lfcam.export`).

Methods: ``lightfield`` (default; the exact light-field fit, ``fast=True`` keeps its
triangulation), ``lenslet`` (the exact forward model fitted to per-lenslet moments, 35-55 ms
a point region on the seed grid), ``diameter`` (the seed's footprint diameter) and ``auto``
(the cheapest method whose measured worst error meets ``tolerance_pct``,
:func:`lfcam.models.auto.choose_method`).
Regions are measured in parallel over ``jobs`` processes (forked from a server that has
loaded the measurement modules once, started before the geometry so that its start-up
overlaps it; the image and the lenslet map are shared once through shared memory); the
results equal the serial run's.
Models: those of
:data:`lfcam.models.DISTANCE_MODELS`; ``auto`` picks per region the cheapest whose predicted
error (model error table ⊕ measurement uncertainty) meets ``tolerance_pct`` (default: best
available, i.e. ``exact``); ``refocus`` is Hahne et al.'s depth from refocus.

A region whose measurement fails numerically gets the status ``failed: <reason>``; the other
regions and the outputs go on. A failed spot or line region that two overlapping blurs explain,
or a round ``ok`` one that one source does not, is split between the two sources: cut in two
and both measured again, or answered by the joint two-point fit (``SPLIT_OVERLAPS``, every
method but ``diameter``: :mod:`lfcam.measure.overlap`).
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from lfcam.calibrate.model import Calibration
from lfcam.camera import CameraProfile
from lfcam.errors import InputFileError, LfcamError, ModelError
from lfcam.export import (
    RegionResult,
    paint_region,
    write_distance_png,
    write_distance_tiff,
    write_regions_csv,
)
from lfcam.measure import (
    METHODS,
    Geometry,
    Measurement,
    Region,
    find_regions,
    lenslet_stats,
    measure_diameter,
    measure_lenslet,
    measure_lightfield,
    measure_refocus,
    noise_sigma,
    prepare_geometry,
)
from lfcam.measure.fastfit import keep_lattice, lattice_of
from lfcam.measure.noise import capture_noise
from lfcam.measure.regions import nearby_regions
from lfcam.measure.verify import verify_regions
from lfcam.models import POINT_MODELS, auto, check_distance_model
from lfcam.models import line as line_model
from lfcam.models.base import Status
from lfcam.progress import Progress
from lfcam.status import RegionStatus, failed, unsupported

# numerical failures of one region's fit that must not take down the capture
_REGION_FAILURES = (ArithmeticError, ValueError, np.linalg.LinAlgError, cv2.error, LfcamError)


class Estimate(NamedTuple):
    """One region's answer as a method and model give it (:func:`_estimate`): NaN numbers
    where there is none."""

    kind: str  # spot or line (the measurement's), or the region's unsupported kind
    model: str  # the distance model that answered
    distance_mm: float
    offset_mm: float
    diameter_mm: float  # |y1 − y2| on the MLA plane
    sigma_mm: float
    status: str
    measurement: Measurement | None  # None: the refocus model, an unsupported region, or a
    #                                  fit that raised (status ``failed: …``)


@dataclass(frozen=True)
class DistanceRun:
    """Everything a distance run produced: one result per region, the float32 map (NaN
    where no estimate) and the time of each stage in seconds."""

    regions: list[RegionResult]
    distance_map: np.ndarray
    timings_s: dict = field(default_factory=dict)
    checks: list = field(default_factory=list)  # lfcam.measure.verify.RegionCheck per region


def _apply_line_model(profile: CameraProfile, meas: Measurement, model: str) -> tuple:
    """Lines: ``exact``/``auto`` keep the exact fit; the closed-form choices run the seed's
    line model (eqs. 18–20) on the endpoints' rim-ray heights."""
    if model in ("exact", "auto"):
        return "exact", meas.distance_mm, meas.offset_mm, meas.sigma_distance_mm, RegionStatus.OK
    (a1, a2), (b1, b2) = meas.endpoints
    inv = line_model.invert(profile, meas.plane_d_in_mm, a1, a2, b1, b2)
    status = Status(int(inv.status)).label
    d = float(inv.distance_mm)
    table = auto.error_table(profile, meas.plane_d_in_mm)
    model_err = float("nan")
    if status == RegionStatus.OK:
        model_err = float(table.predict("offaxis", d, meas.offset_mm)) * d
        if np.isinf(model_err):  # outside where the closed form's error was measured
            status = RegionStatus.OUT_OF_DOMAIN
    return "line", d, abs(float(inv.offset_mm)), model_err, status


def _apply_model(profile: CameraProfile, meas: Measurement, model: str,
                 tolerance_pct: float | None) -> tuple:
    """(model name, distance, offset, sigma, status) for one measured region."""
    nan = float("nan")
    if meas.status != RegionStatus.OK:
        return model, nan, nan, nan, meas.status
    if meas.kind == "line":
        return _apply_line_model(profile, meas, model)
    fitted = np.isfinite(meas.distance_mm)  # the lightfield or lenslet fit located the source
    if fitted and (model == "exact" or (model == "auto" and tolerance_pct is None)):
        # the answer is the fit's own; the exact inversion of its rim heights only checks the
        # round trip (status, offset): its σ propagation (four more inversions, ~4 ms) would
        # be thrown away
        name = "exact"
        inv = POINT_MODELS["exact"](profile, meas.plane_d_in_mm, np.array([meas.y1_mm]),
                                    np.array([meas.y2_mm]))
        sigma = np.array([meas.sigma_distance_mm])
    elif model == "auto":
        names, inv, sigma = auto.choose(profile, meas.plane_d_in_mm, meas.y1_mm, meas.y2_mm,
                                        meas.sigma_y_mm, meas.sigma_y_mm, tolerance_pct)
        name = str(names[0])
    else:
        name = model
        inv, sigma = auto.propagate(model, profile, meas.plane_d_in_mm, np.array([meas.y1_mm]),
                                    np.array([meas.y2_mm]), meas.sigma_y_mm, meas.sigma_y_mm)
        if model != "exact":
            # the model's error where the source is: at the measured offset when the
            # measurement has one (the on-axis form reports 0 for its own)
            off = meas.offset_mm if np.isfinite(meas.offset_mm) else inv.offset_mm
            table = auto.error_table(profile, meas.plane_d_in_mm)
            model_err = table.predict(model, inv.distance_mm, off) * inv.distance_mm
            sigma = np.hypot(sigma, model_err)
    status = Status(int(inv.status[0])).label
    if status == RegionStatus.OK and np.isinf(sigma[0]):
        # a closed form outside where its error was measured (the error table's field and
        # distances): a number no one could defend
        status = RegionStatus.OUT_OF_DOMAIN
    d = float(inv.distance_mm[0])
    s = float(sigma[0])
    if name == "exact" and fitted and status == RegionStatus.OK:
        # the lightfield fit already located the source exactly: use its own uncertainty
        d, s = meas.distance_mm, meas.sigma_distance_mm
    return name, d, abs(float(inv.offset_mm[0])), s, status


def _estimate(profile: CameraProfile, geom: Geometry, img: np.ndarray, stats, reg: Region,
              noise: float, model: str, method: str, tolerance_pct: float | None,
              fast: bool, nearby: tuple[Region, ...] = (),
              light: np.ndarray | None = None, start: Measurement | None = None) -> Estimate:
    """The :class:`Estimate` of one region (``nearby``: the regions whose blur may reach
    into its box; ``light``: touching sources' light taken from its lenslet moments,
    :func:`_take_out_neighbours`, and ``start`` the lenslet answer its refit starts from)."""
    nan = float("nan")
    if reg.kind not in ("spot", "line"):
        return Estimate(reg.kind, model, nan, nan, nan, nan, unsupported(reg.kind), None)
    if model == "refocus":
        d, sig, status = measure_refocus(profile, geom, img, reg)
        return Estimate(reg.kind, "refocus", d, nan, nan, sig, status, None)
    meas = None
    # a line's refit with more rays only where the tolerance needs it (fit_lenslet_line)
    accept = (None if tolerance_pct is None else
              partial(auto.lenslet_answer_meets, tolerance_pct=tolerance_pct))
    if method == "auto":
        method = auto.choose_method(tolerance_pct, reg.kind)
        if method in ("lenslet", "lightfield") and tolerance_pct is not None:
            # the lenslet fit first (~0.1 s). The kind it decides from the data, not the
            # region's shape, picks the rule (vignetting and coma stretch off-axis spots into
            # regions shaped like lines): a line's answer stands (no method measures lines
            # better), a spot's where its own σ meets the tolerance; the pixel fit (seconds)
            # only for the other spots, and for failed regions that look like spots
            first = measure_lenslet(profile, geom, img, reg, noise, accept, others=nearby,
                                    light=light)
            if first.status != RegionStatus.OK:
                meas = first if method == "lenslet" else None
            elif first.kind == "line" or auto.lenslet_answer_meets(
                    first.distance_mm, first.sigma_distance_mm, tolerance_pct):
                meas = first
            method = "lightfield"
    if meas is None:
        if method == "lightfield":
            meas = measure_lightfield(profile, geom, img, reg, noise, fast, nearby)
        elif method == "lenslet":
            meas = measure_lenslet(profile, geom, img, reg, noise, accept, others=nearby,
                                   light=light, start=start)
        else:
            meas = measure_diameter(profile, geom, img, stats, reg, noise)
    return _estimate_of(profile, meas, model, tolerance_pct)


def sensor_gain(profile: CameraProfile, white_value: float | None) -> float:
    """Image units per photo-electron from the profile's full well, for an image whose
    white level reads ``white_value``; 0 when either is unknown. A demosaicked grey image
    averages its noise over neighbours, so this bounds its gain from above, as the measured
    gain does (:func:`lfcam.measure.noise.photon_gain`)."""
    full_well = profile.sensor.full_well_e
    if full_well is None or white_value is None or not white_value > 0:
        return 0.0
    return float(white_value) / float(full_well)


def run_distance(
    image: np.ndarray,
    profile: CameraProfile,
    calibration: Calibration | None,
    model: str = "auto",
    method: str = "lightfield",
    tolerance_pct: float | None = None,
    fast: bool = False,
    progress: Progress | None = None,
    geometry: Geometry | None = None,
    jobs: int | None = 1,
    white_value: float | None = None,
) -> DistanceRun:
    """Detect regions in a linear grey image and estimate a distance for each.

    Parameters
    ----------
    image : (H, W) array
        Linear signal (black level removed), e.g. :meth:`lfcam.io.Capture.grey`.
    profile : CameraProfile
    calibration : Calibration or None
        Used to prepare the lenslet geometry; may be None when ``geometry`` is given.
    model : str
        One of :data:`lfcam.models.DISTANCE_MODELS`.
    method : str
        One of :data:`lfcam.measure.METHODS`.
    tolerance_pct : float, optional
        ``auto``: the largest acceptable predicted error.
    fast : bool
        ``lightfield``: keep the triangulation, skip the per-pixel fit.
    progress : callable, optional
        A :data:`lfcam.progress.Progress`, called as ``progress("regions", done, total)``
        after each region.
    geometry : Geometry, optional
        Reuse a prepared geometry (batches).
    jobs : int or None
        Worker processes for the regions (``None``: all cores; 1: serial, in this process).
        The results do not depend on it.
    white_value : float, optional
        The image's value at the sensor's white level (``lfcam.io.grey.GREY_WHITE`` = 1 for
        :meth:`lfcam.io.Capture.grey`; ``white_level − black_level`` for raw counts). With
        the profile's ``sensor.full_well_e`` it gives the photon gain the noise model takes
        where the capture cannot measure one (:func:`lfcam.measure.noise.capture_noise`);
        without either, such a capture's noise model counts no photon noise.

    Returns
    -------
    DistanceRun
        ``timings_s`` holds the stage times (``geometry``, ``regions``, ``measure``), ``jobs``
        and ``region_s``: each region's measurement CPU seconds, in region order.

    Raises
    ------
    ModelError
        Unknown model or method.
    InputFileError, CalibrationError
        The image does not fit the profile's sensor or the calibration's white image.
    """
    check_distance_model(model)
    from lfcam.calibrate.lensfit import calibration_sigma_mm, resolve_profile

    learned = None
    if profile.main_lens.is_black_box:  # the lens learned from targets replaces the seed
        learned = None if calibration is None else calibration.learned_lens
        profile = resolve_profile(profile, calibration)
    if method not in METHODS:
        raise ModelError(f"unknown method {method!r} (choose from {', '.join(METHODS)})")
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
    if geometry is None and calibration is None:
        raise ModelError("run_distance needs a calibration or a prepared geometry")
    if jobs is None:
        jobs = os.cpu_count() or 1
    pool = _RegionPool(int(jobs)) if int(jobs) > 1 else None
    fitted = method != "diameter" and model != "refocus"  # the lenslet and pixel fits run
    try:
        geom = geometry or prepare_geometry(profile, calibration, img.shape)
        t1 = time.perf_counter()
        stats = lenslet_stats(img, geom.lmap)
        regions = find_regions(stats, geom.lmap, geom.pitch_px)
        noise = noise_sigma(img)
        # the capture's noise model, which the fits' gates read: once, from these statistics
        noise_model = (capture_noise(img, geom.lmap, geom.pitch_px, stats,
                                     sensor_gain=sensor_gain(profile, white_value))
                       if method != "diameter" and regions else None)
        # the geometry's lenslet lattice, which every lenslet fit reads: here (~40 ms at
        # Illum size), not in the time of each worker's first region (the pool gets it)
        lattice = ((lattice_of(geom, profile.mla.pitch_mm),)
                   if method in ("lenslet", "auto") and regions else None)
        jobs = max(1, min(int(jobs), len(regions)))
        serial = pool is None or jobs == 1
        if serial and regions and fitted:
            # the compiled kernels loaded here, as a pool worker loads them before its first
            # region: not in the first region's time (~0.25 s of it in a fresh process)
            from lfcam.measure.kernels import warm_up

            warm_up()
        t2 = time.perf_counter()
        args = (model, method, tolerance_pct, fast)
        near = nearby_regions(regions)  # each region's touching blurs (both fits read them)
        if not serial:
            estimates = pool.estimate(profile, geom, img, stats, regions, near, noise, args,
                                      progress, noise_model, lattice)
        else:
            estimates = []
            for i, reg in enumerate(regions):
                estimates.append(_timed_estimate(profile, geom, img, stats, reg, noise, args,
                                                 near[i]))
                if progress:
                    progress("regions", i + 1, len(regions))
    finally:
        if pool is not None:
            pool.close()
    if SPLIT_OVERLAPS and fitted:
        regions, estimates, near = _split_overlaps(profile, geom, img, stats, regions, near,
                                                   estimates, noise, args)
    if NEIGHBOURS_OUT and fitted and method != "lightfield":
        estimates = _take_out_neighbours(profile, geom, img, stats, regions, near, estimates,
                                         noise, args)
    results = []
    dmap = np.full(img.shape, np.nan, dtype=np.float32)
    nan = float("nan")
    measurements = []
    for reg, (est, _) in zip(regions, estimates, strict=True):
        kind, name, d, off, diameter, sig, status, meas = est
        if status != RegionStatus.OK or not np.isfinite(d):
            # no estimate: no numbers, whatever the model computed on the way
            status = status if status != RegionStatus.OK else RegionStatus.OUT_OF_DOMAIN
            d = off = sig = nan
        results.append(RegionResult(
            region_id=reg.region_id, x_px=reg.centroid_px[0], y_px=reg.centroid_px[1],
            kind=kind, model=name, distance_mm=d, offset_mm=off, diameter_mm=diameter,
            uncertainty_mm=sig, status=status, bbox_px=reg.box_px,
        ))
        measurements.append(meas)
    results, checks = _gate_regions(profile, geom, stats, regions, results, measurements)
    if learned is not None:  # the learned lens's parameter covariance, in quadrature
        from dataclasses import replace as _replace

        results = [
            _replace(r, uncertainty_mm=float(np.hypot(
                r.uncertainty_mm, calibration_sigma_mm(learned, profile, r.distance_mm))))
            if r.status == RegionStatus.OK and np.isfinite(r.distance_mm) else r
            for r in results
        ]
    for reg, res in zip(regions, results, strict=True):
        if res.status == RegionStatus.OK:
            paint_region(dmap, reg, geom.lmap, geom.pitch_px, res.distance_mm)
    t3 = time.perf_counter()
    return DistanceRun(results, dmap, {"geometry": t1 - t0, "regions": t2 - t1,
                                       "measure": t3 - t2, "jobs": jobs,
                                       "region_s": [t for _, t in estimates]}, checks)


SPLIT_OVERLAPS = True  # a region two overlapping blurs explain is split (_split_overlaps)
POINT_AND_LINE = True  # ... and one that only a point and a line explain (overlap.by_turns)
TWO_LINES = True  # ... or two lines (overlap.by_turns, second="line"), tried only where the
#                   region has this many lenslets and is this elongated: two lines 8-14 ‰
#                   apart on system 2 make regions of 516-600 lenslets, elongation 1.36-2.03;
#                   on system 1 of 51-59, where the try fails; two points 1 ‰ apart in front
#                   of focus, where it fails too, 1.0 (docs/distance.md, "Two lines in one
#                   region (stop 72)")
TWO_LINES_MIN_LENSLETS = 150
TWO_LINES_ELONGATION = 1.2
NEIGHBOURS_OUT = True  # touching regions refitted without their neighbours' light
NEIGHBOURS_ABOVE = 0.2  # ... where that light is over this × the region's noise misfit
NEIGHBOURS_WARM = True  # ... each refit started from the region's first answer
_FAILED_FITS = (RegionStatus.POOR_FIT, RegionStatus.NO_SOLUTION)


def _split_overlaps(profile, geom, img, stats, regions, near, estimates, noise, args
                    ) -> tuple[list, list, list]:
    """Regions, estimates and nearby regions with each region that two overlapping blurs
    explain split between those two (:func:`lfcam.measure.overlap.split_overlap`): a failed
    spot or line region, and an ``ok`` one whose footprint is nearly round and whose lenslet
    fit leaves over ``TWO_TRY`` × its noise and model misfits together (:func:`_unexplained`:
    two sources a tenth of a blur apart read as one short line). Where the blurs can be cut both
    parts are measured again, and a part whose own fit fails takes its source's answer from
    the joint two-point fit (:func:`lfcam.measure.overlap.joint_measurements`); where they
    cannot (too nearly one blur), both answers are the joint fit's. A failed region that two
    points do not explain either is tried as a point and a line fitted by turns
    (:func:`lfcam.measure.overlap.by_turns`, :data:`POINT_AND_LINE`), and then as two lines
    (:data:`TWO_LINES`): where both end ``ok`` and explain it, it is split between them (a
    ``spot`` or ``line`` region and a ``line`` region, each lenslet to the source that lights
    it more) and the answers are those fits'.

    A failed region cut from touching blurs is tried together with the other side of its cut
    (the region sharing its band), whose answer the new split replaces: a cut misplaced at a
    waist that two overlapping discs only seem to have leaves one side ``poor-fit`` and the
    other fitted to both blurs' light. The first part keeps the region's id, and its time
    counts the region's first fit and the two-point fit; the second takes the other side's
    id, or a new one at the end."""
    from lfcam.measure.overlap import (
        by_turns,
        by_turns_parts,
        joint_measurements,
        merged_region,
        split_overlap,
    )

    model, _, tolerance_pct, _ = args
    regions, estimates = list(regions), list(estimates)
    near = list(near)
    next_id = max((r.region_id for r in regions), default=-1) + 1
    done: set[int] = set()
    for i in range(len(regions)):
        reg = regions[i]
        status, meas = estimates[i][0].status, estimates[i][0].measurement
        failed_fit = status in _FAILED_FITS
        if (i in done or reg.kind not in ("spot", "line")
                or not (failed_fit or (status == RegionStatus.OK and _unexplained(reg, meas)))):
            continue
        t = time.process_time()
        sides = [j for j, o in enumerate(regions)
                 if failed_fit and j != i and reg.touching and o.shared.size == reg.shared.size
                 and np.array_equal(o.shared, reg.shared)]
        if len(sides) > 1:
            continue
        whole = (reg if not sides else
                 merged_region(reg, regions[sides[0]], stats, geom.lmap, geom.pitch_px))
        others = tuple(o for o in near[i] if not any(o is regions[j] for j in sides))
        tried: list = []
        split = split_overlap(profile, geom, img, stats, whole, next_id, others,
                              beat=math.inf if failed_fit else meas.misfit, tried=tried)
        pl = None
        if split is None and failed_fit and POINT_AND_LINE and tried:
            # nothing one or two points explain: a point and a line, fitted by turns
            two = min(tried, key=lambda t: t.misfit)
            pl = by_turns(profile, geom, img, whole, noise, two, others)
            if (pl is None and TWO_LINES and len(whole.lenslets) >= TWO_LINES_MIN_LENSLETS
                    and whole.elongation >= TWO_LINES_ELONGATION):  # (two lines)
                pl = by_turns(profile, geom, img, whole, noise, two, others, second="line")
        if split is None and pl is None:  # (the two-point fit's time is the region's too;
            #                                the other side, failed as well, would try the
            #                                same union again)
            estimates[i] = (estimates[i][0], estimates[i][1] + time.process_time() - t)
            done.update(sides)
            continue
        pair = (split.parts if pl is None else
                by_turns_parts(pl, whole, next_id, stats, geom.lmap, geom.pitch_px))
        if sides:
            pair = (pair[0], dataclasses.replace(pair[1], region_id=regions[sides[0]].region_id))
        else:
            next_id += 1
        spent = time.process_time() - t + estimates[i][1]  # (the region's first fit too)
        joint: tuple = ()  # both sources' joint answers, made once where a part needs one
        for k, (part, other) in enumerate(((pair[0], pair[1]), (pair[1], pair[0]))):
            nearby = (other,) + others
            est, secs = (None, 0.0)
            if pl is not None:  # (the answers are the fits by turns')
                est = _estimate_of(profile, (pl.other, pl.line)[k], model, tolerance_pct)
            elif split.cut:
                est, secs = _timed_estimate(profile, geom, img, stats, part, noise, args,
                                            nearby)
            if pl is None and (est is None or est.status != RegionStatus.OK):
                # the part's own fit failed (a crescent), or the blurs are not cut: the
                # source's answer is the joint fit's (its first user carries its time)
                t_joint = time.process_time()
                joint = joint or joint_measurements(profile, geom, split.two)
                est = _estimate_of(profile, joint[k], model, tolerance_pct)
                secs += time.process_time() - t_joint
            if k == 0:
                regions[i], estimates[i], near[i] = part, (est, secs + spent), nearby
            elif sides:
                j = sides[0]
                regions[j], estimates[j], near[j] = part, (est, secs), nearby
            else:
                regions.append(part)
                estimates.append((est, secs))
                near.append(nearby)
        done.update([i, *sides])
    return regions, estimates, near


def _take_out_neighbours(profile, geom, img, stats, regions, near, estimates, noise, args
                         ) -> list:
    """Estimates with each touching region's lenslet answer refitted on its moments less the
    light its touching neighbours' fitted sources put there
    (:func:`lfcam.measure.overlap.neighbour_light`), where that light is over
    :data:`NEIGHBOURS_ABOVE` × the region's noise misfit (norms of the moments). The waist
    cut's band leaves out the lenslets both blurs light, but a blur's soft rim reaches past
    it: without this, a line 12 ‰ of its distance from a point read +0.79 % and a point
    beside a larger blur +0.35 %.

    Every refit subtracts the first answers' light (the order of the regions does not
    matter). A region whose refit is not ``ok`` keeps its first answer. The refit's time,
    and the light's, count in the region's. Only lenslet answers are refitted (the pixel
    fit models its neighbours' light itself; a joint two-point answer has no own fit)."""
    def lenslet_answer(k: int) -> Measurement | None:
        meas = estimates[k][0].measurement
        ok = (estimates[k][0].status == RegionStatus.OK and meas is not None
              and meas.method == "lenslet" and len(meas.fitted_mm) > 0)
        return meas if ok else None

    answers = [lenslet_answer(k) for k in range(len(regions))]
    out = list(estimates)
    warm = False
    for i, reg in enumerate(regions):
        own = answers[i]
        if own is None or not reg.touching:
            continue
        sources = touching_sources(i, regions, near, answers)
        if not sources:
            continue
        if not warm:  # (a pool ran the first fits: this process has not loaded the kernels)
            from lfcam.measure.kernels import warm_up

            warm_up()
            warm = True
        t = time.process_time()
        light = light_to_take_out(profile, geom, img, reg, near[i], own, sources)
        spent = estimates[i][1] + time.process_time() - t
        if light is None:
            out[i] = (estimates[i][0], spent)
            continue
        model, _, tolerance_pct, fast = args
        est, secs = _timed_estimate(profile, geom, img, stats, reg, noise,
                                    (model, "lenslet", tolerance_pct, fast), near[i], light,
                                    own if NEIGHBOURS_WARM else None)
        out[i] = ((est if est.status == RegionStatus.OK else estimates[i][0]), spent + secs)
    return out


def touching_sources(i: int, regions: list[Region], near: list[tuple[Region, ...]],
                     answers: list[Measurement | None]
                     ) -> list[tuple[Region, tuple[Region, ...], Measurement]]:
    """The touching neighbours of ``regions[i]`` that share its cut's band and have an
    answer (``answers[k]``: region ``k``'s, or None): each as its region, the regions left
    out of its box (``near``) and its answer, as :func:`light_to_take_out` reads them."""
    index = {id(r): k for k, r in enumerate(regions)}
    return [(o, near[index[id(o)]], answers[index[id(o)]]) for o in near[i]
            if id(o) in index and o.touching and answers[index[id(o)]] is not None
            and np.intersect1d(o.shared, regions[i].shared).size]


def light_to_take_out(profile: CameraProfile, geom: Geometry, img: np.ndarray, reg: Region,
                      nearby: tuple[Region, ...], own: Measurement,
                      sources: list[tuple[Region, tuple, Measurement]]) -> np.ndarray | None:
    """The light touching ``sources`` (each its region, the regions left out of its box and
    its lenslet answer) put on ``reg``'s lenslets (:func:`lfcam.measure.overlap.
    neighbour_light`; ``nearby``: the regions left out of ``reg``'s box), or None where it is
    not over :data:`NEIGHBOURS_ABOVE` × the noise misfit of ``reg``'s answer ``own`` (norms of
    the moments): the gate of :func:`_take_out_neighbours`' refits."""
    from lfcam.measure.fastfit import region_moments
    from lfcam.measure.overlap import neighbour_light

    mom = region_moments(geom, img, reg, nearby)
    light = neighbour_light(profile, geom, img, mom, sources)
    over = float(np.sqrt((light * light).sum())) > NEIGHBOURS_ABOVE * own.noise_misfit * mom.norm
    return light if over else None


def _unexplained(reg: Region, meas: Measurement | None) -> bool:
    """Whether an ``ok`` lenslet answer may be two sources that nearly share a line of sight:
    its region's footprint nearly round (elongation under ``overlap.TWO_ROUND``) and its
    misfit over ``overlap.TWO_TRY`` × its noise and its point models' own misfits in
    quadrature."""
    from lfcam.measure.overlap import TWO_ROUND, TWO_TRY

    if meas is None or not reg.elongation < TWO_ROUND:
        return False
    floor = math.hypot(meas.noise_misfit, meas.model_misfit)
    return bool(math.isfinite(floor) and meas.misfit > TWO_TRY * floor)


def _estimate_of(profile: CameraProfile, meas: Measurement, model: str,
                 tolerance_pct: float | None) -> Estimate:
    """The :class:`Estimate` of a measurement."""
    name, d, off, sig, status = _apply_model(profile, meas, model, tolerance_pct)
    return Estimate(meas.kind, name, d, off, abs(meas.y1_mm - meas.y2_mm), sig, status, meas)


def _timed_estimate(profile, geom, img, stats, reg, noise, args,
                    nearby=(), light=None, start=None) -> tuple[Estimate, float]:
    """(:class:`Estimate` of :func:`_estimate` or its failure, CPU seconds of this
    region)."""
    model, method, tolerance_pct, fast = args
    t = time.process_time()
    try:
        est = _estimate(profile, geom, img, stats, reg, noise, model, method, tolerance_pct,
                        fast, nearby, light, start)
    except _REGION_FAILURES as exc:
        nan = float("nan")
        est = Estimate(reg.kind, model, nan, nan, nan, nan, failed(type(exc).__name__), None)
    return est, time.process_time() - t


# ----------------------------------------------------------------------------- parallel regions
_WORKER: dict = {}
_BLAS_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _worker_boot() -> None:
    """Start-up of a region worker: one thread for OpenCV, the measurement modules imported
    (so that the interpreter's start-up overlaps the parent's geometry and region work), and
    a watch that ends the worker with its parent."""
    cv2.setNumThreads(1)
    import lfcam.measure.fastfit  # noqa: F401
    import lfcam.measure.lightfield  # noqa: F401
    from lfcam.measure.kernels import warm_up

    warm_up()  # the lenslet model's compiled kernel (every method's fits may use it)

    # a worker whose parent was killed would otherwise live on, orphaned: leave with it
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    import threading

    threading.Thread(target=watch, daemon=True).start()


def _worker_ping() -> int:
    return os.getpid()


def _worker_attach(names: tuple[str, str, str], shape: tuple[int, int]) -> dict:
    """The capture a task belongs to: the shared image and lenslet labels and the pickled
    rest (profile, geometry parts, statistics, noise, arguments), attached once a worker."""
    import pickle
    from multiprocessing import shared_memory

    from lfcam.measure.lenslets import LensletMap, LensletStats

    if _WORKER.get("names") == names:
        return _WORKER
    for shm in _WORKER.pop("shm", ()):
        shm.close()
    shm_img, shm_lab, shm_ctx = (shared_memory.SharedMemory(name=n) for n in names)
    img = np.ndarray(shape, dtype=np.float64, buffer=shm_img.buf)
    labels = np.ndarray(shape, dtype=np.int32, buffer=shm_lab.buf)
    ctx = pickle.loads(bytes(shm_ctx.buf))
    shm_ctx.close()
    (centres_px, radius_px), lens_centres_mm, pitch_px, d_in_mm = ctx["geom"]
    geom = Geometry(LensletMap(centres_px, labels, radius_px), lens_centres_mm, pitch_px,
                    d_in_mm)
    if ctx["noise_model"] is not None:  # the parent's, remembered for this image
        capture_noise(img, geom.lmap, pitch_px, known=ctx["noise_model"])
    if ctx["lattice"] is not None:  # the parent's, remembered for this geometry
        keep_lattice(geom, ctx["lattice"][0])
    _WORKER.clear()
    _WORKER.update(names=names, profile=ctx["profile"], geom=geom, img=img,
                   stats=LensletStats(*ctx["stats"]), noise=ctx["noise"], args=ctx["args"],
                   shm=(shm_img, shm_lab))
    return _WORKER


def _worker_region(names: tuple[str, str, str], shape: tuple[int, int], reg: Region,
                   nearby: tuple[Region, ...] = ()) -> tuple[Estimate, float]:
    w = _worker_attach(names, shape)
    return _timed_estimate(w["profile"], w["geom"], w["img"], w["stats"], reg, w["noise"],
                           w["args"], nearby)


class _RegionPool:
    """``jobs`` worker processes for the regions of a capture.

    Started before the geometry, from a thread: the fork server's interpreter start-up and
    imports (~1 s, :mod:`lfcam.measure.preload`) then overlap the parent's geometry and region
    detection instead of following them, and are paid once rather than in every worker (with
    spawned workers, scene (b) of ``benchmarks/many_sources.py`` ran 14.4–15.0 s in process,
    forked 13.4–13.5 s). Each capture's image and lenslet labels are shared once through
    shared memory; the results equal the serial run's.
    """

    def __init__(self, jobs: int):
        import multiprocessing as mp
        import threading

        # workers forked from a server that has loaded the measurement modules and kernels
        # once (lfcam.measure.preload); the server is single-threaded (no fork of a threaded
        # parent) and lives as long as this process
        if "forkserver" in mp.get_all_start_methods():
            ctx = mp.get_context("forkserver")
            ctx.set_forkserver_preload(["lfcam.measure.preload"])
        else:  # (Windows) spawned workers import the modules themselves (_worker_boot)
            ctx = mp.get_context("spawn")
        self.pool = ProcessPoolExecutor(jobs, mp_context=ctx, initializer=_worker_boot)
        # started from a thread: the first start waits for the server's imports (~1 s),
        # which then overlap the parent's geometry instead of delaying it
        self._starter = threading.Thread(target=self._start, args=(jobs,), daemon=True)
        self._starter.start()

    def _start(self, jobs: int) -> None:
        # one BLAS thread a worker: the server reads this when it starts, before importing
        # numpy (setting it in a worker is too late); restored once the workers are started
        saved = {v: os.environ.get(v) for v in _BLAS_THREAD_VARS}
        os.environ.update({v: "1" for v in _BLAS_THREAD_VARS})
        try:
            for _ in range(jobs):  # each submit to a busy pool starts one more worker
                self.pool.submit(_worker_ping)
        finally:
            _restore_environ(saved)

    def estimate(self, profile, geom, img, stats, regions, nearby, noise, args, progress,
                 noise_model=None, lattice=None) -> list:
        """:func:`_timed_estimate` of every region, in region order (``nearby``: each
        region's :func:`~lfcam.measure.regions.nearby_regions`; ``noise_model`` and
        ``lattice``, a 1-tuple of :func:`~lfcam.measure.fastfit.lattice_of`'s: the parent's,
        which the workers keep)."""
        import pickle
        from concurrent.futures import as_completed
        from multiprocessing import shared_memory

        self._starter.join()  # the workers' start (and its BLAS variables) is over

        ctx = pickle.dumps({
            "profile": profile, "geom": ((geom.lmap.centres_px, geom.lmap.radius_px),
                                         geom.lens_centres_mm, geom.pitch_px, geom.d_in_mm),
            "stats": (stats.energy, stats.centroid_px, stats.pixels), "noise": noise,
            "noise_model": noise_model, "lattice": lattice,
            "args": args}, protocol=pickle.HIGHEST_PROTOCOL)
        shms = []
        try:
            for arr in (img, geom.lmap.labels.astype(np.int32, copy=False),
                        np.frombuffer(ctx, dtype=np.uint8)):
                shm = shared_memory.SharedMemory(create=True, size=max(arr.nbytes, 1))
                np.ndarray(arr.shape, dtype=arr.dtype, buffer=shm.buf)[...] = arr
                shms.append(shm)
            names = tuple(s.name for s in shms)
            # the largest regions first, so that no worker is left with a long tail
            order = sorted(range(len(regions)), key=lambda i: -len(regions[i].lenslets))
            futures = {self.pool.submit(_worker_region, names, img.shape, regions[i],
                                        nearby[i]): i
                       for i in order}
            out: list = [None] * len(regions)
            for done, fut in enumerate(as_completed(futures), start=1):
                out[futures[fut]] = fut.result()
                if progress:
                    progress("regions", done, len(regions))
            return out
        finally:
            for shm in shms:
                shm.close()
                shm.unlink()

    def close(self) -> None:
        """Stop the workers (pending tasks are cancelled)."""
        self._starter.join()
        self.pool.shutdown(wait=True, cancel_futures=True)


def _restore_environ(saved: dict) -> None:
    """Put environment variables back as ``saved`` (``None``: was unset)."""
    for name, value in saved.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value


def _gate_regions(profile, geom, stats, regions, results, measurements) -> tuple[list, list]:
    """``ok`` is earned (lfcam.measure.verify): demote regions that fail a gate."""
    from dataclasses import replace

    measured = []
    for res, meas in zip(results, measurements, strict=True):
        usable = (res.status == RegionStatus.OK and meas is not None and res.kind == "spot"
                  and len(meas.source_xy_mm) == 2)
        measured.append((res.status if usable else "skip", meas,
                         meas.source_xy_mm if usable else None, res.uncertainty_mm))
    checks = verify_regions(profile, geom, stats, regions, measured)
    nan = float("nan")
    out = []
    for res, chk, (st, _, _, _) in zip(results, checks, measured, strict=True):
        if st == RegionStatus.OK and chk.status != RegionStatus.OK:
            res = replace(res, status=chk.status, distance_mm=nan, offset_mm=nan,
                          uncertainty_mm=nan)
        out.append(res)
    return out, checks


def write_outputs(outdir: str | Path, run: DistanceRun, title: str = "") -> None:
    """``regions.csv``, ``distance.tiff``, ``distance.png`` (docs/distance.md), atomically;
    ``title`` heads the preview (e.g. capture name and model)."""
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    write_regions_csv(out / "regions.csv", run.regions)
    write_distance_tiff(out / "distance.tiff", run.distance_map)
    write_distance_png(out / "distance.png", run.distance_map, run.regions, title)
