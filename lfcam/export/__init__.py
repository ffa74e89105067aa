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
    """CSV cell text: empty for NaN, repr-precision floats, everything else as ``str``.

    Parameters
    ----------
    value : object

    Returns
    -------
    str
    """
    if isinstance(value, (float, np.floating)):
        return "" if math.isnan(value) else repr(float(value))
    return str(value)


def write_csv(path: str | Path, header: Sequence[str], rows: Iterable[Sequence[object]]) -> None:
    """Write a CSV atomically (``csv`` module quoting, ``\\n`` line ends).

    Parameters
    ----------
    path : str or Path
    header : sequence of str
    rows : iterable of sequences
        Cells formatted by :func:`format_cell`.
    """
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
    """Write ``regions.csv`` (one row a region; empty cells for NaN).

    Parameters
    ----------
    path : str or Path
    regions : sequence of RegionResult
    """
    write_csv(path, REGION_COLUMNS, (r.row() for r in regions))


def write_distance_tiff(path: str | Path, distance_mm: np.ndarray) -> None:
    """Write the distance map as a float32 TIFF in millimetres (NaN where no estimate).

    Parameters
    ----------
    path : str or Path
    distance_mm : (H, W) array
    """
    arr = np.asarray(distance_mm, dtype=np.float32)
    atomic_write(path, lambda tmp: tifffile.imwrite(
        tmp, arr, photometric="minisblack",
        metadata={"unit": "mm", "description": "lfcam distance map"}))


def nice_ticks(lo: float, hi: float, target: int = 5) -> list[float]:
    """Round tick values (1, 2, 2.5 or 5 × 10ⁿ steps) inside [lo, hi].

    Parameters
    ----------
    lo, hi : float
    target : int
        About how many ticks.

    Returns
    -------
    list of float
    """
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo]
    raw = (hi - lo) / max(1, target)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    first = math.ceil(lo / step) * step
    ticks = []
    v = first
    while v <= hi + 1e-9 * step:
        ticks.append(round(v, 10))
        v += step
    return ticks


