"""Resource limits checked from a raster's header before any pixel is decoded.

A PNG or TIFF header is a few bytes that can claim any size: a 1.7 MB PNG can announce
30000 × 30000 16-bit pixels (1.8 GB once inflated, more in the decoder's copies). Every
PNG/TIFF lfcam reads goes through :func:`check_raster` first, which reads only the header
(PNG: the IHDR chunk; TIFF: tifffile's page/series shapes, no pixel data) and refuses:

* more than :data:`MAX_PIXELS` pixels (250 Mpx; a Lytro Illum raw is 41 Mpx);
* more than :data:`MAX_DECODED_BYTES` bytes once decoded (1 GiB, all channels and stacks);
* a PNG announcing more pixel data than :data:`PNG_MAX_INFLATE_RATIO` times its file size
  (deflate cannot compress better than about 1032:1, so such a file is forged or truncated).

The limits are module constants: a caller who really has larger frames may raise them.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

from lfcam.errors import (
    RawDataError,
    ResourceLimitError,
    UnsupportedFormatError,
)

MAX_PIXELS = 250_000_000
MAX_DECODED_BYTES = 1 << 30
PNG_MAX_INFLATE_RATIO = 1100

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
TIFF_MAGICS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
# PNG colour type → (samples per pixel in the file, channels OpenCV returns, allowed depths)
_PNG_TYPES = {
    0: (1, 1, (1, 2, 4, 8, 16)),
    2: (3, 3, (8, 16)),
    3: (1, 4, (1, 2, 4, 8)),  # palette: expanded to BGR(A) by the decoder
    4: (2, 4, (8, 16)),
    6: (4, 4, (8, 16)),
}


@dataclass(frozen=True)
class RasterHeader:
    """What a raster's header announces.

    Attributes
    ----------
    kind : str
        ``"png"`` or ``"tiff"``.
    width_px, height_px : int
        Size of one image plane.
    samples : int
        Samples to be decoded over all channels and pages (``width · height · channels ·
        pages``).
    bytes_per_sample : int
    """

    kind: str
    width_px: int
    height_px: int
    samples: int
    bytes_per_sample: int

    @property
    def pixels(self) -> int:
        """Pixels of one plane."""
        return self.width_px * self.height_px

    @property
    def decoded_bytes(self) -> int:
        """Bytes of the decoded array."""
        return self.samples * self.bytes_per_sample


def png_header(path: str | Path) -> RasterHeader:
    """Parse a PNG's IHDR chunk (the first 33 bytes) without decoding anything.

    Raises
    ------
    UnsupportedFormatError
        Short file, missing or invalid IHDR.
    RawDataError
        Impossible sizes: zero, or more pixel data than the file can hold compressed.
    ResourceLimitError
        Over the limits.
    """
    p = Path(path)
    with p.open("rb") as fh:
        head = fh.read(33)
    if not head.startswith(PNG_MAGIC):
        raise UnsupportedFormatError(f"{p}: not a PNG file")
    if len(head) < 33:
        raise UnsupportedFormatError(f"{p}: PNG could not be decoded (file ends inside its "
                                     f"header, {len(head)} bytes)")
    length, tag = struct.unpack(">I4s", head[8:16])
    if tag != b"IHDR" or length != 13:
        raise UnsupportedFormatError(f"{p}: PNG could not be decoded (no IHDR chunk first)")
    width, height, depth, ctype = struct.unpack(">IIBB", head[16:26])
    if ctype not in _PNG_TYPES or depth not in _PNG_TYPES[ctype][2]:
        raise UnsupportedFormatError(f"{p}: PNG could not be decoded (invalid colour type "
                                     f"{ctype} / bit depth {depth})")
    if width == 0 or height == 0 or width > 2**31 - 1 or height > 2**31 - 1:
        raise RawDataError(f"{p}: PNG header announces an impossible size {width}x{height}")
    file_samples, channels, _ = _PNG_TYPES[ctype]
    header = RasterHeader("png", width, height, width * height * channels,
                          2 if depth == 16 else 1)
    _check_limits(p, header)
    inflated = height * (1 + (width * file_samples * depth + 7) // 8)
    size = _png_chunks(p)
    if inflated > PNG_MAX_INFLATE_RATIO * size:
        raise RawDataError(
            f"{p}: PNG header announces {width}x{height} px ({inflated} bytes of pixel data) but "
            f"the file holds only {size} bytes of it, more than deflate can compress (forged "
            "or truncated)")
    return header


def _png_chunks(p: Path) -> int:
    """Walk the chunk list (lengths only, no data read); returns the IDAT bytes.

    A chunk length pointing past the end of the file makes decoders allocate that much
    before noticing (OpenCV: gigabytes for a flipped bit), so it is refused here.
    """
    size = p.stat().st_size
    idat = 0
    with p.open("rb") as fh:
        pos = 8
        while pos + 8 <= size:
            fh.seek(pos)
            length, tag = struct.unpack(">I4s", fh.read(8))
            if length > 2**31 - 1 or pos + 12 + length > size:
                raise UnsupportedFormatError(
                    f"{p}: PNG could not be decoded (chunk {tag!r} at offset {pos} announces "
                    f"{length} bytes, past the end of the {size}-byte file)")
            if tag == b"IDAT":
                idat += length
            if tag == b"IEND":
                break
            pos += 12 + length
    if idat == 0:
        raise UnsupportedFormatError(f"{p}: PNG could not be decoded (no image data)")
    return idat


def tiff_header(path: str | Path) -> RasterHeader:
    """Shape and sample type of a TIFF's first series, from its tags only (no pixel data).

    Raises
    ------
    UnsupportedFormatError
        When tifffile cannot parse the file's structure.
    """
    import tifffile

    p = Path(path)
    try:
        with tifffile.TiffFile(p) as tf:
            page = tf.pages.first if hasattr(tf.pages, "first") else tf.pages[0]
            width, height = int(page.imagewidth), int(page.imagelength)
            series = tf.series[0] if tf.series else None
            shape = tuple(series.shape) if series is not None else tuple(page.shape)
            itemsize = (series.dtype if series is not None else page.dtype).itemsize
    except Exception as exc:  # noqa: BLE001 - tifffile raises many kinds on bad data
        raise UnsupportedFormatError(f"{p}: TIFF could not be parsed "
                                     f"({type(exc).__name__}: {exc})") from None
    samples = 1
    for n in shape:
        samples *= int(n)
    header = RasterHeader("tiff", width, height, samples, int(itemsize))
    _check_limits(p, header)
    return header


def _check_limits(p: Path, h: RasterHeader) -> None:
    if h.pixels > MAX_PIXELS:
        raise ResourceLimitError(
            f"{p}: {h.kind.upper()} header announces {h.width_px}x{h.height_px} = "
            f"{h.pixels / 1e6:.0f} Mpx, over lfcam's limit of {MAX_PIXELS / 1e6:.0f} Mpx")
    if h.decoded_bytes > MAX_DECODED_BYTES:
        raise ResourceLimitError(
            f"{p}: {h.kind.upper()} would decode to {h.decoded_bytes / 2**20:.0f} MiB, over "
            f"lfcam's limit of {MAX_DECODED_BYTES / 2**20:.0f} MiB")


def check_raster(path: str | Path, kind: str | None = None) -> RasterHeader:
    """Check a PNG/TIFF against the limits from its header alone; returns the header.

    ``kind`` (``"png"``/``"tiff"``) is sniffed from the magic bytes when not given.

    Raises
    ------
    ResourceLimitError
        Over :data:`MAX_PIXELS` or :data:`MAX_DECODED_BYTES`.
    InputFileError
        Or another subclass, for a header that is truncated, impossible or unparseable.
    """
    p = Path(path)
    if kind is None:
        with p.open("rb") as fh:
            head = fh.read(8)
        kind = "png" if head.startswith(PNG_MAGIC) else "tiff" if head[:4] in TIFF_MAGICS else ""
        if not kind:
            raise UnsupportedFormatError(f"{p}: neither PNG nor TIFF (first bytes {head!r})")
    return png_header(p) if kind == "png" else tiff_header(p)
