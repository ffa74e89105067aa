"""Learn an unknown ("black-box") main lens from captures of point sources at known distances.

docs/calibration.md, "Learning an unknown main lens". The learned lens is a
:class:`~lfcam.optics.lens.Prescription` of ideal surfaces (:func:`lfcam.optics.lens.ideal_lens`:
a front reference plane, one ideal surface of focal length f at ``principal_mm`` behind it, the
aperture stop at the exit pupil), plus the MLA distance ``d_in_mm``; every distance stage
(geometry, lenslet fit, exact inverse) runs on it unchanged.

The fit. A point source's blur on the lenslets fixes its **image point** (the apex of the
image-space cone) relative to the MLA, whatever lens made it: the lenslet fit
(:mod:`lfcam.measure.fastfit`, ``method="lenslet"``) run with any ideal lens that has the right
exit pupil returns the source whose ideal image is that apex. The lens parameters act only
through the object ↔ image map, so the stacked problem (lens parameters + every source's
lateral position) separates: each source is fitted freely (its lateral position is its own
nuisance parameter), its apex ``a_i`` (image point − MLA, mm) is read through the current
lens, and the lens parameters are fitted to the apexes by Gauss–Newton:

    a_i = principal + v(D_i + principal; f) − d_in,     v(u; f) = f·u / (u − f)

with D_i the known plane distance. The geometry (micro-image centre → lenslet centre) depends on
the lens, so measure → fit is iterated until the target distances settle (``TOL_DISTANCE_REL``).

Terms: ``d_in_mm`` and ``principal_mm`` are always fitted; ``focal_length_mm`` is fitted with
the stated value as a prior (``FOCAL_PRIOR_REL``) and kept free only where the data support it
(Bayesian information criterion against the fit with f fixed at the stated value). σ and the
covariance come from the Jacobian and the residual (scaled by the reduced χ² when that exceeds
the measurement σ).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from lfcam.calibrate.learned import (
    LEARNED_METHOD,
    MAX_SOURCES,
    PARAMS,
    surfaces_from_json,
    surfaces_to_json,
    validate_learned,
)
from lfcam.camera import CameraProfile, MainLens
from lfcam.errors import CalibrationError, LfcamError
from lfcam.optics.lens import Prescription, ideal_lens
from lfcam.progress import Progress
from lfcam.status import RegionStatus

FOCAL_PRIOR_REL = 0.05  # a barrel's focal length is good to a few %
MAX_ITERATIONS = 12
TOL_DISTANCE_REL = 1e-3  # rounds stop when no target distance moves by more
MIN_PLANES = 3
MIN_RELATIVE_SPREAD = 0.25  # planes must span ≥ 25 % in 1/distance (vergence) of the nearest
LSA_BOUND_F = 0.01  # |marginal longitudinal spherical aberration| ≤ 1 % of f
LSA_TOL_F = 1e-4
MERGE_RATIO = 5.0  # a source fitting this many times worse than the median one: merged light
MERGE_MISFIT = 0.2
TRIM_SHARE = 0.2
SEARCH_EVALUATIONS = 12  # measure rounds per 1-D search (bounded Brent)
PUPIL_MAG_BOUND = 1.6  # exit-pupil diameter within [1/1.6, 1.6] × f/N
PUPIL_LOG_TOL = 0.008
F_CRITICAL = 4.0  # ~95 % for one extra parameter
SEED_D_IN_F = (1.04, 1.1, 1.25)  # seed MLA distances (focal lengths behind the principal plane)
APEX_FLOOR_MM = 1e-4  # σ floor of one apex (numerical noise of the lenslet fit)


@dataclass(frozen=True)
class Target:
    """One target capture: a linear grey image and the plane's distance from the lens front."""

    image: np.ndarray
    distance_mm: float
    name: str = ""


@dataclass(frozen=True)
class SourceResidual:
    """One target source measured freely with the learned lens."""

    target: str
    distance_mm: float  # the known plane distance
    fitted_mm: float  # the source's distance measured with the learned lens
    offset_mm: float
    x_px: float
    y_px: float
    apex_residual_mm: float  # image-point misfit of the lens fit (mm, image space)

    @property
    def error_pct(self) -> float:
        """(fitted − known) / known, %."""
        return 100.0 * (self.fitted_mm / self.distance_mm - 1.0)


