"""Lytro LFP / LFR containers: reader and writer.

Layout (all integers big-endian)::

    file header   8 bytes magic  89 'LFP' 0D 0A 1A 0A
                  4 bytes version (1), 4 bytes length (0)
    section       8 bytes magic  89 'LFM' ... (JSON metadata) or 89 'LFC' ... (data)
                  4 bytes version (0), 4 bytes data length N
                  80 bytes name: "sha1-" + 40 hex digits of sha1(data), NUL padded
                  N bytes data, then NUL padding to the next multiple of 16 (file offset)

The first section is the master ``LFM`` (the picture JSON); every other section is found by
the sha1 name the JSON references (``imageRef``, ``metadataRef``, ``privateMetadataRef``, ...).
Every length is checked against the bytes left in the file before anything is sliced.
"""

from __future__ import annotations

import copy
import hashlib
import json
import struct
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lfcam.atomic import atomic_write_bytes
from lfcam.errors import (
    ChecksumError,
    ContainerError,
    InputFileError,
    MetadataError,
    NoRawFrameError,
    RawDataError,
    TruncatedFileError,
)
from lfcam.io import lytro_meta as lm
from lfcam.io.packing import pack_10bit_le, pack_12bit_be, packed_size, unpack
from lfcam.validate import MAX_JSON_DEPTH, json_depth

LFP_MAGIC = b"\x89LFP\r\n\x1a\n"
LFM_MAGIC = b"\x89LFM\r\n\x1a\n"
LFC_MAGIC = b"\x89LFC\r\n\x1a\n"
NAME_BYTES = 80
HEADER_BYTES = 16
ALIGN = 16
MAX_JSON_BYTES = 64 * 1024 * 1024
CHECKSUM_HINT = "; verify='warn' loads it anyway"  # the CLI swaps in its own flag


class ChecksumWarning(UserWarning):
    """A section's sha1 mismatched and the reader was told to only warn."""


@dataclass(frozen=True)
class LfpSection:
    """One section of a container: kind (``"LFM"``/``"LFC"``), sha1 name, data location."""

    kind: str
    name: str
    offset: int
    length: int


@dataclass(frozen=True)
class LfpFrame:
    """A frame located through the master JSON's references."""

    metadata: dict
    private_metadata: dict
    image_ref: str | None
    has_image: bool
    is_modulation: bool


@dataclass(frozen=True)
class LfpContainer:
    """A parsed container: its sections, master JSON and resolved frames.

    Use :meth:`section_bytes` to get a section's data by sha1 name and
    :meth:`raw_image` to unpack the raw frame.
    """

    path: str
    size: int
    version: int
    sections: tuple[LfpSection, ...]
    master: dict
    frames: tuple[LfpFrame, ...]
    checksum_failures: tuple[str, ...] = ()
    _data: bytes = field(default=b"", repr=False, compare=False)

    def section(self, name: str) -> LfpSection | None:
        """Section with this sha1 name (case-insensitive), or ``None``."""
        key = name.lower()
        for s in self.sections:
            if s.name.lower() == key:
                return s
        return None

    def section_bytes(self, name: str) -> bytes:
        """Data of the named section (:class:`ContainerError` if absent)."""
        s = self.section(name)
        if s is None:
            raise ContainerError(f"{self.path}: no section named {name}")
        return self._data[s.offset : s.offset + s.length]

    @property
    def light_field_frame(self) -> LfpFrame | None:
        """The first non-modulation frame whose pixels are inside the file."""
        for fr in self.frames:
            if fr.has_image and not fr.is_modulation:
                return fr
        return None

    @property
    def white_frame(self) -> LfpFrame | None:
        """The modulation (white) frame, when the container holds one."""
        for fr in self.frames:
            if fr.has_image and fr.is_modulation:
                return fr
        return None

    @property
    def has_raw(self) -> bool:
        """True when a light-field raw frame is inside the file."""
        return self.light_field_frame is not None

    @property
    def camera_metadata(self) -> dict:
        """Frame metadata of the first frame that has any (even if its pixels are absent)."""
        for fr in self.frames:
            if fr.metadata:
                return fr.metadata
        return {}

    def raw_image(self, frame: LfpFrame | None = None) -> np.ndarray:
        """Unpack a frame's raw pixels (default: the light-field frame) as 2-D uint16.

        Raises
        ------
        NoRawFrameError
            For processed pictures (no raw frame inside).
        MetadataError, RawDataError
            If the frame metadata or buffer size is wrong.
        """
        fr = frame if frame is not None else self.light_field_frame
        if fr is None:
            raise NoRawFrameError(
                f"{self.path}: no raw sensor frame inside ({describe_processed(self)}); "
                "this is a processed Lytro picture — use the original .lfr/.raw capture"
            )
        fmt = lm.raw_format(fr.metadata, f"{self.path}: frame metadata")
        try:
            img = unpack(self.section_bytes(fr.image_ref), fmt.width_px, fmt.height_px,
                         fmt.bits_per_pixel, fmt.endianness)
        except RawDataError as exc:
            raise RawDataError(f"{self.path}: raw frame {fr.image_ref}: {exc}") from None
        if fmt.right_shift:
            img >>= fmt.right_shift
        return img


