"""Lenslet centres on the MLA plane from calibrated white-image micro-image centroids.

A calibration returns where each micro-image's light lands on the sensor (intensity centroid
of the white image, docs/calibration.md). The distance fits need the lenslet itself: light crossing
lenslet k with slope σ lands at ``C_k + f_x·σ`` (ideal lenslet), so the white centroid is
``C_k + f_x·⟨σ⟩_white(C_k)``, where ⟨σ⟩ is the mean slope, weighted by cos⁴ of the angle at
which the light of each lenslet point reaches the sensor, of the light that
reaches the lenslet through the aperture stop. By symmetry ⟨σ⟩ is radial; we tabulate its
radial component by tracing backward (exact main lens) from sample points of a lenslet cell
over a grid of slopes, then invert ``r_white = r + f_x·g(r)`` by interpolation.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

from lfcam.calibrate.bias import centroid_bias
from lfcam.calibrate.quality import check_profile_pitch
from lfcam.camera import CameraProfile
from lfcam.errors import CalibrationError
from lfcam.measure.lenslets import LensletMap, build_lenslet_map
from lfcam.optics.mla import MlaGrid, lattice_basis, lattice_index, rotation_matrix, row_column
from lfcam.optics.trace import trace_backward_fast

if TYPE_CHECKING:  # the calibration stage sits above measure: its type only
    from lfcam.calibrate.model import Calibration

RADII = 48
SLOPE_GRID = 96
CELL_NODES = 3  # Gauss–Legendre nodes per side of the lenslet aperture (hex: per rhombus)
EDGE_RAMP = True  # the pupil's edge shared by the slope cells it crosses (ρ's linear ramp)


def _aperture_rule(grid: MlaGrid, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss–Legendre rule over one lenslet's clear aperture (offsets from its centre, mm,
    and weights summing to 1): n × n nodes on the square (rect) or on each of the hexagon's
    three rhombi (hex), rotated as the MLA is (:meth:`MlaGrid.aperture_samples`)."""
    x, w = np.polynomial.legendre.leggauss(n)
    s, t = np.meshgrid(0.5 * (x + 1.0), 0.5 * (x + 1.0))
    ws = np.outer(w, w).ravel() / 4.0
    s, t = s.ravel(), t.ravel()
    if grid.grid == "rect":
        u, v = grid.aperture_samples(s, t)
        return u, v, ws
    parts = [grid.aperture_samples(s, t, np.full(s.shape, k)) for k in range(3)]
    return (np.concatenate([q[0] for q in parts]), np.concatenate([q[1] for q in parts]),
            np.tile(ws, 3) / 3.0)


def _edge_cover(rho: np.ndarray) -> np.ndarray:
    """Share of each slope cell inside the pupil, from ρ (the largest ρ/semi-diameter over
    the surfaces, ≤ 1 inside) on a (…, S, S) grid of slopes. A cell on the pupil's edge (it
    or a 4-neighbour on the other side) takes a linear ramp across it whose width is ρ's
    change over the cell (|∂ρ/∂i| + |∂ρ/∂j|: a straight edge at any angle), so the edge
    moves the centroid smoothly, not by whole cells; every other cell is in or out (far
    outside the pupil, ρ of rays that miss the lens by far is erratic)."""
    r = np.where(np.isfinite(rho), rho, np.inf)
    inside = r <= 1.0
    if not EDGE_RAMP:
        return inside.astype(np.float64)
    pad = [(0, 0)] * (r.ndim - 2) + [(1, 1), (1, 1)]
    rp = np.pad(r, pad, mode="edge")
    ip = rp <= 1.0
    edge = ((ip[..., :-2, 1:-1] != inside) | (ip[..., 2:, 1:-1] != inside)
            | (ip[..., 1:-1, :-2] != inside) | (ip[..., 1:-1, 2:] != inside))
    with np.errstate(invalid="ignore", over="ignore"):
        ramp = (np.abs(rp[..., 2:, 1:-1] - rp[..., :-2, 1:-1])
                + np.abs(rp[..., 1:-1, 2:] - rp[..., 1:-1, :-2])) / 2.0
        cover = np.clip(0.5 + (1.0 - r) / ramp, 0.0, 1.0)
    return np.where(edge & np.isfinite(cover), cover, inside.astype(np.float64))


