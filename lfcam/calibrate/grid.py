"""Microlens centres from a white image, and the global lattice model.

Pipeline (every step vectorised over all lenses; no Python loop per lens):

1. **Pitch** — nearest peak of the autocorrelation of a central crop (robust to overlapping
   micro-images, whose fundamental harmonic nearly vanishes).
2. **Candidates** — local maxima of a flatness score (local mean − 2 local standard
   deviations over 0.3·pitch): inside a micro-image, never on an edge or a bright seam.
3. **Rough lattice** — nearest-neighbour vectors of the candidates; the 4-fold vs 6-fold
   orientation order decides rect vs hex and gives the rotation.
4. **Centroids** — intensity centroid of each micro-image, by one of three methods chosen
   from a disc model of the micro-images (``lfcam.calibrate.microimage``): a soft circle
   window when discs have a dark gap; the micro-image model (disc fit, seam attribution)
   when they touch or overlap; a separable cell window (p × p rect, brick p × √3p/2 hex)
   when they are not disc-like.
5. **Indices** — lattice indices (i, j) by rounding in the rough basis, re-fitted on a disc
   of lenses that doubles in radius, so mild distortion never skips a row.
6. **Models** — least squares, robustly reweighted: similarity (pitch, rotation, offset) for
   both rect and hex (the grid with the lower residual wins), then affine and projective;
   a richer model is kept only when an F-test says it is significant (p < 1e-3) *and* it
   moves some lens prediction by more than 0.01 px.
7. **Rejections** — clipped by the image edge, dim (flux under 70 % of the local median of its
   lattice neighbours: partial or shadowed), window not converged, duplicate index,
   grid outlier (residual above max(0.25 px, 6 robust sigmas)). Rejected lenses are
   reported with their reason, never silently dropped, and every returned centre is a
   measured micro-image (the model only predicts where to measure).

The returned centre is the **intensity centroid** of each micro-image (docs/calibration.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial import cKDTree
from scipy.special import fdtrc

from lfcam.calibrate import kernels
from lfcam.calibrate.microimage import (
    DiscModel,
    Progress,
    _noop,
    circle_window_centroids,
    fit_disc_model,
    fit_discs,
    fixed_point_applies,
    own_light_centroids,
    own_light_fit,
)
from lfcam.calibrate.parallel import run_bands
from lfcam.errors import CalibrationError
from lfcam.optics.mla import lattice_basis, rotation_matrix

RADIAL_NORM_PX = 1000.0  # ρ unit of the radial lattice term
RADIAL_FIT_LENSES = 5_000
MIN_PERIOD_PX = 3.0
MAX_PERIOD_PX = 120.0
CHUNK_LENSES = 16384
# relative RMS misfit of the disc model above which micro-images are not treated as discs
# (renderer white images: 0.035–0.044; blurred light-field-microscope spots: 0.086–0.099)
DISC_LIKE_MAX = 0.065
# the circle-window centroid is exact when the micro-image support stays this far inside half
# the pitch (rounding of the start, the gradient shift of the centroid, the 1-px soft edge)
GAP_MARGIN_PX = 0.75
REJECT_REASONS = ("edge", "dim", "unconverged", "duplicate", "outlier")

@dataclass(frozen=True)
class GridFit:
    """Result of :func:`find_centres`.

    Attributes
    ----------
    grid : str
        ``"rect"`` or ``"hex"``.
    pitch_px, rotation_rad : float
        From the similarity fit: lens centre ≈ offset + pitch·R(rotation)·B·(i, j).
    offset_px : (2,) array
        Similarity-model position of index (0, 0) (the lens nearest the image centre).
    model : str
        Model used for residuals: ``"similarity"``, ``"affine"``, ``"projective"`` or
        ``"projective+radial"``.
    matrix : (3, 3) array
        Homography of the chosen model: (x, y, 1) ∝ matrix @ (i, j, 1).
    centres_px : (N, 2) array
        Accepted measured centres (x, y).
    indices : (N, 2) int array
        Their lattice indices.
    flux : (N,) array
        Windowed flux of each accepted lens (relative brightness).
    residual_rms_px : float
        RMS of |centre − model(index)| over accepted lenses.
    rejected_px : (M, 2) array
        Positions of rejected candidates.
    rejected_reason : tuple of str
        One reason per rejected candidate (see ``REJECT_REASONS``).
    diagnostics : dict
        Model-selection statistics and counts.
    radial : tuple or None
        (cx, cy, k1, k2) of the radial term (:func:`apply_radial`) when the model has one.
    """

    grid: str
    pitch_px: float
    rotation_rad: float
    offset_px: np.ndarray
    model: str
    matrix: np.ndarray
    centres_px: np.ndarray
    indices: np.ndarray
    flux: np.ndarray
    residual_rms_px: float
    rejected_px: np.ndarray
    rejected_reason: tuple[str, ...]
    diagnostics: dict = field(default_factory=dict)
    radial: tuple | None = None

    def predict(self, indices: np.ndarray) -> np.ndarray:
        """Model position (x, y) of lattice ``indices`` (N×2)."""
        return predict_lattice(self.matrix, self.radial, indices)

    @property
    def residuals_px(self) -> np.ndarray:
        """Per-lens residual vectors, measured centre − model."""
        return self.centres_px - self.predict(self.indices)


# ----------------------------------------------------------------------------- helpers


def apply_homography(h: np.ndarray, ij: np.ndarray) -> np.ndarray:
    """Map lattice indices through a 3×3 homography."""
    ij = np.asarray(ij, dtype=np.float64).reshape(-1, 2)
    i, j = ij[:, 0], ij[:, 1]
    z = h[2, 0] * i + h[2, 1] * j + h[2, 2]
    return np.column_stack([(h[0, 0] * i + h[0, 1] * j + h[0, 2]) / z,
                            (h[1, 0] * i + h[1, 1] * j + h[1, 2]) / z])


def apply_radial(pts: np.ndarray, radial) -> np.ndarray:
    """Radial term of the lattice model: c + (q − c)(1 + k1 ρ² + k2 ρ⁴), ρ = |q − c| / 1000 px.

    ``radial`` is (cx, cy, k1, k2) or None (no radial term).
    """
    if radial is None:
        return pts
    cx, cy, k1, k2 = (float(v) for v in radial)
    d = pts - np.array([cx, cy])
    rho2 = np.sum(d * d, axis=1) / RADIAL_NORM_PX**2
    return np.array([cx, cy]) + d * (1.0 + k1 * rho2 + k2 * rho2 * rho2)[:, None]


def predict_lattice(h: np.ndarray, radial, ij: np.ndarray) -> np.ndarray:
    """Lattice-model position (x, y) of indices: homography, then the optional radial term."""
    return apply_radial(apply_homography(h, ij), radial)


def within_sensor(pts: np.ndarray, reach_x: float, reach_y: float,
                  shape: tuple[int, int]) -> np.ndarray:
    """True where everything within (±reach_x, ±reach_y) px of a point lies on the sensor
    (pixel edges at −0.5 and width/height − 0.5)."""
    h, w = shape
    return ((pts[:, 0] - reach_x >= -0.5) & (pts[:, 0] + reach_x <= w - 0.5)
            & (pts[:, 1] - reach_y >= -0.5) & (pts[:, 1] + reach_y <= h - 0.5))


def estimate_pitch(image: np.ndarray, crop: int = 768) -> float:
    """Nearest-neighbour distance (px) of the micro-image lattice from the autocorrelation.

    The autocorrelation of a periodic image peaks at every lattice vector whatever the
    micro-image looks like, so this works where the power spectrum's strongest peak does
    not: with overlapping micro-images (docs/calibration.md) the fundamental harmonic nearly
    vanishes (a disc of radius ≈ 0.55·pitch) and the spectrum peaks at a diagonal harmonic.
    The nearest peak reaching half the zero-lag value (normalised by the overlap area) is
    refined to sub-pixel by a parabola in x and y.
    """
    h, w = image.shape
    n = min(crop, h, w)
    n -= n % 2
    if n < 4 * MIN_PERIOD_PX:
        raise CalibrationError(f"white image too small ({h}×{w}) to find a lens period")
    y0, x0 = (h - n) // 2, (w - n) // 2
    patch = image[y0:y0 + n, x0:x0 + n].astype(np.float64)
    patch -= patch.mean()
    if not np.any(patch):
        raise CalibrationError("no periodic microlens pattern found in the white image")
    spec = np.abs(np.fft.rfft2(patch, s=(2 * n, 2 * n))) ** 2
    acf = np.fft.fftshift(np.fft.irfft2(spec, s=(2 * n, 2 * n)))
    ones = np.abs(np.fft.rfft2(np.ones((n, n)), s=(2 * n, 2 * n))) ** 2
    overlap = np.fft.fftshift(np.fft.irfft2(ones, s=(2 * n, 2 * n)))
    r = min(n // 2, int(2 * MAX_PERIOD_PX))
    sub = (acf / np.maximum(overlap, 1.0))[n - r:n + r + 1, n - r:n + r + 1].astype(np.float32)
    peak0 = float(sub[r, r])
    dil = cv2.dilate(sub, np.ones((3, 3), np.uint8))
    ys, xs = np.nonzero((sub >= dil) & (sub > 0.5 * peak0))
    dist = np.hypot(xs - r, ys - r)
    keep = (dist >= MIN_PERIOD_PX) & (dist <= MAX_PERIOD_PX)
    if not keep.any():
        raise CalibrationError("no periodic microlens pattern found in the white image")
    k = int(np.argmin(np.where(keep, dist, np.inf)))
    py, px = int(ys[k]), int(xs[k])
    if not (0 < py < 2 * r and 0 < px < 2 * r):
        return float(dist[k])

    def vertex(m1: float, m0: float, p1: float) -> float:
        den = m1 - 2.0 * m0 + p1
        return 0.0 if den >= 0 else 0.5 * (m1 - p1) / den

    fx = px + vertex(sub[py, px - 1], sub[py, px], sub[py, px + 1])
    fy = py + vertex(sub[py - 1, px], sub[py, px], sub[py + 1, px])
    return float(np.hypot(fx - r, fy - r))


BAND_ROWS = 512  # the candidate filters' row bands at most this high (their temporaries are
#                 reused from band to band: 1.1 → 0.85 s of wall on an Illum-size white)


def find_candidates(image: np.ndarray, pitch: float) -> tuple[np.ndarray, np.ndarray]:
    """Integer micro-image centre candidates (x, y) and their score.

    Score = local mean − 2·local standard deviation over a disc of radius 0.3·pitch: high
    where the image is bright *and* flat, i.e. inside a micro-image and away from its edge.
    Unlike a smoothed-brightness maximum it is not fooled by the bright seams of overlapping
    micro-images (twice as bright but not flat across). Candidates are its local maxima over
    a disc of radius 0.45·pitch, above 20 % of the bright level.
    """
    img = np.ascontiguousarray(image, dtype=np.float32)
    h = img.shape[0]
    rad = max(1, int(round(0.3 * pitch)))
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rad + 1, 2 * rad + 1))
    k = (k / k.sum()).astype(np.float32)
    sigma = max(0.1 * pitch, 0.5)
    rmax = max(1, int(round(0.45 * pitch)))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rmax + 1, 2 * rmax + 1))
    # row bands on threads; each band is computed with a margin that covers the reach of
    # the three filters (box, Gaussian ≤ 4σ + 1, dilation), so its own rows are exact
    margin = rad + int(np.ceil(4.0 * sigma)) + 1 + rmax + 2
    score = np.empty_like(img)
    dil = np.empty_like(img)

    def band(r0: int, r1: int) -> None:
        a, b = max(0, r0 - margin), min(h, r1 + margin)
        sub = img[a:b]
        mean = cv2.filter2D(sub, cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT)
        sq = cv2.filter2D(cv2.multiply(sub, sub), cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT)
        kernels.flat_score(mean, sq)  # mean − 2·σ, in place
        sc = cv2.GaussianBlur(mean, (0, 0), sigmaX=sigma, borderType=cv2.BORDER_REFLECT)
        score[r0:r1] = sc[r0 - a:r1 - a]
        dil[r0:r1] = cv2.dilate(sc, kernel, borderType=cv2.BORDER_REFLECT)[r0 - a:r1 - a]

    run_bands(band, h, max_rows=BAND_ROWS)
    level = float(np.percentile(score[::3, ::3], 99.5))
    if level <= 0.0:
        raise CalibrationError("white image is dark")

    def peaks(r0: int, r1: int) -> np.ndarray:
        sc = score[r0:r1]
        ys, xs = np.nonzero((sc >= dil[r0:r1]) & (sc > 0.2 * level))
        return np.stack([xs, ys + r0], axis=1)

    pts = np.concatenate(run_bands(peaks, h))
    vals = score[pts[:, 1], pts[:, 0]]
    if len(pts) > 1:  # plateaus: keep one maximum per 0.5·pitch cluster (the first)
        tree = cKDTree(pts)
        pairs = tree.query_pairs(0.5 * pitch, output_type="ndarray")
        if len(pairs):
            drop = np.zeros(len(pts), bool)
            drop[np.maximum(pairs[:, 0], pairs[:, 1])] = True
            pts, vals = pts[~drop], vals[~drop]
    return pts.astype(np.float64), vals


def rough_lattice(points: np.ndarray) -> tuple[str, float, float, float]:
    """Grid kind, pitch, rotation and orientation order from nearest-neighbour vectors.

    Returns
    -------
    grid, pitch_px, rotation_rad, order_strength
    """
    if len(points) < 5:
        raise CalibrationError(f"only {len(points)} micro-images found: not a white image?")
    tree = cKDTree(points)
    k = min(7, len(points))
    step = max(1, len(points) // 20000)  # a subsample is plenty for the rough lattice
    dist, idx = tree.query(points[::step], k=k)
    nn = float(np.median(dist[:, 1]))
    vec = points[idx[:, 1:]] - points[::step, None, :]
    d = dist[:, 1:]
    keep = (d > 0.75 * nn) & (d < 1.25 * nn)
    v = vec[keep]
    phi = np.arctan2(v[:, 1], v[:, 0])
    r4 = np.mean(np.exp(4j * phi))
    r6 = np.mean(np.exp(6j * phi))
    if abs(r6) > abs(r4):
        grid, strength = "hex", abs(r6)
        rot = np.angle(r6) / 6.0
    else:
        grid, strength = "rect", abs(r4)
        rot = np.angle(r4) / 4.0
    if strength < 0.5:
        raise CalibrationError(
            f"micro-image positions do not form a regular grid (orientation order {strength:.2f})"
        )
    pitch = float(np.median(d[keep]))
    return grid, pitch, float(rot), float(strength)


def window_half_widths(grid: str, pitch: float, rotation: float) -> tuple[float, float]:
    """Half-widths (x, y) of the separable centroid window for this lattice."""
    if grid == "rect":
        return 0.5 * pitch, 0.5 * pitch
    # brick: p/2 along the rows, √3p/4 across them; rows ≈ vertical when rotation ≈ ±30°
    if abs(abs(rotation) - np.pi / 6) < abs(rotation):
        return np.sqrt(3.0) * pitch / 4.0, 0.5 * pitch
    return 0.5 * pitch, np.sqrt(3.0) * pitch / 4.0


def refine_centroids(
    image: np.ndarray,
    start: np.ndarray,
    half_x: float,
    half_y: float,
    iterations: int = 12,
    tol: float = 1e-4,
    progress: Progress = _noop,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fixed-point intensity centroids inside a separable soft-edged rectangle.

    Parameters
    ----------
    image : (H, W) float32
    start : (N, 2) float
        Initial (x, y).
    half_x, half_y : float
        Window half-widths; pixel weights ramp linearly from 1 to 0 across one pixel at
        the window edge (the pixel-area coverage of a moving edge).

    Returns
    -------
    centres : (N, 2)
    flux : (N,)
        Window-weighted intensity sum (background-subtracted).
    converged : (N,) bool
        False where the window left the gathered patch or the iteration did not settle.
    """
    h, w = image.shape
    margin = 3
    rx = int(np.ceil(half_x)) + margin
    ry = int(np.ceil(half_y)) + margin
    pad = max(rx, ry)
    padded = cv2.copyMakeBorder(np.ascontiguousarray(image, np.float32), pad, pad, pad, pad,
                                cv2.BORDER_CONSTANT, value=0.0)
    view = np.lib.stride_tricks.sliding_window_view(padded, (2 * ry + 1, 2 * rx + 1))
    ox = np.arange(-rx, rx + 1, dtype=np.float32)
    oy = np.arange(-ry, ry + 1, dtype=np.float32)
    n = len(start)
    centres = np.array(start, dtype=np.float64)
    flux = np.zeros(n)
    converged = np.ones(n, bool)
    for s in range(0, n, CHUNK_LENSES):
        e = min(n, s + CHUNK_LENSES)
        c = centres[s:e]
        base = np.round(c).astype(np.int64)
        bx = np.clip(base[:, 0], 0, w - 1)
        by = np.clip(base[:, 1], 0, h - 1)
        patches = view[by - ry + pad, bx - rx + pad]  # (n, 2ry+1, 2rx+1) copy
        # background: the minimum of each patch, so an unsubtracted level only slows
        # convergence a little instead of biasing anything (the fixed point is unbiased)
        bg = patches.min(axis=(1, 2))
        patches -= bg[:, None, None]
        dxy = (c - base).astype(np.float32)  # centre relative to the patch centre
        ok = np.ones(len(c), bool)
        for _ in range(iterations):
            wx = np.clip(half_x + 0.5 - np.abs(ox[None, :] - dxy[:, :1]), 0.0, 1.0)
            wy = np.clip(half_y + 0.5 - np.abs(oy[None, :] - dxy[:, 1:2]), 0.0, 1.0)
            wxs = np.stack([wx, wx * ox[None, :]], axis=2)  # (n, K, 2)
            rows = np.matmul(patches, wxs)  # (n, Ky, 2): Σx w I, Σx w I x
            s0 = np.einsum("nk,nk->n", rows[:, :, 0], wy)
            sx = np.einsum("nk,nk->n", rows[:, :, 1], wy)
            sy = np.einsum("nk,nk->n", rows[:, :, 0], wy * oy[None, :])
            good = s0 > 0
            with np.errstate(invalid="ignore", divide="ignore"):
                new = np.stack([sx / s0, sy / s0], axis=1)
            new[~good] = dxy[~good]
            step = np.abs(new - dxy).max(axis=1)
            dxy = new.astype(np.float32)
            ok &= good
            if step.max() < tol:
                break
        inside = (np.abs(dxy[:, 0]) < margin - 1) & (np.abs(dxy[:, 1]) < margin - 1)
        converged[s:e] = ok & inside & (step < 1e-2)
        centres[s:e] = base + dxy.astype(np.float64)
        flux[s:e] = s0
        progress("centroids", e, n)
    return centres, flux, converged