# ----------------------------------------------------------------------------- reading


def _parse_json(raw: bytes, where: str) -> Any:
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise MetadataError(f"{where}: metadata is not UTF-8 ({exc.reason} at byte "
                            f"{exc.start})") from None
    depth = json_depth(raw) if raw.count(b"[") + raw.count(b"{") > MAX_JSON_DEPTH else 0
    if depth > MAX_JSON_DEPTH:
        raise MetadataError(f"{where}: metadata JSON nested {depth} levels deep "
                            f"(limit {MAX_JSON_DEPTH})")
    try:
        return json.loads(text)
    except RecursionError:
        raise MetadataError(f"{where}: metadata JSON nested too deeply") from None
    except ValueError as exc:
        raise MetadataError(f"{where}: malformed metadata JSON ({exc})") from None


def _read_sections(data: bytes, where: str, verify: str) -> tuple[int, list[LfpSection],
                                                                  list[str]]:
    size = len(data)
    if size < HEADER_BYTES:
        if LFP_MAGIC.startswith(data[:8]) or data[:8] == LFP_MAGIC:
            raise TruncatedFileError(f"{where}: truncated LFP header ({size} bytes)")
        raise ContainerError(f"{where}: not an LFP container (wrong magic)")
    if data[:8] != LFP_MAGIC:
        raise ContainerError(f"{where}: not an LFP container (wrong magic {data[:8]!r})")
    version, hlen = struct.unpack(">II", data[8:16])
    if hlen > size - HEADER_BYTES:
        raise ContainerError(f"{where}: file header length {hlen} exceeds the file size")
    pos = HEADER_BYTES + hlen
    pos += (-pos) % ALIGN if data[pos : pos + 1] == b"\0" else 0
    sections: list[LfpSection] = []
    failures: list[str] = []
    while pos < size:
        if size - pos < HEADER_BYTES + NAME_BYTES:
            if not data[pos:].strip(b"\0"):
                break  # trailing padding
            raise TruncatedFileError(f"{where}: truncated section header at offset {pos}")
        magic = data[pos : pos + 8]
        if magic == LFM_MAGIC:
            kind = "LFM"
        elif magic == LFC_MAGIC:
            kind = "LFC"
        else:
            raise ContainerError(f"{where}: bad section magic {magic!r} at offset {pos}")
        _ver, length = struct.unpack(">II", data[pos + 8 : pos + 16])
        name_raw = data[pos + 16 : pos + 16 + NAME_BYTES]
        start = pos + HEADER_BYTES + NAME_BYTES
        if length > size - start:
            raise TruncatedFileError(
                f"{where}: section at offset {pos} announces {length} bytes but only "
                f"{size - start} remain (truncated or corrupt length)"
            )
        name_b = name_raw.split(b"\0", 1)[0]
        try:
            name = name_b.decode("ascii")
        except UnicodeDecodeError:
            raise ContainerError(f"{where}: section name at offset {pos} is not ASCII") from None
        if name_raw[len(name_b) :].strip(b"\0"):
            raise ContainerError(f"{where}: section name at offset {pos} is not NUL padded")
        if name.lower().startswith("sha1-"):
            digest = hashlib.sha1(data[start : start + length]).hexdigest()
            if digest != name[5:].lower():
                msg = f"{where}: sha1 mismatch in section {name} (data hashes to sha1-{digest})"
                if verify == "error":
                    raise ChecksumError(msg + CHECKSUM_HINT)
                if verify == "warn":
                    warnings.warn(msg, ChecksumWarning, stacklevel=3)
                failures.append(name)
        sections.append(LfpSection(kind, name, start, length))
        pos = start + length
        pad = (-pos) % ALIGN
        if data[pos : pos + pad].strip(b"\0"):
            # Some writers do not pad: accept a section magic right after the data.
            if data[pos : pos + 5] not in (LFM_MAGIC[:5], LFC_MAGIC[:5]):
                raise ContainerError(f"{where}: non-NUL bytes in padding at offset {pos}")
        else:
            pos += pad
    return version, sections, failures


