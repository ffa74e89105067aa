"""d_in (main-lens centre → MLA) from a capture of a textured plane at a known distance.

Geometry (sensor at the lenslet focal plane, f_x behind the MLA). A sensor pixel at height
``y_j + u`` behind lenslet j (optical centre at height ``y_j``) receives the ray through the
lenslet centre with slope ``u / f_x``. Traced back through the main lens, that ray meets the
reference plane at some point X(y_j, u). The same texture point X is therefore seen in the
neighbouring lenslet at ``u'`` with X(y_j + P, u') = X(y_j, u), and the sensor distance between
the two sightings is ``P + (u' − u)`` (P = lenslet pitch).

* **paraxial**: the plane images to z_img (paraxial image distance of the thick lens), and
  ``u' − u = f_x P / (d_in − z_img)``, so ``d_in = z_img + f_x P / (spacing − P)``.
* **exact**: X(y, u) from the exact thick-lens trace (the lens is symmetric, so a backward
  trace is the forward trace mirrored in z), ``u'`` found by interpolation, averaged over the
  micro-image, and ``d_in`` solved by Brent's method.

Measurement: the capture is flat-fielded by the white image, a square patch around each
calibrated centre is cut (sub-pixel, bilinear), and the shift of the texture between
neighbouring micro-images is found by symmetric Lucas–Kanade iterations (both patches moved
by half the shift, so both get the same interpolation blur), seeded by FFT phase correlation.
spacing = (centre distance) + (texture shift), both in pixels, then × pixel pitch.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import brentq

from lfcam.camera import CameraProfile
from lfcam.errors import CalibrationError
from lfcam.optics.paraxial import image_distance_mm
from lfcam.optics.trace import trace_rays

MAX_PAIRS = 1500


@dataclass(frozen=True)
class DinResult:
    """d_in estimates from one reference-plane capture."""

    d_in_paraxial_mm: float
    d_in_exact_mm: float
    spacing_mm: float  # measured sensor distance between sightings of one texture point
    spacing_std_mm: float  # spread over lens pairs
    n_pairs: int
    z_image_paraxial_mm: float


def paraxial_image_z_mm(profile: CameraProfile, distance_mm: float) -> float:
    """z of the paraxial image of a plane ``distance_mm`` before the front vertex."""
    lens = profile.main_lens
    return lens.back_principal_z_mm + float(image_distance_mm(lens, distance_mm))


def object_heights_mm(
    profile: CameraProfile, d_in_mm: float, distance_mm: float, y_lens_mm: np.ndarray,
    u_mm: np.ndarray,
) -> np.ndarray:
    """Meridional height X on the reference plane seen by sensor offset ``u`` behind lens ``y``.

    Exact trace: the ray through the lenslet centre (height y, at z = d_in) with slope u/f_x,
    traced backward; mirrored in z because the main lens is symmetric about z = 0.
    """
    lens = profile.main_lens
    fx = profile.mla.focal_length_mm
    y, u = np.broadcast_arrays(np.asarray(y_lens_mm, float), np.asarray(u_mm, float))
    slope = u.ravel() / fx
    n = slope.size
    origins = np.column_stack([np.zeros(n), y.ravel(), np.full(n, -d_in_mm)])
    dirs = np.column_stack([np.zeros(n), -slope, np.ones(n)])
    z_plane = 0.5 * lens.thickness_mm + distance_mm
    res = trace_rays(lens, origins, dirs, z_plane)
    return res.points[:, 1].reshape(y.shape)


def spacing_exact_mm(
    profile: CameraProfile, d_in_mm: float, distance_mm: float, half_window_mm: float,
    lens_heights_mm: np.ndarray | None = None,
) -> float:
    """Exact-trace sensor spacing of one texture point between neighbouring lenslets."""
    p = profile.mla.pitch_mm
    ys = np.array([0.0]) if lens_heights_mm is None else np.asarray(lens_heights_mm, float)
    u = np.linspace(-half_window_mm, half_window_mm, 41)
    fine = np.linspace(-2.5 * half_window_mm - p, 2.5 * half_window_mm + p, 801)
    shifts = []
    for y0 in ys:
        x0 = object_heights_mm(profile, d_in_mm, distance_mm, y0, u)
        x1 = object_heights_mm(profile, d_in_mm, distance_mm, y0 + p, fine)
        ok = np.isfinite(x1)
        xs, us = x1[ok], fine[ok]
        order = np.argsort(xs)
        u1 = np.interp(x0, xs[order], us[order], left=np.nan, right=np.nan)
        shifts.append(u1 - u)
    d = np.concatenate(shifts)
    if not np.isfinite(d).any():
        raise CalibrationError("reference plane: exact trace found no corresponding rays")
    return p + float(np.nanmean(d))


def solve_d_in(
    profile: CameraProfile, distance_mm: float, spacing_mm: float, half_window_mm: float
) -> tuple[float, float]:
    """(paraxial, exact) d_in from a measured sensor spacing."""
    p, fx = profile.mla.pitch_mm, profile.mla.focal_length_mm
    z_img = paraxial_image_z_mm(profile, distance_mm)
    excess = spacing_mm - p
    if abs(excess) < 1e-9 * p:
        raise CalibrationError(
            "reference plane is in focus on the MLA: no parallax between micro-images; use a "
            "plane well in front of or behind the focused distance"
        )
    d_par = z_img + fx * p / excess
    def f(d: float) -> float:
        return spacing_exact_mm(profile, d, distance_mm, half_window_mm) - spacing_mm

    if excess > 0:
        lo, hi = z_img + 1e-3, d_par * 1.5 + 50
    else:
        lo, hi = max(d_par * 0.5, 1e-3), z_img - 1e-3
    # bracket around the paraxial answer first (the exact one is close to it)
    span = abs(d_par - z_img)
    a, b = d_par - 0.5 * span, d_par + 0.5 * span
    try:
        fa, fb = f(a), f(b)
        if not (np.isfinite(fa) and np.isfinite(fb) and fa * fb < 0):
            a, b = lo, hi
        d_ex = brentq(f, a, b, xtol=1e-9)
    except ValueError:
        raise CalibrationError(
            "reference plane: exact model has no d_in matching the data"
        ) from None
    return float(d_par), float(d_ex)


def _patches(image: np.ndarray, centres: np.ndarray, half: int) -> np.ndarray:
    size = (2 * half + 1, 2 * half + 1)
    return np.stack([cv2.getRectSubPix(image, size, (float(x), float(y))) for x, y in centres])


def _lk_shift(a_img: np.ndarray, ca: np.ndarray, cb: np.ndarray, half: int,
              start: np.ndarray, iterations: int = 8) -> np.ndarray:
    """Symmetric Lucas–Kanade shift d with B(cb + x + d/2) = A(ca + x − d/2), per pair."""
    d = start.astype(np.float64).copy()
    g = np.hanning(2 * half + 3)[1:-1]
    wgt = np.outer(g, g)
    for _ in range(iterations):
        pa = _patches(a_img, ca - 0.5 * d, half)
        pb = _patches(a_img, cb + 0.5 * d, half)
        gx = 0.5 * (np.gradient(pa, axis=2) + np.gradient(pb, axis=2))
        gy = 0.5 * (np.gradient(pa, axis=1) + np.gradient(pb, axis=1))
        e = pb - pa
        axx = np.sum(wgt * gx * gx, axis=(1, 2))
        axy = np.sum(wgt * gx * gy, axis=(1, 2))
        ayy = np.sum(wgt * gy * gy, axis=(1, 2))
        bx = np.sum(wgt * gx * e, axis=(1, 2))
        by = np.sum(wgt * gy * e, axis=(1, 2))
        det = axx * ayy - axy * axy
        ok = det > 1e-12
        with np.errstate(invalid="ignore", divide="ignore"):
            sx = -(ayy * bx - axy * by) / det
            sy = -(axx * by - axy * bx) / det
        step = np.where(ok[:, None], np.column_stack([sx, sy]), 0.0)
        d += step
    return d


def measure_d_in(
    capture: np.ndarray,
    white: np.ndarray,
    centres_px: np.ndarray,
    indices: np.ndarray,
    profile: CameraProfile,
    distance_mm: float,
    direction: tuple[int, int] = (1, 0),
    window_frac: float = 0.35,
    max_pairs: int = MAX_PAIRS,
) -> DinResult:
    """Estimate d_in from a reference-plane capture and the white-image calibration.

    Parameters
    ----------
    capture, white : (H, W) arrays
        Reference-plane capture and the white image of the same camera setting.
    centres_px, indices : arrays
        From the calibration (accepted lenses).
    profile : CameraProfile
        Main lens, lenslet pitch/focal length and pixel pitch.
    distance_mm : float
        Reference plane → front vertex.
    direction : (di, dj)
        Lattice step between compared lenses (default along the rows).
    window_frac : float
        Patch half-size as a fraction of the lens pitch.
    """
    cap = np.asarray(capture, np.float32)
    wht = np.asarray(white, np.float32)
    if cap.shape != wht.shape:
        raise CalibrationError(f"capture {cap.shape} and white image {wht.shape} differ in size")
    floor = 0.05 * float(np.percentile(wht, 99))
    flat = np.where(wht > floor, cap / np.maximum(wht, floor), 0.0).astype(np.float32)
    pp = profile.sensor.pixel_pitch_mm
    key = {tuple(k): n for n, k in enumerate(np.asarray(indices).tolist())}
    step = np.asarray(direction)
    if abs(int(step[0])) + abs(int(step[1])) != 1:
        raise CalibrationError("reference plane: direction must be one lattice step, e.g. (1, 0)")
    pairs = [(n, key[(i + step[0], j + step[1])]) for (i, j), n in key.items()
             if (i + step[0], j + step[1]) in key]
    if len(pairs) < 4:
        raise CalibrationError("reference plane: too few neighbouring lens pairs")
    pairs = np.array(pairs)
    mid = np.array(cap.shape[::-1], float) / 2.0
    dist = np.hypot(*(centres_px[pairs[:, 0]] - mid).T)
    pairs = pairs[np.argsort(dist)[:max_pairs]]
    ca, cb = centres_px[pairs[:, 0]], centres_px[pairs[:, 1]]
    pitch_px = float(np.median(np.hypot(*(cb - ca).T)))
    half = max(2, int(round(window_frac * pitch_px)))
    # seed: FFT phase correlation (integer-ish), then symmetric Lucas–Kanade
    pa, pb = _patches(flat, ca, half), _patches(flat, cb, half)
    fa = np.fft.fft2(pa - pa.mean(axis=(1, 2), keepdims=True))
    fb = np.fft.fft2(pb - pb.mean(axis=(1, 2), keepdims=True))
    cross = fb * np.conj(fa)
    corr = np.fft.ifft2(cross / np.maximum(np.abs(cross), 1e-12)).real
    n = 2 * half + 1
    flat_idx = corr.reshape(len(corr), -1).argmax(axis=1)
    sy, sx = np.unravel_index(flat_idx, (n, n))
    seed = np.column_stack([np.where(sx > n // 2, sx - n, sx), np.where(sy > n // 2, sy - n, sy)])
    d = _lk_shift(flat, ca, cb, half, seed.astype(float))
    sep = cb - ca
    unit = sep / np.hypot(*sep.T)[:, None]
    spacing_px = np.hypot(*sep.T) + np.sum(d * unit, axis=1)
    good = np.isfinite(spacing_px)
    med = np.median(spacing_px[good])
    mad = 1.4826 * np.median(np.abs(spacing_px[good] - med)) + 1e-9
    good &= np.abs(spacing_px - med) < 4 * mad
    spacing_mm = float(np.mean(spacing_px[good])) * pp
    d_par, d_ex = solve_d_in(profile, distance_mm, spacing_mm, half * pp)
    return DinResult(
        d_in_paraxial_mm=d_par,
        d_in_exact_mm=d_ex,
        spacing_mm=spacing_mm,
        spacing_std_mm=float(np.std(spacing_px[good])) * pp,
        n_pairs=int(good.sum()),
        z_image_paraxial_mm=paraxial_image_z_mm(profile, distance_mm),
    )
