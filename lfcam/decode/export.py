"""Atomic writers for light fields, sub-aperture views and refocused images."""

from __future__ import annotations

import io
import json
from pathlib import Path

import cv2
import numpy as np
import tifffile

from lfcam.atomic import (
    atomic_write_bytes,  # noqa: F401 - part of this module's API
    ordinary_permissions,
)
from lfcam.decode.lightfield import LightField
from lfcam.errors import InputFileError

IMAGE_SUFFIXES = (".png", ".tif", ".tiff")


def npy_bytes(array: np.ndarray) -> bytes:
    """``.npy`` file content of ``array``."""
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


def tiff_bytes(array: np.ndarray) -> bytes:
    """TIFF content (one page per leading index for 3-D input)."""
    buf = io.BytesIO()
    tifffile.imwrite(buf, array)
    return buf.getvalue()


def png16_bytes(image: np.ndarray, scale: float) -> bytes:
    """16-bit grey PNG of ``image·scale`` (clipped to [0, 65535])."""
    img = np.clip(np.nan_to_num(image) * scale, 0, 65535).round().astype(np.uint16)
    ok, enc = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover - OpenCV always encodes uint16 grey
        raise InputFileError("PNG encoding failed")
    return enc.tobytes()


def png_scale(image: np.ndarray) -> float:
    """Scale mapping the 99.9th percentile of a non-negative image to 65535."""
    top = float(np.percentile(image, 99.9)) if image.size else 0.0
    return 65535.0 / top if top > 0 else 1.0


def write_image(path: str | Path, image: np.ndarray) -> None:
    """Write one image as float32 TIFF or as 16-bit PNG (99.9th percentile → 65535)."""
    suffix = Path(path).suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise InputFileError(f"output {path}: use a .png, .tif or .tiff name")
    if suffix == ".png":
        atomic_write_bytes(path, png16_bytes(image, png_scale(image)))
    else:
        atomic_write_bytes(path, tiff_bytes(image.astype(np.float32)))


def write_lightfield(folder: str | Path, lf: LightField, png_views: bool = True) -> list[Path]:
    """Write ``lightfield.npy``, ``weight.npy``, ``views.tiff``, ``lightfield.json`` (and PNGs).

    ``views.tiff`` is a float32 stack of ``nv·nu`` pages, page ``v·nu + u`` = view (v, u).
    PNG views share one scale so their brightness compares.

    Everything is written into a temporary folder next to ``folder`` first. A new ``folder``
    is that temporary folder renamed when complete; into an existing one the files are moved
    one by one (each an atomic replace), ``lightfield.json`` last. An interrupted decode
    therefore leaves no half folder under the output name (only the temporary one, removed
    on the way out).
    """
    import os
    import shutil
    import tempfile

    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputFileError(f"output {folder} exists and is not a folder")
    parent = folder.parent if str(folder.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.partial-", dir=parent))
    try:
        written = _write_lightfield_files(tmp, lf, png_views)
        rel = [w.relative_to(tmp) for w in written]
        if not folder.exists():
            ordinary_permissions(tmp)  # (mkdtemp's folder is 0o700)
            os.rename(tmp, folder)
        else:
            order = sorted(rel, key=lambda r: r.name == "lightfield.json")
            for r in order:
                (folder / r).parent.mkdir(parents=True, exist_ok=True)
                os.replace(tmp / r, folder / r)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return [folder / r for r in rel]


def _write_lightfield_files(folder: Path, lf: LightField, png_views: bool) -> list[Path]:
    """The files of :func:`write_lightfield`, written into ``folder``."""
    nv, nu, t_count, s_count = lf.data.shape
    written = []
    for name, payload in (
        ("lightfield.npy", npy_bytes(lf.data)),
        ("weight.npy", npy_bytes(lf.weight)),
        ("views.tiff", tiff_bytes(lf.data.reshape(nv * nu, t_count, s_count))),
    ):
        atomic_write_bytes(folder / name, payload)
        written.append(folder / name)
    meta = {
        "indexing": "L[v, u, t, s]: v,u angular (rows, cols; 1 sensor pixel per step), "
                    "t,s spatial (lens rows, cols)",
        "shape": [nv, nu, t_count, s_count],
        "angular_centre": list(lf.angular_centre),
        "spacing_px": list(lf.spacing_px),
        "first_t": lf.first_t,
        "first_s": lf.first_s,
        "grid": lf.grid.grid,
        "pitch_px": lf.grid.pitch_px,
        "rotation_rad": lf.grid.rotation_rad,
        "offset_px": list(lf.grid.offset_px),
    }
    atomic_write_bytes(folder / "lightfield.json", (json.dumps(meta, indent=1) + "\n").encode())
    written.append(folder / "lightfield.json")
    if png_views:
        scale = png_scale(lf.data)
        for v in range(nv):
            for u in range(nu):
                p = folder / "views" / f"view_v{v:02d}_u{u:02d}.png"
                atomic_write_bytes(p, png16_bytes(lf.data[v, u], scale))
                written.append(p)
    return written