@lru_cache(maxsize=16)
def white_offset_table(profile: CameraProfile, d_in_mm: float, max_radius_mm: float):
    """(r, r_white) of lenslets along a radius: the radial white-centroid map (mm).

    Each lenslet's light is integrated over its clear aperture by a Gauss–Legendre rule
    (:func:`_aperture_rule`, :data:`CELL_NODES`) and over a grid of slopes whose cells the
    pupil's edge shares (:func:`_edge_cover`). A 3 × 3 midpoint rule on a square cell and a
    hard pupil edge had left system 1's lenslet lattice 1.4e-5 too large (0.01 px at the
    rim), against 3e-6 for this rule (docs/distance.md, "How exactly the pixel polish needs
    the lenslet lattice (stop 64)").
    """
    lens = profile.main_lens
    fx = profile.mla.focal_length_mm
    grid = MlaGrid.from_mla(profile.mla)
    d_a = d_in_mm - lens.exit_pupil_z_mm
    radii = np.linspace(0.0, max_radius_mm, RADII)
    # slopes covering the pupil as seen from any lenslet out to the largest radius
    aperture = lens.pupil_diameter_mm if lens.is_singlet else max(
        lens.pupil_diameter_mm, lens.exit_pupil_diameter_mm)
    reach = (0.5 * aperture + max_radius_mm + grid.pitch_mm) / d_a * 1.2
    g = np.linspace(-reach, reach, SLOPE_GRID)
    sx, sy = np.meshgrid(g, g)
    sx, sy = sx.ravel(), sy.ravel()
    cu, cv, cw = _aperture_rule(grid, CELL_NODES)
    # light from cell point P reaches the sensor point X = C + f_x·σ at the angle of X − P
    ax_ = sx[None, :] - cu[:, None] / fx
    ay_ = sy[None, :] - cv[:, None] / fx
    cos4_p = 1.0 / (1.0 + ax_ * ax_ + ay_ * ay_) ** 2
    # every (cell point, slope) pair: the backward ray must pass every clear aperture (only
    # the lenslet's x moves with the radius)
    px0, py = np.repeat(cu, sx.size), np.repeat(cv, sx.size)
    tsx, tsy = np.tile(sx, cu.size), np.tile(sy, cu.size)
    out = np.empty_like(radii)
    for i, r in enumerate(radii):
        tr = trace_backward_fast(lens, r + px0, py, d_in_mm, tsx, tsy, ratio=True)
        cover = _edge_cover(tr.rho.reshape(cu.size, SLOPE_GRID, SLOPE_GRID))
        w = cw @ (cover.reshape(cu.size, -1) * cos4_p)
        out[i] = r + fx * float((w * sx).sum() / w.sum())
    return radii, out


def lenslet_centres_mm(
    profile: CameraProfile, d_in_mm: float, centroids_px: np.ndarray
) -> np.ndarray:
    """Lenslet centres (mm, MLA plane, from the axis) of calibrated white centroids (px)."""
    c = np.asarray(centroids_px, dtype=np.float64).reshape(-1, 2)
    pp = profile.sensor.pixel_pitch_mm
    ax, ay = profile.sensor.axis_xy_px
    m = np.column_stack([(c[:, 0] - ax) * pp, (c[:, 1] - ay) * pp])
    r_white = np.hypot(m[:, 0], m[:, 1])
    radii, r_w = white_offset_table(profile, float(d_in_mm), float(r_white.max() * 1.05 + 1e-6))
    r = np.interp(r_white, r_w, radii)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(r_white > 0, r / r_white, 1.0 / (r_w[1] / radii[1]))
    return m * scale[:, None]


def white_centroids_px(
    profile: CameraProfile, d_in_mm: float, lens_centres_mm: np.ndarray
) -> np.ndarray:
    """White centroids (px) of lenslets at ``lens_centres_mm`` (MLA plane, from the axis): the
    forward map :func:`lenslet_centres_mm` inverts, through the same table."""
    c = np.asarray(lens_centres_mm, dtype=np.float64).reshape(-1, 2)
    r = np.hypot(c[:, 0], c[:, 1])
    radii, r_w = white_offset_table(profile, float(d_in_mm), float(r.max() * 1.05 + 1e-6))
    m = c * (np.interp(r, radii, r_w) / np.maximum(r, 1e-12))[:, None]
    ax, ay = profile.sensor.axis_xy_px
    pp = profile.sensor.pixel_pitch_mm
    return np.column_stack([m[:, 0] / pp + ax, m[:, 1] / pp + ay])


