"""Lytro metadata: find the frame records, read the raw format, map the optics.

Two key layouts exist in the wild (both seen in public Lytro test files):

* **F01 / picture schema 1** (and Illum caldata ``MOD_*.TXT``): the container's master JSON
  has ``picture.frameArray[i].frame`` (or ``master.picture.frameArray`` in caldata text files);
  the frame metadata stores the raw format under ``image.rawDetails.{pixelPacking,
  pixelFormat, mosaic}`` and colour under ``image.color``.
* **Illum / picture schema 2.x**: ``frames[i].frame``; the raw format sits directly under
  ``image.{pixelPacking, pixelFormat, mosaic}``.

A frame record either inlines ``metadata`` / ``privateMetadata`` or references sections by
``metadataRef`` / ``privateMetadataRef``; the pixels are always referenced by ``imageRef``.

All Lytro lengths are in **metres** (``pixelPitch``, ``lensPitch``, ``sensorOffset``,
``focalLength``, ``exitPupilOffset``); angles (``mla.rotation``) in radians. We convert to
millimetres on the way into lfcam objects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from lfcam.camera import BAYER_PATTERNS, MicrolensArray, Sensor
from lfcam.errors import MetadataError, RawDataError
from lfcam.io.packing import check_dimensions

CFA_CHANNELS = ("r", "gr", "gb", "b")
# Exit-pupil offsets at or beyond this (metres) are the firmware's "at infinity" sentinel
# (both real processed files carry z = 10000); they map to ``math.inf``.
EXIT_PUPIL_SENTINEL_M = 100.0


# ----------------------------------------------------------------------------- key access


def get_path(d: Any, path: str, default: Any = None) -> Any:
    """``get_path(d, "a.b.c")`` → ``d["a"]["b"]["c"]`` or ``default`` when any step is missing."""
    cur = d
    for key in path.split("."):
        if not isinstance(cur, dict) or key not in cur:
            return default
        cur = cur[key]
    return cur


def require(d: Any, path: str, kind: type | tuple[type, ...], where: str = "metadata") -> Any:
    """Return ``d[path]`` checked against ``kind``; :class:`MetadataError` naming the key."""
    v = get_path(d, path, _MISSING)
    if v is _MISSING:
        raise MetadataError(f"{where}: missing key {path}")
    if isinstance(v, bool) and bool not in (kind if isinstance(kind, tuple) else (kind,)):
        raise MetadataError(f"{where}: key {path} has the wrong type (bool)")
    if not isinstance(v, kind):
        raise MetadataError(f"{where}: key {path} has type {type(v).__name__}, expected "
                            f"{getattr(kind, '__name__', kind)}")
    return v


_MISSING = object()


def _number(d: Any, path: str, where: str) -> float:
    v = require(d, path, (int, float), where)
    if not math.isfinite(float(v)):
        raise MetadataError(f"{where}: key {path} is not finite ({v!r})")
    return float(v)


def _opt_number(d: Any, path: str) -> float | None:
    v = get_path(d, path)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        return None
    return float(v)


# ----------------------------------------------------------------------------- frames


def frame_records(doc: Any) -> list[dict]:
    """The frame records (``{"frame": {...}, "parameters": {...}}``) of a master JSON.

    Accepts schema 1 (``picture.frameArray``), schema 2 (``frames``) and caldata text files
    (``master.picture.frameArray``). Returns ``[]`` when there is none.
    """
    if not isinstance(doc, dict):
        return []
    for path in ("frames", "picture.frameArray", "master.picture.frameArray"):
        v = get_path(doc, path)
        if isinstance(v, list):
            return [r for r in v if isinstance(r, dict) and isinstance(r.get("frame"), dict)]
    return []


def is_modulation_frame(record: dict) -> bool:
    """True when a frame record is tagged as a white (modulation) frame."""
    tag = get_path(record, "parameters.vendorContent.com.lytro.tags.modulationFrame")
    if tag is None:  # "com.lytro.tags" holds dots: walk it by hand
        vc = get_path(record, "parameters.vendorContent")
        if isinstance(vc, dict) and isinstance(vc.get("com.lytro.tags"), dict):
            tag = vc["com.lytro.tags"].get("modulationFrame")
    return tag is True or tag == "true"


def looks_like_frame_metadata(doc: Any) -> bool:
    """True for a bare frame-metadata object (``image`` + ``devices``), e.g. ``*_frame.json``."""
    return isinstance(doc, dict) and isinstance(doc.get("image"), dict) and isinstance(
        doc.get("devices"), dict
    )


def sidecar_frame(doc: Any) -> tuple[dict, dict]:
    """(frame metadata, private metadata) of a sidecar JSON/TXT of a bare ``.raw`` file.

    Raises
    ------
    MetadataError
        If the document is neither a frame-metadata object nor a master JSON with an inline
        frame.
    """
    if looks_like_frame_metadata(doc):
        return doc, {}
    for rec in frame_records(doc):
        fr = rec["frame"]
        if looks_like_frame_metadata(fr.get("metadata")):
            priv = fr.get("privateMetadata")
            return fr["metadata"], priv if isinstance(priv, dict) else {}
    raise MetadataError("sidecar holds no frame metadata (expected image/devices keys, or "
                        "frames[].frame.metadata / picture.frameArray[].frame.metadata)")


# ----------------------------------------------------------------------------- raw format


@dataclass(frozen=True)
class LytroRawFormat:
    """How a Lytro raw buffer is packed and what its values mean."""

    width_px: int
    height_px: int
    bits_per_pixel: int
    endianness: str
    bayer: str
    black: dict[str, float]
    white: dict[str, float]
    white_balance: dict[str, float] | None
    right_shift: int = 0

    @property
    def black_level(self) -> float:
        """Scalar black level (the largest channel value; channels agree on real files)."""
        return max(self.black.values())

    @property
    def white_level(self) -> float:
        """Scalar white level (the smallest channel value)."""
        return min(self.white.values())


def bayer_from_mosaic(tile: Any, upper_left: Any, where: str = "metadata") -> str:
    """Bayer pattern name from Lytro's ``mosaic.tile`` and ``mosaic.upperLeftPixel``.

    The tile lists the 2×2 cell row by row (``"r,gr:gb,b"``: rows separated by ``:``);
    ``upperLeftPixel`` names the channel of pixel (0, 0). The cell is cyclically shifted so
    that this channel comes first. ``"monochrome"`` gives ``"none"``.
    """
    if tile == "monochrome":
        return "none"
    if not isinstance(tile, str) or not isinstance(upper_left, str):
        raise MetadataError(f"{where}: mosaic.tile / mosaic.upperLeftPixel missing or not text")
    rows = [r.split(",") for r in tile.split(":")]
    if len(rows) != 2 or any(len(r) != 2 for r in rows) or sorted(sum(rows, [])) != sorted(
        CFA_CHANNELS
    ):
        raise MetadataError(f"{where}: unsupported mosaic.tile {tile!r}")
    for dy in range(2):
        for dx in range(2):
            if rows[dy][dx] == upper_left:
                cell = [[rows[(dy + j) % 2][(dx + i) % 2] for i in range(2)] for j in range(2)]
                name = "".join(c[0].upper() for c in cell[0] + cell[1])
                if name not in BAYER_PATTERNS:  # pragma: no cover - all shifts are valid
                    raise MetadataError(f"{where}: mosaic gives unknown pattern {name}")
                return name
    raise MetadataError(f"{where}: mosaic.upperLeftPixel {upper_left!r} not in tile {tile!r}")


def _channels(d: Any, path: str, where: str) -> dict[str, float]:
    v = get_path(d, path)
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        return {c: float(v) for c in CFA_CHANNELS}
    if not isinstance(v, dict):
        raise MetadataError(f"{where}: missing key {path}")
    return {c: _number(v, c, f"{where}: {path}") for c in CFA_CHANNELS}


def raw_format(meta: Any, where: str = "frame metadata") -> LytroRawFormat:
    """Read the raw format from frame metadata (F01 or Illum layout).

    Parameters
    ----------
    meta : dict
        Frame metadata.
    where : str
        Named in error messages.

    Returns
    -------
    LytroRawFormat
        Size, bit depth, packing, levels and mosaic of the raw frame.

    Raises
    ------
    MetadataError
        Naming the first missing or mistyped key.
    RawDataError
        On absurd dimensions or an unsupported bit depth.
    """
    if not isinstance(meta, dict):
        raise MetadataError(f"{where}: not a JSON object")
    base = "image.rawDetails" if isinstance(get_path(meta, "image.rawDetails"), dict) else "image"
    width = require(meta, "image.width", int, where)
    height = require(meta, "image.height", int, where)
    bits = require(meta, f"{base}.pixelPacking.bitsPerPixel", int, where)
    endian = require(meta, f"{base}.pixelPacking.endianness", str, where)
    try:
        w, h, b = check_dimensions(width, height, bits)
    except RawDataError as exc:
        raise RawDataError(f"{where}: {exc}") from None
    tile = get_path(meta, f"{base}.mosaic.tile")
    upper = get_path(meta, f"{base}.mosaic.upperLeftPixel")
    if tile is None:
        tile = get_path(meta, "devices.sensor.mosaic.tile")
        upper = get_path(meta, "devices.sensor.mosaic.upperLeftPixel")
    bayer = bayer_from_mosaic(tile, upper, where)
    black = _channels(meta, f"{base}.pixelFormat.black", where)
    white = _channels(meta, f"{base}.pixelFormat.white", where)
    if any(white[c] <= black[c] for c in CFA_CHANNELS):
        raise MetadataError(f"{where}: white level must exceed black level in every channel")
    wb_raw = get_path(meta, "image.color.whiteBalanceGain")
    wb = None
    if isinstance(wb_raw, dict):
        try:
            wb = {c: _number(wb_raw, c, where) for c in CFA_CHANNELS}
        except MetadataError:
            wb = None
    shift = get_path(meta, f"{base}.pixelFormat.rightShift", 0)
    if isinstance(shift, bool) or not isinstance(shift, int) or not 0 <= shift < b:
        raise MetadataError(f"{where}: pixelFormat.rightShift must be an int in [0, {b})")
    return LytroRawFormat(w, h, b, endian.lower(), bayer, black, white, wb, shift)


# ----------------------------------------------------------------------------- optics


@dataclass(frozen=True)
class LytroOptics:
    """The Lytro main-lens state that has no place in lfcam's biconvex :class:`MainLens`.

    Attributes
    ----------
    camera_model : str
        ``camera.model`` (``"F01"``, ``"ILLUM"``, ``"B01"`` in caldata).
    focal_length_mm : float
        ``devices.lens.focalLength`` (metres in the file) × 1000.
    f_number : float
        ``devices.lens.fNumber``.
    exit_pupil_offset_mm : float
        ``devices.lens.exitPupilOffset.z`` × 1000; ``inf`` for the ≥ 100 m sentinel.
    zoom_step, focus_step : int
        ``devices.lens.zoomStep`` / ``focusStep`` (motor steps, camera-specific zero).
    infinity_lambda : float or None
        ``devices.lens.infinityLambda`` (Lytro's refocus parameter of infinity).
    serial : str or None
        Camera serial from the private metadata (``camera.serialNumber``).
    """

    camera_model: str
    focal_length_mm: float
    f_number: float
    exit_pupil_offset_mm: float
    zoom_step: int
    focus_step: int
    infinity_lambda: float | None = None
    serial: str | None = None


@dataclass(frozen=True)
class LytroCamera:
    """What Lytro frame metadata says about a camera, in lfcam's units.

    ``mla`` and ``sensor`` are lfcam's own dataclasses; the main lens is reported as
    :class:`LytroOptics` because a zoom lens is not the seed's biconvex lens.
    ``mla.focal_length_mm`` is the MLA-to-sensor separation ``mla.sensorOffset.z`` (the
    sensor sits in the lenslets' focal plane in a plenoptic 1.0 camera); ``mla.offset_mm``
    is ``sensorOffset.{x,y}``, the MLA centre relative to the sensor centre.
    """

    mla: MicrolensArray
    sensor: Sensor
    optics: LytroOptics
    mla_scale_factor: tuple[float, float]
    mla_separation_mm: float


def lytro_camera(meta: Any, private: Any = None, where: str = "frame metadata") -> LytroCamera:
    """Map Lytro frame metadata (F01 or Illum layout) to :class:`LytroCamera`.

    Parameters
    ----------
    meta : dict
        Frame metadata.
    private : dict, optional
        Private metadata (camera serial).
    where : str
        Named in error messages.

    Returns
    -------
    LytroCamera
        Sensor, MLA and lens description of the camera.

    Raises
    ------
    MetadataError
        Naming the first missing, mistyped or non-positive key.
    """
    fmt = raw_format(meta, where)
    pixel_pitch_mm = _number(meta, "devices.sensor.pixelPitch", where) * 1e3
    lens_pitch_mm = _number(meta, "devices.mla.lensPitch", where) * 1e3
    rotation = _number(meta, "devices.mla.rotation", where)
    sep_mm = _number(meta, "devices.mla.sensorOffset.z", where) * 1e3
    off = (
        _number(meta, "devices.mla.sensorOffset.x", where) * 1e3,
        _number(meta, "devices.mla.sensorOffset.y", where) * 1e3,
    )
    for key, v in (("devices.sensor.pixelPitch", pixel_pitch_mm),
                   ("devices.mla.lensPitch", lens_pitch_mm),
                   ("devices.mla.sensorOffset.z", sep_mm)):
        if v <= 0:
            raise MetadataError(f"{where}: {key} must be positive, got {v / 1e3!r}")
    tiling = get_path(meta, "devices.mla.tiling", "")
    grid = "hex" if isinstance(tiling, str) and tiling.startswith("hex") else "rect"
    sx = _opt_number(meta, "devices.mla.scaleFactor.x") or 1.0
    sy = _opt_number(meta, "devices.mla.scaleFactor.y") or 1.0
    epo_m = _number(meta, "devices.lens.exitPupilOffset.z", where)
    model = require(meta, "camera.model", str, where)
    serial = get_path(private, "camera.serialNumber") if isinstance(private, dict) else None
    optics = LytroOptics(
        camera_model=model,
        focal_length_mm=_number(meta, "devices.lens.focalLength", where) * 1e3,
        f_number=_number(meta, "devices.lens.fNumber", where),
        exit_pupil_offset_mm=math.inf if abs(epo_m) >= EXIT_PUPIL_SENTINEL_M else epo_m * 1e3,
        zoom_step=int(require(meta, "devices.lens.zoomStep", (int, float), where)),
        focus_step=int(require(meta, "devices.lens.focusStep", (int, float), where)),
        infinity_lambda=_opt_number(meta, "devices.lens.infinityLambda"),
        serial=serial if isinstance(serial, str) else None,
    )
    mla = MicrolensArray(
        focal_length_mm=sep_mm,
        pitch_mm=lens_pitch_mm,
        grid=grid,
        rotation_rad=rotation,
        offset_mm=off,
    )
    sensor = Sensor(
        pixel_pitch_mm=pixel_pitch_mm,
        width_px=fmt.width_px,
        height_px=fmt.height_px,
        bit_depth=fmt.bits_per_pixel,
        bayer=fmt.bayer,
        black_level=int(round(fmt.black_level)),
        white_level=int(round(fmt.white_level)),
    )
    return LytroCamera(mla=mla, sensor=sensor, optics=optics, mla_scale_factor=(sx, sy),
                       mla_separation_mm=sep_mm)


# ----------------------------------------------------------------------------- profile


def profile_dict_from_lytro(camera: LytroCamera, name: str | None = None) -> dict:
    """The camera-profile mapping (docs/profiles.md) that a Lytro capture's metadata implies.

    The main lens is the black-box form of ``[main_lens]`` (focal length, f-number and, when
    the camera reports a finite one, the exit pupil → MLA distance ``exitPupilOffset.z``): a
    zoom lens's prescription is never in the file, and the distance stage learns what it
    needs from target captures (``lfcam calibrate --targets``). The MLA is
    ``devices.mla`` (``mla.focal_length_mm`` = the MLA → sensor separation
    ``sensorOffset.z``, the sensor lying in the lenslets' focal plane), the sensor is the raw
    frame's format. ``[mla]`` carries no distance: the calibration supplies it.

    Not mapped: ``devices.mla.scaleFactor`` (a ≤ 0.05 % lattice anisotropy that the white
    image's lattice fit measures anyway) and ``devices.lens.opticalCenterOffset`` (its sign
    convention is undocumented; the optical axis stays at the sensor centre).

    Parameters
    ----------
    camera : LytroCamera
        From :func:`lytro_camera`.
    name : str, optional
        Profile name; default ``lytro-<model>-zoom<step>-focus<step>`` (a learned lens is
        valid for one zoom and focus state).

    Returns
    -------
    dict
        ``{"name", "main_lens", "mla", "sensor"}``, ready for
        :func:`lfcam.camera.profile_from_dict`.
    """
    o, mla, s = camera.optics, camera.mla, camera.sensor
    lens: dict[str, Any] = {"focal_length_mm": o.focal_length_mm, "f_number": o.f_number}
    if math.isfinite(o.exit_pupil_offset_mm) and o.exit_pupil_offset_mm > 0.0:
        lens["exit_pupil_mm"] = o.exit_pupil_offset_mm
    if name is None:
        name = (f"lytro-{o.camera_model.lower()}-zoom{o.zoom_step}-focus{o.focus_step}")
    return {
        "name": name,
        "main_lens": lens,
        "mla": {
            "focal_length_mm": mla.focal_length_mm,
            "pitch_mm": mla.pitch_mm,
            "grid": mla.grid,
            "rotation_rad": mla.rotation_rad,
            "offset_mm": [float(mla.offset_mm[0]), float(mla.offset_mm[1])],
        },
        "sensor": {
            "pixel_pitch_mm": s.pixel_pitch_mm,
            "width_px": s.width_px,
            "height_px": s.height_px,
            "bit_depth": s.bit_depth,
            "bayer": s.bayer,
            "black_level": s.black_level,
            "white_level": s.white_level,
        },
    }
