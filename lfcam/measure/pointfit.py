"""Light-field measurement of a point-like source: triangulation through the exact lens.

A point source lights a cluster of lenslets; under each lenslet its light forms a compact spot
whose offset from the lenslet centre is ``f_x`` times the mean slope of the rays that crossed
that lenslet (ideal thin lenslets). Traced *backward* through the exact main lens, each
(lenslet centre, mean slope) pair is a line in object space that passes, to second order in
the lenslet size, through the source. The source is the intensity-weighted least-squares point
closest to all those lines — a 3×3 linear solve, no model error, no iterations.

Spots near the seam of two micro-images (fast systems overlap by ~10 %, docs/calibration.md) are
ambiguous between two lenslets; they are assigned with the smoothness of the slope field:
a robust affine model ``offset = a + B·C`` of spot offset against lenslet centre is fitted on
unambiguous spots, then every spot goes to the candidate lenslet that model explains best.
The signed rim-ray heights (y1, y2) then follow from the exact forward trace of the source.

Behind the focused plane each lenslet images only a small patch of the pupil: its spot spans
2–4 pixels, and pixel integration moves a spot's centroid by up to half a pixel (0.15 px RMS,
zero mean, but smooth across lenslets). The triangulation reads that as a change of the slope
field: −1.5 % of distance at 3.5 m (system 2, focus 1 m). The threshold that cuts spots from
the data and the sensor edge bias it too. :func:`fit_point` therefore simulates the statistic
through the same chain as the data: rays are binned into pixels of the region's box, spots are
cut with the same threshold and mask and assigned the same way (``SpotExtraction``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from lfcam.camera import CameraProfile
from lfcam.measure.noise import clipped_mean
from lfcam.measure.sampling import pixel_boxes, vogel_disc
from lfcam.optics.trace import trace_backward_fast, trace_source_fast, trace_sources_fast
from lfcam.status import RegionStatus

MIN_SPOTS = 6
PARTIAL_FRACTION = 0.5  # lenslets dimmer than this × the median are edge (partially lit) ones
PUPIL_SAMPLES = 160  # per side of the stratified pupil grid of the forward model (~20 k rays)
SPOT_PUPIL_SAMPLES = 480  # per side when the statistic is simulated through pixels (~180 k rays)
MAX_ITERATIONS = 8
SPOT_ITERATIONS = 12


@dataclass(frozen=True)
class PointFit:
    """Result of triangulating one point-like region."""

    source_mm: np.ndarray  # (3,) x, y, z of the source (z < 0, in front of the lens)
    covariance_mm2: np.ndarray  # (3, 3)
    spots: int  # spots used
    rms_miss_mm: float  # weighted RMS distance of the lines from the source
    ok: bool
    reason: str = ""


def find_spots(image: np.ndarray, mask: np.ndarray, threshold: float):
    """Connected bright spots inside ``mask``: (centroid_px (M, 2), energy (M,))."""
    lit = ((image > threshold) & mask).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(lit, connectivity=8)
    if n <= 1:
        return np.zeros((0, 2)), np.zeros(0)
    lab = labels.ravel()
    keep = lab > 0
    val = image.ravel()[keep].astype(np.float64)
    idx = np.flatnonzero(keep)
    yy, xx = np.divmod(idx, image.shape[1])
    lk = lab[keep]
    e = np.bincount(lk, val, minlength=n)[1:]
    cx = np.bincount(lk, val * xx, minlength=n)[1:] / e
    cy = np.bincount(lk, val * yy, minlength=n)[1:] / e
    return np.column_stack([cx, cy]), e


def _affine_fit(c: np.ndarray, off: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted least squares ``off ≈ [1, cx, cy] @ M`` (M: 3×2)."""
    a = np.column_stack([np.ones(len(c)), c])
    sw = np.sqrt(w)[:, None]
    m, *_ = np.linalg.lstsq(a * sw, off * sw, rcond=None)
    return m


def assign_spots(
    spots_mm: np.ndarray, weights: np.ndarray, lens_centres_mm: np.ndarray, pitch_mm: float,
    magnification: float,
) -> np.ndarray:
    """Lenslet index of every spot (see module docstring); −1 where none fits.

    Parameters
    ----------
    spots_mm : (M, 2) spot centroids on the sensor, mm from the axis.
    weights : (M,) spot energies.
    lens_centres_mm : (N, 2) lenslet centres on the MLA plane.
    pitch_mm : lenslet pitch.
    magnification : micro-image centre = lenslet centre × magnification (chief ray).
    """
    tree = cKDTree(lens_centres_mm * magnification)
    dist, cand = tree.query(spots_mm, k=min(4, len(lens_centres_mm)))
    cand = np.atleast_2d(cand)
    dist = np.atleast_2d(dist)
    first = cand[:, 0]
    # unambiguous: clearly nearer one micro-image centre than the next
    clear = (dist[:, 1] - dist[:, 0]) > 0.25 * pitch_mm * magnification if dist.shape[1] > 1 \
        else np.ones(len(first), bool)
    if clear.sum() < 3:
        return first
    centres = lens_centres_mm[first]
    model = _affine_fit(centres[clear], spots_mm[clear] - centres[clear], weights[clear])
    best = first.copy()
    best_err = np.full(len(first), np.inf)
    for k in range(cand.shape[1]):
        c = lens_centres_mm[cand[:, k]]
        pred = np.column_stack([np.ones(len(c)), c]) @ model
        err = np.hypot(*(spots_mm - c - pred).T)
        better = err < best_err
        best[better], best_err[better] = cand[better, k], err[better]
    best[best_err > 0.5 * pitch_mm] = -1
    return best


def triangulate_lines(points: np.ndarray, dirs: np.ndarray, w: np.ndarray):
    """Weighted least-squares point nearest to lines (point, unit direction); (S, cov, rms)."""
    proj = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]
    a = np.einsum("n,nij->ij", w, proj)
    b = np.einsum("n,nij,nj->i", w, proj, points)
    s = np.linalg.solve(a, b)
    resid = np.einsum("nij,nj->ni", proj, s[None] - points)
    r2 = (resid**2).sum(1)
    dof = max(2 * len(w) - 3, 1)
    sigma2 = float((w * r2).sum() / w.sum()) * len(w) / dof
    # lines are independent measurements: cov = σ² (Σ w P)⁻¹ (Σ w² P) (Σ w P)⁻¹ / (Σ w)… → use
    # the standard weighted normal-equation form with weights normalised to mean 1
    wn = w / w.mean()
    an = np.einsum("n,nij->ij", wn, proj)
    cov = sigma2 * np.linalg.inv(an)
    return s, cov, float(np.sqrt(sigma2))