def read_lfp(path: str | Path, verify: str = "error") -> LfpContainer:
    """Read and check an LFP/LFR container.

    Parameters
    ----------
    path : str or Path
        The container file.
    verify : {"error", "warn", "off"}
        What a sha1 mismatch does: raise :class:`ChecksumError`, warn
        (:class:`ChecksumWarning`, the names are kept in ``checksum_failures``), or nothing.

    Returns
    -------
    LfpContainer

    Raises
    ------
    ContainerError, TruncatedFileError, ChecksumError, MetadataError
        For a damaged container, with the offset or section concerned.
    """
    if verify not in ("error", "warn", "off"):
        raise ValueError(f"verify must be 'error', 'warn' or 'off', not {verify!r}")
    p = Path(path)
    where = str(p)
    try:
        data = p.read_bytes()
    except IsADirectoryError:
        raise InputFileError(f"{where}: is a directory, not a capture file") from None
    except FileNotFoundError:
        raise InputFileError(f"{where}: file not found") from None
    version, sections, failures = _read_sections(data, where, verify)
    if not sections or sections[0].kind != "LFM":
        raise ContainerError(f"{where}: first section must be the LFM metadata")
    by_name = {s.name.lower(): s for s in sections}

    def blob(s: LfpSection) -> bytes:
        return data[s.offset : s.offset + s.length]

    m0 = sections[0]
    if m0.length > MAX_JSON_BYTES:
        raise MetadataError(f"{where}: master metadata of {m0.length} bytes is implausibly large")
    master = _parse_json(blob(m0), f"{where}: master metadata")
    if not isinstance(master, dict):
        raise MetadataError(f"{where}: master metadata is not a JSON object")

    def resolve(ref: Any, what: str) -> dict:
        if not isinstance(ref, str):
            raise MetadataError(f"{where}: {what} reference is not a string")
        s = by_name.get(ref.lower())
        if s is None:
            return {}
        if s.kind != "LFM" or s.length > MAX_JSON_BYTES:
            raise ContainerError(f"{where}: {what} {ref} is not a metadata section")
        doc = _parse_json(blob(s), f"{where}: {what} {ref}")
        if not isinstance(doc, dict):
            raise MetadataError(f"{where}: {what} {ref} is not a JSON object")
        return doc

    frames = []
    for rec in lm.frame_records(master):
        fr = rec["frame"]
        meta = fr.get("metadata")
        if not isinstance(meta, dict):
            meta = resolve(fr["metadataRef"], "metadataRef") if "metadataRef" in fr else {}
        priv = fr.get("privateMetadata")
        if not isinstance(priv, dict):
            priv = (resolve(fr["privateMetadataRef"], "privateMetadataRef")
                    if "privateMetadataRef" in fr else {})
        iref = fr.get("imageRef")
        iref = iref if isinstance(iref, str) else None
        sec = by_name.get(iref.lower()) if iref else None
        if sec is not None and sec.kind != "LFC":
            raise ContainerError(f"{where}: imageRef {iref} names a metadata section")
        frames.append(LfpFrame(meta, priv, iref, sec is not None, lm.is_modulation_frame(rec)))
    return LfpContainer(where, len(data), version, tuple(sections), master, tuple(frames),
                        tuple(failures), data)


