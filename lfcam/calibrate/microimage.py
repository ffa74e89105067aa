"""Micro-image model of a white image, and own-light centroids of touching micro-images.

Why a model
-----------
A micro-image's centre (docs/calibration.md; the renderer's truth) is the intensity centroid of
the light *that lenslet* puts on the sensor. When micro-images are separated by a dark gap, a
window that holds one whole micro-image measures it exactly. When they touch (the seed's
system 1: disc radius 7.98 px in a 16.4 px lattice) or overlap (system 2, docs/calibration.md),
the pixels along each seam hold light of two lenslets, and no window can separate it: the
cell-window centroid is then biased by the brightness gradient across the micro-image (cos⁴
and vignetting make the side nearer the optical axis brighter), 0.07 px RMS on system 1 and
0.3 px on system 2.

The model
---------
Micro-image k is a disc of radius R centred at ``d_k`` (the geometric centre, not the
centroid) with a linear brightness ``a_k + g_k·(x − d_k)``; its edge is a linear ramp of
half-width ``w`` (pixel area coverage of the edge, widened by the blur of the lenslet aperture
across the pupil). R and w are global, fitted on a central crop. The white image is modelled
as the sum of all discs:  M(x) = Σ_k (a_k + g_k·(x − d_k))·cov(|x − d_k|; R, w).

Per-lens parameters (d_k, a_k, g_k) are fitted by damped block-Jacobi Gauss–Newton (each lens
against the data minus its neighbours' current model; all lenses at once, vectorised).

Own-light centroid
------------------
The reported centre is not the model's centroid but the centroid of the **data** attributed
to the lenslet: each pixel's value is split among the micro-images that cover it in
proportion to their model values, ``own_k(x) = I(x)·m_k(x)/M(x)``. Pixels covered by one
micro-image only keep their measured value, so the model matters only on the seams.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize
from scipy.spatial import cKDTree

from lfcam.calibrate import kernels
from lfcam.calibrate.parallel import run_chunks
from lfcam.errors import CalibrationError
from lfcam.progress import Progress

CHUNK = 8192  # lenses per vectorised block (memory ≈ CHUNK × patch² × 8 doubles)
def _noop(stage: str, done: int, total: int) -> None:
    return None


@dataclass(frozen=True)
class DiscModel:
    """Shape of the micro-images of a white image (global over the sensor).

    Attributes
    ----------
    radius_px : float
        Disc radius R at which the edge ramp is at half height.
    edge_px : float
        Half-width w of the linear edge ramp (coverage goes 1 → 0 over R − w … R + w).
    rel_residual : float
        RMS of (data − model) over the fitting crop, relative to the mean bright level:
        how disc-like the micro-images are.
    """

    radius_px: float
    edge_px: float
    rel_residual: float

    @property
    def support_px(self) -> float:
        """Radius beyond which a micro-image puts no light on the sensor."""
        return self.radius_px + self.edge_px

    def patch_half_px(self) -> int:
        """Half-size of the square patch that holds one micro-image and its search margin."""
        return int(np.ceil(self.support_px)) + 1


class _Patches:
    """Pixel coordinates and flat indices of square patches around lens positions."""

    def __init__(self, shape: tuple[int, int], centres: np.ndarray, half: int) -> None:
        h, w = shape
        off = np.arange(-half, half + 1)
        base = np.round(centres).astype(np.int64)
        self.x = np.broadcast_to(base[:, 0, None, None] + off[None, None, :],
                                 (len(base), off.size, off.size))
        self.y = np.broadcast_to(base[:, 1, None, None] + off[None, :, None],
                                 (len(base), off.size, off.size))
        self.inside = (self.x >= 0) & (self.x < w) & (self.y >= 0) & (self.y < h)
        self.flat = np.where(self.inside, self.y * w + self.x, 0)
        self.base = base
        self.off = off.astype(np.float32)


def _disc_terms(p: _Patches, centres: np.ndarray, coef: np.ndarray, model: DiscModel):
    """Offsets, distance, coverage, edge-band mask and brightness of each patch pixel.

    Float32 (offsets are taken from the patch's integer base first, so nothing is lost).
    """
    frac = (centres - p.base).astype(np.float32)
    dx = p.off[None, None, :] - frac[:, 0, None, None]
    dy = p.off[None, :, None] - frac[:, 1, None, None]
    d = np.sqrt(dx * dx + dy * dy)
    t = (np.float32(model.radius_px + model.edge_px) - d) * np.float32(0.5 / model.edge_px)
    cov = np.clip(t, 0.0, 1.0) * p.inside
    band = (t > 0.0) & (t < 1.0) & p.inside
    cf = coef.astype(np.float32)
    b = cf[:, 0, None, None] + cf[:, 1, None, None] * dx + cf[:, 2, None, None] * dy
    return dx, dy, d, cov, band, b


def _chunks(n: int, chunk: int = CHUNK):
    for s in range(0, n, chunk):
        yield slice(s, min(n, s + chunk))


def _run_chunks(fn, n: int, chunk: int | None = None) -> list:
    """:func:`lfcam.calibrate.parallel.run_chunks` with this module's lens chunk."""
    return run_chunks(fn, n, CHUNK if chunk is None else chunk)


def core_radius_px(model: DiscModel, pitch_px: float) -> float:
    """Radius of a micro-image's seam-free core: no neighbour's light reaches it even when
    micro-images overlap (min(R − 1, pitch − R − w − 0.5), at least 1.5 px)."""
    return max(1.5, min(model.radius_px - 1.0, pitch_px - model.support_px - 0.5))


def brightness_planes(image: np.ndarray, centres: np.ndarray, half: int,
                      core_px: float) -> np.ndarray:
    """Least-squares brightness plane (a, gx, gy) of each micro-image over its core: the
    on-sensor pixels of its patch within ``core_px`` of its centre (sums:
    :func:`lfcam.calibrate.kernels.core_plane_sums`; batched 3×3 solves).

    ``half`` is the patch half-size, ``core_px`` the core radius (:func:`core_radius_px`).
    """
    img = np.ascontiguousarray(image, dtype=np.float64)
    q = kernels.core_plane_sums(img.shape[0], img.shape[1],
                                np.ascontiguousarray(centres, np.float64), half, core_px,
                                img.ravel())
    ata = q[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(-1, 3, 3) + 1e-9 * np.eye(3)
    return np.linalg.solve(ata, q[:, 6:, None])[..., 0]


def model_image(shape: tuple[int, int], centres: np.ndarray, coef: np.ndarray,
                model: DiscModel) -> np.ndarray:
    """Flattened model image M(x) = Σ_k m_k(x) (:func:`lfcam.calibrate.kernels.disc_models`)."""
    total = np.zeros(shape[0] * shape[1])
    kernels.disc_models(shape[0], shape[1], np.ascontiguousarray(centres, np.float64),
                        np.ascontiguousarray(coef, np.float32), model.patch_half_px(),
                        np.float32(model.support_px), np.float32(0.5 / model.edge_px), total)
    return total


def _central_crop(image: np.ndarray, centres: np.ndarray, half_px: float):
    """Crop of the image around its centre, the centres inside it, and the crop origin."""
    h, w = image.shape
    mid = np.array([0.5 * (w - 1), 0.5 * (h - 1)])
    x0 = int(max(0, np.floor(mid[0] - half_px)))
    y0 = int(max(0, np.floor(mid[1] - half_px)))
    x1 = int(min(w, np.ceil(mid[0] + half_px) + 1))
    y1 = int(min(h, np.ceil(mid[1] + half_px) + 1))
    crop = np.ascontiguousarray(image[y0:y1, x0:x1], dtype=np.float64)
    origin = np.array([x0, y0], dtype=np.float64)
    return crop, centres - origin, mid - origin


def r_eval_lenses(radius_lenses: float) -> float:
    """Radius (in pitches) of the region whose pixels the shape fit compares."""
    return radius_lenses - 1.5


def fit_disc_model(image: np.ndarray, centres: np.ndarray, pitch_px: float,
                   radius_lenses: float = 4.5, refine: bool = True) -> DiscModel:
    """Fit the global disc radius and edge width on the lenses near the image centre.

    Minimises Σ (I − M)² over the pixels within ``radius_lenses − 1`` pitches of the centre,
    each lens's brightness plane re-fitted from its core for every trial (R, w). With
    ``refine`` the central discs are then re-centred (:func:`fit_discs`) and (R, w) fitted
    again, so rough starting centres do not inflate the shape or the residual.
    """
    crop, cen, mid = _central_crop(image, centres, (radius_lenses + 1.0) * pitch_px)
    lim = np.array(crop.shape[::-1]) + pitch_px
    sel = cen[((cen > -pitch_px) & (cen < lim)).all(axis=1)]  # every lens touching the crop
    if np.sum(np.hypot(*(sel - mid).T) < r_eval_lenses(radius_lenses) * pitch_px) < 4:
        raise CalibrationError("too few micro-images near the image centre to fit their shape")
    r_eval = r_eval_lenses(radius_lenses) * pitch_px
    flat_img = crop.ravel()

    def evaluated(pts: np.ndarray, half: int, cache: dict) -> np.ndarray:
        # the crop pixels a trial's residual sums: those of the patches (half-size ``half``)
        # within r_eval of the centre (the same for every trial of one patch size: kept)
        if half not in cache:
            p = _Patches(crop.shape, pts, half)
            keep = p.inside & (np.hypot(p.x - mid[0], p.y - mid[1]) < r_eval)
            cache[half] = np.unique(p.flat[keep])
        return cache[half]

    def residual(params, pts: np.ndarray, coef: np.ndarray,
                 cache: dict | None = None) -> tuple[float, float]:
        radius, edge = float(params[0]), abs(float(params[1])) + 0.05
        if not 0.1 * pitch_px < radius < pitch_px:
            return np.inf, np.inf
        trial = DiscModel(radius, edge, 0.0)
        m = model_image(crop.shape, pts, coef, trial)
        idx = evaluated(pts, trial.patch_half_px(), {} if cache is None else cache)
        r = flat_img[idx] - m[idx]
        level = max(float(np.mean(coef[:, 0])), 1e-12)
        return float(np.sum(r * r)), float(np.sqrt(np.mean(r * r)) / level)

    x0 = [0.45 * pitch_px, 0.5]
    model = DiscModel(x0[0], x0[1] + 0.05, 0.0)
    for _ in range(2 if refine else 1):
        coef = brightness_planes(crop, sel, model.patch_half_px() + 2,
                                 core_radius_px(model, pitch_px))
        pixels: dict = {}  # (this round's lenses: evaluated's pixels per patch size)
        scale = residual(x0, sel, coef, pixels)[0]
        res = minimize(lambda q, pts=sel, cf=coef, k=scale, px=pixels:
                       residual(q, pts, cf, px)[0] / k, x0=x0,
                       method="Nelder-Mead", options={"xatol": 5e-3, "fatol": 1e-7,
                                                      "maxiter": 150})
        x0 = [float(res.x[0]), abs(float(res.x[1]))]
        model = DiscModel(x0[0], x0[1] + 0.05, 0.0)
        if refine:
            sel, _, _ = fit_discs(crop, sel, model, pitch_px, iterations=15, tol_px=2e-3)
    coef = brightness_planes(crop, sel, model.patch_half_px(), core_radius_px(model, pitch_px))
    # Pixel noise is no shape misfit: remove it in quadrature (issue 16: an independent white
    # with 4 % pixel noise read as "not disc-like" and fell back to the cell window)
    rel = residual(x0, sel, coef)[1]
    level = max(float(np.mean(coef[:, 0])), 1e-12)
    noise = _pixel_noise(crop) / level
    return DiscModel(model.radius_px, model.edge_px, float(np.sqrt(max(rel**2 - noise**2, 0.0))))


def _pixel_noise(img: np.ndarray) -> float:
    """Robust σ of white pixel noise from the second difference along rows (edges are rare
    outliers; a smooth brightness ramp has none): σ_d = σ·√1.5."""
    d = img[:, 1:-1] - 0.5 * (img[:, :-2] + img[:, 2:])
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(1.5))


def fit_discs(
    image: np.ndarray,
    centres: np.ndarray,
    model: DiscModel,
    pitch_px: float,
    iterations: int = 40,
    tol_px: float = 1e-3,
    damping: float = 0.6,
    fixed: np.ndarray | None = None,
    fit_fixed_centres: np.ndarray | None = None,
    hold: np.ndarray | None = None,
    progress: Progress = _noop,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fit every disc's centre against the data minus its neighbours' current model.

    Block-Jacobi Gauss–Newton on the two centre coordinates of every lens at once (the
    brightness planes come from each seam-free core and are refreshed every few steps).
    ``damping`` < 1 keeps two lenses that share a seam from both claiming it in one step.

    Returns
    -------
    disc_centres : (N, 2)
    coef : (N, 3)
        Brightness planes (a, gx, gy).
    converged : (N,) bool
        The last centre update was below ``10·tol_px``.

    ``fixed`` marks discs whose brightness cannot be measured (micro-images cut by the sensor
    border): their brightness plane is the nearest measured disc's, about their own centre
    (neighbouring micro-images repeat one brightness pattern), so their light on the seams
    of visible neighbours is accounted for. Their centres
    are fitted only when ``fit_fixed_centres`` says so (enough of their edge is visible).
    ``hold`` marks measured discs whose centres are kept (their light is modelled with their
    own brightness planes): the context of a fit of a subset of the lenses.
    """
    img = np.asarray(image, dtype=np.float64)
    flat_img = img.ravel()
    c = np.array(centres, dtype=np.float64)
    fixed = np.zeros(len(c), bool) if fixed is None else np.asarray(fixed, bool)
    held = np.zeros(len(c), bool) if hold is None else np.asarray(hold, bool)
    hold = fixed.copy()
    if fit_fixed_centres is not None:
        hold &= ~np.asarray(fit_fixed_centres, bool)
    hold |= held
    free = np.flatnonzero(~fixed)
    if free.size == 0:
        raise CalibrationError("no micro-image lies fully on the sensor")
    half = model.patch_half_px()
    step = np.zeros(len(c))
    core = core_radius_px(model, pitch_px)
    donor = free[cKDTree(c[free]).query(c)[1]]  # nearest free disc (itself when free)

    def planes() -> np.ndarray:
        out = np.zeros((len(c), 3))
        out[free] = brightness_planes(img, c[free], half, core)
        out = out[donor]
        # fixed discs: the donor's plane as it is about the donor's centre. The gradient
        # within a micro-image is mostly its own pattern (cos⁴ and the stop across the
        # lenslet's view), which every neighbour repeats; extrapolated over a pitch as if it
        # were a trend across the sensor it made cut discs on the dim side 5–10 % too dim,
        # and their fully visible neighbours' centroids 0.1 px off (docs/calibration.md)
        return out

    coef = planes()
    sup, inv2w = np.float32(model.support_px), np.float32(0.5 / model.edge_px)
    h, w = img.shape
    # at least four chunks, so that a full sensor of ~10 000 lenses keeps the threads busy
    chunk = max(512, min(CHUNK, -(-len(c) // 4)))
    for it in range(iterations):
        if it % 4 == 3:
            coef = planes()
        coef32 = coef.astype(np.float32)
        total = np.zeros(img.size)  # the model image (one pass, compiled)
        kernels.disc_models(h, w, c, coef32, half, sup, inv2w, total)
        new_c = c.copy()

        def step_part(sl: slice, c: np.ndarray = c, coef32: np.ndarray = coef32,
                      total: np.ndarray = total, new_c: np.ndarray = new_c) -> None:
            sums = kernels.disc_step_sums(h, w, c, coef32, half, sup, inv2w, flat_img, total,
                                          np.arange(sl.start, sl.stop))
            axx, ayy, axy, bx, by = sums.T
            axx, ayy = axx + 1e-12, ayy + 1e-12
            det = axx * ayy - axy * axy
            ok = det > 0
            sx = np.where(ok, (ayy * bx - axy * by) / np.where(ok, det, 1.0), 0.0)
            sy = np.where(ok, (axx * by - axy * bx) / np.where(ok, det, 1.0), 0.0)
            dc = damping * np.clip(np.column_stack([sx, sy]), -0.5, 0.5)
            new_c[sl] = c[sl] + dc
            step[sl] = np.abs(dc).max(axis=1)

        _run_chunks(step_part, len(c), chunk)
        new_c[hold] = c[hold]
        step[fixed | held] = 0.0
        c = new_c
        progress("micro-image fit", it + 1, iterations)
        # settled: nearly every disc moves < tol; a few edge pixels crossing the ramp's kinks
        # keep some discs bouncing at a few thousandths of a pixel, harmlessly
        if float(np.percentile(step, 99)) < tol_px and float(step.max()) < 5.0 * tol_px:
            break
    return c, planes(), step < 10.0 * tol_px


def own_light_centroids(image: np.ndarray, disc_centres: np.ndarray, coef: np.ndarray,
                        model: DiscModel) -> tuple[np.ndarray, np.ndarray]:
    """Centroid and flux of the data attributed to each lens (see the module docstring).

    Returns
    -------
    centroids : (N, 2)
    flux : (N,)
    """
    img = np.asarray(image, dtype=np.float64)
    flat_img = img.ravel()
    total = model_image(img.shape, disc_centres, coef, model)
    ratio = np.where(total > 0.0, flat_img / np.where(total > 0.0, total, 1.0), 0.0)
    half = model.patch_half_px()
    cen = np.zeros((len(disc_centres), 2))
    flux = np.zeros(len(disc_centres))
    for sl in _chunks(len(disc_centres)):
        p = _Patches(img.shape, disc_centres[sl], half)
        _, _, _, cov, _, b = _disc_terms(p, disc_centres[sl], coef[sl], model)
        q = np.where(p.inside, ratio[p.flat], 0.0) * np.maximum(b, 0.0) * cov
        s0 = q.sum(axis=(1, 2))
        good = s0 > 0
        with np.errstate(invalid="ignore", divide="ignore"):
            cen[sl, 0] = np.where(good, (q * p.x).sum(axis=(1, 2)) / s0, np.nan)
            cen[sl, 1] = np.where(good, (q * p.y).sum(axis=(1, 2)) / s0, np.nan)
        flux[sl] = s0
    return cen, flux


# --- fast own-light fit -------------------------------------------------------------------

SLACK_PX = 1.5  # |disc centre − its integer base pixel| the pixel classes allow for
CONVERGED_PX = 0.01  # a lens whose last fixed-point step exceeds this is "unconverged"
# after the polish: a disc step of 0.03 px moves the own-light centroid by ≲ 0.005 px (the
# seam split follows the disc by ~0.15); the failures it catches step by 0.1–0.3 px
POLISH_CONVERGED_PX = 0.03


def _coverage_moments(model: DiscModel) -> float:
    """K = ∫ u_x² cov / ∫ cov over the plane, for the linear edge ramp ``cov(r)``.

    A disc ``(a + g·u)·cov(|u|)`` has its centroid at ``g·K/a`` from its centre (the radial
    coverage has no odd moments), so ``K`` converts a centroid into a disc centre.
    """
    r = np.linspace(0.0, model.support_px, 20_001)
    cov = np.clip((model.support_px - r) / (2.0 * model.edge_px), 0.0, 1.0) * r
    return float(0.5 * np.trapezoid(cov * r * r, r) / np.trapezoid(cov, r))


def fixed_point_applies(model: DiscModel, pitch_px: float) -> bool:
    """Whether :func:`own_light_fit` is used: the discs touch but do not overlap at half height
    (R ≤ pitch/2), so only edge ramps share pixels.

    There the own-light centroid moves by only ~0.15 of a disc-centre error and the fixed
    point converges in 3–4 steps. Overlapping discs (system 2, R ≈ 0.55 pitch) share whole
    plateaus; the centroid then barely constrains the disc centre (the map contracts by only
    ~0.9 per step) and :func:`fit_discs` (Gauss–Newton on the disc edges) is used instead.
    """
    return model.radius_px <= 0.5 * pitch_px


def _neighbour_offsets(pts: np.ndarray, pitch_px: float, sample: int = 4000) -> np.ndarray:
    """Distinct offsets (rounded to 0.25 px) to the lattice neighbours of a sample of points."""
    sel = pts[:: max(1, len(pts) // sample)]
    d, j = cKDTree(pts).query(sel, k=9, distance_upper_bound=1.5 * pitch_px)
    ok = np.isfinite(d) & (d > 0.5 * pitch_px)
    vec = pts[np.minimum(j, len(pts) - 1)] - sel[:, None, :]
    return np.unique(np.round(vec[ok] * 4.0) / 4.0, axis=0)


def _core_planes(values: np.ndarray, frac: np.ndarray, oxc: np.ndarray, oyc: np.ndarray,
                 quad: np.ndarray, core_px: float) -> np.ndarray:
    """Least-squares brightness plane (a, gx, gy) in base-pixel offsets, per lens, over the
    pixels within ``core_px`` of its start position ``base + frac`` (batched 3×3 solves)."""
    fr = frac.astype(np.float32)
    ux, uy = oxc - fr[:, :1], oyc - fr[:, 1:]
    m = (ux * ux + uy * uy < np.float32(core_px * core_px)).astype(np.float32)
    q = (m @ quad).astype(np.float64)  # Σ 1, x, y, x², xy, y² over each lens's core
    v = m * values
    b = np.stack([v.sum(axis=1), v @ oxc, v @ oyc], axis=1).astype(np.float64)
    ata = q[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(-1, 3, 3) + 1e-9 * np.eye(3)
    return np.linalg.solve(ata, b[..., None])[..., 0]


def own_light_fit(
    image: np.ndarray,
    centres: np.ndarray,
    model: DiscModel,
    pitch_px: float,
    fixed: np.ndarray | None = None,
    anchor: np.ndarray | None = None,
    iterations: int = 3,
    tol_px: float = 5e-3,
    polish: int = 1,
    polish_damping: float = 1.0,
    polish_tol_px: float = 1e-3,
    refit: bool = True,
    progress: Progress = _noop,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Own-light centroids of touching micro-images: a fixed point on the disc centres, then
    a Gauss–Newton polish of the disc edges.

    The same model and the same reported quantity as :func:`fit_discs` followed by
    :func:`own_light_centroids` (module docstring), reached more cheaply; used when the discs
    touch but do not overlap (:func:`fixed_point_applies`).

    * **Fixed point first.** The own-light centroid ``c_k`` depends on the disc centres only
      through the seam split ``m_k/M`` and the support edge. Each step sets every disc
      centre to ``d_k = c_k − g_k·K/a_k`` (the model disc whose centroid is the measured
      own-light centroid; :func:`_coverage_moments`) and recomputes ``c_k``. An error δ in
      the disc centres moves ``c_k`` by only ~0.15 δ on touching whites, so a few steps from
      a circle-window start bring the discs within a few hundredths of a pixel of their
      final place, with no Jacobians or normal equations.
    * **Gauss–Newton polish.** The fixed point's discs match centroids; :func:`fit_discs`'s
      match the edges, and those split the seams better (0.0131 vs 0.0216 px on the rendered
      system 1 full-sensor white, whose corner micro-images are cat's eyes, not discs; 0.0176
      vs 0.0199 px on the F01-size generator white, whose erfc edges the linear ramp only
      approximates). ``polish`` undamped block-Jacobi Gauss–Newton steps of the disc
      centres follow, with :func:`fit_discs`'s residual and Jacobian (data minus all
      models; edge ramp plus the plane sliding with the disc) evaluated on the seam and
      outer pixels only (the inner pixels enter through their fixed sums). The map
      contracts by ~0.3 per step; lenses whose step falls below ``polish_tol_px`` drop out.
      Cut discs whose centre is on the sensor are fitted too, on their on-sensor pixels
      (as :func:`fit_discs` with ``fit_fixed_centres``).
    * **Pixel classes fixed once.** Every lens keeps the integer base pixel of its start
      (its disc centre may drift ``SLACK_PX`` from it). Offsets from the base within
      ``min(R − w, pitch − R − w) − SLACK_PX`` are *inner*: fully covered by the lens and
      out of every neighbour's reach for any allowed drift, so their attributed light is
      their value, and Σ I·(1, x, y) over them is taken once. Of the remaining offsets
      within ``R + w + SLACK_PX``, *outer* ones are out of every neighbour's reach (their
      weight is 1 inside the lens's support, 0 beyond), and only *seam* ones need the model
      of the neighbours.
    * **Brightness planes** (a, gx, gy) are fitted by least squares over the seam-free core
      about each start position (:func:`core_radius_px`; batched 3×3 solves), and once more
      about the disc centres after the first fixed-point step (``refit``; the core pixels
      are kept), when every model is recomputed anyway.
    * **Model image** M is kept on a padded float32 image and updated only on seam pixels, by
      the change of each lens's model (compiled passes over the seam pixels:
      :mod:`lfcam.calibrate.kernels`).
    * **Active set.** From the third step on, only discs that still moved by ≥ ``tol_px``
      (and the cut discs anchored to them) are re-modelled, and only they and their
      neighbours re-attributed.

    Cost: docs/calibration.md ("Touching micro-images at full size") has the breakdown.

    Parameters
    ----------
    image : (H, W)
        Prepared white image.
    centres : (N, 2)
        Start positions (x, y), within about half a pixel of the disc centres (e.g. circle-
        window centroids, or lattice predictions for ``fixed`` lenses).
    model : DiscModel
    pitch_px : float
    fixed : (N,) bool, optional
        Micro-images cut by the sensor border: modelled (their light reaches the seams of
        their neighbours) but not measured. Their brightness plane is their ``anchor``'s,
        extrapolated, and their centre follows the anchor's: ``d = d_anchor + (start −
        start_anchor)``.
    anchor : (N,) int, optional
        For each fixed lens, a measured (not fixed) lens, normally its nearest; default the
        nearest by start position.
    iterations : int
        Maximum fixed-point steps.
    tol_px : float
        Stop when 99 % of the measured disc centres moved less than this in the last step
        (and none more than ``CONVERGED_PX``); lenses moving less are left out of further
        steps.
    polish : int
        Gauss–Newton steps after the fixed point (0: fixed point only).
    polish_damping : float
        Fraction of each Gauss–Newton step taken.
    polish_tol_px : float
        A lens whose polish step is below this is left out of further steps.
    refit : bool
        Refit the brightness planes after the first fixed-point step.
    progress : callable(stage, fraction)

    Returns
    -------
    centroids : (N, 2)
        Own-light centroids (NaN for fixed lenses or lenses without attributed light).
    flux : (N,)
        Attributed light per lens (0 for fixed lenses).
    disc_centres : (N, 2)
    converged : (N,) bool
        The last step was below ``CONVERGED_PX`` (after a polish: ``POLISH_CONVERGED_PX``;
        the polish contracts by ~0.3 per step, so two steps leave up to ~0.015 px p99) and
        the disc centre stayed within the slack of its base pixel (always True for fixed
        lenses). A few cat's-eye corner lenses fail the latter (their disc centre lies ~0.6 px
        from their centroid): :func:`lfcam.calibrate.grid._model_centroids` re-fits them with
        :func:`fit_discs`.
    """
    img = np.ascontiguousarray(image, dtype=np.float32)
    h, w = img.shape
    c = np.array(centres, dtype=np.float64)
    n = len(c)
    fixed = np.zeros(n, bool) if fixed is None else np.asarray(fixed, bool)
    free = np.flatnonzero(~fixed)
    if free.size == 0:
        raise CalibrationError("no micro-image lies fully on the sensor")
    fix = np.flatnonzero(fixed)
    if anchor is None:
        anchor = free[cKDTree(c[free]).query(c)[1]]
    anchor = np.asarray(anchor, np.int64)
    anchor_off = c - c[anchor]

    support = model.support_px
    reach = support + SLACK_PX  # from the base pixel, for any allowed drift
    half = int(np.ceil(reach))
    pad = 2 * half + 2  # a fixed lens's base lies at most support + 1 px off the sensor
    wp = w + 2 * pad  # the model image's padded width
    off = np.arange(-half, half + 1)
    ox, oy = (a.ravel() for a in np.meshgrid(off, off))
    g = np.hypot(ox, oy)
    inner = g < min(model.radius_px - model.edge_px, pitch_px - support) - SLACK_PX
    # seam offsets: within reach of a neighbour too (its offset from this lens's base, taken
    # from the start positions of a sample of lenses, plus 0.5 px for rounding and drift)
    nb = _neighbour_offsets(c[free], pitch_px)
    seam = np.zeros(g.shape, bool)
    for vx, vy in nb:
        seam |= np.hypot(ox - vx, oy - vy) < reach + 0.5
    ring = (g < reach) & ~inner
    seam &= ring
    outer = ring & ~seam
    core_px = core_radius_px(model, pitch_px)
    cols_c = np.flatnonzero(g < core_px + SLACK_PX)  # where a core about the start can be
    oxc, oyc = ox[cols_c].astype(np.float32), oy[cols_c].astype(np.float32)
    quad = np.stack([np.ones(cols_c.size), oxc, oyc, oxc * oxc, oxc * oyc, oyc * oyc],
                    axis=1).astype(np.float32)
    lin_s = (oy * wp + ox).astype(np.int64)[seam]  # seam offsets in the padded model image
    oxs, oys = ox[seam].astype(np.float32), oy[seam].astype(np.float32)
    oxo, oyo = ox[outer].astype(np.float32), oy[outer].astype(np.float32)

    # Σ I·(1, x, y) weights over the whole patch, zero off the inner disc
    w_in = (np.stack([np.ones(g.size), ox, oy], axis=1) * inner[:, None]).astype(np.float32)
    mom_in = w_in.sum(axis=0).astype(np.float64)  # Σ 1, x, y over the inner disc

    base = np.round(c).astype(np.int64)
    bflat = (base[:, 1] + pad) * wp + (base[:, 0] + pad)
    ns = int(seam.sum())

    # once: brightness planes about the base pixel (fixed lenses: the anchor's, extrapolated),
    # inner sums, and the core, seam and outer pixel values
    coef = np.zeros((n, 3))
    s_in = np.zeros((n, 3))
    p_s = np.zeros((n, ns), np.float32)
    p_o = np.zeros((n, int(outer.sum())), np.float32)
    p_c = np.zeros((n, cols_c.size), np.float32)  # core pixels, for the plane refit
    # cut discs whose centre is on the sensor: their visible edges are fitted by the polish
    cut_fit = fix[(c[fix, 0] >= 0) & (c[fix, 0] <= w - 1) & (c[fix, 1] >= 0)
                  & (c[fix, 1] <= h - 1)] if polish else fix[:0]
    gathered = np.r_[free, cut_fit]

    # the offsets (int) of the core, seam, outer and inner pixels from a lens's base pixel
    sets = [(ox[m].astype(np.int64), oy[m].astype(np.int64))
            for m in (cols_c, seam, outer, inner)]

    def gather(sl: slice) -> None:
        k = gathered[sl]
        for (ox_, oy_), out in zip(sets[:3], (p_c, p_s, p_o), strict=True):
            kernels.gather_patch(img, base, k, ox_, oy_, out)
        s_in[k] = kernels.patch_sums(img, base, k, *sets[3])
        coef[k] = _core_planes(p_c[k], c[k] - base[k], oxc, oyc, quad, core_px)

    _run_chunks(gather, gathered.size)
    # on-sensor masks of the cut discs that are fitted: seam, outer, and inner moments
    cut_row = np.full(n, -1)
    cut_row[cut_fit] = np.arange(cut_fit.size)

    def on_sensor(k: np.ndarray, ox_: np.ndarray, oy_: np.ndarray) -> np.ndarray:
        x = base[k, :1] + ox_
        y = base[k, 1:] + oy_
        return (x >= 0) & (x < w) & (y >= 0) & (y < h)

    ins_s = on_sensor(cut_fit, ox[seam], oy[seam])
    ins_o = on_sensor(cut_fit, ox[outer], oy[outer])
    mom_cut = on_sensor(cut_fit, ox, oy).astype(np.float64) @ w_in.astype(np.float64)
    coef32 = np.empty((n, 3), np.float32)  # the planes as the kernels take them

    def planes_on_seams() -> None:
        """Cut lenses: the anchor's plane, extrapolated; the float32 planes refreshed."""
        coef[fix] = coef[anchor[fix]]
        # extrapolated here (the Gauss–Newton path copies the plane instead): with touching
        # discs only edge ramps are shared, and on the rendered system 1 white the extrapolated
        # plane left the border row at 0.032 px against 0.039 px for the copy
        coef[fix, 0] += np.sum(coef[fix, 1:] * (base[fix] - base[anchor[fix]]), axis=1)
        coef32[:] = coef

    planes_on_seams()
    kmom = _coverage_moments(model)
    inv2w = np.float32(0.5 / model.edge_px)
    sup = np.float32(support)

    m_cur = np.zeros((n, ns), np.float32)  # each lens's current model on its seam pixels
    total = np.zeros((h + 2 * pad) * wp, np.float32)  # model image M on the padded grid
    step = np.full(n, np.inf)
    step[fix] = 0.0
    own = np.full((n, 2), np.nan)
    flux = np.zeros(n)
    c_mod = np.full((n, 2), np.nan)  # the disc centres M currently holds

    scatter_lock = threading.Lock()

    def remodel(mov: np.ndarray, frac: np.ndarray) -> None:
        """Model m_k of the lenses ``mov`` on their seam pixels; scatter the change into M
        (one thread scatters at a time, the others compute meanwhile)."""

        def one(sl: slice) -> None:
            k = mov[sl]
            delta = np.empty((k.size, ns), np.float32)
            kernels.seam_models(k, frac, oxs, oys, sup, inv2w, coef32, m_cur, delta)
            c_mod[k] = c[k]
            with scatter_lock:
                kernels.scatter_seams(total, bflat, k, lin_s, delta)

        _run_chunks(one, mov.size)

    def attribute(att: np.ndarray, frac: np.ndarray) -> np.ndarray:
        """Own-light centroid and flux of the lenses ``att`` (seam pixels split in proportion
        m_k / M; outer pixels, which no neighbour reaches, are the lens's own where its model
        is non-zero); returns the disc centres whose model centroids are those centroids."""
        new = c[att].copy()

        def one(sl: slice) -> None:
            k = att[sl]
            sm = s_in[k] + kernels.own_light_sums(k, frac, sup, m_cur, total, bflat, lin_s,
                                                  p_s, oxs, oys, p_o, oxo, oyo)
            ok = sm[:, 0] > 0
            cen = base[k] + sm[:, 1:] / np.where(ok, sm[:, 0], 1.0)[:, None]
            own[k] = np.where(ok[:, None], cen, np.nan)
            flux[k] = sm[:, 0]
            fr = c[k] - base[k]
            a_d = coef[k, 0] + np.sum(coef[k, 1:] * fr, axis=1)
            shift = coef[k, 1:] * (kmom / np.where(a_d > 0, a_d, np.inf))[:, None]
            new[sl] = np.where(ok[:, None], cen - shift, c[k])

        _run_chunks(one, att.size)
        return new

    def edge_step(act: np.ndarray, frac: np.ndarray) -> np.ndarray:
        """Gauss–Newton step of the disc centres ``act`` on their ring pixels, against the data
        minus the neighbours' model (the disc edges; brightness planes held)."""
        dc = np.zeros((act.size, 2))

        def one(sl: slice) -> None:
            k = act[sl]
            cr = cut_row[k]
            cm = cr >= 0
            sums = kernels.edge_sums(k, frac, coef32, sup, inv2w, total, bflat, lin_s, p_s,
                                     oxs, oys, p_o, oxo, oyo, cut_row, ins_s, ins_o)
            # inner pixels: covered, no neighbour; the plane slides with the disc (as in
            # :func:`fit_discs`), so J = −g there and r = I − plane
            gx, gy = coef[k, 1], coef[k, 2]
            mom = np.broadcast_to(mom_in, (k.size, 3)).copy()
            mom[cm] = mom_cut[cr[cm]]
            r_in = s_in[k, 0] - np.sum(coef[k] * mom, axis=1)
            sums += np.stack([gx * gx * mom[:, 0], gy * gy * mom[:, 0], gx * gy * mom[:, 0],
                              -gx * r_in, -gy * r_in], axis=1)
            axx, ayy, axy, bx, by = sums.T
            axx, ayy = axx + 1e-12, ayy + 1e-12
            det = axx * ayy - axy * axy
            ok = det > 0
            sx = np.where(ok, (ayy * bx - axy * by) / np.where(ok, det, 1.0), 0.0)
            sy = np.where(ok, (axx * by - axy * bx) / np.where(ok, det, 1.0), 0.0)
            dc[sl] = polish_damping * np.clip(np.column_stack([sx, sy]), -0.5, 0.5)

        _run_chunks(one, act.size)
        return dc

    def refit_planes(frac: np.ndarray) -> None:
        """Brightness planes about the current disc centres (not the start positions); the
        model must then be recomputed."""
        def one(sl: slice) -> None:
            k = free[sl]
            coef[k] = _core_planes(p_c[k], frac[k], oxc, oyc, quad, core_px)

        _run_chunks(one, free.size)
        planes_on_seams()

    moving = np.ones(n, bool)  # lenses whose model is re-evaluated
    attrib = free.copy()  # lenses whose own light is re-attributed
    nbrs = None
    for it in range(iterations):
        frac = (c - base).astype(np.float32)
        # 1. model of every moving lens; 2. own-light centroids; 3. the disc whose model
        #    centroid is that own-light centroid
        remodel(np.flatnonzero(moving), frac)
        new = attribute(attrib, frac)
        step[attrib] = np.max(np.abs(new - c[attrib]), axis=1)
        c[attrib] = new
        if it == 0 and refit:
            # after the first step the discs are within a few hundredths of a pixel: fit the
            # brightness planes about them (every lens is re-modelled in the second step)
            refit_planes((c - base).astype(np.float32))
            c_mod[:] = np.nan  # every model is stale
        if it < 2:
            # cut discs follow their anchors through the first steps, then stay: a disc in a
            # sensor corner whose cut neighbours kept following it would chase its own seams
            c[fix] = c[anchor[fix]] + anchor_off[fix]
        progress("micro-image fit", it + 1, iterations + polish)
        # settled: nearly every disc moves < tol, none by more than the convergence limit
        # (a few, whose edge pixels cross the ramp's kinks, keep bouncing at a few thousandths
        # of a pixel, harmlessly)
        sf = step[free]
        if float(np.percentile(sf, 99)) < tol_px and float(sf.max()) < CONVERGED_PX:
            break
        if it >= 1:
            # from the third step on, only discs still moving by ≥ tol (and cut discs that
            # follow them) are re-modelled, and only they and their neighbours re-attributed
            if nbrs is None:
                nbrs = cKDTree(c).query(c, k=9, distance_upper_bound=2.0 * reach)[1]
            moving = step >= tol_px
            moving[fix] = moving[anchor[fix]] if it < 2 else False
            mark = moving.copy()
            nb_idx = nbrs[moving].ravel()
            mark[nb_idx[nb_idx < n]] = True
            attrib = np.flatnonzero(mark & ~fixed)
    if polish:
        # Gauss–Newton polish of the disc edges: the fixed point's discs match centroids, the
        # polished ones the edges, which split the seams better where the brightness is not a
        # plane or the micro-images are not discs (cat's-eye corners)
        # lenses whose model image disc is within tol of their centre start from that disc
        # (their last fixed-point update is dropped rather than re-modelling them for it);
        # the others are re-modelled where they are
        held = np.all(np.abs(c - c_mod) < tol_px, axis=1)  # False where c_mod is NaN
        c[held] = c_mod[held]
        frac = (c - base).astype(np.float32)
        remodel(np.flatnonzero(~held), frac)
        act = np.r_[free, cut_fit]
        for it in range(polish):
            dc = edge_step(act, frac)
            c[act] += dc
            st = np.abs(dc).max(axis=1)
            step[act] = st
            step[fix] = 0.0
            frac = (c - base).astype(np.float32)
            remodel(act, frac)
            progress("micro-image fit", iterations + it + 1, iterations + polish)
            act = act[st >= polish_tol_px]
            if act.size == 0:
                break
        attribute(free, frac)
    drift = np.hypot(*(c - base).T) <= SLACK_PX
    return own, flux, c, (step < (POLISH_CONVERGED_PX if polish else CONVERGED_PX)) & drift


def circle_window_centroids(
    image: np.ndarray,
    start: np.ndarray,
    radius_px: float,
    iterations: int = 6,
    tol_px: float = 1e-3,
    progress: Progress = _noop,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fixed-point centroids inside a soft-edged circle, for micro-images with a dark gap.

    When every micro-image fits inside a circle of radius ``radius_px`` centred on it and no
    neighbour's light reaches that circle (support ≤ radius − 0.5 ≤ pitch − support − 1), the
    fixed point is the exact intensity centroid, whatever the brightness gradient. Pixel
    weights ramp linearly from 1 to 0 over one pixel at the circle (area coverage); each
    patch's minimum is removed first (an offset then only slows convergence).

    Speed: one plain centroid in a fixed disc re-centres every patch to within half a pixel;
    then the pixels that are inside the circle for any sub-pixel position are summed once
    (a matrix product), and only the ring of edge pixels is re-weighted per iteration.

    Returns
    -------
    centres : (N, 2)
    flux : (N,)
    converged : (N,) bool
    """
    img = np.ascontiguousarray(image, dtype=np.float32)
    h, w = img.shape
    half = int(np.ceil(radius_px)) + 2
    padded = np.pad(img, half, mode="constant")
    view = np.lib.stride_tricks.sliding_window_view(padded, (2 * half + 1, 2 * half + 1))
    off = np.arange(-half, half + 1, dtype=np.float32)
    gx = np.tile(off, off.size)
    gy = np.repeat(off, off.size)
    g = np.hypot(gx, gy)
    slack = 0.75  # |sub-pixel offset| allowed after re-centring, plus margin
    inner = g <= radius_px - 0.5 - slack
    ring = np.flatnonzero((g > radius_px - 0.5 - slack) & (g < radius_px + 0.5 + slack))
    fixed_w = np.stack([inner, inner * gx, inner * gy], axis=1).astype(np.float32)
    disc_w = (g <= radius_px).astype(np.float32)
    gxr, gyr = gx[ring][None, :], gy[ring][None, :]
    centres = np.array(start, dtype=np.float64)
    flux = np.zeros(len(centres))
    converged = np.zeros(len(centres), bool)
    chunk = 4 * CHUNK  # read at call time (tests shrink CHUNK to exercise the threads)

    def gather(base: np.ndarray) -> np.ndarray:
        bx = np.clip(base[:, 0], 0, w - 1)
        by = np.clip(base[:, 1], 0, h - 1)
        pt = view[by, bx].reshape(len(base), -1)  # padded index = pixel + half
        return pt - pt.min(axis=1, keepdims=True)

    def one(sl: slice) -> None:
        s, e = sl.start, sl.stop
        base = np.round(centres[s:e]).astype(np.int64)
        pt = gather(base)
        # 1. plain centroid in the fixed disc → re-centre to the nearest pixel
        s0 = pt @ disc_w
        ok = s0 > 0
        cx = (pt @ (disc_w * gx)) / np.where(ok, s0, 1.0)
        cy = (pt @ (disc_w * gy)) / np.where(ok, s0, 1.0)
        first = base + np.column_stack([np.where(ok, cx, 0.0), np.where(ok, cy, 0.0)])
        base = np.column_stack([np.clip(np.round(first[:, 0]), 0, w - 1),
                                np.clip(np.round(first[:, 1]), 0, h - 1)]).astype(np.int64)
        pt = gather(base)
        dxy = (first - base).astype(np.float32)
        # 2. soft circle: fixed inner sums + per-iteration ring weights
        sums = pt @ fixed_w  # (n, 3): Σ I, Σ I x, Σ I y over the always-inside pixels
        pr = pt[:, ring]
        gr = np.stack([np.ones_like(gxr[0]), gxr[0], gyr[0]], axis=1)  # (ring, 3)
        step = np.full(e - s, np.inf, dtype=np.float32)
        s0 = np.zeros(e - s, dtype=np.float32)
        ok = np.zeros(e - s, bool)
        act = np.arange(e - s)  # lenses still moving
        for _ in range(iterations):
            d = dxy[act]
            wr = np.clip(radius_px + 0.5 - np.sqrt((gxr - d[:, :1]) ** 2 + (gyr - d[:, 1:]) ** 2),
                         0.0, 1.0)
            tot = sums[act] + (wr * pr[act]) @ gr
            good = tot[:, 0] > 0
            new = np.where(good[:, None], tot[:, 1:] / np.where(good, tot[:, 0], 1.0)[:, None], d)
            step[act] = np.abs(new - d).max(axis=1)
            dxy[act] = new
            s0[act] = tot[:, 0]
            ok[act] = good
            act = act[step[act] >= tol_px]
            if act.size == 0:
                break
        centres[s:e] = base + dxy.astype(np.float64)
        flux[s:e] = s0
        converged[s:e] = ok & (step < 10 * tol_px) & (np.abs(dxy) <= slack).all(axis=1)
    # chunks on threads (each writes its own slice); progress once, from this thread
    _run_chunks(one, len(centres), chunk)
    progress("centroids", len(centres), len(centres))
    return centres, flux, converged
