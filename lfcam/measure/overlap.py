"""Two sources whose blurs overlap too far to show a waist: fitted as two points, then cut.

Two blurs that touch narrow where they meet, and :func:`lfcam.measure.regions.find_regions`
cuts them there (``WAIST_RATIO``). Blurs that overlap by more than about a quarter of their
width leave no such waist (two uniform discs 0.65 diameters apart already narrow only to
0.76 of their width), so they form one region, which no single point or line explains: the
lenslet fit ends ``poor-fit`` and neither source gets a distance.

Such a region is fitted here as two point sources (six parameters) on its lenslet moments,
the two models' brightnesses solved linearly at every step (:func:`two_points`). Where two
points explain the region (their misfit under :data:`TWO_NOISE` × its noise misfit, or
:data:`TWO_FLOOR`, and under its poor-fit limit), the fit only places the two blurs: the
region is cut, as touching blurs are, into the lenslets each blur lights alone, and a band
that both light (``Region.shared``, left out of both fits' data) (:func:`split_overlap`).
Each part is then measured as any touching region is, with the other as its neighbour, so
that its answer, σ and status come from the same fits as every other region's
(docs/distance.md, "Blurs that overlap without a waist (stop 68)").

Where a part's own fit fails (a crescent of a blur the other overlaps by ~80 %), or the two
blurs are too nearly one to cut (two sources a tenth of a blur apart, which one short line
explains all but their misfit), the source's answer is the joint fit's own, carried on on the
point polish's rays with a σ of its own (:attr:`TwoPoints.answer`,
:func:`joint_measurements`; docs/distance.md, "Two sources one fit explains: the joint answer
(stop 69)"). Those answers are the lenslet moments' whatever the method.

A touching blur's rim reaches past the band left out of both parts: :func:`neighbour_light`
models a fitted neighbour's light on a region's lenslets, which
:func:`lfcam.distance.run_distance` takes from the region's moments before its refit
(docs/distance.md, "A touching blur's light taken out (stop 71)").
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from lfcam.camera import CameraProfile
from lfcam.measure import fastfit as ff
from lfcam.measure.base import Measurement, point_measurement
from lfcam.measure.geometry import Geometry
from lfcam.measure.lenslets import LensletMap, LensletStats
from lfcam.measure.noise import capture_noise
from lfcam.measure.pointfit import chief_ray_gains, chief_ray_offset
from lfcam.measure.regions import Region, footprint_moments, make_region
from lfcam.measure.sampling import segment_points
from lfcam.measure.solve import (
    fd_jacobian,
    levenberg_marquardt,
    linear_step,
    log_distance_sigma,
    sq,
)
from lfcam.measure.verify import poor_fit_limit
from lfcam.status import RegionStatus

TWO_MIN_LENSLETS = 40  # a region of fewer lenslets is not tried as two blurs
TWO_RAYS = 3000  # rays a point of the two-point model (it places the blurs; it does not measure)
TWO_FINE_RAYS = 12000  # ... and of its last steps
TWO_ITERATIONS = 8  # Levenberg–Marquardt iterations on the coarse model ...
TWO_FINE_ITERATIONS = 3  # ... and on the fine one
TWO_ANSWER_RAYS = ff.POLISH_RAYS  # rays a point where the joint fit gives the answers ...
TWO_ANSWER_ITERATIONS = 8  # ... its Levenberg–Marquardt iterations, at most ...
TWO_SETTLE_LOG = ff.POLISH_SETTLE_LOG  # ... ending on a step under this (log distance)
TWO_STARTS = ("halves", "spread")  # the two-point fit's starts, tried in turn until two points
#                                     explain the region (two_points)
TWO_SCAN = (0.7, 0.85, 1.0, 1.18, 1.4)  # each blur's distance about the common scan's best
TWO_NOISE = 1.5  # two points must leave under this × the region's noise misfit (they explain
#                  all there is),
TWO_FLOOR = 0.02  # ... or this, where the noise misfit is less (the model's own ray noise)
TWO_LIT_SHARE = 0.05  # a blur lights the lenslets over this share of its brightest
TWO_BAND_SHARE = 0.005  # a lenslet is in the band where both blurs put over this share of
#                        their brightest lenslet's light on it
TWO_MIN_PART = 12  # each part keeps at least this many lenslets (else: the joint answers)
TWO_TRY = 2.2  # an ``ok`` lenslet answer whose misfit is over this × its noise and model
#               misfits in quadrature is tried as two sources (lfcam.distance._unexplained)
TWO_ROUND = 1.5  # ... where its footprint's elongation is under this (two sources a tenth
#                 to a fifth of a blur apart: 1.05-1.18; the grid's 720 mm lines on system
#                 2, whose misfit passes TWO_TRY: 3.5-4.5)
TWO_BEATS = 0.5  # where one source's fit explains a region, two must leave under this × its
#                  misfit (as a line must a point's: fastfit.LINE_GAIN)
LIGHT_RAYS = 20000  # rays of a neighbour's point model (neighbour_light) ...
LIGHT_LINE_POINTS = 24  # ... points of its line model ...
LIGHT_LINE_RAYS = 2000  # ... and rays of each of them
PL_TURNS = 5  # a point and a line in one region: at most this many turns of the two fits
#               (by_turns) ...
PL_SETTLE_SIGMAS = 0.25  # ... ending where neither distance moved by this × its σ
PL_PART_BAND = 0.5  # two lines: each first fitted on the lenslets where the other's light (the
#                     two-point fit's) is under this × its own
PL_COUPLED_SIGMA = True  # each answer's σ × the two sources' coupling (coupling_factors: its
#                          σ with both sources free over its σ with the other held fixed)


class TwoPoints(NamedTuple):
    """Two point sources fitted to one region's lenslet moments."""

    sources_mm: np.ndarray  # (2, 3) lens frame
    misfit: float  # the normalised misfit of the two together
    light: np.ndarray  # (2, K) each source's light on the box's lenslets (its fitted share)
    ids: np.ndarray  # (K,) the box's lenslets (indices into the lenslet list)
    noise_misfit: float  # the region's noise misfit
    # () -> JointAnswer: the fit carried on to an answer (TWO_ANSWER_RAYS), run once on call
    answer: Callable[[], JointAnswer]


