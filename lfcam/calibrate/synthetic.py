"""A small, self-contained white-image generator for testing and benchmarking calibration.

This is *not* the project renderer (``lfcam.sim``). It draws each micro-image as a disc
(radius ``radius_px``) with a one-pixel linear edge ramp, optionally clipped by a second,
field-dependent disc (the "cat's eye" of mechanical vignetting), multiplied by a smooth
natural-vignetting falloff over the sensor. Micro-images never overlap, so the truth is
unambiguous: the **intensity centroid** of each lens's own noise-free pixels, computed by
``np.bincount`` over the pixels that lens painted. That truth does not depend on how the
calibration detects or refines centres.

Lattice: the one convention of :func:`lfcam.optics.mla.lattice_basis`, in pixel coordinates
(x = column, y = row, pixel centres at integers).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lfcam.optics.mla import lattice_basis, rotation_matrix


@dataclass(frozen=True)
class SyntheticWhite:
    """A generated white image and its truth.

    Attributes
    ----------
    image : (H, W) float32 array
        The white image (noise included when requested).
    centres_px : (N, 2) array
        Truth intensity centroids (x, y) of the fully visible micro-images.
    disc_centres_px : (N, 2) array
        The lattice positions the discs were drawn at (differ from the centroids by the
        vignetting asymmetry).
    indices : (N, 2) int array
        Lattice indices (i, j) of those lenses.
    pitch_px, rotation_rad : float
    offset_px : (2,) array
        Lattice origin (position of index (0, 0)).
    grid : str
    """

    image: np.ndarray
    centres_px: np.ndarray
    disc_centres_px: np.ndarray
    indices: np.ndarray
    pitch_px: float
    rotation_rad: float
    offset_px: np.ndarray
    grid: str


def make_white(
    width_px: int,
    height_px: int,
    pitch_px: float,
    grid: str = "rect",
    rotation_rad: float = 0.0,
    offset_px: tuple[float, float] | None = None,
    radius_frac: float = 0.42,
    vignetting: float = 0.5,
    cats_eye: float = 0.0,
    peak: float = 1000.0,
    background: float = 0.0,
    noise_electrons: bool = False,
    read_noise: float = 0.0,
    hot_pixel_fraction: float = 0.0,
    seed: int = 0,
    rows_per_chunk: int = 256,
) -> SyntheticWhite:
    """Render a white image of disc micro-images on a rect or hex lattice.

    Parameters
    ----------
    width_px, height_px : int
        Image size.
    pitch_px : float
        Lens pitch (nearest-neighbour distance) in pixels.
    grid : {"rect", "hex"}
    rotation_rad : float
        Lattice rotation.
    offset_px : (x, y), optional
        Position of lattice index (0, 0); default the image centre plus (0.31, -0.17).
    radius_frac : float
        Disc radius as a fraction of the pitch (< 0.5 keeps micro-images apart).
    vignetting : float
        Natural vignetting: brightness ``1 - vignetting·(r/r_corner)²`` over the sensor.
    cats_eye : float
        Mechanical vignetting: each disc is intersected with a disc of the same radius shifted
        outward by ``cats_eye · radius · r/r_corner``.
    peak : float
        Brightness (electrons) at the centre of an unvignetted disc.
    background : float
        Constant added everywhere (an unsubtracted dark level).
    noise_electrons : bool
        Add Poisson shot noise.
    read_noise : float
        Gaussian read-noise sigma (electrons).
    hot_pixel_fraction : float
        Fraction of pixels set to ``4·peak`` after the truth is computed.
    seed : int
    rows_per_chunk : int
        Memory control for large images.

    Returns
    -------
    SyntheticWhite
    """
    w, h = int(width_px), int(height_px)
    if offset_px is None:
        offset_px = (0.5 * (w - 1) + 0.31, 0.5 * (h - 1) - 0.17)
    off = np.asarray(offset_px, dtype=np.float64)
    a = pitch_px * rotation_matrix(rotation_rad) @ lattice_basis(grid)
    a_inv = np.linalg.inv(a)
    radius = radius_frac * pitch_px
    centre = np.array([0.5 * (w - 1), 0.5 * (h - 1)])
    r_corner = float(np.hypot(*centre))

    # index range covering the image
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], dtype=np.float64)
    ij = (corners - off) @ a_inv.T
    i_lo, j_lo = np.floor(ij.min(axis=0)).astype(int) - 2
    i_hi, j_hi = np.ceil(ij.max(axis=0)).astype(int) + 2
    n_i, n_j = i_hi - i_lo + 1, j_hi - j_lo + 1

    image = np.zeros((h, w), dtype=np.float64)
    sums = np.zeros((3, n_i * n_j))
    xs = np.arange(w, dtype=np.float64)
    # candidates: the rounded index and its neighbours (hex needs the 3x3 block)
    cand = np.array([(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1)])
    for r0 in range(0, h, rows_per_chunk):
        r1 = min(h, r0 + rows_per_chunk)
        yy, xx = np.meshgrid(np.arange(r0, r1, dtype=np.float64), xs, indexing="ij")
        p = np.stack([xx.ravel(), yy.ravel()], axis=1)
        f = (p - off) @ a_inv.T
        base = np.round(f).astype(np.int64)
        best_d2 = np.full(len(p), np.inf)
        best = np.zeros_like(base)
        for di, dj in cand:
            idx = base + (di, dj)
            c = off + idx @ a.T
            d2 = ((p - c) ** 2).sum(axis=1)
            better = d2 < best_d2
            best_d2 = np.where(better, d2, best_d2)
            best[better] = idx[better]
        c = off + best @ a.T
        d = np.sqrt(best_d2)
        cover = np.clip(radius - d + 0.5, 0.0, 1.0)
        rc = (c - centre) / r_corner  # field position of the lens, unit at the corner
        if cats_eye > 0.0:
            c2 = c + cats_eye * radius * rc
            d2b = np.sqrt(((p - c2) ** 2).sum(axis=1))
            cover *= np.clip(radius - d2b + 0.5, 0.0, 1.0)
        rp2 = (((p - centre) / r_corner) ** 2).sum(axis=1)
        val = peak * cover * (1.0 - vignetting * rp2)
        image[r0:r1] = val.reshape(r1 - r0, w)
        flat = (best[:, 0] - i_lo) * n_j + (best[:, 1] - j_lo)
        nz = val > 0
        sums[0] += np.bincount(flat[nz], weights=val[nz], minlength=n_i * n_j)
        sums[1] += np.bincount(flat[nz], weights=(val * p[:, 0])[nz], minlength=n_i * n_j)
        sums[2] += np.bincount(flat[nz], weights=(val * p[:, 1])[nz], minlength=n_i * n_j)

    ii, jj = np.meshgrid(np.arange(i_lo, i_hi + 1), np.arange(j_lo, j_hi + 1), indexing="ij")
    idx_all = np.stack([ii.ravel(), jj.ravel()], axis=1)
    disc = off + idx_all @ a.T
    # fully visible: the whole disc (plus its edge ramp) lies inside the image
    m = radius + 1.0
    inside = (
        (disc[:, 0] - m >= -0.5)
        & (disc[:, 0] + m <= w - 0.5)
        & (disc[:, 1] - m >= -0.5)
        & (disc[:, 1] + m <= h - 0.5)
        & (sums[0] > 0)
    )
    with np.errstate(invalid="ignore", divide="ignore"):
        cen = np.stack([sums[1] / sums[0], sums[2] / sums[0]], axis=1)

    rng = np.random.default_rng(seed)
    if noise_electrons:
        image = rng.poisson(image).astype(np.float64)
    if read_noise > 0.0:
        image += rng.normal(0.0, read_noise, image.shape)
    image += background
    if hot_pixel_fraction > 0.0:
        n_hot = int(hot_pixel_fraction * w * h)
        image.flat[rng.choice(w * h, n_hot, replace=False)] = 4.0 * peak
    return SyntheticWhite(
        image=image.astype(np.float32),
        centres_px=cen[inside],
        disc_centres_px=disc[inside],
        indices=idx_all[inside],
        pitch_px=float(pitch_px),
        rotation_rad=float(rotation_rad),
        offset_px=off,
        grid=grid,
    )