def render_preview(
    distance_mm: np.ndarray,
    regions: Sequence[RegionResult] = (),
    max_side_px: int = 1024,
    colormap: int = cv2.COLORMAP_TURBO,
    title: str = "",
) -> np.ndarray:
    """Colour preview (BGR uint8): title, distance colour map with pixel axes, region outlines
    and a colour bar with round ticks in millimetres.

    NaN pixels are dark grey. The colour range spans the finite distances (near = blue,
    far = red). Each ``ok`` region is outlined in white with a line width that grows with its
    relative uncertainty (1 px below 0.5 %, 2 px below 2 %, 3 px above) and labelled
    ``#id d ± σ mm``; other regions are outlined in red and labelled with their status.

    Parameters
    ----------
    distance_mm : (H, W) array
    regions : sequence of RegionResult
    max_side_px : int
        The map is shrunk to fit.
    colormap : int
        OpenCV colour map.
    title : str

    Returns
    -------
    (h, w, 3) uint8 array
    """
    d = np.asarray(distance_mm)
    if d.dtype not in (np.float32, np.float64):
        d = d.astype(np.float64)
    h, w = d.shape
    scale = min(1.0, max_side_px / max(h, w))
    finite = np.isfinite(d)
    lo, hi = (float(np.nanmin(d)), float(np.nanmax(d))) if finite.any() else (0.0, 1.0)
    mid = 0.5 * (lo + hi)
    if hi - lo < 0.1 * abs(mid):  # one distance (or nearly): show it mid-scale, ±5 %
        lo, hi = mid - 0.05 * abs(mid) - 0.5, mid + 0.05 * abs(mid) + 0.5
    # colour index in the map's own precision, in place (an Illum-size map is 41 Mpx: float64
    # temporaries of it cost seconds)
    with np.errstate(invalid="ignore"):
        idx = np.subtract(d, d.dtype.type(lo))
        idx *= d.dtype.type(255.0 / (hi - lo))
        np.clip(idx, 0, 255, out=idx)
    idx[~finite] = 0
    img = cv2.applyColorMap(idx.astype(np.uint8), colormap)
    img = np.where(finite[..., None], img, np.uint8(40))  # NaN: dark grey (a 2-D mask is slow)
    if scale < 1.0:
        img = cv2.resize(img, (max(1, int(w * scale)), max(1, int(h * scale))),
                         interpolation=cv2.INTER_AREA)
    font, fs = cv2.FONT_HERSHEY_SIMPLEX, 0.35
    for r in regions:
        x0, y0, x1, y1 = (int(round(v * scale)) for v in r.bbox_px)
        if r.status == "ok":
            rel = r.uncertainty_mm / r.distance_mm if r.distance_mm else float("inf")
            thick = 1 if rel < 0.005 else 2 if rel < 0.02 else 3
            colour, label = (255, 255, 255), f"#{r.region_id} {r.distance_mm:.0f}"
            if math.isfinite(r.uncertainty_mm):
                label += f" +/- {r.uncertainty_mm:.2g} mm"
        else:
            thick, colour, label = 1, (0, 0, 255), f"#{r.region_id} {r.status}"
        cv2.rectangle(img, (x0, y0), (max(x0, x1 - 1), max(y0, y1 - 1)), colour, thick)
        cv2.putText(img, label, (x0, max(10, y0 - 3)), font, fs, colour, 1, cv2.LINE_AA)
    ih, iw = img.shape[:2]
    top, left, bottom = 24, 44, 22
    bar_w, margin, label_w = 16, 8, 70
    canvas = np.full((ih + top + bottom, left + iw + bar_w + label_w + 2 * margin, 3), 255,
                     np.uint8)
    canvas[top : top + ih, left : left + iw] = img
    cv2.putText(canvas, title or "lfcam distance map", (left, 16), font, 0.45, (0, 0, 0), 1,
                cv2.LINE_AA)
    # pixel axes: ticks in raw sensor pixels
    for v in nice_ticks(0, w - 1, 4):
        x = left + int(round(v * scale))
        cv2.line(canvas, (x, top + ih), (x, top + ih + 4), (0, 0, 0), 1)
        cv2.putText(canvas, f"{v:g}", (max(0, x - 10), top + ih + 15), font, fs, (0, 0, 0), 1,
                    cv2.LINE_AA)
    for v in nice_ticks(0, h - 1, 4):
        y = top + int(round(v * scale))
        cv2.line(canvas, (left - 4, y), (left, y), (0, 0, 0), 1)
        cv2.putText(canvas, f"{v:g}", (2, min(top + ih, y + 4)), font, fs, (0, 0, 0), 1,
                    cv2.LINE_AA)
    cv2.putText(canvas, "px", (left + iw - 14, top + ih + bottom - 2), font, fs, (0, 0, 0), 1,
                cv2.LINE_AA)
    ramp = np.linspace(255, 0, ih).astype(np.uint8)[:, None].repeat(bar_w, axis=1)
    x_bar = left + iw + margin
    canvas[top : top + ih, x_bar : x_bar + bar_w] = cv2.applyColorMap(ramp, colormap)
    for value in nice_ticks(lo, hi, 5):
        frac = (value - lo) / (hi - lo)
        y = top + int(round((1 - frac) * (ih - 1)))
        cv2.line(canvas, (x_bar + bar_w, y), (x_bar + bar_w + 4, y), (0, 0, 0), 1)
        cv2.putText(canvas, f"{value:g}", (x_bar + bar_w + 6, y + 4), font, fs, (0, 0, 0), 1,
                    cv2.LINE_AA)
    cv2.putText(canvas, "mm", (x_bar, top + ih + 15), font, fs, (0, 0, 0), 1, cv2.LINE_AA)
    return canvas


def write_distance_png(path: str | Path, distance_mm: np.ndarray,
                       regions: Sequence[RegionResult] = (), title: str = "") -> None:
    """Write the colour preview (see :func:`render_preview`) as PNG.

    Parameters
    ----------
    path : str or Path
    distance_mm : (H, W) array
    regions : sequence of RegionResult
    title : str
    """
    ok, buf = cv2.imencode(".png", render_preview(distance_mm, regions, title=title))
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
