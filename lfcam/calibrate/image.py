"""Preparing white images for calibration (files are read by :func:`lfcam.io.load_capture`)."""

from __future__ import annotations

import cv2
import numpy as np

from lfcam.calibrate.parallel import run_bands
from lfcam.errors import CalibrationError
from lfcam.robust import mad_sigma


def bayer_to_grey(image: np.ndarray, pattern: str) -> np.ndarray:
    """Equalise the four colour planes of a Bayer mosaic so a white image looks grey.

    Each of the four 2×2 sub-lattices is divided by its own median over bright pixels, so the
    colour of the illuminant and the filter transmissions cancel. No interpolation is done:
    every pixel keeps its position, so centroids are not shifted by half a pixel.
    """
    if pattern == "none":
        return image
    out = np.array(image, dtype=np.float32, copy=True)
    for dy in (0, 1):
        for dx in (0, 1):
            plane = out[dy::2, dx::2]
            hi = np.percentile(plane, 90.0)
            level = float(np.median(plane[plane >= 0.5 * hi])) if hi > 0 else 0.0
            if level <= 0.0:
                raise CalibrationError(f"Bayer plane ({dy}, {dx}) is dark: not a white image")
            plane /= level
    return out


def remove_hot_pixels(image: np.ndarray) -> tuple[np.ndarray, int]:
    """Replace isolated hot pixels by the median of their 3×3 neighbourhood.

    A pixel is hot when it exceeds the brightest of its eight neighbours by more than half
    that neighbour value plus six robust noise sigmas. Optical blur never makes a real pixel
    stand that far above all of its neighbours.

    Returns
    -------
    cleaned : ndarray (float32)
    n_hot : int
    """
    img = np.ascontiguousarray(image, dtype=np.float32)
    kernel = np.ones((3, 3), np.uint8)
    kernel[1, 1] = 0
    h, w = img.shape
    crop = img[h // 2 - min(h, 512) // 2:, w // 2 - min(w, 512) // 2:][:512, :512]
    step = (crop - cv2.medianBlur(np.ascontiguousarray(crop), 3)).ravel()
    sigma = mad_sigma(step)

    def band(r0: int, r1: int) -> tuple[np.ndarray, np.ndarray]:
        # rows r0 − 1 … r1 (the 3×3 neighbourhood), reflected only at the image border
        a, b = max(0, r0 - 1), min(h, r1 + 1)
        nb_max = cv2.dilate(img[a:b], kernel, borderType=cv2.BORDER_REFLECT)[r0 - a:r1 - a]
        lim = np.abs(nb_max)
        lim *= 0.5
        lim += nb_max
        lim += 6.0 * sigma
        ys, xs = np.nonzero(img[r0:r1] > lim)
        return ys + r0, xs

    found = run_bands(band, h)
    ys = np.concatenate([f[0] for f in found])
    xs = np.concatenate([f[1] for f in found])
    n_hot = int(ys.size)
    if n_hot:
        padded = np.pad(img, 1, mode="reflect")
        ring = [padded[ys + 1 + dy, xs + 1 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)
                if dy or dx]
        img = img.copy() if img is image else img
        img[ys, xs] = np.median(np.stack(ring), axis=0)
    return img, n_hot


def prepare_white(
    white: np.ndarray, dark: np.ndarray | None = None, bayer: str = "none"
) -> tuple[np.ndarray, int]:
    """Dark-subtract, equalise Bayer planes and remove hot pixels.

    Parameters
    ----------
    white : (H, W) array
    dark : (H, W) array, optional
    bayer : str
        ``"none"`` or a colour filter pattern.

    Returns
    -------
    image : (H, W) float32
    n_hot : int
        Number of hot pixels replaced.

    Raises
    ------
    CalibrationError
        Shape mismatch with the dark frame, non-finite samples, or an empty image.
    """
    img = np.asarray(white, dtype=np.float32)
    if img.ndim != 2 or min(img.shape) < 8:
        raise CalibrationError(f"white image must be 2-D and at least 8×8, got {img.shape}")
    if not np.isfinite(img).all():
        raise CalibrationError("white image contains NaN or infinite samples")
    if dark is not None:
        d = np.asarray(dark, dtype=np.float32)
        if d.shape != img.shape:
            raise CalibrationError(f"dark frame {d.shape} does not match white image {img.shape}")
        img = img - d
    img = bayer_to_grey(img, bayer)
    if float(np.max(img)) <= 0.0:
        raise CalibrationError("white image has no light after dark subtraction")
    return remove_hot_pixels(img)