def assign_indices(
    points: np.ndarray, basis: np.ndarray, origin: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Lattice indices by rounding, refitting an affine lattice on a growing disc.

    Returns
    -------
    indices : (N, 2) int
    matrix : (2, 3) affine [A | o] of the last fit
    """
    a = np.array(basis, dtype=np.float64)
    o = np.array(origin, dtype=np.float64)
    pitch = float(np.sqrt(abs(np.linalg.det(a))))
    r = np.hypot(*(points - o).T)
    radius = 8.0 * pitch
    r_max = float(r.max())
    while True:
        sel = r <= radius
        f = (points[sel] - o) @ np.linalg.inv(a).T
        idx = np.round(f)
        good = (np.abs(f - idx) < 0.3).all(axis=1)
        if good.sum() >= 6:
            # (three unknowns: the normal equations rather than an SVD of 233 000 rows)
            design = np.column_stack([idx[good], np.ones(good.sum())])
            sol = np.linalg.solve(design.T @ design, design.T @ points[sel][good])
            a, o = sol[:2].T, sol[2]
        if radius >= r_max:
            break
        radius = min(2.0 * radius, r_max)
    f = (points - o) @ np.linalg.inv(a).T
    return np.round(f).astype(np.int64), np.column_stack([a, o])


def _wlstsq(design: np.ndarray, rhs: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted least squares through the normal equations (few unknowns, many rows)."""
    dw = design * weights[:, None]
    return np.linalg.solve(dw.T @ design, dw.T @ rhs)


def _robust_weights(res: np.ndarray) -> np.ndarray:
    """Tukey-biweight weights from residual magnitudes (scale from the MAD)."""
    mag = np.hypot(res[:, 0], res[:, 1])
    scale = 1.4826 * float(np.median(mag)) + 1e-9
    u = mag / (4.685 * scale)
    return np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0)