@dataclass(frozen=True)
class LensFit:
    """The learned lens, its parameters with σ, the kept terms and the per-source residuals."""

    prescription: Prescription
    d_in_mm: float
    names: tuple[str, ...]
    values: np.ndarray
    sigma: np.ndarray
    covariance: np.ndarray
    kept: tuple[str, ...]
    why: dict
    residuals: tuple[SourceResidual, ...]
    n_planes: int
    n_sources: int
    iterations: int
    exit_pupil_mm: float | None
    f_number: float
    spherical_lsa_mm: float = 0.0
    spherical_zone_lsa_mm: float | None = None
    exit_pupil_diameter_mm: float = math.nan

    def param(self, name: str) -> float:
        """A parameter's value by name."""
        return float(self.values[self.names.index(name)])

    def to_dict(self) -> dict:
        """The calibration JSON's ``learned_lens`` block."""
        from lfcam.optics.zmx import prescription_to_toml_dict

        return {
            "model": "ideal-lens",
            "measured_with": LEARNED_METHOD,
            "surfaces": surfaces_to_json(
                prescription_to_toml_dict(self.prescription)["main_lens"]["surfaces"]),
            "d_in_mm": float(self.d_in_mm),
            "f_number": float(self.f_number),
            "exit_pupil_mm": self.exit_pupil_mm,
            "spherical_lsa_mm": float(self.spherical_lsa_mm),
            "spherical_zone_lsa_mm": self.spherical_zone_lsa_mm,
            "exit_pupil_diameter_mm": float(self.exit_pupil_diameter_mm),
            "parameters": {n: float(v) for n, v in zip(self.names, self.values, strict=True)},
            "sigma": {n: float(v) for n, v in zip(self.names, self.sigma, strict=True)},
            "covariance": self.covariance.tolist(),
            "kept_terms": list(self.kept),
            "why": self.why,
            "n_planes": self.n_planes,
            "n_sources": self.n_sources,
            "residuals": [
                {"target": r.target, "distance_mm": r.distance_mm, "fitted_mm": r.fitted_mm,
                 "offset_mm": r.offset_mm, "x_px": r.x_px, "y_px": r.y_px,
                 "apex_residual_mm": r.apex_residual_mm}
                for r in self.residuals
            ],
        }


# ----------------------------------------------------------------------------- the model


def spherical_coefficients(profile: CameraProfile, focal_length_mm: float, lsa_mm: float,
                           zone_lsa_mm: float | None = None) -> tuple[float, ...]:
    """Ideal-surface coefficients (a1 in mm⁻³, a2 in mm⁻⁵) giving a longitudinal spherical
    aberration ``lsa_mm`` for the marginal ray and ``zone_lsa_mm`` for the ray at 1/√2 of
    the pupil radius, object at infinity. A ray at height r crosses the axis at
    1/P(r) ≈ f − f²·(a1 r² + a2 r⁴); with r_m = f / 2N the entrance-pupil radius,
    A = a1 r_m², B = a2 r_m⁴: A + B = −LSA_m / f², A/2 + B/4 = −LSA_z / f². Without a zone
    value the aberration is pure a1 (LSA_z = LSA_m / 2)."""
    if lsa_mm == 0.0 and not zone_lsa_mm:
        return ()
    f = focal_length_mm
    r = 0.5 * f / profile.main_lens.black_box.f_number
    zone = 0.5 * lsa_mm if zone_lsa_mm is None else zone_lsa_mm
    b = 2.0 * (2.0 * zone - lsa_mm) / (f * f)
    a = -lsa_mm / (f * f) - b
    return (a / r**2,) if b == 0.0 else (a / r**2, b / r**4)


def build_lens(profile: CameraProfile, focal_length_mm: float, principal_mm: float,
               d_in_mm: float, exit_pupil_diameter_mm: float | None = None,
               lsa_mm: float = 0.0, zone_lsa_mm: float | None = None) -> CameraProfile:
    """``profile`` with the ideal lens of these parameters and the MLA at ``d_in_mm``.

    The exit pupil lies the black box's ``exit_pupil_mm`` in front of the MLA when the profile
    states it, else on the principal plane. Its diameter is ``exit_pupil_diameter_mm``,
    default f / N (a pupil magnification of 1: what the image side sees does not then depend
    on where the fit has put the principal plane). Spherical aberration: see
    :func:`spherical_coefficients`.
    """
    box = profile.main_lens.black_box
    if box is None:
        raise CalibrationError(
            f"profile {profile.name!r}: learning a lens needs the black-box [main_lens] form "
            "(focal_length_mm, f_number)"
        )
    xp = None if box.exit_pupil_mm is None else d_in_mm - box.exit_pupil_mm
    d_xp = (box.focal_length_mm / box.f_number if exit_pupil_diameter_mm is None
            else exit_pupil_diameter_mm)
    try:
        rx = ideal_lens(focal_length_mm, None, principal_mm, xp,
                        spherical=spherical_coefficients(profile, focal_length_mm, lsa_mm,
                                                         zone_lsa_mm),
                        name=f"learned ideal lens f {focal_length_mm:.3f} mm",
                        exit_pupil_diameter_mm=d_xp)
    except LfcamError as exc:
        raise CalibrationError(f"the lens fit left the physical range: {exc}") from None
    lens = MainLens(prescription=rx)
    mla = replace(profile.mla, distance_mm=float(d_in_mm), focus_mm=None)
    return replace(profile, main_lens=lens, mla=mla)


