"""``load_capture``: one entry point for every capture lfcam reads, dispatched by content.

Dispatch order (magic bytes first, the extension only where a format has no magic):

===========================  ===================================================
first bytes                  reader
===========================  ===================================================
``89 'LFP' 0D 0A 1A 0A``     Lytro LFP/LFR container (:mod:`lfcam.io.lfp`)
``89 'PNG' 0D 0A 1A 0A``     PNG raster (OpenCV, 8/16 bit)
TIFF (``II*\\0``/``MM\\0*``)  camera raw through rawpy when it is a DNG (tag 50706) or a
                             TIFF-based raw (``.cr2 .nef .arw .dng ...``), else a TIFF
                             raster (tifffile, 8/16/32 bit)
other raw magics             rawpy (``FUJIFILMCCD-RAW``, ``IIRO``, ``IIU\\0``, CR3 ``ftypcrx``)
none (``.raw``/``.RAW``)     bare Lytro packed raw + ``.json``/``.txt`` sidecar
===========================  ===================================================
"""

from __future__ import annotations

import os
import sys
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lfcam.camera import CameraProfile
from lfcam.errors import (
    InputFileError,
    MetadataError,
    RawDataError,
    SaturatedCaptureError,
    UnsupportedFormatError,
)
from lfcam.io import lytro_meta as lm
from lfcam.io.lfp import LFP_MAGIC, merged_metadata, read_lfp
from lfcam.io.limits import check_raster
from lfcam.io.packing import check_dimensions, packed_size, unpack

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
TIFF_MAGICS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
RAW_EXTENSIONS = {
    ".dng", ".cr2", ".cr3", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".orf", ".rw2", ".raf",
    ".pef", ".srw", ".3fr", ".iiq", ".erf", ".kdc", ".dcr", ".mrw", ".x3f", ".rwl",
}
SIDECAR_SUFFIXES = (".json", ".JSON", ".txt", ".TXT")


@dataclass(frozen=True)
class Capture:
    """A loaded raw capture.

    Attributes
    ----------
    raw : numpy.ndarray
        2-D sensor mosaic (uint16 for packed/camera raws and integer rasters, float32 for
        float TIFFs), read-only, pixel (0, 0) top-left.
    bayer : str
        ``"none"`` or ``"RGGB"``/``"BGGR"``/``"GRBG"``/``"GBRG"`` (colour of pixels (0,0),
        (0,1), (1,0), (1,1)).
    black_level, white_level : float
        Raw value of no light and of saturation, in the units of ``raw``.
    metadata : dict
        Everything the file said (Lytro: ``master``, ``frame``, ``privateMetadata``).
    source_kind : str
        ``"lytro-lfp"``, ``"lytro-raw"``, ``"camera-raw"``, ``"png"`` or ``"tiff"``.
    path : str
        Where it came from.
    profile : CameraProfile or None
        The profile passed to :func:`load_capture`, if any.
    white_balance : tuple of float or None
        Gains for the four CFA positions in ``bayer`` order, when the file states them.
    """

    raw: np.ndarray
    bayer: str
    black_level: float
    white_level: float
    metadata: dict = field(repr=False)
    source_kind: str
    path: str
    profile: CameraProfile | None = None
    white_balance: tuple[float, float, float, float] | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """(height_px, width_px)."""
        return (int(self.raw.shape[0]), int(self.raw.shape[1]))

    def grey(self) -> np.ndarray:
        """Linear grey float32 image: demosaicked, black level 0, white level 1
        (:func:`lfcam.io.grey.to_grey`)."""
        from lfcam.io.grey import to_grey

        return to_grey(self.raw, self.bayer, self.black_level, self.white_level)


