"""White (modulation) image lookup in a Lytro calibration-data folder.

A caldata folder (as unpacked from the camera: ``caldata-<serial>/...``) holds white images as
``MOD_nnnn.RAW`` packed raws, each with a ``MOD_nnnn.TXT`` JSON description (the layout of
``illum-whiteimage-metadata.TXT``: ``master.picture.frameArray[0].frame.{metadata,
privateMetadata}``, tagged ``modulationFrame: true``).

Choice for a capture: same camera serial, then the nearest zoom step, then among those the
nearest focus step (ties: the lower file name).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lfcam.errors import InputFileError, LfcamError, WhiteImageNotFoundError
from lfcam.io import lytro_meta as lm
from lfcam.io.capture import read_json_file


@dataclass(frozen=True)
class WhiteImageEntry:
    """One white image of a caldata folder."""

    raw_path: Path
    meta_path: Path
    serial: str | None
    zoom_step: int
    focus_step: int
    metadata: dict


def _entry(txt: Path) -> WhiteImageEntry | None:
    raw = None
    for suf in (".RAW", ".raw"):
        if txt.with_suffix(suf).is_file():
            raw = txt.with_suffix(suf)
    if raw is None:
        return None
    try:
        meta, priv = lm.sidecar_frame(read_json_file(txt))
        zoom = lm.require(meta, "devices.lens.zoomStep", (int, float), str(txt))
        focus = lm.require(meta, "devices.lens.focusStep", (int, float), str(txt))
    except LfcamError:
        return None
    serial = lm.get_path(priv, "camera.serialNumber")
    return WhiteImageEntry(raw, txt, serial if isinstance(serial, str) else None, int(zoom),
                           int(focus), meta)


def scan_caldata(folder: str | Path) -> list[WhiteImageEntry]:
    """Every usable ``MOD_*`` white image below ``folder`` (recursively), sorted by name."""
    root = Path(folder)
    if not root.is_dir():
        raise InputFileError(f"{root}: calibration folder not found")
    txts = sorted(q for q in root.rglob("*") if q.is_file() and q.name.upper().startswith("MOD_")
                  and q.suffix.upper() in (".TXT", ".JSON"))
    return [e for e in (_entry(t) for t in txts) if e is not None]


def capture_lens_state(metadata: dict) -> tuple[str | None, int, int]:
    """(serial, zoom step, focus step) of a capture from its merged or frame metadata."""
    frame = metadata.get("frame", metadata) if isinstance(metadata, dict) else {}
    priv = metadata.get("privateMetadata", {}) if isinstance(metadata, dict) else {}
    zoom = lm.require(frame, "devices.lens.zoomStep", (int, float), "capture metadata")
    focus = lm.require(frame, "devices.lens.focusStep", (int, float), "capture metadata")
    serial = lm.get_path(priv, "camera.serialNumber")
    return (serial if isinstance(serial, str) else None), int(zoom), int(focus)


def find_white_image(folder: str | Path, serial: str | None, zoom_step: int,
                     focus_step: int) -> WhiteImageEntry:
    """The white image of ``folder`` that fits a capture best.

    Parameters
    ----------
    folder : path
        Caldata folder.
    serial : str or None
        Camera serial of the capture (``privateMetadata.camera.serialNumber``); ``None``
        accepts any serial only when the folder holds a single camera's images.
    zoom_step, focus_step : int
        The capture's ``devices.lens.zoomStep`` / ``focusStep``.

    Returns
    -------
    WhiteImageEntry
        The nearest white image of that camera in (zoom, focus) steps.

    Raises
    ------
    WhiteImageNotFoundError
        When the folder has no white image, none of this camera, or the serial is unknown
        and the folder mixes cameras; the message lists what was found.
    """
    entries = scan_caldata(folder)
    if not entries:
        raise WhiteImageNotFoundError(f"{folder}: no white images (MOD_*.RAW with a MOD_*.TXT "
                                      "description) found")
    serials = sorted({str(e.serial) for e in entries})
    if serial is None:
        if len(serials) > 1:
            raise WhiteImageNotFoundError(
                f"{folder}: capture has no camera serial and the folder holds white images of "
                f"{len(serials)} cameras ({', '.join(serials)})"
            )
        pool = entries
    else:
        pool = [e for e in entries if e.serial == serial]
        if not pool:
            raise WhiteImageNotFoundError(
                f"{folder}: no white image of camera {serial} (found serials: "
                f"{', '.join(serials)})"
            )
    dz = min(abs(e.zoom_step - zoom_step) for e in pool)
    pool = [e for e in pool if abs(e.zoom_step - zoom_step) == dz]
    return min(pool, key=lambda e: (abs(e.focus_step - focus_step), e.meta_path.name))


def white_image_for(capture_metadata: dict[str, Any], folder: str | Path) -> WhiteImageEntry:
    """:func:`find_white_image` using the serial and lens steps of a capture's metadata.

    Parameters
    ----------
    capture_metadata : dict
        The capture's Lytro metadata (``Capture.metadata``).
    folder : path
        Caldata folder.

    Returns
    -------
    WhiteImageEntry
    """
    serial, zoom, focus = capture_lens_state(capture_metadata)
    return find_white_image(folder, serial, zoom, focus)