def _lenslet_lines(lens, d_in_mm, fx, centres_mm, energy, landing_mm):
    """Backward-traced object-space line of each well-lit lenslet: (points, dirs, weights)."""
    full = energy >= PARTIAL_FRACTION * np.median(energy)
    c = centres_mm[full]
    slope = (landing_mm[full] - c) / fx
    tr = trace_backward_fast(lens, c[:, 0], c[:, 1], d_in_mm, slope[:, 0], slope[:, 1])
    ok = tr.ok
    pts = np.column_stack([tr.x, tr.y, tr.z])[ok]
    dirs = np.column_stack([tr.dx, tr.dy, tr.dz])[ok]
    return pts, dirs, energy[full][ok]


def _statistic(lens, d_in_mm, fx, centres_mm, energy, landing_mm):
    """The triangulated point of a set of lenslet measurements (the fit's summary statistic)."""
    pts, dirs, w = _lenslet_lines(lens, d_in_mm, fx, centres_mm, energy, landing_mm)
    if len(w) < MIN_SPOTS:
        return None
    return triangulate_lines(pts, dirs, w)


def pupil_pattern(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Stratified points of the unit disc (cell centres of an n×n grid inside the disc)."""
    g = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    u, v = np.meshgrid(g, g)
    inside = u * u + v * v <= 1.0
    return u[inside], v[inside]


def simulate_lenslets(profile, d_in_mm, source_mm, tree: cKDTree, centres_mm, pattern):
    """Per-lenslet energy and mean landing point of a point source (exact trace, ideal lenslets).

    This is what the camera records of the source (the micro-image energy and centroid of each
    lenslet), up to pixel integration, which does not move centroids.
    """
    lens = profile.main_lens
    fx = profile.mla.focal_length_mm
    half = 0.5 * lens.pupil_diameter_mm
    rx, ry = pattern[0] * half, pattern[1] * half
    tr = trace_source_fast(lens, tuple(source_mm), rx, ry, d_in_mm)
    ok = tr.ok
    x, y = tr.x[ok], tr.y[ok]
    sx, sy = tr.dx[ok] / tr.dz[ok], tr.dy[ok] / tr.dz[ok]
    # solid angle of each rim-plane cell seen from the source ∝ cos³θ / L²
    along = lens.rim_z_mm - source_mm[2]
    rho2 = (rx[ok] - source_mm[0]) ** 2 + (ry[ok] - source_mm[1]) ** 2 + along**2
    w = (along / np.sqrt(rho2)) ** 3
    _, k = tree.query(np.column_stack([x, y]))
    n = len(centres_mm)
    e = np.bincount(k, w, minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        lx = centres_mm[:, 0] + fx * np.bincount(k, w * sx, minlength=n) / e
        ly = centres_mm[:, 1] + fx * np.bincount(k, w * sy, minlength=n) / e
    return e, np.column_stack([lx, ly])


@dataclass(frozen=True)
class SpotExtraction:
    """How the measured spots were cut from the data, so that a simulation can repeat it.

    ``box`` = (x0, y0, x1, y1) of the region in sensor pixels, ``mask`` (y1−y0, x1−x0) the
    pixels spots may use, ``threshold`` the absolute level of :func:`find_spots` and
    ``energy`` the data's sum over the mask (the simulation is scaled to it).
    """

    box: tuple[int, int, int, int]
    mask: np.ndarray
    threshold: float
    energy: float


def _lenslet_of(lattice: LocalLattice | None, tree: cKDTree, centres: np.ndarray, pitch: float,
                x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre (x, y) of the lenslet each MLA point crosses; NaN where it is unknown.

    With a lattice the crossed cell is exact, also beyond the calibrated lenslets (their light
    may still reach the region, or fall off the sensor). Otherwise the nearest calibrated
    centre, within 0.75 pitch.
    """
    if lattice is not None:
        cx, cy = lattice.node(x, y)
        return cx, cy
    d, k = tree.query(np.column_stack([x, y]))
    cx, cy = centres[k, 0].copy(), centres[k, 1].copy()
    far = d > 0.75 * pitch
    cx[far] = np.nan
    cy[far] = np.nan
    return cx, cy


def simulate_spots(profile, d_in_mm, source_mm, extraction: SpotExtraction, lattice, tree,
                   centres_mm, pattern):
    """Spots a point source would give through the data's own chain (pixels, threshold, mask).

    Rays are traced exactly, cross the lenslet whose cell they hit, land at
    ``C + f_x·slope`` and are added to the pixel that contains them (the sensor integrates);
    the box image is scaled to the data's energy and cut by :func:`find_spots`.
    Returns (spots_px (M, 2), energy (M,)) in sensor pixels.
    """
    lens = profile.main_lens
    fx = profile.mla.focal_length_mm
    pp = profile.sensor.pixel_pitch_mm
    ax, ay = profile.sensor.axis_xy_px
    half = 0.5 * lens.pupil_diameter_mm
    rx, ry = pattern[0] * half, pattern[1] * half
    tr = trace_source_fast(lens, tuple(source_mm), rx, ry, d_in_mm)
    ok = tr.ok
    along = lens.rim_z_mm - source_mm[2]
    rho2 = (rx[ok] - source_mm[0]) ** 2 + (ry[ok] - source_mm[1]) ** 2 + along**2
    w = (along * along / rho2) ** 1.5
    cx, cy = _lenslet_of(lattice, tree, centres_mm, profile.mla.pitch_mm, tr.x[ok], tr.y[ok])
    px = (cx + fx * tr.dx[ok] / tr.dz[ok]) / pp + ax
    py = (cy + fx * tr.dy[ok] / tr.dz[ok]) / pp + ay
    x0, y0, x1, y1 = extraction.box
    h, w_box = y1 - y0, x1 - x0
    with np.errstate(invalid="ignore"):
        col = np.floor(px + 0.5) - x0
        row = np.floor(py + 0.5) - y0
        inside = (col >= 0) & (col < w_box) & (row >= 0) & (row < h)
    img = np.bincount((row[inside] * w_box + col[inside]).astype(np.int64), w[inside],
                      minlength=h * w_box).reshape(h, w_box)
    total = float(img[extraction.mask].sum())
    if not total > 0:
        return np.zeros((0, 2)), np.zeros(0)
    img *= extraction.energy / total
    spots, energy = find_spots(img, extraction.mask, extraction.threshold)
    return spots + np.array([x0, y0]), energy


def _spot_statistic(profile, d_in_mm, spots_px, energy, lens_centres_mm, mag):
    """Assign spots to lenslets and triangulate: (statistic or None, lit lenslet indices)."""
    lens = profile.main_lens
    fx = profile.mla.focal_length_mm
    pp = profile.sensor.pixel_pitch_mm
    ax, ay = profile.sensor.axis_xy_px
    if len(spots_px) < MIN_SPOTS:
        return None, np.zeros(0, dtype=np.int64)
    spots_mm = np.column_stack([(spots_px[:, 0] - ax) * pp, (spots_px[:, 1] - ay) * pp])
    k = assign_spots(spots_mm, energy, lens_centres_mm, profile.mla.pitch_mm, mag)
    good = k >= 0
    n = len(lens_centres_mm)
    e_meas = np.bincount(k[good], energy[good], minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        land = np.column_stack([
            np.bincount(k[good], energy[good] * spots_mm[good, 0], minlength=n) / e_meas,
            np.bincount(k[good], energy[good] * spots_mm[good, 1], minlength=n) / e_meas,
        ])
    lit = np.flatnonzero(e_meas > 0)
    return _statistic(lens, d_in_mm, fx, lens_centres_mm[lit], e_meas[lit], land[lit]), lit


def fit_point(
    profile: CameraProfile,
    d_in_mm: float,
    spots_px: np.ndarray,
    energy: np.ndarray,
    lens_centres_mm: np.ndarray,
    extraction: SpotExtraction | None = None,
) -> PointFit:
    """Locate a point source from its spots (see module docstring).

    The triangulation of the measured lenslet lines is a biased summary of the source when the
    slope field folds inside a lenslet (F/2 spherical aberration beyond focus). The fit removes
    the bias by indirect inference: it simulates the same summary from a candidate source with
    the exact forward model and moves the candidate by the difference,
    ``S ← S + (T_measured − T_simulated(S))``, until the step is below 1e-6 of the distance.

    Parameters
    ----------
    profile : CameraProfile
    d_in_mm : float
        Calibrated MLA distance.
    spots_px : (M, 2) spot centroids in sensor pixels (x, y).
    energy : (M,) spot energies.
    lens_centres_mm : (N, 2) lenslet centres on the MLA plane.
    extraction : SpotExtraction, optional
        How ``spots_px`` were cut from the data. With it, the simulated statistic goes through
        pixels, threshold and assignment like the data's (needed behind focus, where spots are
        2–4 px and pixel integration moves their centroids); without it, per-lenslet ray
        centroids are used (exact only for spots much larger than a pixel).
    """
    lens = profile.main_lens
    fx = profile.mla.focal_length_mm
    ax, ay = profile.sensor.axis_xy_px
    nan3, nan33 = np.full(3, np.nan), np.full((3, 3), np.nan)
    if len(spots_px) < MIN_SPOTS:
        return PointFit(nan3, nan33, len(spots_px), np.nan, False, RegionStatus.NEAR_FOCUS)
    mag = 1.0 + fx / (d_in_mm - lens.exit_pupil_z_mm)
    measured, lit = _spot_statistic(profile, d_in_mm, spots_px, energy, lens_centres_mm, mag)
    n_lit = int(len(lit))
    if measured is None:
        return PointFit(nan3, nan33, n_lit, np.nan, False, RegionStatus.NEAR_FOCUS)
    t_meas, cov, rms = measured
    if not (np.isfinite(t_meas).all() and t_meas[2] < lens.front_vertex_z_mm):
        return PointFit(t_meas, cov, n_lit, rms, False, RegionStatus.NO_SOLUTION)
    if extraction is not None:
        return _fit_point_spots(profile, d_in_mm, lens_centres_mm, mag, extraction, t_meas,
                                cov, rms, n_lit)
    # neighbourhood of the lit lenslets for the forward model's binning
    tree_all = cKDTree(lens_centres_mm)
    near = np.unique(np.concatenate(tree_all.query_ball_point(
        lens_centres_mm[lit], 3.0 * profile.mla.pitch_mm)))
    centres = lens_centres_mm[near]
    tree = cKDTree(centres)
    pattern = pupil_pattern(PUPIL_SAMPLES)
    source = t_meas.copy()
    for _ in range(MAX_ITERATIONS):
        e_sim, land_sim = simulate_lenslets(profile, d_in_mm, source, tree, centres, pattern)
        lit_sim = e_sim > 0
        sim = _statistic(lens, d_in_mm, fx, centres[lit_sim], e_sim[lit_sim], land_sim[lit_sim])
        if sim is None:
            return PointFit(source, cov, int(len(lit)), rms, False, RegionStatus.NEAR_FOCUS)
        step = t_meas - sim[0]
        source = source + step
        if not (np.isfinite(source).all() and source[2] < lens.front_vertex_z_mm):
            return PointFit(source, cov, int(len(lit)), rms, False, RegionStatus.NO_SOLUTION)
        if abs(step[2]) < 1e-6 * abs(source[2]):
            break
    return PointFit(source, cov, int(len(lit)), rms, True)


def _fit_point_spots(profile, d_in_mm, lens_centres_mm, mag, extraction, t_meas, cov, rms,
                     n_lit) -> PointFit:
    """Indirect inference with the statistic simulated through pixels (``SpotExtraction``).

    The simulated statistic is piecewise constant on the scale where spots cross pixel
    borders, so the fixed-point iteration ends in a small cycle: it stops when the step falls
    below 1e-5 of the distance or returns the mean of its last iterates.
    """
    lens = profile.main_lens
    lattice = LocalLattice.fit(lens_centres_mm, profile.mla.pitch_mm)
    tree = cKDTree(lens_centres_mm)
    pattern = pupil_pattern(SPOT_PUPIL_SAMPLES)
    source = t_meas.copy()
    history = []
    for _ in range(SPOT_ITERATIONS):
        spots, energy = simulate_spots(profile, d_in_mm, source, extraction, lattice, tree,
                                       lens_centres_mm, pattern)
        sim, _ = _spot_statistic(profile, d_in_mm, spots, energy, lens_centres_mm, mag)
        if sim is None:
            return PointFit(source, cov, n_lit, rms, False, RegionStatus.NEAR_FOCUS)
        step = t_meas - sim[0]
        source = source + step
        if not (np.isfinite(source).all() and source[2] < lens.front_vertex_z_mm):
            return PointFit(source, cov, n_lit, rms, False, RegionStatus.NO_SOLUTION)
        history.append(source.copy())
        if abs(step[2]) < 1e-5 * abs(source[2]):
            break
    else:
        source = np.mean(history[-4:], axis=0)
    return PointFit(source, cov, n_lit, rms, True)


# ----------------------------------------------------------------------------- image matching

IMAGE_PUPIL_SAMPLES = 180  # per side (~25 k rays per model evaluation)
SCAN_PUPIL_SAMPLES = 72  # per side for the basin-finding distance scan (~4 k rays)
MATCH_BLUR_PX = 0.8  # both model and data are smoothed alike before comparison
SPLAT_BOX_PX = 0.5  # each model ray is binned as a box this wide (the pupil patch it stands for)
DATA_BLUR_PX = float(np.sqrt(MATCH_BLUR_PX**2 + SPLAT_BOX_PX**2 / 12.0))  # data: + its σ
GOOD_MISFIT = 0.08  # a start whose refined misfit is below this needs no distance scan
BEHIND_FOCUS_RAYS = 4  # behind focus the end of the point fit is redone with this × the rays
CLIP_SCALE_STEPS = 3  # Gauss–Newton steps of the scale on a clipped capture (_Patch)


@dataclass(frozen=True)
class ImageFit:
    """Source found by matching the exact forward model to the pixels of a region."""

    source_mm: np.ndarray  # (3,)
    misfit: float  # relative residual |data − a·model| / |data|
    sigma_distance_mm: float  # from the curvature of the misfit along the distance
    evaluations: int
    ok: bool
    reason: str = ""


NEAREST_KEPT = 16  # LocalLattice.fit: nearest centres searched for the basis first


@dataclass(frozen=True)
class LocalLattice:
    """Exact nearest-lenslet lookup for centres that form an affine lattice."""

    origin: np.ndarray  # (2,)
    basis: np.ndarray  # (2, 2), columns a1, a2
    inverse: np.ndarray
    table: np.ndarray  # (ni, nj) index into the centres, −1 where none
    i0: int
    j0: int
    centres: np.ndarray

    @classmethod
    def fit(cls, centres: np.ndarray, pitch_mm: float) -> LocalLattice | None:
        """Fit the lattice through ``centres``; ``None`` if they are not one (→ k-d tree)."""
        c = np.asarray(centres, dtype=np.float64)
        if len(c) < 4:
            return None
        ref = c[0]
        d = c - ref
        # nominal basis from the nearest neighbours of the reference centre (the nearest
        # NEAREST_KEPT in order, partitioned out of all: a full sort of an Illum's 235 000
        # took 20 ms; all of them where those hold no second direction)
        r = np.hypot(d[:, 0], d[:, 1])
        for keep in (min(NEAREST_KEPT, len(r)), len(r)):
            near = np.argpartition(r, keep - 1)[:keep] if keep < len(r) else np.arange(len(r))
            order = near[np.argsort(r[near])][1:]
            a1 = d[order[0]]
            a2 = next((d[k] for k in order[1:]
                       if abs(a1[0] * d[k][1] - a1[1] * d[k][0]) > 0.5 * pitch_mm * pitch_mm),
                      None)
            if a2 is not None:
                break
        else:
            return None
        ij = np.round(np.linalg.solve(np.column_stack([a1, a2]), d.T).T).astype(np.int64)
        a = np.column_stack([np.ones(len(ij)), ij])
        coef, *_ = np.linalg.lstsq(a, c, rcond=None)
        if np.sqrt(((a @ coef - c) ** 2).sum(axis=1).mean()) > 1e-3 * pitch_mm:
            return None
        basis = np.column_stack([coef[1], coef[2]])
        i0, j0 = ij.min(axis=0)
        table = np.full(tuple(ij.max(axis=0) - ij.min(axis=0) + 1), -1, dtype=np.int64)
        table[ij[:, 0] - i0, ij[:, 1] - j0] = np.arange(len(c))
        return cls(coef[0], basis, np.linalg.inv(basis), table, int(i0), int(j0), c)

    def node(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centre of the lattice cell (Voronoi) holding each point, in or beyond the set."""
        bi, bj = self.cell_indices(x, y)
        return (self.origin[0] + self.basis[0, 0] * bi + self.basis[0, 1] * bj,
                self.origin[1] + self.basis[1, 0] * bi + self.basis[1, 1] * bj)

    def cell_indices(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Lattice indices (i, j) of the nearest node of each point."""
        u = self.inverse @ np.vstack([x - self.origin[0], y - self.origin[1]])
        fu, fv = np.floor(u[0]), np.floor(u[1])
        best = np.full(x.shape, np.inf)
        bi = np.zeros(x.shape, dtype=np.int64)
        bj = np.zeros(x.shape, dtype=np.int64)
        for di in (0.0, 1.0):
            for dj in (0.0, 1.0):
                ci, cj = fu + di, fv + dj
                px = self.origin[0] + self.basis[0, 0] * ci + self.basis[0, 1] * cj
                py = self.origin[1] + self.basis[1, 0] * ci + self.basis[1, 1] * cj
                dist = (x - px) ** 2 + (y - py) ** 2
                better = dist < best
                best[better] = dist[better]
                bi[better], bj[better] = ci[better], cj[better]
        return bi, bj

    def nearest(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Index of the lenslet whose Voronoi cell holds each point (−1: not in the set)."""
        bi, bj = self.cell_indices(x, y)
        ti, tj = bi - self.i0, bj - self.j0
        inside = (ti >= 0) & (ti < self.table.shape[0]) & (tj >= 0) & (tj < self.table.shape[1])
        out = np.full(x.shape, -1, dtype=np.int64)
        out[inside] = self.table[ti[inside], tj[inside]]
        return out


class _Patch:
    """Forward model of one region: renders a candidate source into the region's pixels."""

    def __init__(self, profile, d_in_mm, image, box, lens_centres_mm, floor_sigma=0.0):
        x0, y0, x1, y1 = box
        # other sources' light in the box, unit intensity, before the blur and after it (fixed:
        # blurred once, add_others)
        self.others: list[np.ndarray] = []
        self.others_blurred: list[np.ndarray] = []
        # a capture that clips its noise at zero reads E[max(0, s + n)] (σ of n: this), not s
        # (lfcam.measure.noise.clipped_mean); 0: it does not clip
        self.floor_sigma = float(floor_sigma)
        self.profile, self.d_in = profile, d_in_mm
        self.box = box
        self.shape = (y1 - y0, x1 - x0)
        # the model bins each ray into pixels like the sensor, as a box SPLAT_BOX_PX wide
        # (pixel box ⊛ ray box): the data get that box's variance as extra blur
        self.data = cv2.GaussianBlur(np.asarray(image[y0:y1, x0:x1], np.float64), (0, 0),
                                     DATA_BLUR_PX)
        self.norm = float(np.sqrt((self.data**2).sum()))
        self.tree = cKDTree(lens_centres_mm)
        self.centres = lens_centres_mm
        self.lattice = LocalLattice.fit(lens_centres_mm, profile.mla.pitch_mm)
        # a quasi-random (Vogel) pupil sample of the grid's ray count: a regular grid aliases
        # with the pixels and leaves ±0.3 % ripples in the misfit along the line of sight
        self.pattern = vogel_disc(len(pupil_pattern(IMAGE_PUPIL_SAMPLES)[0]))
        self.evaluations = 0

    def render(self, source_mm, pattern=None):
        """Model image of a unit-intensity source (blurred like the data).

        ``source_mm`` is one point (3,) or several (M, 3) of equal intensity (a line).
        """
        return cv2.GaussianBlur(self.render_pixels(source_mm, pattern), (0, 0), MATCH_BLUR_PX)

    def render_pixels(self, source_mm, pattern=None):
        """:meth:`render` before its blur: the rays binned into the box's pixels."""
        p = self.profile
        lens = p.main_lens
        half = 0.5 * lens.pupil_diameter_mm
        pattern = self.pattern if pattern is None else pattern
        points = np.atleast_2d(np.asarray(source_mm, dtype=np.float64))
        xs, ys, sxs, sys_, ws = [], [], [], [], []
        rx, ry = pattern[0] * half, pattern[1] * half
        for pt in points:
            tr = trace_source_fast(lens, tuple(pt), rx, ry, self.d_in)
            ok = tr.ok
            xs.append(tr.x[ok])
            ys.append(tr.y[ok])
            sxs.append(tr.dx[ok] / tr.dz[ok])
            sys_.append(tr.dy[ok] / tr.dz[ok])
            # each rim-plane cell carries the solid angle it subtends at the source, ∝ cos³θ
            along = lens.rim_z_mm - pt[2]
            rho2 = (rx[ok] - pt[0]) ** 2 + (ry[ok] - pt[1]) ** 2 + along * along
            ws.append((along * along / rho2) ** 1.5)
        x, y = np.concatenate(xs), np.concatenate(ys)
        weight = np.concatenate(ws)
        if self.lattice is not None:
            k = self.lattice.nearest(x, y)
            known = k >= 0
            x, y, weight, k = x[known], y[known], weight[known], k[known]
            sx_all, sy_all = np.concatenate(sxs)[known], np.concatenate(sys_)[known]
        else:
            _, k = self.tree.query(np.column_stack([x, y]))
            sx_all, sy_all = np.concatenate(sxs), np.concatenate(sys_)
        c = self.centres[k]
        fx = p.mla.focal_length_mm
        pp = p.sensor.pixel_pitch_mm
        ax, ay = p.sensor.axis_xy_px
        px = (c[:, 0] + fx * sx_all) / pp + ax - self.box[0]
        py = (c[:, 1] + fx * sy_all) / pp + ay - self.box[1]
        h, w = self.shape
        # Binned into the pixel that holds each ray, as the sensor integrates, but each ray a
        # box SPLAT_BOX_PX wide so that the image stays continuous in the source position. The
        # former bilinear splat (a tent, matched to the pixel box in variance only) biased
        # 1–2 px spots behind focus by up to −1.3 % (docs/distance.md).
        jx, jy, wt = pixel_boxes(px, py, weight, SPLAT_BOX_PX)
        inside = (jx >= 0) & (jx < w) & (jy >= 0) & (jy < h)
        return np.bincount(jy[inside] * w + jx[inside], wt[inside], minlength=h * w).astype(
            np.float64).reshape(h, w)  # (no ray inside: bincount's int64, GaussianBlur refuses)

    def residual(self, source_mm, pattern=None) -> np.ndarray:
        """Data minus the best-scaled model, over ‖data‖: the scale in closed form, or, on a
        capture that clips its noise at zero, the model's pixels ``a·m`` read as the clipped
        mean ``E[max(0, a·m + n)]`` and ``a`` by Gauss–Newton (:meth:`_clipped_model`)."""
        self.evaluations += 1
        own = self.render_pixels(source_mm, pattern)
        blurred = [cv2.GaussianBlur(own, (0, 0), MATCH_BLUR_PX)] + self.others_blurred
        if self.floor_sigma > 0:
            model = self._clipped_model([own] + self.others, blurred)
        else:
            model = self._linear_model(blurred)
        return ((self.data - model) / self.norm).ravel()

    def add_others(self, sources_mm: list[np.ndarray]) -> None:
        """Model the light of other sources (points) in the box as well, each at its own free
        intensity: a touching blur's edge lenslets that the region took in are explained, not
        fitted by moving this source (docs/distance.md, "Touching blurs fitted together").
        Rendered once, with 4× the rays of a model evaluation; a source that puts no light in
        the box is left out."""
        dense = vogel_disc(4 * len(self.pattern[0]))
        for src in sources_mm:
            img = self.render_pixels(np.asarray(src, dtype=np.float64), dense)
            if img.sum() > 0:
                self.others.append(img)
                self.others_blurred.append(cv2.GaussianBlur(img, (0, 0), MATCH_BLUR_PX))

    def _linear_model(self, cols: list[np.ndarray]) -> np.ndarray:
        """Σ aₖ·cₖ at the least-squares scales (the others' at ≥ 0); ``cols``: the blurred
        components, this source's first."""
        if len(cols) == 1:
            m = cols[0]
            mm = float((m * m).sum())
            return m * (float((m * self.data).sum()) / mm if mm > 0 else 0.0)
        a = np.stack([c.ravel() for c in cols], axis=1)
        use = np.ones(len(cols), dtype=bool)
        full = np.zeros(len(cols))
        for _ in range(len(cols)):
            full[:] = 0.0
            full[use] = np.linalg.lstsq(a[:, use], self.data.ravel(), rcond=None)[0]
            negative = use & (full < 0)
            negative[0] = False  # this source's own scale is free
            if not negative.any():
                break
            use &= ~negative
        return (a @ full).reshape(self.data.shape)

    def _clipped_model(self, pixels: list[np.ndarray], blurred: list[np.ndarray]) -> np.ndarray:
        """The blurred model image of the clipped capture, ``B(E[max(0, Σ aₖ·pₖ + n)])``, at
        the best scales ``aₖ`` (least squares against the data; ``pₖ``: this source's pixels,
        then the others'): the dark pixels' floor (0.4 σ) and the dim ones' excess are in the
        model, not left in the residual, where they widened and lengthened dim blurs
        (docs/distance.md, "The clipped dark floor, and the pixel fit's own rays behind
        focus").

        ``blurred``: the components ``pₖ`` after the blur. The scales start from the linear
        fit to the data less the floor and take
        ``CLIP_SCALE_STEPS`` Gauss–Newton steps (the model is linear in them where the
        signal is over ~2 σ: a step or two settles them)."""
        sigma = self.floor_sigma
        floor = float(clipped_mean(np.zeros(1), sigma)[0][0])
        cols = np.stack([b.ravel() for b in blurred], axis=1)
        if not float((cols * cols).sum()) > 0:
            return np.full_like(self.data, floor)
        a = np.clip(np.linalg.lstsq(cols, self.data.ravel() - floor, rcond=None)[0], 0.0,
                    None)
        stack = np.stack(pixels)
        for _ in range(CLIP_SCALE_STEPS):
            value, slope = clipped_mean(np.tensordot(a, stack, 1), sigma)
            model = cv2.GaussianBlur(value, (0, 0), MATCH_BLUR_PX)
            jac = np.stack([cv2.GaussianBlur(slope * p, (0, 0), MATCH_BLUR_PX).ravel()
                            for p in pixels], axis=1)
            step = np.linalg.lstsq(jac, (self.data - model).ravel(), rcond=None)[0]
            a = np.clip(a + step, 0.0, None)
            if np.all(np.abs(step) <= 1e-6 * np.maximum(np.abs(a), 1e-300)):
                break
        value, _ = clipped_mean(np.tensordot(a, stack, 1), sigma)
        return cv2.GaussianBlur(value, (0, 0), MATCH_BLUR_PX)

    def misfit(self, source_mm, pattern=None) -> float:
        """Relative residual norm after the best intensity scale."""
        r = self.residual(source_mm, pattern)
        return float(np.sqrt((r * r).sum()))


def _centroid_px(img: np.ndarray) -> np.ndarray:
    tot = img.sum()
    if tot <= 0:
        return np.full(2, np.nan)
    yy, xx = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    return np.array([(xx * img).sum() / tot, (yy * img).sum() / tot])


def _match_centroid(patch, profile, d_in_mm, distance_mm, target_xy_mm, z_front, pattern=None):
    """Lateral source position at a trial distance whose *modelled* light centroid matches the
    data's: chief-ray start, then two Newton steps through the exact render (coma and
    aberrations move the light centroid off the chief ray)."""
    xy = chief_ray_offset(profile, d_in_mm, distance_mm, target_xy_mm)
    want = _centroid_px(patch.data)
    gain = None
    for _ in range(2):
        got = _centroid_px(patch.render(np.array([xy[0], xy[1], z_front - distance_mm]),
                                        pattern))
        patch.evaluations += 1
        if not np.isfinite(got).all():
            break
        if gain is None:
            g = chief_ray_offset(profile, d_in_mm, distance_mm, np.array([1.0, 0.0]))[0]
            mag = 1.0 + profile.mla.focal_length_mm / (d_in_mm - profile.main_lens.exit_pupil_z_mm)
            gain = g * profile.sensor.pixel_pitch_mm / mag  # source mm per data pixel
        xy = xy + (want - got) * gain
    return xy


def chief_ray_gains(profile, d_in_mm, distances_mm) -> np.ndarray:
    """MLA height per unit source height of the chief ray (through the stop centre), for each
    of ``distances_mm`` in one trace (0 where it does not reach the MLA)."""
    lens = profile.main_lens
    d = np.atleast_1d(np.asarray(distances_mm, dtype=np.float64))
    probe = 1.0
    src = np.column_stack([np.full(d.size, probe), np.zeros(d.size),
                           lens.front_vertex_z_mm - d])
    tr = trace_sources_fast(lens, src, np.zeros(1), np.zeros(1), d_in_mm)
    gain = tr.x[:, 0] / probe  # linear to first order in the source height
    return np.where(np.isfinite(gain), gain, 0.0)


def chief_ray_offset(profile, d_in_mm, distance_mm, target_xy_mm, gain=None):
    """Lateral source position whose chief ray (through the stop centre) meets the MLA at
    ``target_xy_mm`` — the paraxial-free starting point of the image fit at a trial distance.
    ``gain``: :func:`chief_ray_gains` at that distance, when the caller has it."""
    if gain is None:
        gain = float(chief_ray_gains(profile, d_in_mm, distance_mm)[0])
    if gain == 0:
        return np.zeros(2)
    return np.asarray(target_xy_mm, dtype=np.float64) / gain


class PhysicalJacobian:
    """Residual function with a forward-difference Jacobian in physically sized steps.

    Parameters are ``(log distance, lateral mm …)``. Steps are 0.2 % in distance and
    ``1e-4 × distance`` laterally (~0.1 px of image motion): relative steps would vanish for
    lateral positions near 0 and only sample the ray-hopping noise of the render. The residual
    at the point the optimiser just evaluated is reused for the Jacobian's base.
    """

    def __init__(self, residual: Callable[[np.ndarray], np.ndarray]):
        self._residual = residual
        self._last_q: np.ndarray | None = None
        self._last_r: np.ndarray | None = None

    def forget(self) -> None:
        """Drop the remembered residual (the residual function has changed)."""
        self._last_q = self._last_r = None

    def fun(self, q: np.ndarray) -> np.ndarray:
        """Residual at ``q`` (remembered for :meth:`jac`)."""
        r = self._residual(q)
        self._last_q, self._last_r = np.array(q, dtype=np.float64), r
        return r

    def jac(self, q: np.ndarray) -> np.ndarray:
        """Forward-difference Jacobian at ``q``."""
        if self._last_q is not None and np.array_equal(self._last_q, q):
            base = self._last_r
        else:
            base = self.fun(q)
        steps = np.full(len(q), 1e-4 * np.exp(q[0]))
        steps[0] = 2e-3
        cols = []
        for i, h in enumerate(steps):
            dq = np.zeros(len(q))
            dq[i] = h
            cols.append((self._residual(q + dq) - base) / h)
        return np.column_stack(cols)


SURFACE_RISE = 0.04  # the quadratic surface spans where the misfit² rises by this share
SURFACE_SPAN = (1e-3, 0.03)  # its half-width along the line of sight: at least / at most
SURFACE_ROUNDS = 6  # fits of the surface at most, each recentred on the last one's minimum
SURFACE_SETTLED = 0.25  # ... settled when that lies within this (half-widths) of its centre
# the design, in units of the half-widths: centre, axes at ±1 and ±0.5, cube corners at ±0.6
_DESIGN = np.vstack([np.zeros(3), np.eye(3), -np.eye(3), 0.5 * np.eye(3), -0.5 * np.eye(3),
                     0.6 * np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1)
                                     for k in (-1, 1)])])


def _quadratic_basis(t: np.ndarray) -> np.ndarray:
    """(N, 10) full quadratic in three variables."""
    a, b, c = t[:, 0], t[:, 1], t[:, 2]
    return np.column_stack([np.ones(len(t)), a, b, c, a * a, b * b, c * c, a * b, a * c,
                            b * c])


# the least-squares map from the misfit² at the design's points to the surface's coefficients
# (the design is fixed in units of the half-widths: one pseudo-inverse for every fit)
_DESIGN_LSQ = np.linalg.pinv(_quadratic_basis(_DESIGN))  # (10, 21)


def _quadratic_vertices(coef: np.ndarray) -> np.ndarray:
    """Minima of full quadratics (rows of coefficients as :func:`_quadratic_basis`),
    (K, 10) → (K, 3); NaN rows where a quadratic has no minimum."""
    coef = np.atleast_2d(coef)
    h = np.empty((len(coef), 3, 3))
    h[:, 0, 0], h[:, 1, 1], h[:, 2, 2] = 2 * coef[:, 4], 2 * coef[:, 5], 2 * coef[:, 6]
    h[:, 0, 1] = h[:, 1, 0] = coef[:, 7]
    h[:, 0, 2] = h[:, 2, 0] = coef[:, 8]
    h[:, 1, 2] = h[:, 2, 1] = coef[:, 9]
    ok = np.linalg.eigvalsh(h).min(axis=1) > 0
    h[~ok] = np.eye(3)
    t = -np.linalg.solve(h, coef[:, 1:4, None])[..., 0]
    t[~ok] = np.nan
    return t


def _surface_minimum(patch, pupil: np.ndarray, source: np.ndarray, f0: float,
                     curvature: float, block_px: int):
    """The minimum of the misfit² near ``source`` from a least-squares quadratic surface, and
    the σ of its distance by the delete-one-block jackknife.

    Coordinates: the scale ``u`` along the line of sight (the source moves by u·(source −
    pupil)) and the lateral shifts x, y (mm). The design (:data:`_DESIGN`, 21 points) spans
    half-widths where the misfit² rises by :data:`SURFACE_RISE` of its minimum: started from
    the polish's curvature (``curvature``, of the misfit along u) and two probes a lateral
    axis, then rescaled to each fitted surface's own curvature, and recentred on its minimum
    (at most one half-width a round) until that lies within :data:`SURFACE_SETTLED` of the
    design's centre and no half-width would change by more than 1.5×.

    The surface is linear in the misfit² values, and those are sums over pixels: leaving out
    a block of ``block_px``² pixels (about one lenslet) changes its coefficients by that
    block's share, so the jackknife of the minimum, ``(K − 1)/K Σ_k δ_k²``, costs one batched
    3×3 solve (docs/distance.md, "The pixel fit's minimum").

    Returns (source, misfit at the minimum, σ of the distance), or None where a surface has
    no minimum or the rounds end still moving.
    """
    if not (curvature > 0 and f0 > 0):
        return None
    axis = source - pupil
    f02 = f0 * f0
    widths = [float(np.clip(math.sqrt(SURFACE_RISE * f0 / curvature), *SURFACE_SPAN))]
    for e in (np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])):
        d = 1e-4 * abs(float(axis[2]))
        for _ in range(2):
            rise = 0.5 * (patch.misfit(source + d * e) ** 2 + patch.misfit(source - d * e) ** 2)
            k = (rise - f02) / (d * d)
            if not k > 0:
                return None
            d = math.sqrt(SURFACE_RISE * f02 / k)
        widths.append(d)
    w = np.array(widths)

    def point(p):
        return source + p[0] * axis + np.array([p[1], p[2], 0.0])

    centre = np.zeros(3)  # (u, x, y) of the design's centre
    settled = False
    for _ in range(SURFACE_ROUNDS):
        res = np.array([patch.residual(point(centre + t * w)) for t in _DESIGN])
        vals = (res * res).sum(axis=1)
        coef = _DESIGN_LSQ @ vals
        vertex = _quadratic_vertices(coef)[0]
        if not np.isfinite(vertex).all():
            return None
        reach = float(np.abs(vertex).max())
        lowest = max(float(_quadratic_basis(vertex[None])[0] @ coef), 1e-300)
        scale = np.clip(np.sqrt(SURFACE_RISE * lowest / np.maximum(coef[4:7], 1e-300)),
                        0.5, 2.0)
        w_next = w * scale
        w_next[0] = float(np.clip(w_next[0], *SURFACE_SPAN))
        if reach <= 1.0:
            if reach < SURFACE_SETTLED and np.all(np.abs(np.log(w_next / w)) < math.log(1.5)):
                settled = True
                break
            centre = centre + vertex * w
        else:  # trusted within its design only: move to the design's edge, fit again
            centre = centre + vertex / reach * w
        w = w_next
    if not settled:
        return None
    h, wd = patch.shape
    yy, xx = np.divmod(np.arange(h * wd), wd)
    ids = (yy // block_px) * (-(-wd // block_px)) + xx // block_px
    nblk = int(ids.max()) + 1
    share = np.stack([np.bincount(ids, r * r, minlength=nblk) for r in res])  # (N, K)
    moves = _quadratic_vertices((coef[:, None] - _DESIGN_LSQ @ share).T)[:, 0] - vertex[0]
    if not np.isfinite(moves).all():
        return None
    best = centre + vertex * w
    sigma_u = w[0] * math.sqrt((nblk - 1) / nblk * float(moves @ moves))
    return point(best), math.sqrt(lowest), sigma_u * abs(float(axis[2]))


def fit_point_image(
    profile: CameraProfile,
    d_in_mm: float,
    image: np.ndarray,
    box: tuple[int, int, int, int],
    lens_centres_mm: np.ndarray,
    start_mm: np.ndarray | None = None,
    floor_sigma: float = 0.0,
    others_mm: list[np.ndarray] | None = None,
) -> ImageFit:
    """Match the exact forward model of a point source to the pixels inside ``box``.

    ``floor_sigma``: the σ of the noise the capture clips at zero (0: it does not clip;
    :attr:`lfcam.measure.noise.NoiseModel.floor_sigma`). ``others_mm``: points of other
    sources whose blurs may reach into the box: their light is modelled with them, each at
    its own free intensity (:meth:`_Patch.add_others`).

    Without a start, a coarse scan over distance (lateral position from the chief ray through
    the light's centroid) picks the basin; a trust-region least-squares fit
    (``scipy.optimize.least_squares``) then refines (log distance, x, y), and a parabolic
    polish along the line of sight finishes.
    """
    lens = profile.main_lens
    patch = _Patch(profile, d_in_mm, image, box, lens_centres_mm, floor_sigma)
    if others_mm:
        patch.add_others(others_mm)
    if patch.norm <= 0:
        return ImageFit(np.full(3, np.nan), 1.0, np.nan, 0, False, RegionStatus.EMPTY)
    pp = profile.sensor.pixel_pitch_mm
    ax, ay = profile.sensor.axis_xy_px
    h, w = patch.shape
    yy, xx = np.mgrid[0:h, 0:w]
    tot = patch.data.sum()
    cen_mm = np.array([((xx * patch.data).sum() / tot + box[0] - ax) * pp,
                       ((yy * patch.data).sum() / tot + box[1] - ay) * pp])
    mag = 1.0 + profile.mla.focal_length_mm / (d_in_mm - lens.exit_pupil_z_mm)
    target = cen_mm / mag
    z_front = lens.front_vertex_z_mm

    def source_of(params):
        return np.array([params[1], params[2], z_front - np.exp(params[0])])

    f = lens.focal_length_mm
    from scipy.optimize import least_squares

    model = PhysicalJacobian(lambda q: patch.residual(source_of(q)))
    fun, jac = model.fun, model.jac

    def refine(x0):
        res = least_squares(fun, x0, jac=jac, method="trf", x_scale="jac", max_nfev=15)
        return float(np.sqrt((res.fun**2).sum())), res.x

    best = None
    if start_mm is not None and np.isfinite(start_mm).all() and start_mm[2] < z_front - 1.05 * f:
        best = refine(np.array([np.log(z_front - start_mm[2]), start_mm[0], start_mm[1]]))
    if best is None or best[0] > GOOD_MISFIT:
        # no (good) start: scan the distance, lateral position from the chief ray
        # the scan only has to find the basin: a coarse pupil sample (~1/6 of the rays) will do
        coarse = pupil_pattern(SCAN_PUPIL_SAMPLES)

        def scan_cost(params):
            return patch.misfit(source_of(params), coarse)

        scored = []
        for d in np.geomspace(1.1 * f, 2e4, 32):
            xy = _match_centroid(patch, profile, d_in_mm, d, target, z_front, coarse)
            params = np.array([np.log(d), xy[0], xy[1]])
            scored.append((scan_cost(params), params))
        scored.sort(key=lambda t: t[0])
        # the coarse grid steps ~18 % in distance; the basin is a few % wide: refine around
        # the two best coarse points before handing over to the local optimiser
        fine = []
        for _, params in scored[:2]:
            for d in np.exp(params[0]) * np.linspace(0.9, 1.1, 9):
                xy = _match_centroid(patch, profile, d_in_mm, d, target, z_front, coarse)
                q = np.array([np.log(d), xy[0], xy[1]])
                fine.append((scan_cost(q), q))
        scored = sorted(fine + scored, key=lambda t: t[0])
        for _, params in scored[:2]:
            cand = refine(params)
            if best is None or cand[0] < best[0]:
                best = cand

    # Escape side basins along the line of sight (distance and lateral position trade off
    # there): scan ±15 %, restart the refinement from a better point if one turns up.
    pupil = np.array([0.0, 0.0, lens.rim_z_mm])
    source = source_of(best[1])
    scales = np.linspace(0.85, 1.15, 13)
    vals = [patch.misfit(pupil + sc * (source - pupil)) for sc in scales]
    k = int(np.argmin(vals))
    if vals[k] < best[0] and abs(scales[k] - 1.0) > 1e-9:
        s2 = pupil + scales[k] * (source - pupil)
        cand = refine(np.array([np.log(z_front - s2[2]), s2[0], s2[1]]))
        if cand[0] < best[0]:
            best = cand

    # Polish along the line of sight (through the entrance-pupil centre), where the misfit is
    # shallow but smooth on the 0.5 % scale that finite differences cannot resolve: fit a
    # parabola to the misfit at seven scale factors, recentre, repeat with half the span; then
    # let the local refinement move across the valley again, and polish once more.
    def polish(source, f0, span=0.02):
        curvature = np.nan
        for _ in range(3):
            scales = 1.0 + span * np.linspace(-1.0, 1.0, 7)
            vals = np.array([patch.misfit(pupil + sc * (source - pupil)) for sc in scales])
            c2, c1, c0 = np.polyfit(scales - 1.0, vals, 2)
            if c2 <= 0:
                k = int(np.argmin(vals))
                source, f0 = pupil + scales[k] * (source - pupil), float(vals[k])
                continue
            vertex = float(np.clip(-c1 / (2 * c2), -span, span))
            source = pupil + (1.0 + vertex) * (source - pupil)
            f0 = float(c0 - c1 * c1 / (4 * c2))
            curvature = 2 * c2
            span *= 0.5
        return source, f0, curvature

    source, f0, curvature = polish(source_of(best[1]), best[0])
    again = refine(np.array([np.log(z_front - source[2]), source[0], source[1]]))
    if again[0] < f0:
        source, f0, curvature = polish(source_of(again[1]), again[0], span=0.01)
    block_px = max(2, int(round(profile.mla.pitch_mm / profile.sensor.pixel_pitch_mm)))
    surf = _surface_minimum(patch, pupil, source, f0, curvature, block_px)
    sigma_surface = math.nan
    if surf is not None:
        source, f0, sigma_surface = surf
    # Behind the focused plane each lenslet sees a small patch of the pupil and its spot spans
    # a few pixels: the model's own ray sample then moves the minimum, on the infinite-draw
    # mean of system 2's 12-source capture (focus 1 m) by up to 0.65 % at the default rays,
    # 0.25 % at 4×, 0.12 % at 16×; in front of focus by under 0.03 %. A turned sample, or a
    # Gauss–Newton step towards the 4× model, predicts none of it (≤ 0.07 %). So behind focus
    # the polish and the surface are redone from the minimum with BEHIND_FOCUS_RAYS × the rays
    # (docs/distance.md, "The clipped dark floor, and the pixel fit's own rays behind focus").
    if z_front - source[2] > lens.focus_for_d_in(d_in_mm):
        patch.pattern = vogel_disc(BEHIND_FOCUS_RAYS * len(patch.pattern[0]))
        model.forget()
        source, f0, curvature = polish(source, f0, span=0.01)
        surf = _surface_minimum(patch, pupil, source, f0, curvature, block_px)
        if surf is not None:
            source, f0, sigma_surface = surf
    dist = float(z_front - source[2])
    npix = max(int((patch.data > 0.05 * patch.data.max()).sum()), 1)
    # misfit is an RMS over the patch: its noise is ~ f0/√npix per unit of misfit
    if math.isfinite(sigma_surface):
        # the quadratic surface's jackknife (docs/distance.md, "The pixel fit's minimum")
        sigma_d = sigma_surface
    else:
        # the polish's parabola, with a noise scale that overstates the spread 1.5-7×
        sigma_scale = np.sqrt(2 * f0 / np.sqrt(npix) / curvature) if curvature > 0 else np.inf
        sigma_d = float(sigma_scale) * dist
    # the valley couples distance and lateral position: the full normal matrix of the three
    # parameters, with the residual's per-pixel variance, gives the marginal σ of the distance
    q = np.array([np.log(dist), source[0], source[1]])
    jm = jac(q)
    r = fun(q)
    n_eff = max(npix - 3, 1)
    s2 = float((r * r).sum()) / n_eff
    try:
        cov = s2 * np.linalg.inv(jm.T @ jm)
        sigma_d = max(sigma_d, dist * float(np.sqrt(max(cov[0, 0], 0.0))))
    except np.linalg.LinAlgError:
        sigma_d = np.inf
    return ImageFit(source, float(f0), sigma_d, patch.evaluations, bool(np.isfinite(f0)))