def fit_similarity(
    idx: np.ndarray, pts: np.ndarray, grid: str, weights: np.ndarray | None = None
) -> tuple[np.ndarray, float, float, np.ndarray]:
    """Least-squares pitch·R(θ)·B lattice. Returns (homography, pitch, rotation, weights)."""
    u = idx.astype(np.float64) @ lattice_basis(grid).T
    n = len(u)
    wts = np.ones(n) if weights is None else weights
    u0, u1 = u[:, 0], u[:, 1]
    px, py = pts[:, 0], pts[:, 1]
    for _ in range(4):
        # unknowns (ox, oy, a, b) with a = p cos θ, b = p sin θ: x = ox + a·u₀ − b·u₁,
        # y = oy + a·u₁ + b·u₀; the normal equations from weighted sums (no (2N × 4) rows)
        sw, su0, su1 = wts.sum(), wts @ u0, wts @ u1
        suu = wts @ (u0 * u0 + u1 * u1)
        wpx, wpy = wts * px, wts * py
        normal = np.array([[sw, 0.0, su0, -su1], [0.0, sw, su1, su0],
                           [su0, su1, suu, 0.0], [-su1, su0, 0.0, suu]])
        rhs = np.array([wpx.sum(), wpy.sum(), wpx @ u0 + wpy @ u1, wpy @ u0 - wpx @ u1])
        sol = np.linalg.solve(normal, rhs)
        pred = np.column_stack([sol[0] + sol[2] * u0 - sol[3] * u1,
                                sol[1] + sol[2] * u1 + sol[3] * u0])
        wts = _robust_weights(pts - pred)
    ox, oy, ca, sb = sol
    pitch = float(np.hypot(ca, sb))
    rot = float(np.arctan2(sb, ca))
    a = pitch * rotation_matrix(rot) @ lattice_basis(grid)
    hmat = np.array([[a[0, 0], a[0, 1], ox], [a[1, 0], a[1, 1], oy], [0.0, 0.0, 1.0]])
    return hmat, pitch, rot, wts


