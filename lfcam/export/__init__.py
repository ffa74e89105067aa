"""Outputs of a distance run (docs/distance.md): ``regions.csv``, ``distance.tiff``,
``distance.png``, and the one CSV writer of lfcam (:func:`write_csv`).

Every file is written atomically (temporary file in the target folder, then a rename), so a
reader or an interrupted batch never sees half a file.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import tifffile

from lfcam.atomic import atomic_write, atomic_write_bytes, atomic_write_text

REGION_COLUMNS = (
    "region_id", "x_px", "y_px", "kind", "model", "distance_mm", "offset_mm", "diameter_mm",
    "uncertainty_mm", "status",
)


def format_cell(value: object) -> str:
    """CSV cell text: empty for NaN, repr-precision floats, everything else as ``str``."""
    if isinstance(value, (float, np.floating)):
        return "" if math.isnan(value) else repr(float(value))
    return str(value)


def write_csv(path: str | Path, header: Sequence[str], rows: Iterable[Sequence[object]]) -> None:
    """Write a CSV atomically (``csv`` module quoting, ``\\n`` line ends)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(header)
    writer.writerows([format_cell(v) for v in row] for row in rows)
    atomic_write_text(path, buf.getvalue())


@dataclass(frozen=True)
class RegionResult:
    """One detected region and its distance estimate (a row of ``regions.csv``)."""

    region_id: int
    x_px: float
    y_px: float
    kind: str
    model: str
    distance_mm: float
    offset_mm: float
    diameter_mm: float
    uncertainty_mm: float
    status: str
    bbox_px: tuple[int, int, int, int] = (0, 0, 0, 0)  # x0, y0, x1, y1 (exclusive), not in CSV

    def row(self) -> tuple:
        """Values in :data:`REGION_COLUMNS` order."""
        return tuple(getattr(self, c) for c in REGION_COLUMNS)


def write_regions_csv(path: str | Path, regions: Sequence[RegionResult]) -> None:
    """Write ``regions.csv`` (one row a region; empty cells for NaN)."""
    write_csv(path, REGION_COLUMNS, (r.row() for r in regions))


def write_distance_tiff(path: str | Path, distance_mm: np.ndarray) -> None:
    """Write the distance map as a float32 TIFF in millimetres (NaN where no estimate)."""
    arr = np.asarray(distance_mm, dtype=np.float32)
    atomic_write(path, lambda tmp: tifffile.imwrite(
        tmp, arr, photometric="minisblack",
        metadata={"unit": "mm", "description": "lfcam distance map"}))


def render_preview(
    distance_mm: np.ndarray,
    regions: Sequence[RegionResult] = (),
    max_side_px: int = 1024,
    colormap: int = cv2.COLORMAP_TURBO,
) -> np.ndarray:
    """Colour preview (BGR uint8): distance colour map, region outlines and a scale bar.

    NaN pixels are dark grey. The colour range spans the finite distances (near = blue,
    far = red); the bar on the right is labelled in millimetres.
    """
    d = np.asarray(distance_mm, dtype=np.float64)
    h, w = d.shape
    scale = min(1.0, max_side_px / max(h, w))
    finite = np.isfinite(d)
    lo, hi = (float(np.nanmin(d)), float(np.nanmax(d))) if finite.any() else (0.0, 1.0)
    mid = 0.5 * (lo + hi)
    if hi - lo < 0.1 * abs(mid):  # one distance (or nearly): show it mid-scale, ±5 %
        lo, hi = mid - 0.05 * abs(mid) - 0.5, mid + 0.05 * abs(mid) + 0.5
    norm = np.zeros_like(d)
    norm[finite] = (d[finite] - lo) / (hi - lo)
    img = cv2.applyColorMap((norm * 255).astype(np.uint8), colormap)
    img[~finite] = (40, 40, 40)
    if scale < 1.0:
        img = cv2.resize(img, (max(1, int(w * scale)), max(1, int(h * scale))),
                         interpolation=cv2.INTER_AREA)
    for r in regions:
        x0, y0, x1, y1 = (int(round(v * scale)) for v in r.bbox_px)
        colour = (255, 255, 255) if r.status == "ok" else (0, 0, 255)
        cv2.rectangle(img, (x0, y0), (max(x0, x1 - 1), max(y0, y1 - 1)), colour, 1)
        cv2.putText(img, str(r.region_id), (x0, max(10, y0 - 3)), cv2.FONT_HERSHEY_SIMPLEX,
                    0.35, colour, 1, cv2.LINE_AA)
    ih = img.shape[0]
    bar_w, margin, label_w = 16, 8, 90
    canvas = np.full((ih, img.shape[1] + bar_w + label_w + 2 * margin, 3), 255, np.uint8)
    canvas[:, : img.shape[1]] = img
    ramp = np.linspace(255, 0, ih).astype(np.uint8)[:, None].repeat(bar_w, axis=1)
    x_bar = img.shape[1] + margin
    canvas[:, x_bar : x_bar + bar_w] = cv2.applyColorMap(ramp, colormap)
    for frac in (0.0, 0.25, 0.5, 0.75, 1.0):
        y = int(round((1 - frac) * (ih - 1)))
        value = lo + frac * (hi - lo)
        cv2.line(canvas, (x_bar + bar_w, y), (x_bar + bar_w + 4, y), (0, 0, 0), 1)
        cv2.putText(canvas, f"{value:.4g} mm", (x_bar + bar_w + 6, min(ih - 3, max(10, y + 4))),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    return canvas


def write_distance_png(path: str | Path, distance_mm: np.ndarray,
                       regions: Sequence[RegionResult] = ()) -> None:
    """Write the colour preview (see :func:`render_preview`) as PNG."""
    ok, buf = cv2.imencode(".png", render_preview(distance_mm, regions))
    if not ok:  # pragma: no cover - cv2 failure
        raise OSError("PNG encoding failed")
    atomic_write_bytes(path, buf.tobytes())


def paint_region(distance_map: np.ndarray, region, lmap, pitch_px: float,
                 distance_mm: float) -> None:
    """Paint ``distance_mm`` in place over a region's footprint: the pixels of its lenslets,
    morphologically closed over one pitch so the map has no holes between micro-images.

    Parameters
    ----------
    distance_map : (H, W) float32 array
    region : lfcam.measure.Region
    lmap : lfcam.measure.LensletMap
    pitch_px : float
    distance_mm : float
    """
    x0, y0, x1, y1 = region.box_px
    m = np.isin(lmap.labels[y0:y1, x0:x1], region.lenslets).astype(np.uint8)
    k = max(3, int(pitch_px) | 1)
    m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, np.ones((k, k), np.uint8)).astype(bool)
    distance_map[y0:y1, x0:x1][m] = distance_mm