LATTICE_MAX_RMS_PITCH = 0.02  # a regular MLA explains its centres to better than this


def nominal_indices(centres_mm: np.ndarray, pitch_mm: float, grid: str,
                    rotation_rad: float) -> np.ndarray:
    """Lattice indices of lenslet centres by rounding on the nominal lattice
    (:func:`lfcam.optics.mla.lattice_basis`) about the centre nearest the axis; for centres
    that come without the calibration's indices."""
    c = np.asarray(centres_mm, dtype=np.float64)
    ref = c[np.argmin(np.hypot(c[:, 0], c[:, 1]))]
    basis = pitch_mm * rotation_matrix(rotation_rad) @ lattice_basis(grid)
    return np.round(np.linalg.solve(basis, (c - ref).T).T).astype(np.int64)


def regularise_to_lattice(
    centres_mm: np.ndarray, indices: np.ndarray, pitch_mm: float,
    fit_mask: np.ndarray | None = None,
) -> tuple[np.ndarray, float]:
    """Replace lenslet centres by a least-squares affine lattice through them.

    The MLA is one rigid part: an affine lattice ``C = o + i·a1 + j·a2`` over the
    calibration's lattice indices averages the per-lenslet errors of the white-centroid
    inversion away (system 1: 1.6 → 0.9 µm RMS). When the fit leaves more than
    ``LATTICE_MAX_RMS_PITCH`` pitch RMS, the lattice does not describe the array and the
    centres are returned unchanged.

    Parameters
    ----------
    centres_mm : (N, 2) array
        Lenslet centres on the MLA plane.
    indices : (N, 2) int array
        Their lattice indices (:func:`lfcam.optics.mla.lattice_basis`).
    pitch_mm : float
        Lenslet pitch (scales the acceptance limit).
    fit_mask : (N,) bool array, optional
        Centres the lattice is fitted to (default: all); the others only receive its
        positions (lenses placed by the calibration's lattice model, not measured).

    Returns
    -------
    centres_mm : ndarray
    rms_pitch : float
        RMS residual of the lattice fit, in pitches.
    """
    c = np.asarray(centres_mm, dtype=np.float64)
    use = np.ones(len(c), bool) if fit_mask is None else np.asarray(fit_mask, bool)
    if use.sum() < 8:
        return c, float("nan")
    a = np.column_stack([np.ones(len(c)), np.asarray(indices, dtype=np.float64)])
    coef, *_ = np.linalg.lstsq(a[use], c[use], rcond=None)
    fitted = a @ coef
    rms = float(np.sqrt(((fitted[use] - c[use]) ** 2).sum(axis=1).mean())) / pitch_mm
    if not rms <= LATTICE_MAX_RMS_PITCH:
        return c, rms
    return fitted, rms


