"""Reading and preparing white images for calibration.

Files are read by :func:`lfcam.io.load_capture` (``lfcam.calibrate.calibrate_white_file``);
:func:`read_raster` is a plain PNG/TIFF reader for in-memory work (tests, benchmarks, the
microscope frames) that keeps the values exactly as stored.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from lfcam.errors import CalibrationError, InputFileError
from lfcam.io.limits import check_raster

MAX_PIXELS = 200_000_000  # refuse absurd rasters before allocating float copies


def read_raster(path: str | Path) -> np.ndarray:
    """Read a grey or mosaicked PNG/TIFF raster as a 2-D float32 array (values unchanged).

    Raises
    ------
    InputFileError
        Missing file, unsupported or unreadable content, or not a single-channel image.
    """
    p = Path(path)
    if not p.is_file():
        raise InputFileError(f"file not found: {p}")
    suffix = p.suffix.lower()
    if suffix in (".tif", ".tiff", ".png"):
        check_raster(p, "png" if suffix == ".png" else "tiff")  # header-only size limits
    try:
        if suffix in (".tif", ".tiff"):
            import tifffile

            with tifffile.TiffFile(p) as tf:
                page = tf.pages[0]
                n = int(np.prod(page.shape))
                if n > MAX_PIXELS:
                    raise InputFileError(f"{p}: {page.shape} is too large ({n} samples)")
                data = page.asarray()
        elif suffix == ".png":
            data = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            if data is None:
                raise InputFileError(f"{p}: not a readable PNG")
        else:
            raise InputFileError(
                f"{p}: unsupported file type {suffix!r} for calibration (PNG or TIFF raster)"
            )
    except InputFileError:
        raise
    except Exception as exc:  # tifffile raises many types on damaged files
        raise InputFileError(f"{p}: cannot read raster ({type(exc).__name__}: {exc})") from None
    data = np.asarray(data)
    if data.ndim == 3 and data.shape[2] in (3, 4):
        if not (np.array_equal(data[..., 0], data[..., 1]) and
                np.array_equal(data[..., 1], data[..., 2])):
            raise InputFileError(
                f"{p}: colour raster {data.shape}; calibration needs a single-channel (grey or "
                "Bayer-mosaicked) white image"
            )
        data = data[..., 0]
    if data.ndim != 2:
        raise InputFileError(f"{p}: expected a 2-D raster, got shape {data.shape}")
    if data.dtype.kind not in "uif":
        raise InputFileError(f"{p}: unsupported sample type {data.dtype}")
    return data.astype(np.float32)


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
    nb_max = cv2.dilate(img, kernel, borderType=cv2.BORDER_REFLECT)
    h, w = img.shape
    crop = img[h // 2 - min(h, 512) // 2:, w // 2 - min(w, 512) // 2:][:512, :512]
    step = (crop - cv2.medianBlur(np.ascontiguousarray(crop), 3)).ravel()
    sigma = 1.4826 * float(np.median(np.abs(step - np.median(step))))
    hot = img > nb_max + 0.5 * np.abs(nb_max) + 6.0 * sigma
    n_hot = int(hot.sum())
    if n_hot:
        ys, xs = np.nonzero(hot)
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
