"""White images with touching micro-images and their truth centroids (benchmark generator).

``lfcam.calibrate.synthetic.make_white`` paints each pixel with the light of its *nearest*
lens only, so its micro-images never share a pixel. Real Lytro whites (F01, Illum) have soft
micro-image edges that touch: the seam pixels hold light of two lenslets. This module draws
each micro-image independently and **adds** them, so seams are shared, and it keeps the light
of every lens separately to compute the truth.

Model of one micro-image k (lattice site ``c_k``)::

    L_k(x) = peak · V(x) · ½ erfc((|x − c_k| − R) / (√2 σ))
    V(x)   = 1 − vignetting · (|x − m| / r_corner)²        (m = image centre)

The pixel value is the mean of ``L_k`` over ``supersample²`` points inside the pixel, summed
over lenses; shot (Poisson) and Gaussian read noise are added afterwards.

Truth
-----
The reported centre of a micro-image is its **intensity centroid** (docs/calibration.md). With
vignetting, ``V`` brightens the side nearer the image centre, so the centroid is *not* the
lattice point: it is shifted toward the centre by up to a few thousandths of a pixel. The
truth here is the centroid of lens k's own noise-free pixel values (the same supersampled
light that went into the image), accumulated lens by lens, independent of any calibration
code. ``continuous_centroids`` gives the closed-form centroid of the continuous light
(``V`` is quadratic, so only the radial moments of the disc profile enter) as a check of that
truth: the two agree to ~1e-4 px.

Run ``python benchmarks/whites.py`` for a small self-check of the truth definitions.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.special import erfc

from lfcam.calibrate.synthetic import lattice_basis, rotation_matrix


@dataclass(frozen=True)
class TouchingWhite:
    """A generated white with touching micro-images and its truth.

    Attributes
    ----------
    image : (H, W) float32
    centres_px : (N, 2)
        Truth intensity centroids (x, y) of the fully visible micro-images.
    lattice_px : (N, 2)
        Their lattice sites (the disc centres).
    indices : (N, 2) int
        Lattice indices (i, j).
    continuous_px : (N, 2)
        Closed-form centroid of the continuous (not pixel-sampled) light, for checking.
    pitch_px, rotation_rad : float
    grid : str
    """

    image: np.ndarray
    centres_px: np.ndarray
    lattice_px: np.ndarray
    indices: np.ndarray
    continuous_px: np.ndarray
    pitch_px: float
    rotation_rad: float
    grid: str


def _profile(r: np.ndarray, radius: float, sigma: float) -> np.ndarray:
    return 0.5 * erfc((r - radius) / (np.sqrt(2.0) * sigma))


def continuous_centroids(sites: np.ndarray, radius: float, sigma: float, vignetting: float,
                         centre: np.ndarray, r_corner: float) -> np.ndarray:
    """Closed-form centroid of ``V(x)·f(|x − c|)`` for each site ``c`` (module docstring).

    With u = x − c and V(c + u) = V(c) − 2α(c − m)·u/r² − α|u|²/r² (α = vignetting,
    r = r_corner), the centroid shift is −α(c − m)·M2 / (r²·V(c)·M0 − α·M2), where
    M0 = ∫ f and M2 = ∫ |u|² f over the plane (computed by fine radial quadrature).
    """
    rr = np.linspace(0.0, radius + 12.0 * sigma, 200_001)
    f = _profile(rr, radius, sigma) * 2.0 * np.pi * rr
    m0 = np.trapezoid(f, rr)
    m2 = np.trapezoid(f * rr * rr, rr)
    a = vignetting / r_corner**2
    rel = sites - centre
    v_c = 1.0 - a * np.sum(rel * rel, axis=1)
    shift = -a * rel * m2 / (v_c * m0 - a * m2)[:, None]
    return sites + shift


def make_touching_white(
    width_px: int,
    height_px: int,
    pitch_px: float,
    grid: str = "hex",
    rotation_rad: float = 0.0,
    offset_px: tuple[float, float] | None = None,
    radius_frac: float = 0.46,
    edge_sigma_px: float = 0.5,
    vignetting: float = 0.45,
    peak: float = 1000.0,
    noise: bool = True,
    read_noise: float = 3.0,
    supersample: int = 3,
    seed: int = 0,
    chunk: int = 4096,
) -> TouchingWhite:
    """Render a white image whose micro-images touch (or overlap), and its truth.

    Parameters
    ----------
    width_px, height_px : int
    pitch_px : float
        Nearest-neighbour lens distance.
    grid : {"hex", "rect"}
    rotation_rad : float
    offset_px : (x, y), optional
        Lattice index (0, 0); default image centre + (0.31, −0.17).
    radius_frac : float
        Disc radius (half-height of the soft edge) over the pitch. 0.46 with
        ``edge_sigma_px`` 0.5 leaves no dark gap: the seams are at ~25 % of the peak.
    edge_sigma_px : float
        Gaussian blur σ of the disc edge (erfc profile).
    vignetting : float
        Radial falloff, brightness 1 − vignetting at the image corners.
    peak : float
        Electrons at the centre of an unvignetted disc.
    noise : bool
        Poisson shot noise.
    read_noise : float
        Gaussian read-noise σ (electrons).
    supersample : int
        Sample points per pixel side.
    seed : int
    chunk : int
        Lenses per vectorised block.

    Returns
    -------
    TouchingWhite
    """
    w, h = int(width_px), int(height_px)
    if offset_px is None:
        offset_px = (0.5 * (w - 1) + 0.31, 0.5 * (h - 1) - 0.17)
    off = np.asarray(offset_px, dtype=np.float64)
    a = pitch_px * rotation_matrix(rotation_rad) @ lattice_basis(grid)
    radius = radius_frac * pitch_px
    reach = radius + 4.5 * edge_sigma_px  # light beyond this is < 1e-5 of the peak
    centre = np.array([0.5 * (w - 1), 0.5 * (h - 1)])
    r_corner = float(np.hypot(*centre))

    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], dtype=np.float64)
    f = (corners - off) @ np.linalg.inv(a).T
    lo = np.floor(f.min(axis=0)).astype(int) - 2
    hi = np.ceil(f.max(axis=0)).astype(int) + 2
    ii, jj = np.mgrid[lo[0]:hi[0] + 1, lo[1]:hi[1] + 1]
    idx = np.column_stack([ii.ravel(), jj.ravel()])
    sites = off + idx @ a.T
    lit = ((sites[:, 0] + reach > -0.5) & (sites[:, 0] - reach < w - 0.5)
           & (sites[:, 1] + reach > -0.5) & (sites[:, 1] - reach < h - 0.5))
    idx, sites = idx[lit], sites[lit]

    half = int(np.ceil(reach)) + 1
    o = np.arange(-half, half + 1)
    px, py = np.meshgrid(o, o)  # (S, S): x varies along columns
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    sx, sy = np.meshgrid(sub, sub)
    sx, sy = sx.ravel(), sy.ravel()
    image = np.zeros(h * w)
    sums = np.zeros((len(sites), 3))
    for s in range(0, len(sites), chunk):
        c = sites[s:s + chunk]
        base = np.round(c).astype(np.int64)
        gx = base[:, 0, None, None] + px[None]  # (n, S, S) pixel x
        gy = base[:, 1, None, None] + py[None]
        val = np.zeros(gx.shape)
        for dx, dy in zip(sx, sy, strict=True):
            xs, ys = gx + dx, gy + dy
            r = np.hypot(xs - c[:, 0, None, None], ys - c[:, 1, None, None])
            vig = 1.0 - vignetting * ((xs - centre[0]) ** 2 + (ys - centre[1]) ** 2) / r_corner**2
            val += _profile(r, radius, edge_sigma_px) * vig
        val *= peak / supersample**2
        inside = (gx >= 0) & (gx < w) & (gy >= 0) & (gy < h)
        val = np.where(inside, val, 0.0)
        sums[s:s + chunk, 0] = val.sum(axis=(1, 2))
        sums[s:s + chunk, 1] = (val * gx).sum(axis=(1, 2))
        sums[s:s + chunk, 2] = (val * gy).sum(axis=(1, 2))
        flat = np.where(inside, gy * w + gx, 0)
        image += np.bincount(flat[inside], weights=val[inside], minlength=h * w)

    full = ((sites[:, 0] - reach >= -0.5) & (sites[:, 0] + reach <= w - 0.5)
            & (sites[:, 1] - reach >= -0.5) & (sites[:, 1] + reach <= h - 0.5))
    truth = sums[full, 1:] / sums[full, :1]
    rng = np.random.default_rng(seed)
    image = image.reshape(h, w)
    if noise:
        image = rng.poisson(image).astype(np.float64)
    if read_noise > 0.0:
        image += rng.normal(0.0, read_noise, image.shape)
    return TouchingWhite(
        image=image.astype(np.float32),
        centres_px=truth,
        lattice_px=sites[full],
        indices=idx[full],
        continuous_px=continuous_centroids(sites[full], radius, edge_sigma_px, vignetting,
                                           centre, r_corner),
        pitch_px=float(pitch_px),
        rotation_rad=float(rotation_rad),
        grid=grid,
    )


# the benchmark cases (name → make_touching_white keyword arguments)
CASES = {
    "illum-touching": dict(width_px=7728, height_px=5368, pitch_px=14.29,
                           rotation_rad=float(np.deg2rad(0.3)), radius_frac=0.46),
    "f01-touching": dict(width_px=3280, height_px=3280, pitch_px=9.9,
                         rotation_rad=float(np.deg2rad(-0.4)), radius_frac=0.46),
}


def load_case(name: str) -> TouchingWhite:
    """Generate a :data:`CASES` white once and cache it in $TMPDIR."""
    cache = Path(tempfile.gettempdir()) / f"lfcam_bench_{name}_v1.npz"
    if cache.exists():
        z = np.load(cache)
        return TouchingWhite(z["image"], z["truth"], z["lattice"], z["idx"], z["cont"],
                             float(z["pitch"]), float(z["rot"]), str(z["grid"]))
    t = time.perf_counter()
    sw = make_touching_white(**CASES[name])
    np.savez(cache, image=sw.image, truth=sw.centres_px, lattice=sw.lattice_px,
             idx=sw.indices, cont=sw.continuous_px, pitch=sw.pitch_px, rot=sw.rotation_rad,
             grid=sw.grid)
    print(f"{name}: generated in {time.perf_counter() - t:.1f} s (cached: {cache})", flush=True)
    return sw


if __name__ == "__main__":
    sw = make_touching_white(640, 480, 14.29, rotation_rad=0.01, noise=False, read_noise=0.0)
    d_cont = np.hypot(*(sw.centres_px - sw.continuous_px).T)
    d_lat = np.hypot(*(sw.centres_px - sw.lattice_px).T)
    print(f"{len(sw.centres_px)} lenses; pixel truth vs continuous centroid: max "
          f"{d_cont.max():.2e} px; vs lattice site: max {d_lat.max():.4f} px")