def _freeze(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


def _wb_tuple(fmt: lm.LytroRawFormat) -> tuple[float, float, float, float] | None:
    if fmt.white_balance is None or fmt.bayer == "none":
        return None
    names = {"R": "r", "B": "b"}
    pat = fmt.bayer
    out = []
    for i, ch in enumerate(pat):
        out.append(fmt.white_balance[names.get(ch, "gr" if i in (0, 1) else "gb")])
    return tuple(out)  # type: ignore[return-value]


def _sniff(path: Path) -> bytes:
    try:
        with path.open("rb") as f:
            return f.read(32)
    except IsADirectoryError:
        raise InputFileError(f"{path}: is a directory, not a capture file") from None
    except FileNotFoundError:
        raise InputFileError(f"{path}: file not found") from None
    except PermissionError:
        raise InputFileError(f"{path}: permission denied") from None


def sniff_kind(path: str | Path) -> str:
    """Content kind of a file: ``lfp``, ``png``, ``tiff``, ``camera-raw``, ``lytro-raw``.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    str
        The kind, decided by magic bytes (bare raws: by extension and sidecar).

    Raises
    ------
    UnsupportedFormatError
        When neither the magic bytes nor (for bare raws) the extension identify it.
    """
    p = Path(path)
    head = _sniff(p)
    ext = p.suffix.lower()
    if head.startswith(LFP_MAGIC):
        return "lfp"
    if head.startswith(PNG_MAGIC):
        return "png"
    if head[:4] in TIFF_MAGICS:
        if ext in RAW_EXTENSIONS or head[8:10] == b"CR" or _is_dng(p):
            return "camera-raw"
        return "tiff"
    if head.startswith((b"FUJIFILMCCD-RAW", b"IIRO", b"IIU\x00")) or head[4:11] == b"ftypcrx":
        return "camera-raw"
    if ext == ".raw":
        return "lytro-raw"
    if ext in RAW_EXTENSIONS:
        return "camera-raw"
    if head[:1] in (b"{", b"[") and ext in (".json", ".txt"):
        raise UnsupportedFormatError(f"{p}: a metadata text file, not a capture (pass the .raw)")
    raise UnsupportedFormatError(
        f"{p}: unsupported capture format (first bytes {head[:8]!r}); lfcam reads Lytro "
        ".lfp/.lfr, bare .raw with a JSON sidecar, camera raws, PNG and TIFF"
    )


def _is_dng(path: Path) -> bool:
    try:
        import tifffile

        with tifffile.TiffFile(path) as tf:
            return 50706 in tf.pages[0].tags
    except Exception:  # noqa: BLE001 - a TIFF tifffile cannot parse is handled later
        return False


# ----------------------------------------------------------------------------- readers


def _from_lfp(p: Path, profile: CameraProfile | None, verify: str) -> Capture:
    c = read_lfp(p, verify=verify)
    img = c.raw_image()  # NoRawFrameError for processed pictures
    fr = c.light_field_frame
    fmt = lm.raw_format(fr.metadata, f"{p}: frame metadata")
    return Capture(
        raw=_freeze(img), bayer=fmt.bayer, black_level=fmt.black_level,
        white_level=fmt.white_level, metadata=merged_metadata(c), source_kind="lytro-lfp",
        path=str(p), profile=profile, white_balance=_wb_tuple(fmt),
    )


def find_sidecar(raw_path: str | Path) -> Path | None:
    """The ``.json``/``.txt`` (any case) metadata file next to a bare ``.raw``."""
    p = Path(raw_path)
    for suf in SIDECAR_SUFFIXES:
        q = p.with_suffix(suf)
        if q.is_file():
            return q
    return None


def read_json_file(path: Path, max_bytes: int = 64 * 1024 * 1024) -> Any:
    """Parse a JSON/TXT metadata file; :class:`MetadataError` on non-UTF-8 or bad JSON."""
    if path.stat().st_size > max_bytes:
        raise MetadataError(f"{path}: metadata file implausibly large")
    from lfcam.io.lfp import _parse_json

    return _parse_json(path.read_bytes(), str(path))


def read_sidecar_metadata(raw_path: str | Path) -> tuple[dict, dict, Path]:
    """Frame and private metadata of a bare Lytro ``.raw`` from its sidecar.

    Returns
    -------
    frame, private : dict
    sidecar : Path

    Raises
    ------
    MetadataError
        No sidecar next to the raw, or one that is not valid metadata.
    """
    p = Path(raw_path)
    side = find_sidecar(p)
    if side is None:
        raise MetadataError(
            f"{p}: bare raw without metadata: expected {p.with_suffix('.json').name} or "
            f"{p.with_suffix('.txt').name} next to it"
        )
    meta, priv = lm.sidecar_frame(read_json_file(side))
    return meta, priv, side


def _from_bare_raw(p: Path, profile: CameraProfile | None) -> Capture:
    meta, priv, side = read_sidecar_metadata(p)
    fmt = lm.raw_format(meta, f"{side}")
    size = p.stat().st_size
    need = packed_size(fmt.width_px, fmt.height_px, fmt.bits_per_pixel)
    if size != need:
        raise RawDataError(
            f"{p}: {size} bytes, but {fmt.width_px}x{fmt.height_px} at {fmt.bits_per_pixel} bit "
            f"needs {need} (wrong sidecar or truncated raw)"
        )
    img = unpack(p.read_bytes(), fmt.width_px, fmt.height_px, fmt.bits_per_pixel,
                 fmt.endianness)
    if fmt.right_shift:
        img >>= fmt.right_shift
    return Capture(
        raw=_freeze(img), bayer=fmt.bayer, black_level=fmt.black_level,
        white_level=fmt.white_level,
        metadata={"frame": meta, "privateMetadata": priv, "sidecar": str(side)},
        source_kind="lytro-raw", path=str(p), profile=profile, white_balance=_wb_tuple(fmt),
    )


def bayer_from_rawpy(pattern: np.ndarray, color_desc: bytes) -> str:
    """Bayer name from rawpy's 2×2 ``raw_pattern`` indices into ``color_desc``.

    Raises
    ------
    RawDataError
        For non-2×2 (e.g. X-Trans) or non-RGB patterns.
    """
    desc = color_desc.decode("ascii", "replace") if isinstance(color_desc, bytes) else color_desc
    pat = np.asarray(pattern)
    if pat.shape != (2, 2):
        raise RawDataError(f"unsupported colour filter pattern of shape {pat.shape} "
                           "(only 2x2 Bayer mosaics)")
    name = "".join(desc[int(i)] for i in pat.reshape(-1)).upper()
    if name not in ("RGGB", "BGGR", "GRBG", "GBRG"):
        raise RawDataError(f"unsupported colour filter pattern {name!r}")
    return name


def _from_camera_raw(p: Path, profile: CameraProfile | None) -> Capture:
    import rawpy

    try:
        with rawpy.imread(str(p)) as r:
            img = np.array(r.raw_image_visible, dtype=np.uint16, copy=True)
            if r.num_colors == 1 or r.raw_pattern is None:
                bayer = "none"
            else:
                bayer = bayer_from_rawpy(r.raw_pattern, r.color_desc)
            blacks = [float(b) for b in r.black_level_per_channel]
            white = float(r.white_level)
            meta = {"rawpy": {"black_level_per_channel": blacks, "white_level": white,
                              "color_desc": r.color_desc.decode("ascii", "replace"),
                              "camera_whitebalance": [float(x) for x in r.camera_whitebalance],
                              "sizes": {"raw_width": r.sizes.raw_width,
                                        "raw_height": r.sizes.raw_height,
                                        "width": r.sizes.width, "height": r.sizes.height}}}
    except (rawpy.LibRawError, OSError, ValueError) as exc:  # type: ignore[attr-defined]
        raise UnsupportedFormatError(f"{p}: camera raw not readable by LibRaw "
                                     f"({type(exc).__name__}: {exc})") from None
    if img.ndim != 2:
        raise RawDataError(f"{p}: camera raw is not a single-plane mosaic (shape {img.shape})")
    return Capture(raw=_freeze(img), bayer=bayer, black_level=max(blacks),
                   white_level=white, metadata=meta, source_kind="camera-raw", path=str(p),
                   profile=profile)


def _raster_levels(img: np.ndarray, profile: CameraProfile | None, p: Path):
    if profile is not None:
        s = profile.sensor
        if (s.height_px, s.width_px) != img.shape:
            raise RawDataError(
                f"{p}: image is {img.shape[1]}x{img.shape[0]} px but profile {profile.name!r} "
                f"has a {s.width_px}x{s.height_px} px sensor"
            )
        return s.bayer, float(s.black_level), float(s.white_level)
    if img.dtype.kind == "f":
        return "none", 0.0, 1.0
    return "none", 0.0, float(np.iinfo(img.dtype).max)


@contextmanager
def native_stderr():
    """Collect what native decoders (libpng, OpenCV) print on file descriptor 2.

    Yields a list that holds the captured text once the block ends, so a damaged file gives
    lfcam's one-line error instead of stray ``libpng error:`` lines. Falls back to doing
    nothing where fd 2 cannot be redirected.
    """
    said: list[str] = []
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        yield said
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield said
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            said.append(tmp.read(64 * 1024).decode("utf-8", "replace"))


def _from_raster(p: Path, kind: str, profile: CameraProfile | None) -> Capture:
    check_raster(p, kind)  # header only: refuse oversized / forged sizes before decoding
    if kind == "png":
        import cv2

        with native_stderr() as said:
            try:
                img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            except cv2.error as exc:
                raise UnsupportedFormatError(f"{p}: PNG could not be decoded "
                                             f"({str(exc).strip().splitlines()[-1]})") from None
        if img is None:
            why = said[0].strip().splitlines()[-1] if said and said[0].strip() else "damaged?"
            raise UnsupportedFormatError(f"{p}: PNG could not be decoded ({why})")
    else:
        import tifffile

        try:
            img = tifffile.imread(p)
        except Exception as exc:  # noqa: BLE001 - tifffile raises many kinds on bad data
            raise UnsupportedFormatError(f"{p}: TIFF could not be decoded ({exc})") from None
    img = np.asarray(img)
    if img.ndim != 2:
        raise RawDataError(
            f"{p}: expected a single-channel (grey or Bayer-mosaicked) raster, got shape "
            f"{img.shape}; save the raw mosaic, not a demosaicked colour image"
        )
    check_dimensions(img.shape[1], img.shape[0], 16)
    if img.dtype == np.float64 or img.dtype == np.float16:
        img = img.astype(np.float32)
    if img.dtype not in (np.uint8, np.uint16, np.uint32, np.float32):
        raise RawDataError(f"{p}: unsupported pixel type {img.dtype}")
    if img.dtype.kind == "f" and not np.all(np.isfinite(img)):
        raise RawDataError(f"{p}: float raster contains NaN or infinity")
    bayer, black, white = _raster_levels(img, profile, p)
    if img.dtype == np.uint8:
        img = img.astype(np.uint16)
    return Capture(raw=_freeze(img), bayer=bayer, black_level=black, white_level=white,
                   metadata={"dtype": str(np.asarray(img).dtype)}, source_kind=kind,
                   path=str(p), profile=profile)


MAX_SATURATED_FRACTION = 0.5


def check_saturation(cap: Capture, max_fraction: float = MAX_SATURATED_FRACTION) -> float:
    """Refuse a capture with more than ``max_fraction`` of its pixels at the white level.

    Such a frame (over-exposed, or a white image passed as a capture) has no measurable
    blur: the pipeline would report "0 regions" as if the scene were empty.

    Returns
    -------
    float
        The saturated fraction.

    Raises
    ------
    SaturatedCaptureError
        Naming the file, the fraction and the white level.
    """
    raw = cap.raw
    frac = float(np.count_nonzero(raw >= cap.white_level)) / max(raw.size, 1)
    if frac > max_fraction:
        raise SaturatedCaptureError(
            f"{cap.path}: {100 * frac:.1f} % of the pixels sit at the white level "
            f"{cap.white_level:g} (over {100 * max_fraction:g} %): over-exposed, nothing "
            "can be measured")
    return frac


def load_capture(path: str | Path, profile: CameraProfile | None = None,
                 verify: str = "error") -> Capture:
    """Load any supported capture; the format is chosen by content, not by extension.

    Parameters
    ----------
    path : str or Path
        ``.lfp``/``.lfr`` container, bare ``.raw`` + sidecar, camera raw, PNG or TIFF.
    profile : CameraProfile, optional
        Gives Bayer pattern and black/white level of PNG/TIFF rasters (and must match their
        size); attached to the returned capture for every kind.
    verify : {"error", "warn", "off"}
        sha1 checking of LFP sections (see :func:`lfcam.io.lfp.read_lfp`).

    Returns
    -------
    Capture

    Raises
    ------
    InputFileError
        Or one of its subclasses (``UnsupportedFormatError``, ``TruncatedFileError``,
        ``ContainerError``, ``ChecksumError``, ``MetadataError``, ``RawDataError``,
        ``NoRawFrameError``), with a one-line message naming the file and the problem.
    """
    p = Path(path)
    kind = sniff_kind(p)
    if kind == "lfp":
        return _from_lfp(p, profile, verify)
    if kind == "lytro-raw":
        return _from_bare_raw(p, profile)
    if kind == "camera-raw":
        return _from_camera_raw(p, profile)
    return _from_raster(p, kind, profile)