def fit_affine(
    idx: np.ndarray, pts: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Robust affine lattice fit. Returns (homography, weights)."""
    design = np.column_stack([idx.astype(np.float64), np.ones(len(idx))])
    wts = weights
    for _ in range(3):
        sol = _wlstsq(design, pts, wts)
        wts = _robust_weights(pts - design @ sol)
    hmat = np.vstack([sol.T, [0.0, 0.0, 1.0]])
    return hmat, wts


def fit_projective(idx: np.ndarray, pts: np.ndarray, weights: np.ndarray,
                   start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Robust projective lattice fit (Gauss–Newton on reprojection error from ``start``)."""
    hmat = start / start[2, 2]
    ij = np.ascontiguousarray(idx, dtype=np.float64)
    pts = np.ascontiguousarray(pts, dtype=np.float64)
    wts = weights
    for _ in range(6):
        # (the normal equations in one compiled pass: 0.25 → 0.11 s on an Illum-size white)
        a, b = kernels.projective_normal(ij, pts, np.ascontiguousarray(wts, dtype=np.float64),
                                         hmat)
        p = hmat.ravel()[:8] + np.linalg.solve(a, b)
        hmat = np.append(p, 1.0).reshape(3, 3)
        wts = _robust_weights(pts - apply_homography(hmat, ij))
    return hmat, wts


def fit_radial(idx: np.ndarray, pts: np.ndarray, weights: np.ndarray, start: np.ndarray,
               centre: np.ndarray) -> tuple[np.ndarray, tuple, np.ndarray]:
    """Projective lattice plus a radial term (k1, k2 about a fitted centre), robustly.

    Two rounds of weighted least squares (``scipy.optimize.least_squares``), Tukey weights
    recomputed in between; on at most ``RADIAL_FIT_LENSES`` lenses spread evenly over the
    image (12 parameters are pinned long before that). Returns (homography,
    (cx, cy, k1, k2), weights of the lenses used).
    """
    from scipy.optimize import least_squares

    step = max(1, len(idx) // RADIAL_FIT_LENSES)
    ij = idx[::step].astype(np.float64)
    pts = pts[::step]
    p = np.r_[(start / start[2, 2]).ravel()[:8], centre, 0.0, 0.0]
    wts = weights[::step]

    def resid(q: np.ndarray, sw: np.ndarray) -> np.ndarray:
        pred = predict_lattice(np.append(q[:8], 1.0).reshape(3, 3), q[8:], ij)
        return ((pred - pts) * sw[:, None]).ravel()

    for _ in range(2):
        sol = least_squares(resid, p, args=(np.sqrt(wts),), x_scale="jac", max_nfev=60)
        p = sol.x
        h = np.append(p[:8], 1.0).reshape(3, 3)
        wts = _robust_weights(pts - predict_lattice(h, p[8:], ij))
    return np.append(p[:8], 1.0).reshape(3, 3), tuple(float(v) for v in p[8:]), wts


def _rss(hmat: np.ndarray, idx: np.ndarray, pts: np.ndarray, wts: np.ndarray,
         radial=None) -> float:
    res = pts - predict_lattice(hmat, radial, idx)
    return float(np.sum(wts[:, None] * res * res))


def _richer_warranted(
    rss_a: float, rss_b: float, k_a: int, k_b: int, n_eff: float, shift_px: float
) -> tuple[bool, float]:
    """F-test of a richer nested model; also requires a practical effect (> 0.01 px)."""
    dof = 2.0 * n_eff - k_b
    if dof <= 0 or rss_b <= 0.0:
        return False, 1.0
    f = ((rss_a - rss_b) / (k_b - k_a)) / (rss_b / dof)
    # the F distribution's survival function from scipy.special (scipy.stats would cost
    # ~0.3 s to import, a few % of a full-size white's calibration)
    pval = float(fdtrc(k_b - k_a, dof, max(f, 0.0)))
    return bool(pval < 1e-3 and shift_px > 0.01), pval


def find_centres(
    image: np.ndarray,
    pitch_hint_px: float | None = None,
    progress: Progress = _noop,
) -> GridFit:
    """Detect, refine and fit every fully visible micro-image of a prepared white image.

    Parameters
    ----------
    image : (H, W) float32
        Output of :func:`lfcam.calibrate.image.prepare_white`.
    pitch_hint_px : float, optional
        Expected pitch; only checked against the measured one (a factor-1.5 disagreement
        raises, it usually means the wrong profile).
    progress : lfcam.progress.Progress

    Returns
    -------
    GridFit

    Raises
    ------
    CalibrationError
        No periodic pattern, too few micro-images, or an irregular grid.
    """
    img = np.ascontiguousarray(image, dtype=np.float32)
    h, w = img.shape
    progress("period", 0, 1)
    period = estimate_pitch(img)
    progress("candidates", 0, 1)
    cand, _ = find_candidates(img, period)
    grid, pitch, rot, order = rough_lattice(cand)
    if pitch_hint_px is not None and not (pitch_hint_px / 1.5 < period < pitch_hint_px * 1.5):
        raise CalibrationError(
            f"measured lens pitch {period:.2f} px is far from the profile's {pitch_hint_px:.2f} px"
        )
    hx, hy = window_half_widths(grid, period, rot)
    progress("micro-image shape", 0, 1)
    try:
        disc = fit_disc_model(img, cand, period)
    except CalibrationError:
        disc = None
    disc_like = disc is not None and disc.rel_residual < DISC_LIKE_MAX
    method = "cell window"
    if disc_like and disc.support_px <= 0.5 * period - GAP_MARGIN_PX:
        method = "circle window"
    elif disc_like:
        method = "micro-image model"
    if method == "micro-image model":
        centres, flux, conv, at_edge = _model_centroids(img, cand, disc, period, grid, rot,
                                                        progress)
    elif method == "circle window":
        # a dark gap around every micro-image: a circle of half the pitch holds one whole
        centres, flux, conv = circle_window_centroids(img, cand, 0.5 * period,
                                                      progress=progress)
        at_edge = ~within_sensor(centres, disc.support_px + 0.5, disc.support_px + 0.5,
                                 img.shape)
    else:
        # separated micro-images (or not disc-like): the cell window holds each one whole
        centres, flux, conv = refine_centroids(img, cand, hx, hy, progress=progress)
        # fully visible = the whole window (the lens's cell, edge ramp included) is on the sensor
        at_edge = ~within_sensor(centres, hx + 0.5, hy + 0.5, img.shape)
    reason = np.full(len(centres), "", dtype=object)
    reason[at_edge] = "edge"
    reason[(reason == "") & ~conv] = "unconverged"

    # lattice indices around the usable lens nearest the image centre
    usable = reason == ""
    if usable.sum() < 5:
        raise CalibrationError(f"only {int(usable.sum())} fully visible micro-images found")
    pts_u = centres[usable]
    mid = np.array([0.5 * (w - 1), 0.5 * (h - 1)])
    origin = pts_u[np.argmin(np.hypot(*(pts_u - mid).T))]
    basis = pitch * rotation_matrix(rot) @ lattice_basis(grid)
    idx_all = np.zeros((len(centres), 2), np.int64)
    idx_u, _ = assign_indices(pts_u, basis, origin)
    idx_all[usable] = idx_u

    # duplicates: same index twice → keep the one nearest the affine prediction
    _dedupe(idx_all, centres, usable, reason)
    # dim lenses: flux far below the local median of lattice neighbours
    _mark_dim(idx_all, flux, reason)

    progress("fit", 0, 1)
    diag: dict = {"pitch_acf_px": period, "orientation_order": order,
                  "n_candidates": len(cand),
                  "centroid_method": method}
    if disc is not None:
        diag.update({"disc_radius_px": disc.radius_px, "disc_edge_px": disc.edge_px,
                     "disc_rel_residual": disc.rel_residual})
    if method == "micro-image model":
        fp = fixed_point_applies(disc, period)
        diag["model_solver"] = "fixed point" if fp else "gauss-newton"
    for _ in range(2):  # refit after outlier rejection
        keep = reason == ""
        idx_k, pts_k = idx_all[keep], centres[keep]
        fits = {}
        for g in ("rect", "hex"):
            fits[g] = fit_similarity(idx_k if g == grid else _reindex(idx_k, grid, g), pts_k, g)
        rms = {}
        for g, (hm, _p, _r, _w) in fits.items():
            ii = idx_k if g == grid else _reindex(idx_k, grid, g)
            res = pts_k - apply_homography(hm, ii)
            rms[g] = float(np.sqrt(np.mean(np.sum(res * res, axis=1))))
        best = min(rms, key=rms.get)
        if best != grid:
            idx_all = _reindex(idx_all, grid, best)
            idx_k = idx_all[keep]
            grid = best
        h_sim, pitch, rot, w_sim = fits[grid]
        h_aff, w_aff = fit_affine(idx_k, pts_k, w_sim)
        h_prj, w_prj = fit_projective(idx_k, pts_k, w_aff, h_aff)
        n_eff = float(np.sum(w_prj))
        rss_s = _rss(h_sim, idx_k, pts_k, w_prj)
        rss_a = _rss(h_aff, idx_k, pts_k, w_prj)
        rss_p = _rss(h_prj, idx_k, pts_k, w_prj)
        pred_s = apply_homography(h_sim, idx_k)
        pred_a = apply_homography(h_aff, idx_k)
        pred_p = apply_homography(h_prj, idx_k)
        shift_a = float(np.abs(pred_a - pred_s).max())
        shift_p = float(np.abs(pred_p - pred_a).max())
        use_a, p_a = _richer_warranted(rss_s, rss_a, 4, 6, n_eff, shift_a)
        if use_a:
            use_p, p_p = _richer_warranted(rss_a, rss_p, 6, 8, n_eff, shift_p)
        else:  # the projective terms may matter even when the affine ones do not
            shift_p = float(np.abs(pred_p - pred_s).max())
            use_p, p_p = _richer_warranted(rss_s, rss_p, 4, 8, n_eff, shift_p)
        if use_p:
            model, hmat, k_base = "projective", h_prj, 8
        elif use_a:
            model, hmat, k_base = "affine", h_aff, 6
        else:
            model, hmat, k_base = "similarity", h_sim, 4
        radial = None
        # radial term (vignetted corners, relay distortion) on top of the projective model
        mid = np.array([0.5 * (w - 1), 0.5 * (h - 1)])
        h_rad, rad, _ = fit_radial(idx_k, pts_k, w_prj, h_prj, mid)
        rss_r = _rss(h_rad, idx_k, pts_k, w_prj, rad)
        shift_r = float(np.abs(predict_lattice(h_rad, rad, idx_k)
                               - apply_homography(hmat, idx_k)).max())
        use_r, p_r = _richer_warranted(_rss(hmat, idx_k, pts_k, w_prj), rss_r, k_base, 12,
                                       n_eff, shift_r)
        if use_r:
            model, hmat, radial = "projective+radial", h_rad, rad
        res_all = centres - predict_lattice(hmat, radial, idx_all)
        mag = np.hypot(res_all[:, 0], res_all[:, 1])
        sigma = 1.4826 * float(np.median(mag[keep]))
        outlier = (reason == "") & (mag > max(0.25, 6.0 * sigma))
        reason[outlier] = "outlier"
        if not outlier.any():
            break
    diag.update({
        "similarity_rms_rect_px": rms["rect"], "similarity_rms_hex_px": rms["hex"],
        "affine_p_value": p_a, "projective_p_value": p_p,
        "affine_max_shift_px": shift_a, "projective_max_shift_px": shift_p,
        "radial_p_value": p_r, "radial_max_shift_px": shift_r,
    })
    keep = reason == ""
    res = centres[keep] - predict_lattice(hmat, radial, idx_all[keep])
    rms_px = float(np.sqrt(np.mean(np.sum(res * res, axis=1))))
    rej = ~keep
    progress("fit", 1, 1)
    return GridFit(
        grid=grid,
        pitch_px=pitch,
        rotation_rad=rot,
        offset_px=h_sim[:2, 2].copy(),
        model=model,
        matrix=hmat,
        centres_px=centres[keep],
        indices=idx_all[keep],
        flux=flux[keep],
        residual_rms_px=rms_px,
        rejected_px=centres[rej],
        rejected_reason=tuple(str(r) for r in reason[rej]),
        diagnostics=diag,
        radial=radial,
    )


def _model_centroids(img: np.ndarray, cand: np.ndarray, disc: DiscModel, pitch: float,
                     grid: str, rot: float, progress: Progress):
    """Own-light centroids of touching/overlapping micro-images (``lfcam.calibrate.microimage``).

    Micro-images cut by the sensor border are not measured, but their light reaches the seams
    of their fully visible neighbours, so they are modelled at the lattice position predicted
    from their nearest fully visible neighbour (fixed centre, the neighbour's brightness).
    Returns centroids, fluxes and convergence of the fully visible lenses followed by the
    candidates that were cut, and an ``edge`` mask marking the latter (reported as rejected,
    at their candidate position).
    """
    h, w = img.shape
    reach = disc.support_px

    def inside(pts: np.ndarray) -> np.ndarray:
        return within_sensor(pts, reach, reach, img.shape)

    fast = fixed_point_applies(disc, pitch)
    if fast:
        # start: the integer candidates themselves (within about a pixel of the disc centres;
        # the fixed point contracts by ~0.15 per step, and its pixel classes allow 1.5 px of
        # drift). Circle-window centroids as a start cost 2.4 s CPU at Illum size and gave
        # no better centres (F01 0.0181 vs 0.0174 px, rendered system 1 0.0133 vs 0.0127 px)
        disc_c = cand.copy()
    else:
        disc_c, _, _ = fit_discs(img, cand, disc, pitch, iterations=12, tol_px=5e-3)
    full = inside(disc_c)
    if full.sum() < 5:
        raise CalibrationError(f"only {int(full.sum())} fully visible micro-images found")
    pts = disc_c[full]
    mid = np.array([0.5 * (w - 1), 0.5 * (h - 1)])
    origin = pts[np.argmin(np.hypot(*(pts - mid).T))]
    idx, affine = assign_indices(pts, pitch * rotation_matrix(rot) @ lattice_basis(grid), origin)
    basis = affine[:, :2]
    # every lattice site whose micro-image reaches the sensor but is not fully on it
    corners = np.array([[-reach, -reach], [w + reach, -reach], [-reach, h + reach],
                        [w + reach, h + reach]])
    f = (corners - affine[:, 2]) @ np.linalg.inv(basis).T
    lo, hi = np.floor(f.min(axis=0)) - 1, np.ceil(f.max(axis=0)) + 1
    gi, gj = np.mgrid[int(lo[0]):int(hi[0]) + 1, int(lo[1]):int(hi[1]) + 1]
    sites = np.column_stack([gi.ravel(), gj.ravel()])
    sites, near = _nearest_measured(sites, idx, affine, (h, w), reach + 2.0 * pitch)
    pred = pts[near] + (sites - idx[near]) @ basis.T
    if not fast:
        # overlapping micro-images: the first pass fitted the outermost lenses without their
        # cut neighbours, which pulled them toward the border, and a neighbour predicted from
        # them would inherit that (their own-light centroids then came out 0.1–0.15 px toward
        # the border). Predict every site from a projective lattice fit of the lenses at least
        # one pitch further in.
        deep = within_sensor(pts, reach + pitch, reach + pitch, img.shape)
        if deep.sum() >= 20:
            h_aff, w_aff = fit_affine(idx[deep], pts[deep], np.ones(int(deep.sum())))
            h_prj, _ = fit_projective(idx[deep], pts[deep], w_aff, h_aff)
            pred = apply_homography(h_prj, sites)
    touches = ((pred[:, 0] + reach > -0.5) & (pred[:, 0] - reach < w - 0.5)
               & (pred[:, 1] + reach > -0.5) & (pred[:, 1] - reach < h - 0.5))
    # sites with no measured lens: cut by the border → modelled only (fixed); fully on the
    # sensor but missed by the candidate search → measured like the others (and still subject
    # to the ``dim`` test, so an empty site is never reported as a lens)
    occupied = np.all(sites == idx[near], axis=1)
    extra = pred[touches & ~occupied]
    extra_free = inside(extra)
    allc = np.vstack([pts, extra])
    fixed = np.r_[np.zeros(len(pts), bool), ~extra_free]
    if fast:
        # a cut micro-image follows the measured lens it was predicted from
        anchor = np.r_[np.arange(len(pts)), near[touches & ~occupied]]
        anchor[len(pts):][extra_free] = np.arange(len(pts), len(allc))[extra_free]
        own, flux_own, disc_all, conv_all = own_light_fit(img, allc, disc, pitch, fixed=fixed,
                                                          anchor=anchor, progress=progress)
        # the few lenses the fast fit left unconverged (a disc drifting beyond its pixel
        # classes, e.g. in cat's-eye corners): Gauss–Newton, their neighbours held
        retry = ~fixed & ~conv_all
        if retry.any():
            _refit_discs(img, disc, pitch, retry, fixed, disc_all, own, flux_own, conv_all)
    else:
        centre_on = ((allc[:, 0] >= 0) & (allc[:, 0] <= w - 1) & (allc[:, 1] >= 0)
                     & (allc[:, 1] <= h - 1))
        disc_all, coef, conv_all = fit_discs(img, allc, disc, pitch, fixed=fixed,
                                             fit_fixed_centres=centre_on, progress=progress)
        own, flux_own = own_light_centroids(img, disc_all, coef, disc)
    measured = ~fixed
    good = np.isfinite(own).all(axis=1)
    centres = np.vstack([np.where(good[:, None], own, disc_all)[measured], cand[~full]])
    flux = np.r_[flux_own[measured], np.zeros(int((~full).sum()))]
    conv = np.r_[(conv_all & good)[measured], np.ones(int((~full).sum()), bool)]
    # the fully-visible test again on the fitted disc centres (the start may be ~0.1 px off)
    at_edge = np.r_[~inside(disc_all[measured]), np.ones(int((~full).sum()), bool)]
    return centres, flux, conv, at_edge


def _nearest_measured(sites: np.ndarray, idx: np.ndarray, affine: np.ndarray,
                      shape: tuple[int, int], margin_px: float) -> tuple[np.ndarray, np.ndarray]:
    """For each lattice site (i, j), the row of ``idx`` nearest it in index space: itself
    where a lens was measured there (a table lookup), else by a k-d tree query. Sites that
    the lattice ``affine`` puts over ``margin_px`` off the sensor are dropped (no micro-image
    there reaches it); those sites and their rows are returned.

    The same rows as a k-d tree query of every site (two lenses given one index: the first),
    at a fraction of its cost: an Illum-size white has ~340 000 sites, of which ~230 000 are
    measured, and the full query took 0.46 s of serial CPU.
    """
    h, w = shape
    lo = sites.min(axis=0)
    rel = idx - lo
    span = sites.max(axis=0) - lo + 1
    if (rel < 0).any() or (rel >= span).any():  # (measured lenses outside the sites' box)
        return sites, cKDTree(idx).query(sites)[1]
    slot = np.full(tuple(span), -1, np.int64)
    rows = np.arange(len(idx))[::-1]  # the first lens of an index wins
    slot[rel[rows, 0], rel[rows, 1]] = rows
    near = slot[sites[:, 0] - lo[0], sites[:, 1] - lo[1]]
    xy = sites @ affine[:, :2].T + affine[:, 2]
    keep = ((xy[:, 0] > -margin_px) & (xy[:, 0] < w - 1 + margin_px)
            & (xy[:, 1] > -margin_px) & (xy[:, 1] < h - 1 + margin_px)) | (near >= 0)
    sites, near = sites[keep], near[keep]
    free = near < 0
    if free.any():
        near[free] = cKDTree(idx).query(sites[free])[1]
    return sites, near


def _refit_discs(img: np.ndarray, disc: DiscModel, pitch: float, sel: np.ndarray,
                 fixed: np.ndarray, disc_c: np.ndarray, own: np.ndarray, flux: np.ndarray,
                 conv: np.ndarray, tile: int = 512) -> None:
    """Re-fit the discs ``sel`` by Gauss–Newton (:func:`fit_discs`), in place.

    Their neighbours within two pitches are modelled at their current centres (held; cut ones
    with their donors' brightness, fitted when their centre is on the sensor, as in the
    Gauss–Newton path); own-light centroid, flux, disc centre and convergence of ``sel``
    are replaced. Done per ``tile``-pixel tile on an image crop (the few lenses are spread
    over the corners; a full-image model per fit step would cost more than the fit).
    """
    h, w = img.shape
    margin = 2.0 * pitch + 2.0 * disc.patch_half_px() + 2.0
    tree = cKDTree(disc_c)
    ks = np.flatnonzero(sel)
    key = (disc_c[ks, 1] // tile) * (w // tile + 1) + disc_c[ks, 0] // tile
    for kk in np.unique(key):
        grp = ks[key == kk]
        near = tree.query_ball_point(disc_c[grp], 2.0 * pitch + 1.0)
        sub = np.zeros(len(disc_c), bool)
        sub[np.concatenate([np.asarray(x, np.int64) for x in near])] = True
        sub[grp] = True
        si = np.flatnonzero(sub)
        lo = np.maximum(np.floor(disc_c[grp].min(axis=0) - margin), 0).astype(int)
        hi = np.minimum(np.ceil(disc_c[grp].max(axis=0) + margin) + 1, [w, h]).astype(int)
        crop = img[lo[1]:hi[1], lo[0]:hi[0]]
        c = disc_c[si] - lo
        centre_on = ((disc_c[si, 0] >= 0) & (disc_c[si, 0] <= w - 1) & (disc_c[si, 1] >= 0)
                     & (disc_c[si, 1] <= h - 1))
        fit = np.isin(si, grp)
        d_s, coef_s, conv_s = fit_discs(crop, c, disc, pitch, iterations=15, fixed=fixed[si],
                                        fit_fixed_centres=centre_on, hold=~fit & ~fixed[si])
        own_s, flux_s = own_light_centroids(crop, d_s, coef_s, disc)
        t = si[fit]
        own[t], flux[t], disc_c[t] = own_s[fit] + lo, flux_s[fit], d_s[fit] + lo
        conv[t] = conv_s[fit]


def _reindex(idx: np.ndarray, src: str, dst: str) -> np.ndarray:
    """Re-express indices of one lattice basis in the other (rounded, for the grid test)."""
    if src == dst:
        return idx
    m = np.linalg.inv(lattice_basis(dst)) @ lattice_basis(src)
    return np.round(idx.astype(np.float64) @ m.T).astype(np.int64)


def _dedupe(idx: np.ndarray, centres: np.ndarray, usable: np.ndarray, reason: np.ndarray) -> None:
    sel = np.flatnonzero(usable)
    if len(sel) < 2:
        return
    key = idx[sel]
    design = np.column_stack([key.astype(np.float64), np.ones(len(sel))])
    sol, *_ = np.linalg.lstsq(design, centres[sel], rcond=None)
    err = np.hypot(*(centres[sel] - design @ sol).T)
    order = np.lexsort((err, key[:, 1], key[:, 0]))
    k_sorted = key[order]
    same = np.zeros(len(sel), bool)
    same[1:] = (k_sorted[1:] == k_sorted[:-1]).all(axis=1)
    reason[sel[order[same]]] = "duplicate"


def _mark_dim(idx: np.ndarray, flux: np.ndarray, reason: np.ndarray, frac: float = 0.7) -> None:
    sel = np.flatnonzero(reason == "")
    if len(sel) == 0:
        return
    key = idx[sel]
    lo = key.min(axis=0)
    shape = tuple(key.max(axis=0) - lo + 1 + 4)
    table = np.full(shape, np.nan)
    table[key[:, 0] - lo[0] + 2, key[:, 1] - lo[1] + 2] = flux[sel]
    win = np.lib.stride_tricks.sliding_window_view(np.pad(table, 2, constant_values=np.nan),
                                                   (5, 5))
    local = win[key[:, 0] - lo[0] + 2, key[:, 1] - lo[1] + 2].reshape(len(sel), -1)
    count = np.sum(np.isfinite(local), axis=1)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(local, axis=1)
    glob = float(np.median(flux[sel]))
    ref = np.where(count >= 4, med, glob)
    dim = flux[sel] < frac * ref
    reason[sel[dim]] = "dim"