def sensor_lenses(calibration: Calibration, shape: tuple[int, int],
                  radius_px: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Micro-image centres of every lens whose micro-image reaches the sensor.

    The calibration measures only whole micro-images; lenses cut by the sensor edge are
    placed by its fitted lattice model (:meth:`Calibration.lens_centres`). A lens is kept
    when a pixel centre of the sensor lies within ``radius_px`` of its centre (the lenslet
    map's disc, :func:`lfcam.measure.lenslets.build_lenslet_map`).

    Parameters
    ----------
    calibration : Calibration
    shape : tuple of int
        (rows, cols) of the sensor.
    radius_px : float
        Micro-image radius of the lenslet map.

    Returns
    -------
    centres_px : (N, 2) array
        The measured centres (calibration order) followed by the model-placed ones.
    indices : (N, 2) int array
        Their lattice indices.
    n_measured : int
        Number of measured centres (the first rows).
    """
    h, w = int(shape[0]), int(shape[1])
    measured = np.asarray(calibration.centres_px, dtype=np.float64).reshape(-1, 2)
    m_idx = np.asarray(calibration.indices, dtype=np.int64).reshape(-1, 2)
    lc = calibration.lens_centres(shape, margin_px=radius_px)
    t, s = np.meshgrid(np.arange(lc.x.shape[0]) + lc.first_t,
                       np.arange(lc.x.shape[1]) + lc.first_s, indexing="ij")
    i, j = lattice_index(calibration.grid, t.ravel(), s.ravel())
    x, y = lc.x.ravel(), lc.y.ravel()
    gap = np.hypot(x - np.clip(x, 0.0, w - 1.0), y - np.clip(y, 0.0, h - 1.0))
    mt, ms = row_column(calibration.grid, m_idx[:, 0], m_idx[:, 1])
    is_measured = np.isin(t.ravel() * 2**31 + s.ravel(), mt * 2**31 + ms)  # |s| ≪ 2**30
    new = (gap <= radius_px) & ~is_measured
    centres = np.vstack([measured, np.column_stack([x[new], y[new]])])
    indices = np.vstack([m_idx, np.column_stack([i[new], j[new]])])
    return centres, indices, len(measured)


@dataclass(frozen=True)
class Geometry:
    """Per-calibration data reused for every capture.

    Attributes
    ----------
    lmap : LensletMap
        Which lenslet's micro-image each sensor pixel belongs to.
    lens_centres_mm : (N, 2) array
        Lenslet centres on the MLA plane (mm from the axis), in the order of ``lmap``.
    pitch_px : float
        Micro-image pitch on the sensor.
    d_in_mm : float
        Main lens → MLA distance used by every fit.
    """

    lmap: LensletMap
    lens_centres_mm: np.ndarray
    pitch_px: float
    d_in_mm: float


def prepare_geometry(profile: CameraProfile, calibration: Calibration,
                     shape: tuple[int, int]) -> Geometry:
    """Lenslet map and lenslet centres for one calibration and sensor size.

    Every lens whose micro-image reaches the sensor takes part (:func:`sensor_lenses`): the
    measured ones first, in the calibration's order, then those cut by the sensor edge, placed
    by the calibration's lattice model. Where the white's micro-images touch, the centroids
    first lose their estimator's bias, learnt on a model white of ``profile``
    (:func:`lfcam.calibrate.bias.centroid_bias`; the lenslet map keeps them as measured). The
    MLA-plane lattice is fitted to the measured lenses only.

    Parameters
    ----------
    profile : CameraProfile
    calibration : Calibration
        Measured micro-image centres; its ``d_in_mm`` (when set) overrides the profile's.
    shape : tuple of int
        (rows, cols) of the captures.

    Returns
    -------
    Geometry

    Raises
    ------
    CalibrationError
        The calibration was made on a white image of another size, or holds no centre.
    CalibrationMismatchError
        The profile's predicted micro-image pitch is more than 5 % off the calibration's.
    """
    calibration.check_image(shape)
    if not calibration.n_lenses:
        raise CalibrationError(f"{calibration.source or 'calibration'}: no measured centres")
    d_in = calibration.d_in_mm if calibration.d_in_mm is not None else profile.d_in_mm
    check_profile_pitch(profile, calibration, d_in)  # a wrong profile, before any heavy work
    radius_px = 0.5 * calibration.pitch_px * 1.08
    centres, indices, n_measured = sensor_lenses(calibration, shape, radius_px)
    # touching or overlapping micro-images: the centroids less their estimator's bias, learnt
    # on a model white (lfcam.calibrate.bias; None where the discs leave gaps)
    bias = centroid_bias(profile, d_in, calibration, shape)
    corrected = centres if bias is None else bias.correct(centres)
    # the lenslet map (a compiled loop that releases the GIL) and the lenslet centres (numpy
    # traces) are independent: on a large frame they run side by side (Illum size: the map
    # 1.2 s, the white-offset table 0.6 s)
    with ThreadPoolExecutor(1) as side:
        # measured and edge-placed lenses in one call: one white-offset table (one trace)
        lens_job = side.submit(lenslet_centres_mm, profile, d_in, corrected)
        lmap = build_lenslet_map(centres, shape, radius_px)
        lens_mm = lens_job.result()
    lens_mm, _ = regularise_to_lattice(lens_mm, indices, profile.mla.pitch_mm,
                                       fit_mask=np.arange(len(centres)) < n_measured)
    return Geometry(lmap, lens_mm, float(calibration.pitch_px), d_in)