def apex_mm(focal_length_mm: float, principal_mm: float, d_in_mm: float,
            distance_mm: np.ndarray) -> np.ndarray:
    """Image point − MLA (mm, +z toward the sensor) of sources ``distance_mm`` in front of the
    lens front, for the ideal lens."""
    u = np.asarray(distance_mm, dtype=np.float64) + principal_mm
    v = focal_length_mm * u / (u - focal_length_mm)
    return principal_mm + v - d_in_mm


def distance_of_apex(focal_length_mm: float, principal_mm: float, d_in_mm: float,
                     apex: np.ndarray) -> np.ndarray:
    """Inverse of :func:`apex_mm`: the source distance whose image point is ``apex``."""
    v = np.asarray(apex, dtype=np.float64) + d_in_mm - principal_mm
    with np.errstate(divide="ignore", invalid="ignore"):
        u = focal_length_mm * v / (v - focal_length_mm)
    return u - principal_mm


def distance_gradient(values: np.ndarray, apex: float) -> np.ndarray:
    """∂ distance / ∂ (f, principal, d_in) at fixed measured image point (central
    differences of :func:`distance_of_apex`)."""
    g = np.zeros(3)
    for j, h in enumerate((1e-4, 1e-4, 1e-5)):
        p, m = np.array(values, dtype=np.float64), np.array(values, dtype=np.float64)
        p[j] += h
        m[j] -= h
        g[j] = (distance_of_apex(*p, apex) - distance_of_apex(*m, apex)) / (2 * h)
    return g


def _bounded(q: np.ndarray, f_label: float, d_in_min: float = -math.inf) -> np.ndarray:
    """Keep a Gauss–Newton iterate physical: f within [0.7, 1.4] of the label, the principal
    plane from 1 f in front of the lens front to 1.5 f behind it, the MLA 1.0001–3 f behind
    the principal plane and not in front of ``d_in_min`` (a stated exit pupil stays behind the
    lens front)."""
    f = float(np.clip(q[0], 0.7 * f_label, 1.4 * f_label))
    h = float(np.clip(q[1], -1.0 * f_label, 1.5 * f_label))
    d = float(np.clip(q[2] - h, 1.0001 * f, 3.0 * f)) + h
    return np.array([f, h, max(d, d_in_min)])


def _solve(d: np.ndarray, a: np.ndarray, w: np.ndarray, q0: np.ndarray, free: np.ndarray,
           f_prior: float | None, robust: bool = False,
           d_in_min: float = -math.inf) -> tuple[np.ndarray, np.ndarray, float]:
    """Weighted Gauss–Newton of ``apex_mm`` on (f, principal, d_in); parameters not ``free``
    stay at ``q0``. ``robust``: Huber weights (1.5 × the residuals' robust scale) so that one
    badly measured plane does not drag an early round. Returns (q, Jacobian over the free
    parameters, χ² without the prior)."""
    q = np.array(q0, dtype=np.float64)
    idx = np.flatnonzero(free)
    jac = np.zeros((len(d), len(idx)))
    label = f_prior if f_prior is not None else float(q0[0])
    for _ in range(50):
        r = (a - apex_mm(*q, d)) * w
        ww = w
        if robust:
            scale = max(1.4826 * float(np.median(np.abs(r - np.median(r)))), 1.0)
            hub = np.minimum(1.0, 1.5 * scale / np.maximum(np.abs(r), 1e-300))
            ww = w * np.sqrt(hub)
            r = r * np.sqrt(hub)
        cols = []
        for j in idx:
            h = 1e-6 * max(1.0, abs(q[j]))
            qp = q.copy()
            qp[j] += h
            cols.append((apex_mm(*qp, d) - apex_mm(*q, d)) * ww / h)
        jac = np.column_stack(cols)
        rows_j, rows_r = [jac], [r]
        if f_prior is not None and free[0]:
            pj = np.zeros((1, len(idx)))
            pj[0, 0] = 1.0 / (FOCAL_PRIOR_REL * f_prior)
            rows_j.append(pj)
            rows_r.append(np.array([(f_prior - q[0]) / (FOCAL_PRIOR_REL * f_prior)]))
        jj, rr = np.vstack(rows_j), np.concatenate(rows_r)
        step, *_ = np.linalg.lstsq(jj, rr, rcond=None)

        def cost(qq: np.ndarray, ww: np.ndarray = ww) -> float:
            res = (a - apex_mm(*qq, d)) * ww
            out = float(res @ res)
            if f_prior is not None and free[0]:
                out += ((f_prior - qq[0]) / (FOCAL_PRIOR_REL * f_prior)) ** 2
            return out if math.isfinite(out) else math.inf

        c0 = cost(q)
        for _ in range(30):  # halve the step until the cost drops (damped Gauss–Newton)
            q_try = q.copy()
            q_try[idx] += step
            q_new = _bounded(q_try, label, d_in_min)
            if cost(q_new) <= c0:
                break
            step = 0.5 * step
        else:
            break
        done = np.all(np.abs(q_new - q) < 1e-10 * np.maximum(1.0, np.abs(q)))
        q = q_new
        if done:
            break
    r = (a - apex_mm(*q, d)) * w
    return q, jac, float(r @ r)