class JointAnswer(NamedTuple):
    """The two sources as the joint fit measures them (:attr:`TwoPoints.answer`)."""

    sources_mm: np.ndarray  # (2, 3) lens frame
    sigma_mm: np.ndarray  # (2,) σ of each distance from the front vertex: the fit's
    #                       statistical σ and its ray sample's shift in quadrature
    misfit: float


class Split(NamedTuple):
    """A region that two point sources explain (:func:`split_overlap`)."""

    parts: tuple[Region, Region]  # the lenslets each source lights more (source order)
    two: TwoPoints
    cut: bool  # the parts are measured on their own (else: the joint fit's answers)


def _amplitudes(data: np.ndarray, m1: np.ndarray, m2: np.ndarray) -> np.ndarray:
    """The non-negative brightnesses of two models that fit ``data`` best (least squares)."""
    a = np.array([[float((m1 * m1).sum()), float((m1 * m2).sum())],
                  [float((m1 * m2).sum()), float((m2 * m2).sum())]])
    b = np.array([float((m1 * data).sum()), float((m2 * data).sum())])
    try:
        x = np.linalg.solve(a, b)
    except np.linalg.LinAlgError:
        x = np.full(2, -1.0)
    if (x >= 0).all():
        return x
    # one of them at zero: the other alone
    one = [b[k] / a[k, k] if a[k, k] > 0 else 0.0 for k in (0, 1)]
    cost = [float(((data - max(one[k], 0.0) * m) ** 2).sum()) for k, m in ((0, m1), (1, m2))]
    k = int(np.argmin(cost))
    x = np.zeros(2)
    x[k] = max(one[k], 0.0)
    return x


