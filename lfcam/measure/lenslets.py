"""Per-lenslet statistics of a raw capture: energy and micro-image centroid of every lenslet.

Every pixel belongs to the micro-image whose (calibrated) centre is nearest, if it lies within
``radius_px`` of it; pixels further out (seams between micro-images, where neighbours overlap
in fast systems, docs/calibration.md) are ignored. The assignment is computed once per calibration
and reused for every capture: each centre stamps the pixels of its disc (a fixed stencil of
integer offsets), band by band of sensor rows, and where two discs overlap the nearer centre
keeps the pixel. The work is proportional to the lit discs (~π r² a lenslet), not to a
nearest-neighbour search per pixel: a 41 Mpx sensor takes ~1 s of CPU instead of ~13 s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lfcam.errors import CalibrationError

BAND_PIXELS = 2_000_000  # pixels of one band of sensor rows (bounds the stencil's memory)


COMPILED_FRAME_PX = 8_000_000  # frames this large are mapped and summed per lenslet by
#                               lfcam.measure.kernels (its import costs ~0.5 s; numpy's chains
#                               take ~40 ms/Mpx)


@dataclass(frozen=True)
class LensletMap:
    """Pixel → lenslet assignment for one sensor size and one set of micro-image centres."""

    centres_px: np.ndarray  # (N, 2) x, y
    labels: np.ndarray  # (H, W) int32, −1 = unassigned
    radius_px: float

    @property
    def count(self) -> int:
        """Number of lenslets."""
        return int(self.centres_px.shape[0])


def start_frame_kernels(shape: tuple[int, int]):
    """For a frame of ``shape`` that will take the compiled paths (``COMPILED_FRAME_PX``),
    load those kernels now in a background thread: numba's first load in a process costs
    ~0.45 s, which then overlaps the caller's reading of the capture (its decoding releases
    the GIL) instead of delaying the lenslet map (Illum size: the load-to-geometry span
    2.66-3.38 → 2.47-3.10 s). A smaller frame loads nothing. Returns the thread, or None."""
    if int(shape[0]) * int(shape[1]) < COMPILED_FRAME_PX:
        return None
    import threading

    def load() -> None:
        from lfcam.measure.kernels import warm_up_frame

        warm_up_frame()

    thread = threading.Thread(target=load, daemon=True)
    thread.start()
    return thread


def build_lenslet_map(
    centres_px: np.ndarray, shape: tuple[int, int], radius_px: float
) -> LensletMap:
    """Assign every pixel of an ``(H, W)`` sensor to its nearest micro-image centre.

    Raises
    ------
    CalibrationError
        If there are no centres or the radius is not positive.
    """
    centres = np.asarray(centres_px, dtype=np.float64).reshape(-1, 2)
    if centres.shape[0] == 0:
        raise CalibrationError("no micro-image centres in the calibration")
    if not radius_px > 0:
        raise CalibrationError(f"micro-image radius must be positive, got {radius_px}")
    h, w = shape
    labels = np.full((h, w), -1, dtype=np.int32)
    reach = int(np.ceil(radius_px)) + 1
    oy, ox = np.mgrid[-reach : reach + 1, -reach : reach + 1]
    # offsets that can lie within the radius of a centre up to half a pixel from their origin
    near = np.hypot(ox, oy) <= radius_px + 0.75
    ox, oy = ox[near], oy[near]
    keep_c = np.isfinite(centres).all(axis=1)
    ids = np.flatnonzero(keep_c)
    ids = ids[np.argsort(centres[ids, 1], kind="stable")]
    cy_sorted = centres[ids, 1]
    r2 = float(radius_px) ** 2
    band = max(32, BAND_PIXELS // max(w, 1))
    if h * w >= COMPILED_FRAME_PX:  # the same stamping, compiled (Illum size: 1.6 → 0.8 s)
        from lfcam.measure.kernels import stamp_labels

        stamp_labels(labels, centres, ids.astype(np.int64), ox.astype(np.int64).ravel(),
                     oy.astype(np.int64).ravel(), r2, int(band))
        return LensletMap(centres, labels, float(radius_px))
    for r0 in range(0, h, band):
        r1 = min(h, r0 + band)
        lo = np.searchsorted(cy_sorted, r0 - reach, side="left")
        hi = np.searchsorted(cy_sorted, r1 - 1 + reach, side="right")
        if hi <= lo:
            continue
        best = np.full((r1 - r0) * w, np.inf)
        parts = []
        step = max(1, BAND_PIXELS // ox.size)
        for c0 in range(lo, hi, step):  # bounded memory for wide stencils
            k = ids[c0 : min(hi, c0 + step)]
            cx, cy = centres[k, 0], centres[k, 1]
            bx, by = np.rint(cx), np.rint(cy)
            d2 = (ox[None, :] + (bx - cx)[:, None]) ** 2 + (oy[None, :] + (by - cy)[:, None]) ** 2
            px = bx.astype(np.int64)[:, None] + ox[None, :]
            py = by.astype(np.int64)[:, None] + oy[None, :]
            ok = (d2 <= r2) & (py >= r0) & (py < r1) & (px >= 0) & (px < w)
            flat = (py[ok] - r0) * w + px[ok]
            d2 = d2[ok]
            np.minimum.at(best, flat, d2)
            parts.append((flat, d2, np.broadcast_to(k[:, None].astype(np.int32), ok.shape)[ok]))
        # overlapping discs: the nearest centre keeps the pixel
        out = labels[r0:r1].reshape(-1)
        for flat, d2, lab in parts:
            win = d2 <= best[flat]
            out[flat[win]] = lab[win]
    return LensletMap(centres, labels, float(radius_px))


@dataclass(frozen=True)
class LensletStats:
    """Energy and intensity centroid of each micro-image of one capture."""

    energy: np.ndarray  # (N,) summed signal
    centroid_px: np.ndarray  # (N, 2) x, y; NaN where the energy is not positive
    pixels: np.ndarray  # (N,) number of pixels assigned


def lenslet_stats(image: np.ndarray, lmap: LensletMap) -> LensletStats:
    """Sum and first moments of ``image`` over each lenslet's pixels (vectorised bincount).

    Parameters
    ----------
    image : (H, W) array
        Linear signal, black level already removed (negative values allowed: noise).
    lmap : LensletMap

    Returns
    -------
    LensletStats
        Energy and intensity centroid of every lenslet.

    Raises
    ------
    CalibrationError
        The image and the lenslet map differ in size.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.shape != lmap.labels.shape:
        raise CalibrationError(
            f"capture is {img.shape[1]}×{img.shape[0]} px but the calibration is for "
            f"{lmap.labels.shape[1]}×{lmap.labels.shape[0]} px"
        )
    if img.size >= COMPILED_FRAME_PX:  # one compiled pass (the same sums in the same order)
        from lfcam.measure.kernels import lenslet_sums

        pixels, energy, mx, my = lenslet_sums(
            np.ascontiguousarray(lmap.labels, dtype=np.int32), np.ascontiguousarray(img),
            int(lmap.count))
    else:
        # bin 0 collects the unassigned pixels (label −1); no masks or index arrays of the frame
        lab = lmap.labels.ravel().astype(np.intp) + 1
        n = lmap.count + 1
        h, w = img.shape
        val = img.ravel()
        energy = np.bincount(lab, weights=val, minlength=n)[1:]
        mx = np.bincount(lab, weights=(img * np.arange(w, dtype=np.float64)).ravel(),
                         minlength=n)[1:]
        my = np.bincount(lab, weights=(img * np.arange(h, dtype=np.float64)[:, None]).ravel(),
                         minlength=n)[1:]
        pixels = np.bincount(lab, minlength=n)[1:]
    with np.errstate(invalid="ignore", divide="ignore"):
        centroid = np.column_stack([mx / energy, my / energy])
    centroid[~(energy > 0)] = np.nan
    return LensletStats(energy, centroid, pixels)