# ----------------------------------------------------------------------------- measuring


@dataclass
class _Source:
    target: str
    distance_mm: float
    fitted_mm: float
    offset_mm: float
    x_px: float
    y_px: float
    sigma_mm: float
    misfit: float


def _measure(profile: CameraProfile, calibration, targets: list[Target]) -> list[_Source]:
    """Every lit source of every target, fitted freely as a point with ``profile``'s lens
    (the lenslet fit, :func:`lfcam.measure.fastfit.fit_lenslet_point`)."""
    from lfcam.measure import find_regions, lenslet_stats, prepare_geometry
    from lfcam.measure.fastfit import fit_lenslet_point

    out = []
    geometries: dict = {}
    for t in targets:
        shape = t.image.shape
        geom = geometries.get(shape)
        if geom is None:
            geom = geometries[shape] = prepare_geometry(profile, calibration, shape)
        img = np.asarray(t.image, dtype=np.float64)
        regions = find_regions(lenslet_stats(img, geom.lmap), geom.lmap, geom.pitch_px)
        if not regions:
            raise CalibrationError(
                f"target {t.name} ({t.distance_mm:g} mm): no lit source found (or its blur is "
                "too small to measure: a plane near the focused distance)")
        lines = [r for r in regions if r.kind == "line"]
        if lines:
            x, y = lines[0].centroid_px
            raise CalibrationError(
                f"target {t.name} ({t.distance_mm:g} mm): the light near ({x:.0f}, {y:.0f}) px "
                "is elongated: sources merge (space them farther apart) or one is not a point")
        found = []
        unresolved = 0
        for reg in regions:
            try:
                fit = fit_lenslet_point(profile, geom, img, reg, polish_above=0.0)  # always
            except (LfcamError, ArithmeticError, ValueError, np.linalg.LinAlgError):
                continue  # this lens cannot place the source: the region counts as unfitted
            if not fit.ok:
                unresolved += fit.reason == RegionStatus.NEAR_FOCUS
                continue
            src = fit.source_mm
            found.append(_Source(t.name, float(t.distance_mm),
                                 profile.main_lens.front_vertex_z_mm - float(src[2]),
                                 float(np.hypot(src[0], src[1])), float(reg.centroid_px[0]),
                                 float(reg.centroid_px[1]), float(fit.sigma_distance_mm),
                                 float(fit.misfit)))
        if not found and unresolved == len(regions):
            continue  # every blur too small to fix a distance (a plane near focus): no data
        if not found:
            raise CalibrationError(
                f"target {t.name} ({t.distance_mm:g} mm): none of its {len(regions)} light "
                "region(s) fits a point source")
        out.extend(found)
    return out


def _misfit_limit(sources: list[_Source]) -> float:
    misfits = np.array([s_.misfit for s_ in sources])
    return max(MERGE_RATIO * float(np.nanmedian(misfits)), MERGE_MISFIT)


def _inliers(sources: list[_Source]) -> list[_Source]:
    """Sources whose point fit is not far worse than the rest (early rounds: a lens still far
    from the truth may fail on a few)."""
    limit = _misfit_limit(sources)
    good = [s_ for s_ in sources if s_.misfit <= limit]
    return good if len(good) >= MIN_PLANES else sources


def _check_merged(sources: list[_Source]) -> None:
    """With the learned lens, a source fitting far worse than the others is merged light."""
    limit = _misfit_limit(sources)
    med = float(np.nanmedian([s_.misfit for s_ in sources]))
    for s_ in sources:
        if s_.misfit > limit:
            raise CalibrationError(
                f"target {s_.target} ({s_.distance_mm:g} mm): the light near ({s_.x_px:.0f}, "
                f"{s_.y_px:.0f}) px does not fit one point source (misfit {s_.misfit:.2f}, the "
                f"others' median {med:.2f}): its sources merge; space them farther apart")


def _apexes(profile_values: np.ndarray, sources: list[_Source]) -> tuple[np.ndarray, np.ndarray]:
    """Image points (− MLA) and their σ of measured sources, read through the lens they were
    measured with."""
    d = np.array([s.fitted_mm for s in sources])
    a = apex_mm(*profile_values, d)
    sig = np.array([s.sigma_mm if np.isfinite(s.sigma_mm) else 0.0 for s in sources])
    da = np.abs(apex_mm(*profile_values, d + np.maximum(sig, 1e-9)) - a)
    da = np.where(sig > 0, da, 0.0)
    return a, np.maximum(da, APEX_FLOOR_MM)