def merged_metadata(c: LfpContainer) -> dict:
    """One dict with the master JSON and the resolved frame metadata.

    Keys: ``master`` (the picture JSON), ``frame`` (light-field frame metadata),
    ``privateMetadata`` and, when present, ``whiteFrame`` (the modulation frame's metadata).
    """
    lf = c.light_field_frame
    first = lf or (c.frames[0] if c.frames else None)
    out: dict = {"master": c.master,
                 "frame": first.metadata if first else {},
                 "privateMetadata": first.private_metadata if first else {}}
    if c.white_frame is not None:
        out["whiteFrame"] = c.white_frame.metadata
    return out


def describe_processed(c: LfpContainer) -> str:
    """Short text of what a container without raw frame holds (JPEG views, depth maps...)."""
    kinds: dict[str, int] = {}
    for s in c.sections[1:]:
        d = c._data[s.offset : s.offset + 4]
        if s.kind == "LFM":
            k = "metadata"
        elif d[:3] == b"\xff\xd8\xff":
            k = "JPEG"
        elif d == b"\x00\x00\x00\x01":
            k = "H.264"
        else:
            k = "binary"
        kinds[k] = kinds.get(k, 0) + 1
    if not kinds:
        return "only metadata"
    return ", ".join(f"{n} {k}" for k, n in sorted(kinds.items()))


# ----------------------------------------------------------------------------- writing


def _section(kind_magic: bytes, payload: bytes) -> tuple[str, bytes]:
    name = "sha1-" + hashlib.sha1(payload).hexdigest()
    head = kind_magic + struct.pack(">II", 0, len(payload)) + name.encode("ascii").ljust(
        NAME_BYTES, b"\0"
    )
    body = head + payload
    return name, body + b"\0" * ((-len(body)) % ALIGN)


def _set(d: dict, path: str, value: Any) -> None:
    keys = path.split(".")
    for k in keys[:-1]:
        d = d.setdefault(k, {})
        if not isinstance(d, dict):
            raise MetadataError(f"metadata key {k} must be an object to hold {path}")
    d[keys[-1]] = value


def _frame_meta(raw: np.ndarray, metadata: dict, packing: str) -> tuple[dict, bytes]:
    meta = copy.deepcopy(metadata) if metadata else {}
    if not isinstance(meta, dict):
        raise MetadataError("metadata must be a dict")
    h, w = raw.shape
    if packing == "12bit":
        bits, endian, base, payload = 12, "big", "image.rawDetails", pack_12bit_be(raw)
    elif packing == "10bit":
        bits, endian, base, payload = 10, "little", "image", pack_10bit_le(raw)
    else:
        raise ValueError(f"packing must be '12bit' or '10bit', not {packing!r}")
    _set(meta, "image.width", int(w))
    _set(meta, "image.height", int(h))
    _set(meta, "image.representation", "rawPacked")
    _set(meta, f"{base}.pixelPacking.bitsPerPixel", bits)
    _set(meta, f"{base}.pixelPacking.endianness", endian)
    if lm.get_path(meta, f"{base}.pixelFormat.black") is None:
        _set(meta, f"{base}.pixelFormat.black", {c: 0 for c in lm.CFA_CHANNELS})
    if lm.get_path(meta, f"{base}.pixelFormat.white") is None:
        _set(meta, f"{base}.pixelFormat.white", {c: (1 << bits) - 1 for c in lm.CFA_CHANNELS})
    if lm.get_path(meta, f"{base}.pixelFormat.rightShift") is None:
        _set(meta, f"{base}.pixelFormat.rightShift", 0)
    if lm.get_path(meta, f"{base}.mosaic") is None:
        _set(meta, f"{base}.mosaic", {"tile": "monochrome", "upperLeftPixel": "gr"})
    _set(meta, "devices.sensor.bitsPerPixel", bits)
    lm.raw_format(meta, "metadata to write")  # refuse to write what we could not read back
    assert len(payload) == packed_size(w, h, bits)
    return meta, payload