def _two_rest(mom: ff.LensletMoments, m1: np.ndarray, m2: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """The data's moments less two models at their best brightnesses (:func:`_amplitudes`),
    over the data's norm (K, 4), and those brightnesses (2,)."""
    a = _amplitudes(mom.data, m1, m2)
    return (mom.data - a[0] * m1 - a[1] * m2) / mom.norm, a


def _explained_below(noise_misfit: float, beat: float = math.inf) -> float:
    """The misfit under which two sources explain a region: :data:`TWO_NOISE` × its noise
    misfit (or :data:`TWO_FLOOR`), under its poor-fit limit, and under :data:`TWO_BEATS` ×
    ``beat`` (the misfit of one source that already explains it)."""
    return min(poor_fit_limit(noise_misfit, ff.POOR_FIT),
               max(TWO_NOISE * noise_misfit, TWO_FLOOR), TWO_BEATS * beat)


def _lobes(pos: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The energy centroids (2, 2) of a footprint's two halves along its long axis: two
    means of the lenslets' positions ``pos`` (weights ``w``) on that axis."""
    mean, _, vecs = footprint_moments(w, pos, 0.0)
    t = (pos - mean) @ vecs[:, 1]
    order = np.argsort(t)
    cum = np.cumsum(w[order]) / w.sum()
    c = np.array([t[order][np.searchsorted(cum, 0.25)], t[order][np.searchsorted(cum, 0.75)]])
    for _ in range(20):
        near = np.abs(t - c[0]) <= np.abs(t - c[1])
        if near.all() or not near.any():
            break
        new = np.array([(t[near] * w[near]).sum() / w[near].sum(),
                        (t[~near] * w[~near]).sum() / w[~near].sum()])
        if np.allclose(new, c):
            break
        c = new
    near = np.abs(t - c[0]) <= np.abs(t - c[1])
    return np.array([(pos[m] * w[m, None]).sum(0) / w[m].sum() for m in (near, ~near)])


def _spread(pos: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Two points (2, 2) about a footprint's centre on its long axis, as far apart as two
    equally bright blurs of one size whose sum has that footprint: the variance along the
    axis less the variance across it is a quarter of their separation squared."""
    mean, (across, along), vecs = footprint_moments(w, pos, 0.0)
    half = math.sqrt(max(float(along - across), 0.0))
    return np.array([mean - half * vecs[:, 1], mean + half * vecs[:, 1]])


def two_points(profile: CameraProfile, geom: Geometry, image: np.ndarray, region: Region,
               others: tuple[Region, ...] = (), starts: str = "halves") -> TwoPoints | None:
    """Fit ``region``'s lenslet moments as two point sources (module docstring).

    Starts (``starts``): ``"halves"``, the light centroids of the footprint's two halves along
    its long axis (:func:`_lobes`); ``"spread"``, two points on that axis as far apart as its
    second moments say (:func:`_spread`: the halves of two blurs that overlap by over ~90 %
    lie far outside their sources, in front of focus most). Each through the chief ray at
    each trial distance: both at each distance of the point fit's scan, then each at
    :data:`TWO_SCAN` × the best; then Levenberg–Marquardt on (log distance, x/L, y/L) of
    both, the two brightnesses solved at every evaluation. ``others``' lenslets and the
    region's ``shared`` band are left out of the data, as in :func:`fastfit.measure_lenslet`.
    Returns None for a region of fewer than :data:`TWO_MIN_LENSLETS` lenslets or where the
    two points do not both take light.
    """
    if region.lenslets.size < TWO_MIN_LENSLETS:
        return None
    mom = ff.region_moments(geom, image, region, others)
    energy = mom.data[:, 0]
    lit = energy > TWO_LIT_SHARE * energy.max()
    if lit.sum() < TWO_MIN_LENSLETS // 2:
        return None
    nm = capture_noise(image, geom.lmap, geom.pitch_px).moments_misfit_of(mom.noise_sums,
                                                                          mom.norm)
    frame = ff.SourceFrame(profile)
    lobes = (_spread if starts == "spread" else _lobes)(geom.lens_centres_mm[mom.ids[lit]],
                                                         energy[lit])

    def pairs_of(model: ff.LensletModel, qs: list[np.ndarray]) -> list[np.ndarray]:
        pts = np.concatenate([[frame.source(q[:3]), frame.source(q[3:])] for q in qs])
        m = model.simulate_groups(pts, np.arange(len(pts), dtype=np.int64), len(pts),
                                  len(qs))
        return [_two_rest(mom, m[2 * k], m[2 * k + 1])[0].ravel() for k in range(len(qs))]

    def at(d1: float, d2: float, g1: float, g2: float) -> np.ndarray:
        q = []
        for d, g, c in ((d1, g1, lobes[0]), (d2, g2, lobes[1])):
            xy = chief_ray_offset(profile, geom.d_in_mm, d, c, gain=g)
            q.append(frame.params(np.array([xy[0], xy[1], frame.z_front - d])))
        return np.concatenate(q)

    coarse = ff.LensletModel(profile, geom, mom, TWO_RAYS)
    f_mm = profile.main_lens.focal_length_mm
    distances = np.geomspace(1.1 * f_mm, 3e4, ff.SCAN_DISTANCES)
    gains = chief_ray_gains(profile, geom.d_in_mm, distances)
    scan = [at(d, d, g, g) for d, g in zip(distances, gains, strict=True)]
    costs = [sq(r) for r in pairs_of(coarse, scan)]
    best = float(distances[int(np.argmin(costs))])
    trial = np.array(TWO_SCAN) * best
    g_trial = chief_ray_gains(profile, geom.d_in_mm, trial)
    grid = [at(d1, d2, g1, g2) for d1, g1 in zip(trial, g_trial, strict=True)
            for d2, g2 in zip(trial, g_trial, strict=True)]
    costs = [sq(r) for r in pairs_of(coarse, grid)]
    q = grid[int(np.argmin(costs))]
    fine = ff.LensletModel(profile, geom, mom, TWO_FINE_RAYS)
    steps = np.tile(ff.point_steps(profile, geom, ff.lit_lenslets(mom)), 2)

    def fit(model: ff.LensletModel, q: np.ndarray, iterations: int, **lm) -> tuple:
        fun = (lambda qq: pairs_of(model, [qq])[0])  # noqa: E731
        many = (lambda qs: pairs_of(model, qs))  # noqa: E731
        q, r, f, jac = levenberg_marquardt(fun, q, steps, iterations, 1e-4, many, **lm)
        if jac is None:  # (ended before its first Jacobian)
            jac = fd_jacobian(fun, many, q, r, steps)
        return q, r, f, jac

    for model, iterations in ((coarse, TWO_ITERATIONS), (fine, TWO_FINE_ITERATIONS)):
        q, r, f, _ = fit(model, q, iterations)
    sources = np.array([frame.source(q[:3]), frame.source(q[3:])])
    m = fine.simulate_groups(sources, np.arange(2, dtype=np.int64), 2, 1)
    a = _amplitudes(mom.data, m[0], m[1])
    if not (a > 0).all():
        return None
    light = np.array([a[0] * m[0][:, 0], a[1] * m[1][:, 0]])
    done: list[JointAnswer] = []

    def answer() -> JointAnswer:
        # The placing fit's 12 000 rays a source leave its minimum where their own sample
        # puts it (two equal sources at 2 000 mm: 2 017 / 2 009 mm after its 3 iterations,
        # 2 010 / 2 003 after 8, 2 001 / 2 004 on 40 000 rays, 1 999.4 / 1 998.5 on 100 000):
        # the answer is carried on on the point polish's rays. Each distance's σ: the
        # Jacobian's (the point fit's rule, that distance's column first) and the shift a
        # turned pupil sample's Gauss–Newton step gives it (fastfit's settled tests).
        if not done:
            model = ff.LensletModel(profile, geom, mom, TWO_ANSWER_RAYS)
            qa, ra, fa, jac = fit(model, q, TWO_ANSWER_ITERATIONS, settle_log=TWO_SETTLE_LOG)
            turned = ff.LensletModel(profile, geom, mom, TWO_ANSWER_RAYS, phase=1.0)
            shift = linear_step(jac, pairs_of(turned, [qa])[0] - ra)
            sigma_log = np.array([
                math.hypot(log_distance_sigma(jac[:, np.roll(np.arange(6), -k)], ra),
                           math.inf if shift is None else float(shift[0][k]))
                for k in (0, 3)])
            src = np.array([frame.source(qa[:3]), frame.source(qa[3:])])
            done.append(JointAnswer(src, sigma_log * (frame.z_front - src[:, 2]),
                                    math.sqrt(fa)))
        return done[0]

    return TwoPoints(sources, math.sqrt(f), light, mom.ids, nm, answer)


def split_overlap(profile: CameraProfile, geom: Geometry, image: np.ndarray,
                  stats: LensletStats, region: Region, new_id: int,
                  others: tuple[Region, ...] = (), beat: float = math.inf,
                  tried: list | None = None) -> Split | None:
    """``region`` split between the two sources a two-point fit finds in it
    (:func:`two_points`), or None where two points do not explain it: their misfit over
    :data:`TWO_NOISE` × the region's noise misfit (or :data:`TWO_FLOOR`), over its poor-fit
    limit, or — for a region one source already explains, whose misfit is ``beat`` — over
    :data:`TWO_BEATS` × that.

    The parts: the region's lenslets where one blur puts over :data:`TWO_BAND_SHARE` of its
    brightest lenslet's light and the other does not, each to the blur that puts more light
    on it; the band where both do is ``shared`` by both and in neither. Where either part
    would keep fewer than :data:`TWO_MIN_PART` lenslets the blurs are too nearly one to be
    cut (``cut`` false): the parts are then the lenslets each source lights more, for the
    map, and the answers the joint fit's (:func:`joint_measurements`). The first part keeps
    ``region``'s id, the second takes ``new_id``; both are ``spot`` regions. ``tried``: a
    list to which each two-point fit made is appended."""
    for starts in TWO_STARTS:
        two = two_points(profile, geom, image, region, others, starts)
        if two is None:
            return None
        if tried is not None:  # (the caller's: a point-and-line fit starts from them)
            tried.append(two)
        if two.misfit < _explained_below(two.noise_misfit, beat):
            break
    else:
        return None
    share = two.light / two.light.max(axis=1, keepdims=True)
    mine = np.isin(two.ids, region.lenslets)
    band = mine & (share > TWO_BAND_SHARE).all(axis=0)
    first = mine & ~band & (two.light[0] >= two.light[1])
    second = mine & ~band & ~first
    cut = min(first.sum(), second.sum()) >= TWO_MIN_PART
    if cut:
        shared = np.union1d(two.ids[band], region.shared)
    else:  # (no band: each lenslet to the source that lights it more)
        first = mine & (two.light[0] >= two.light[1])
        second = mine & ~first
        shared = region.shared
        if not (first.any() and second.any()):
            first = second = mine
    # each part's place: its source's light as the two-point fit spreads it (the part alone
    # may be a crescent whose own centroid lies far off its source's)
    centres = geom.lmap.centres_px[two.ids]
    parts = [make_region(rid, "spot", two.ids[m], stats, geom.lmap, geom.pitch_px, 1, shared,
                         (centres * two.light[k, :, None]).sum(0) / two.light[k].sum())
             for k, (rid, m) in enumerate(((region.region_id, first), (new_id, second)))]
    return Split((parts[0], parts[1]), two, cut)


def joint_measurements(profile: CameraProfile, geom: Geometry,
                       two: TwoPoints) -> tuple[Measurement, Measurement]:
    """Each source's answer as the joint two-point fit measures it (:attr:`TwoPoints.answer`):
    its distance, that distance's σ (with :data:`fastfit.SIGMA_FLOOR_REL` in quadrature) and
    the pair's misfit; ``poor-fit`` where that σ is not finite (a singular Jacobian)."""
    got = two.answer()
    out = [point_measurement(profile, geom.d_in_mm, src, float(sig), ff.SIGMA_FLOOR_REL,
                             misfit=got.misfit, noise_misfit=two.noise_misfit)
           if math.isfinite(sig) else Measurement.failed(RegionStatus.POOR_FIT, geom.d_in_mm)
           for src, sig in zip(got.sources_mm, got.sigma_mm, strict=True)]
    return out[0], out[1]


def merged_region(a: Region, b: Region, stats: LensletStats, lmap: LensletMap,
                  pitch_px: float) -> Region:
    """The region two touching regions ``a`` and ``b`` were cut from (both sides and the band
    they share), with ``a``'s id."""
    members = np.union1d(np.union1d(a.lenslets, b.lenslets), a.shared)
    return make_region(a.region_id, "spot", members, stats, lmap, pitch_px, a.parts + b.parts)


def neighbour_light(profile: CameraProfile, geom: Geometry, image: np.ndarray,
                    mom: ff.LensletMoments, sources: list[tuple[Region, tuple, Measurement]]
                    ) -> np.ndarray:
    """The light that touching blurs' fitted sources put on a region's lenslets.

    A touching blur's light reaches past the band the waist cut leaves out of both regions
    (soft rims, vignetting): it pulls the fit on this side toward a larger blur (a line
    touching a point read +0.79 % where it reads +0.02 % alone). Each source is modelled on
    this region's lenslets and on its own region's, with the same pupil sample (so the same
    units), and scaled to its own region's data (least squares, as the lenslet fit scales
    its model): what it puts here is then subtracted by
    :func:`lfcam.measure.fastfit.measure_lenslet` (``light``).

    Parameters
    ----------
    profile : CameraProfile
    geom : Geometry
    image : (H, W) float array
    mom : fastfit.LensletMoments
        This region's moments as its fit reads them (:func:`fastfit.region_moments`).
    sources : list of (Region, tuple of Region, Measurement)
        Each touching neighbour's region, the regions left out of its box, and its lenslet
        answer (:attr:`Measurement.fitted_mm`: a point, or a line's two ends).

    Returns
    -------
    (K, 4) array
        Moments in ``mom``'s layout (zero where no source reaches).
    """
    out = np.zeros_like(mom.data)
    for region, others, meas in sources:
        own = ff.region_moments(geom, image, region, others)
        m_own = _source_moments(profile, geom, own, meas.fitted_mm)
        mm = float((m_own * m_own).sum())
        scale = float((m_own * own.data).sum()) / mm if mm > 0 else 0.0
        if scale > 0:
            out += scale * _source_moments(profile, geom, mom, meas.fitted_mm)
    return out


def _source_moments(profile: CameraProfile, geom: Geometry, mom: ff.LensletMoments,
                    fitted_mm) -> np.ndarray:
    """(K, 4) model moments on ``mom``'s lenslets of a fitted source (a point, or a line's
    two ends: :attr:`Measurement.fitted_mm`), unscaled: a point on :data:`LIGHT_RAYS` rays,
    a line as :data:`LIGHT_LINE_POINTS` equally bright points (as the line fit models it) on
    :data:`LIGHT_LINE_RAYS` each. The same source on two layouts gives the same units."""
    ends = np.asarray(fitted_mm, dtype=np.float64).reshape(-1, 3)
    if len(ends) == 1:
        pts, rays = ends, LIGHT_RAYS
    else:
        pts, rays = segment_points(ends[0], ends[1], LIGHT_LINE_POINTS), LIGHT_LINE_RAYS
    return ff.LensletModel(profile, geom, mom, rays).simulate(pts)


class ByTurns(NamedTuple):
    """A line and a second source (a point or a line) fitted to one region by turns
    (:func:`by_turns`)."""

    other: Measurement  # the second source: a ``spot`` or a ``line``
    line: Measurement
    misfit: float  # the two models together, their brightnesses solved jointly
    light: np.ndarray  # (2, K) the second source's and the line's light on the box's lenslets
    ids: np.ndarray  # (K,) the box's lenslets (indices into the lenslet list)


def by_turns(profile: CameraProfile, geom: Geometry, image: np.ndarray, region: Region,
             noise: float, two: TwoPoints, others: tuple[Region, ...] = (),
             second: str = "spot") -> ByTurns | None:
    """A region that one point, one line and two points all leave ``poor-fit``, fitted as a
    line and a second source (``second``: ``spot``, a point; ``line``, another line) by turns.

    The two-point fit (``two``) places the blurs; one of its points is taken for the second
    source (each in turn), the other for the line. Then, up to :data:`PL_TURNS` times: the
    line is fitted (:func:`fastfit.measure_lenslet`) on the region's moments less the second
    source's light (a point's model of it, the first time), and the second source on them
    less the line's, each light scaled with the other's model by least squares
    (:func:`_amplitudes`), until neither distance moves by :data:`PL_SETTLE_SIGMAS` × its σ.
    Each answer's σ is its own fit's, the other source's light held fixed. Returns the
    assignment whose two models leave the lower misfit together, or None where neither ends
    with two ``ok`` answers of those kinds, or they leave over :data:`TWO_NOISE` × the
    region's noise misfit (or :data:`TWO_FLOOR`), or over its poor-fit limit (a line
    beside a point 4–10 ‰ of their distance apart: docs/distance.md, "A point and a line in
    one region (stop 71)"; two lines: "Two lines in one region (stop 72)")."""
    mom = ff.region_moments(geom, image, region, others)
    limit = _explained_below(two.noise_misfit)
    best: ByTurns | None = None

    def turn(light: np.ndarray, kind: str) -> Measurement | None:
        # one source's lenslet fit with the other's light taken out: None unless an ``ok``
        # answer of that kind
        got = ff.measure_lenslet(profile, geom, image, region, noise, others=others,
                                 light=light)
        return got if got.status == RegionStatus.OK and got.kind == kind else None

    placed = [_source_moments(profile, geom, mom, src) for src in two.sources_mm]
    amp2 = _amplitudes(mom.data, placed[0], placed[1])
    for k in (0, 1):
        if second == "line" and best is not None:
            break  # (two lines: the other order only where the first fails; on parallel
            #        lines it ended at the same misfit, to 1 %, at twice the CPU)
        m_other = placed[k]
        if second == "line":
            # a point's light taken from a line's blur leaves the rest of the line: the
            # second line's first answer is its own fit on the lenslets the first line's
            # light (as the two points place them) leaves nearly alone
            own, near_light = amp2[k] * placed[k][:, 0], amp2[1 - k] * placed[1 - k][:, 0]
            part = dataclasses.replace(region, shared=np.union1d(
                region.shared, mom.ids[near_light > PL_PART_BAND * own]))
            first = ff.measure_lenslet(profile, geom, image, part, noise, others=others)
            if not (first.status == RegionStatus.OK and first.kind == "line"):
                continue
            m_other = _source_moments(profile, geom, mom, first.fitted_mm)
        amp = _amplitudes(mom.data, m_other, placed[1 - k])
        line = other = None
        for _ in range(PL_TURNS):
            new_line = turn(amp[0] * m_other, "line")
            if new_line is None:
                line = None
                break
            m_line = _source_moments(profile, geom, mom, new_line.fitted_mm)
            amp = _amplitudes(mom.data, m_other, m_line)
            new_other = turn(amp[1] * m_line, second)
            if new_other is None:
                line = None
                break
            m_other = _source_moments(profile, geom, mom, new_other.fitted_mm)
            amp = _amplitudes(mom.data, m_other, m_line)
            settled = line is not None and all(
                abs(new.distance_mm - old.distance_mm) < PL_SETTLE_SIGMAS * new.sigma_distance_mm
                for new, old in ((new_line, line), (new_other, other)))
            line, other = new_line, new_other
            if settled:
                break
        if line is None:
            continue
        rest, amp = _two_rest(mom, m_other, m_line)
        misfit = float(np.sqrt((rest * rest).sum()))
        if misfit < limit and (best is None or misfit < best.misfit):
            light = np.array([amp[0] * m_other[:, 0], amp[1] * m_line[:, 0]])
            best = ByTurns(other, line, misfit, light, mom.ids)
    if best is None or not PL_COUPLED_SIGMA:
        return best
    # each turn's σ holds the other source's light fixed; the two trade light
    f_other, f_line = coupling_factors(profile, geom, mom,
                                       (best.other.fitted_mm, best.line.fitted_mm))
    return best._replace(other=_sigma_times(best.other, f_other),
                         line=_sigma_times(best.line, f_line))


def _sigma_times(m: Measurement, factor: float) -> Measurement:
    """``m`` with its σ (distance and rim heights) × ``factor``."""
    return dataclasses.replace(m, sigma_distance_mm=m.sigma_distance_mm * factor,
                               sigma_y_mm=m.sigma_y_mm * factor)


def coupling_factors(profile: CameraProfile, geom: Geometry, mom: ff.LensletMoments,
                     fitted: tuple) -> tuple[float, ...]:
    """How much two sources that share a region's light widen each other's σ: for each
    source (a point's or a line's :attr:`Measurement.fitted_mm`), the σ of its log distance
    with every parameter of both free (both places, distances and brightnesses), over its σ
    with the other source held fixed (:func:`marginal_over_own`). The Jacobian is taken by
    differences of :func:`_source_moments` at the answers (the fits' difference steps,
    :func:`fastfit.point_steps`), in the units of the fits' residual (the data's moments less
    the two models, over the data's norm). 1 where that Jacobian is singular.

    Turns of two fits, each on the data less the other's light, end where both settle, but each
    fit's σ is conditional on the other's light: on system 1's point beside a line 12-16 ‰
    apart the point and the line err in opposite directions (docs/distance.md, "Two sources'
    σ with both free (stop 74)")."""
    frame = ff.SourceFrame(profile)
    steps = ff.point_steps(profile, geom, ff.lit_lenslets(mom))
    qs = [frame.fitted_params(f) for f in fitted]
    base = [_source_moments(profile, geom, mom, frame.fitted_source(q)) for q in qs]
    amp = _amplitudes(mom.data, base[0], base[1])
    cols: list[np.ndarray] = []
    blocks: list[list[int]] = []
    for k, q in enumerate(qs):
        h = np.r_[steps, steps[1:]] if len(q) == 5 else steps
        shifted = [q + h[j] * np.eye(len(q))[j] for j in range(len(q))]
        block = []
        for j, qj in enumerate(shifted):
            m = _source_moments(profile, geom, mom, frame.fitted_source(qj))
            block.append(len(cols))
            cols.append((amp[k] * (m - base[k]) / h[j] / mom.norm).ravel())
        block.append(len(cols))  # (its brightness)
        cols.append((base[k] / mom.norm).ravel())
        blocks.append(block)
    return marginal_over_own(np.array(cols).T, blocks)


def marginal_over_own(jac: np.ndarray, blocks: list[list[int]]) -> tuple[float, ...]:
    """For each block of columns of ``jac`` (a least-squares problem's Jacobian), the σ of
    its first parameter with all parameters free over its σ with only its own block free:
    √([(JᵀJ)⁻¹]₀₀ / [(J_bᵀJ_b)⁻¹]₀₀), at least 1 (1 where a matrix is singular). For two
    parameters of correlation ρ: 1/√(1 − ρ²)."""
    jtj = jac.T @ jac
    try:
        cov = np.linalg.inv(jtj)
        out = []
        for b in blocks:
            own = np.linalg.inv(jtj[np.ix_(b, b)])
            ratio = cov[b[0], b[0]] / own[0, 0]
            out.append(math.sqrt(ratio) if math.isfinite(ratio) and ratio > 1.0 else 1.0)
    except np.linalg.LinAlgError:
        return tuple(1.0 for _ in blocks)
    return tuple(out)


def by_turns_parts(pl: ByTurns, region: Region, new_id: int, stats: LensletStats,
                   lmap: LensletMap, pitch_px: float) -> tuple[Region, Region]:
    """``region``'s lenslets, each to the source of :func:`by_turns` that lights it more: the
    second source's region (``spot`` or ``line``, its answer's kind) with ``region``'s id and
    the line's with ``new_id``, each placed at its source's light centroid."""
    mine = np.isin(pl.ids, region.lenslets)
    first = mine & (pl.light[0] >= pl.light[1])
    masks = (first, mine & ~first) if first.any() and (mine & ~first).any() else (mine, mine)
    centres = lmap.centres_px[pl.ids]
    parts = [make_region(rid, kind, pl.ids[m], stats, lmap, pitch_px, 1, region.shared,
                         (centres * pl.light[k, :, None]).sum(0) / pl.light[k].sum())
             for k, (rid, kind, m) in enumerate(((region.region_id, pl.other.kind, masks[0]),
                                                 (new_id, "line", masks[1])))]
    return parts[0], parts[1]