def _total_misfit(sources: list[_Source]) -> float:
    """Σ misfit² of the sources' lenslet fits (relative moment residuals), the worst
    ``TRIM_SHARE`` left out (a source the current lens fails on must not steer a search)."""
    m = np.sort([s_.misfit**2 for s_ in sources if np.isfinite(s_.misfit)])
    keep = max(1, int(math.ceil((1.0 - TRIM_SHARE) * len(m))))
    return float(m[:keep].sum())


def _check_targets(targets: list[Target], profile: CameraProfile) -> None:
    if not targets:
        raise CalibrationError("no target captures given")
    expected = (profile.sensor.height_px, profile.sensor.width_px)
    f = profile.main_lens.black_box.focal_length_mm
    for t in targets:
        d = t.distance_mm
        if isinstance(d, bool) or not isinstance(d, (int, float, np.floating)) or not (
                math.isfinite(d) and d > 0):
            raise CalibrationError(f"target {t.name}: distance_mm must be a positive number, "
                                   f"got {d!r}")
        if d <= 1.2 * f:
            raise CalibrationError(f"target {t.name}: {d} mm is too close to a {f:g} mm lens "
                                   "(at least 1.2 focal lengths)")
        if np.ndim(t.image) != 2 or tuple(np.shape(t.image)) != expected:
            raise CalibrationError(
                f"target {t.name}: capture is {np.shape(t.image)[::-1]} px, the profile's "
                f"sensor is {expected[1]}×{expected[0]} px")
    planes = sorted({float(t.distance_mm) for t in targets})
    if len(planes) < MIN_PLANES:
        raise CalibrationError(
            f"{len(planes)} distinct target plane(s): the lens model ({', '.join(PARAMS)}) "
            f"needs at least {MIN_PLANES} planes at different distances")
    vergence = 1.0 / np.array(planes)
    if (vergence.max() - vergence.min()) < MIN_RELATIVE_SPREAD * vergence.max():
        raise CalibrationError(
            f"the target planes ({planes[0]:g}–{planes[-1]:g} mm) are too close together to "
            "separate the focal length from the MLA distance: spread them (e.g. 300 mm to "
            "3 m)")