def write_lfp(
    path: str | Path,
    raw_uint16: np.ndarray,
    metadata: dict,
    packing: str = "12bit",
    private_metadata: dict | None = None,
    white_image: np.ndarray | None = None,
    white_metadata: dict | None = None,
) -> Path:
    """Write a raw light-field capture as an LFP container (atomically).

    ``packing="12bit"`` writes the F01 layout (picture schema 1: ``picture.frameArray``,
    raw format under ``image.rawDetails``), ``"10bit"`` the Illum layout (schema 2:
    ``frames``, raw format under ``image``). The metadata, private metadata and raw frame
    go into their own sections referenced by sha1; ``image.width/height`` and the packing
    keys are set from the array; black/white levels and mosaic are kept when given (defaults:
    0, full scale, monochrome). An optional ``white_image`` is stored as a second frame tagged
    ``modulationFrame``.

    Parameters
    ----------
    path : str or Path
        Output file.
    raw_uint16 : (H, W) uint16 array
        The raw mosaic.
    metadata : dict
        Frame metadata (Lytro keys).
    packing : str
        ``"12bit"`` (F01) or ``"10bit"`` (Illum).
    private_metadata : dict, optional
    white_image : (H, W) uint16 array, optional
    white_metadata : dict, optional

    Returns
    -------
    Path
        The written file.

    Raises
    ------
    RawDataError
        If the array is not 2-D integer data within the packing's range.
    """
    raw = np.asarray(raw_uint16)
    meta, payload = _frame_meta(raw, metadata, packing)
    priv = copy.deepcopy(private_metadata) if private_metadata else {}
    blobs: list[bytes] = []

    def add_frame(m: dict, pix: bytes, pr: dict, modulation: bool) -> dict:
        mname, mblob = _section(LFM_MAGIC, json.dumps(m, indent=1).encode("utf-8"))
        pname, pblob = _section(LFM_MAGIC, json.dumps(pr, indent=1).encode("utf-8"))
        iname, iblob = _section(LFC_MAGIC, pix)
        blobs.extend([mblob, pblob, iblob])
        return {
            "frame": {"metadataRef": mname, "privateMetadataRef": pname, "imageRef": iname},
            "parameters": {"vendorContent": {"com.lytro.tags": {
                "darkFrame": False, "modulationFrame": modulation}}},
        }

    records = [add_frame(meta, payload, priv, False)]
    if white_image is not None:
        wmeta, wpayload = _frame_meta(np.asarray(white_image), white_metadata or metadata,
                                      packing)
        records.append(add_frame(wmeta, wpayload, priv, True))
    if packing == "12bit":
        master = {"picture": {"frameArray": records, "viewArray": [], "accelerationArray": [],
                              "derivationArray": []},
                  "thumbnailArray": [], "version": {"major": 1, "minor": 0}}
    else:
        master = {"schema": "lfcam/picture-2", "generators": ["lfcam"], "thumbnails": [],
                  "frames": records, "views": []}
    _, master_blob = _section(LFM_MAGIC, json.dumps(master, indent=1).encode("utf-8"))
    header = LFP_MAGIC + struct.pack(">II", 1, 0)
    out = Path(path)
    atomic_write_bytes(out, [header, master_blob, *blobs])
    return out