def fit_lens(profile: CameraProfile, calibration, targets: list[Target], *,
             progress: Progress | None = None, search_spherical: bool = True) -> LensFit:
    """Learn the black-box main lens and the MLA distance from target captures.

    Parameters
    ----------
    profile : CameraProfile
        Black-box form (``main_lens.black_box`` set): focal length, f-number, optional exit
        pupil; MLA and sensor as built.
    calibration : Calibration
        The white-image calibration (micro-image centres); its ``d_in_mm`` is ignored.
    targets : list of Target
        Linear grey captures of point sources on planes at known distances from the lens
        front (lateral positions unknown), one plane a capture.
    progress : Progress, optional
        Called as ``progress("lens fit", round, round + 1)`` after every measure → fit round.
    search_spherical : bool
        Try the spherical-aberration term (a 1-D search over the marginal LSA, each step a
        measure → fit round; kept by an F-test on the lenslet-fit misfits). ``False``: a
        first-order lens only (≈ 10× faster).

    Returns
    -------
    LensFit

    Raises
    ------
    CalibrationError
        Not a black-box profile; too few or too closely spaced planes; a capture of the wrong
        size, with no lit source, or whose sources merge; a fit that does not converge.
    """
    if not profile.main_lens.is_black_box:
        raise CalibrationError(
            f"profile {profile.name!r}: --targets learns a black-box main lens; this profile "
            "already states its lens")
    targets = list(targets)
    _check_targets(targets, profile)
    box = profile.main_lens.black_box
    cal = replace(calibration, d_in_mm=None, d_in_method=None)
    f0 = box.focal_length_mm
    try:
        d_in0 = profile.d_in_mm
    except LfcamError:
        # no MLA distance given: seeds with the MLA a little behind the rear focal point (every
        # image point behind the seed's F′, on both sides of the real focus, has a real
        # source through the seed lens), the best explaining one kept
        d_in0 = None
    d_in_min = -math.inf
    free = np.array([True, True, True])
    calls = [0]

    def tick(stage: str) -> None:
        calls[0] += 1
        if progress:
            progress(stage, calls[0], calls[0] + 1)

    def converge(q: np.ndarray, lsa: float, rounds: int,
                 zone: float | None = None) -> tuple[np.ndarray, list, int]:
        """Measure → fit rounds at a fixed cone and aberration until the distances the lens
        gives the target image points change by less than ``TOL_DISTANCE_REL`` (or stop
        shrinking: the lenslet fits' numerical noise)."""
        moved, last = math.inf, math.inf
        for it in range(1, rounds + 1):
            srcs = _measure(build_lens(profile, *q, d_xp, lsa, zone), cal, targets)
            if len(srcs) > MAX_SOURCES:
                raise CalibrationError(f"{len(srcs)} target sources: at most {MAX_SOURCES}")
            use = _inliers(srcs)
            d = np.array([s_.distance_mm for s_ in use])
            a, sa = _apexes(q, use)
            q_new, _, _ = _solve(d, a, 1.0 / sa, q, free, f0, robust=True, d_in_min=d_in_min)
            with np.errstate(invalid="ignore", divide="ignore"):
                moved = float(np.nanmax(np.abs(distance_of_apex(*q_new, a)
                                               / distance_of_apex(*q, a) - 1.0)))
            q = q_new
            tick("lens fit")
            if moved < TOL_DISTANCE_REL or (it >= 3 and moved >= 0.7 * last
                                            and moved < 100 * TOL_DISTANCE_REL):
                return q, srcs, it
            last = moved
        if rounds >= MAX_ITERATIONS:
            raise CalibrationError(
                f"the lens fit did not settle in {MAX_ITERATIONS} rounds (target distances "
                f"still moving by {100 * moved:.3g} %)")
        return q, srcs, rounds

    from scipy.optimize import minimize_scalar

    # 1. seed: the MLA distance (focal lengths behind the principal plane) whose lens explains
    # the target blurs best, with the cone of pupil magnification 1
    d_xp = f0 / box.f_number
    if d_in0 is None:
        seeds = []
        for k in SEED_D_IN_F:
            qk = np.array([f0, 0.0, k * f0])
            srcs = _measure(build_lens(profile, *qk, d_xp), cal, targets)
            tick("seed")
            seeds.append((_total_misfit(srcs), k))
        d_in0 = min(seeds)[1] * f0
    q = np.array([f0, 0.0, d_in0])
    # 2. first-order rounds, 3. the exit-pupil diameter (f/N times the unknown pupil
    # magnification) of least lenslet-fit misfit at that lens, 4. rounds again
    q, sources, iteration = converge(q, 0.0, MAX_ITERATIONS)

    def aperture_misfit(log_m: float) -> float:
        srcs = _measure(build_lens(profile, *q, math.exp(log_m) * f0 / box.f_number), cal,
                        targets)
        tick("exit pupil")
        return _total_misfit(srcs)

    res = minimize_scalar(aperture_misfit, bounds=(-math.log(PUPIL_MAG_BOUND),
                                                   math.log(PUPIL_MAG_BOUND)),
                          method="bounded", options={"xatol": PUPIL_LOG_TOL,
                                                     "maxiter": SEARCH_EVALUATIONS})
    d_xp = math.exp(float(res.x)) * f0 / box.f_number
    q, sources, iteration = converge(q, 0.0, MAX_ITERATIONS)
    misfit0 = _total_misfit(sources)
    lsa, zone, why_sa, why_zone = 0.0, None, "not tried", "not tried"
    if search_spherical:
        n_src = len(sources)
        cache: dict = {}

        def search(objective, lo: float, hi: float):
            return minimize_scalar(objective, bounds=(lo, hi), method="bounded",
                                   options={"xatol": LSA_TOL_F, "maxiter": SEARCH_EVALUATIONS})

        def f_test(before: float, after: float) -> float:
            # one extra parameter shared by n_src sources, on their lenslet-fit misfits
            return (before - after) / max(after / max(n_src - 1, 1), 1e-300)

        def objective_m(x: float) -> float:
            qq, srcs, _ = converge(q, x * f0, 2)
            cache[("m", x)] = qq
            return _total_misfit(srcs)

        res = search(objective_m, -LSA_BOUND_F, LSA_BOUND_F)
        misfit1 = float(res.fun)
        f1 = f_test(misfit0, misfit1)
        why_sa = (f"{'kept' if f1 > F_CRITICAL else 'dropped'}: misfit² {misfit0:.4g} "
                  f"without, {misfit1:.4g} at LSA {float(res.x) * f0:+.4f} mm (F = {f1:.3g}, "
                  f"limit {F_CRITICAL})")
        if f1 > F_CRITICAL and ("m", res.x) in cache:
            lsa = float(res.x) * f0
            q = cache[("m", res.x)]

            def objective_z(x: float) -> float:
                qq, srcs, _ = converge(q, lsa, 2, 0.5 * lsa + x * f0)
                cache[("z", x)] = qq
                return _total_misfit(srcs)

            res2 = search(objective_z, -LSA_BOUND_F, LSA_BOUND_F)
            misfit2 = float(res2.fun)
            f2 = f_test(misfit1, misfit2)
            z_val = 0.5 * lsa + float(res2.x) * f0
            why_zone = (f"{'kept' if f2 > F_CRITICAL else 'dropped'}: misfit² {misfit1:.4g} "
                        f"with the r² term alone, {misfit2:.4g} with the zone at LSA "
                        f"{z_val:+.4f} mm (F = {f2:.3g}, limit {F_CRITICAL})")
            if f2 > F_CRITICAL and ("z", res2.x) in cache:
                zone = z_val
                q = cache[("z", res2.x)]
            q, sources, _ = converge(q, lsa, MAX_ITERATIONS, zone)
    # final: measured with the learned lens; keep terms by BIC, σ from the Jacobian
    _check_merged(sources)
    used = sorted({s_.distance_mm for s_ in sources})
    idle = sorted({float(t.distance_mm) for t in targets} - set(used))
    if len(used) < MIN_PLANES:
        raise CalibrationError(
            f"only {len(used)} target plane(s) have blurs that fix a distance; the sources at "
            f"{', '.join(f'{d:g}' for d in idle)} mm light too few lenslets (a plane near the "
            "focused distance): add planes nearer the camera")
    d = np.array([s.distance_mm for s in sources])
    a, sa = _apexes(q, sources)
    w = 1.0 / sa
    q_free, jac, chi2_free = _solve(d, a, w, q, free, None, d_in_min=d_in_min)
    fixed = np.array([False, True, True])
    q_fix, jac_fix, chi2_fix = _solve(d, a, w, np.array([f0, q[1], q[2]]), fixed, None,
                                      d_in_min=d_in_min)
    n = len(d)
    bic_free = n * math.log(max(chi2_free, 1e-300) / n) + 3 * math.log(n)
    bic_fix = n * math.log(max(chi2_fix, 1e-300) / n) + 2 * math.log(n)
    keep_f = bic_free < bic_fix
    why = {"focal_length_mm": (
        f"{'kept' if keep_f else 'fixed at the stated value'}: BIC {bic_free:.1f} free vs "
        f"{bic_fix:.1f} fixed"),
        "principal_mm": "always fitted", "d_in_mm": "always fitted"}
    if keep_f:
        q, jac, chi2, n_par = q_free, jac, chi2_free, 3
    else:
        q, jac, chi2, n_par = q_fix, jac_fix, chi2_fix, 2
    edge = np.array([[0.7, -1.0], [1.4, 1.5]]) * f0
    if np.any(np.abs(q[[0, 1]] - edge) < 1e-6 * f0):
        raise CalibrationError(
            f"the lens fit ran into its bounds (f {q[0]:.4g} mm for a {f0:g} mm label, "
            f"principal plane {q[1]:.4g} mm, MLA {q[2]:.4g} mm): the targets do not describe "
            "this lens; check the plane distances and the profile")
    dof = n - n_par
    if dof <= 0:
        raise CalibrationError(
            f"{n} measured target sources for {n_par} lens parameters: add sources or planes")
    scale = max(chi2 / dof, 1.0)
    jtj = jac.T @ jac
    try:
        cov_free = np.linalg.inv(jtj) * scale
    except np.linalg.LinAlgError:
        raise CalibrationError("the targets cannot determine the lens (singular fit): spread "
                               "the planes in distance") from None
    cov = np.zeros((3, 3))
    idx = [0, 1, 2] if keep_f else [1, 2]
    cov[np.ix_(idx, idx)] = cov_free
    sigma = np.sqrt(np.diag(cov))
    if not (np.isfinite(sigma).all() and sigma[2] < 0.05 * q[2]):
        raise CalibrationError("the targets cannot determine the lens: the MLA distance is "
                               f"uncertain to {sigma[2]:.3g} mm; spread the planes in distance")
    learned = build_lens(profile, *q, d_xp, lsa, zone)
    fitted = distance_of_apex(*q, a)
    resid = [
        SourceResidual(s.target, s.distance_mm, float(fd), s.offset_mm, s.x_px, s.y_px,
                       float(ai - apex_mm(*q, s.distance_mm)))
        for s, fd, ai in zip(sources, fitted, a, strict=True)
    ]
    kept = tuple(n_ for n_, k in zip(PARAMS, (keep_f, True, True), strict=True) if k)
    if idle:
        why["planes_without_distance"] = (
            f"{', '.join(f'{d:g}' for d in idle)} mm: every source there lights too few "
            "lenslets to fix its distance (blur within 2×2 lenslets); not used")
    why["spherical_lsa_mm"] = why_sa
    why["spherical_zone_lsa_mm"] = why_zone
    why["exit_pupil_diameter_mm"] = (
        f"always fitted: {d_xp:.4f} mm = {d_xp * box.f_number / f0:.4f} × f/N, least "
        "lenslet-fit misfit")
    if lsa:
        kept = (*kept, "spherical_lsa_mm")
    if zone is not None:
        kept = (*kept, "spherical_zone_lsa_mm")
    return LensFit(
        prescription=learned.main_lens.as_prescription, d_in_mm=float(q[2]), names=PARAMS,
        values=q.copy(), sigma=sigma, covariance=cov, kept=kept, why=why,
        residuals=tuple(resid), n_planes=len({s.distance_mm for s in sources}),
        n_sources=len(sources), iterations=calls[0], exit_pupil_mm=box.exit_pupil_mm,
        f_number=box.f_number, spherical_lsa_mm=lsa, exit_pupil_diameter_mm=d_xp,
        spherical_zone_lsa_mm=zone)


def read_targets(csv_path, profile: CameraProfile) -> list[Target]:
    """Read ``targets.csv`` (columns ``capture,distance_mm``; capture paths relative to the
    CSV's folder) and load every capture as a linear grey image (:mod:`lfcam.io`).

    Raises
    ------
    CalibrationError
        A missing CSV or capture, missing columns, an empty table, or a distance that is not a
        positive number (the message names the row).
    """
    import csv
    from pathlib import Path

    from lfcam.io import load_capture

    path = Path(csv_path)
    if not path.is_file():
        raise CalibrationError(f"targets file not found: {path}")
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
            header = rows[0].keys() if rows else []
    except (UnicodeDecodeError, csv.Error) as exc:
        raise CalibrationError(f"{path}: not a readable CSV ({exc})") from None
    if not rows:
        raise CalibrationError(f"{path}: no target rows (columns capture,distance_mm)")
    if not {"capture", "distance_mm"} <= set(header):
        raise CalibrationError(f"{path}: needs the columns capture,distance_mm")
    if len(rows) > 1000:
        raise CalibrationError(f"{path}: {len(rows)} targets, at most 1000")
    out = []
    for i, row in enumerate(rows, start=2):
        where = f"{path.name} line {i}"
        try:
            dist = float(row["distance_mm"])
        except (TypeError, ValueError):
            raise CalibrationError(
                f"{where}: distance_mm {row['distance_mm']!r} is not a number") from None
        if not (math.isfinite(dist) and dist > 0):
            raise CalibrationError(f"{where}: distance_mm must be positive, got {dist}")
        cap_path = path.parent / (row["capture"] or "").strip()
        if not row["capture"] or not cap_path.is_file():
            raise CalibrationError(f"{where}: target capture not found: {cap_path}")
        img = load_capture(cap_path, profile).grey()
        out.append(Target(np.asarray(img, dtype=np.float64), dist, cap_path.name))
    return out


# ----------------------------------------------------------------------------- using it


def learned_profile(profile: CameraProfile, learned: dict) -> CameraProfile:
    """``profile`` with the calibration's learned lens and MLA distance (block of
    :meth:`LensFit.to_dict`, validated by the calibration loader)."""
    rx = surfaces_from_json(learned["surfaces"])
    mla = replace(profile.mla, distance_mm=float(learned["d_in_mm"]), focus_mm=None)
    return replace(profile, main_lens=MainLens(prescription=rx), mla=mla)


def default_method(profile: CameraProfile, calibration) -> str:
    """The distance stage's measurement method when none is asked for: the one the
    calibration's learned lens was learned with, for a black-box profile; else
    ``lightfield``."""
    learned = None if calibration is None else calibration.learned_lens
    if profile.main_lens.is_black_box and learned:
        return str(learned.get("measured_with", LEARNED_METHOD))
    return "lightfield"


def resolve_profile(profile: CameraProfile, calibration) -> CameraProfile:
    """The profile the distance stage runs on: a black-box profile gets the calibration's
    learned lens; a profile that states its lens is returned unchanged.

    Raises
    ------
    CalibrationError
        A black-box profile whose calibration holds no learned lens.
    """
    learned = None if calibration is None else getattr(calibration, "learned_lens", None)
    if profile.main_lens.is_black_box:
        if learned is None:
            raise CalibrationError(
                f"profile {profile.name!r} describes its main lens as a black box (focal "
                "length, f-number): the calibration holds no learned lens; calibrate with "
                "--targets first")
        return learned_profile(profile, learned)
    return profile


def calibration_sigma_mm(learned: dict, profile: CameraProfile, distance_mm: float) -> float:
    """σ of a region's distance from the learned lens's parameter covariance: the measured
    image point held fixed, the distance re-inverted with perturbed parameters (first order)."""
    names = learned["parameters"]
    values = np.array([names[n] for n in PARAMS])
    cov = np.asarray(learned["covariance"], dtype=np.float64)
    if not math.isfinite(distance_mm):
        return float("nan")
    apex = float(apex_mm(*values, distance_mm))
    g = distance_gradient(values, apex)
    var = float(g @ cov @ g)
    return math.sqrt(max(var, 0.0))


__all__ = ["LensFit", "SourceResidual", "Target", "apex_mm", "build_lens",
           "calibration_sigma_mm", "default_method", "distance_of_apex", "fit_lens",
           "learned_profile", "read_targets", "resolve_profile", "validate_learned"]
