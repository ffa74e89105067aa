"""Packed raw pixel buffers: Lytro 12-bit big-endian (F01) and 10-bit little-endian (Illum).

Bit layouts (one image row after another, pixels left to right, no row padding):

* **12-bit big-endian** — 2 pixels in 3 bytes ``b0 b1 b2``:
  ``p0 = b0 << 4 | b1 >> 4`` and ``p1 = (b1 & 0x0F) << 8 | b2``.
* **10-bit little-endian** — 4 pixels in 5 bytes ``b0 b1 b2 b3 b4``: bytes 0–3 hold the upper
  8 bits of pixels 0–3, byte 4 holds the two low bits of every pixel, pixel *k* in bits
  ``2k`` and ``2k+1``: ``p_k = b_k << 2 | (b4 >> 2k) & 3``.
* **16-bit** — plain ``uint16`` in the stated byte order.

Every function checks the buffer size against the requested dimensions *before* allocating
the output, so a corrupt header can never make us allocate more than the file holds.
"""

from __future__ import annotations

import numpy as np

from lfcam.errors import RawDataError

MAX_SIDE_PX = 100_000
SUPPORTED_BITS = (10, 12, 16)


def packed_size(width_px: int, height_px: int, bits: int) -> int:
    """Bytes of a packed buffer of ``width_px × height_px`` pixels at ``bits`` per pixel."""
    return (int(width_px) * int(height_px) * int(bits) + 7) // 8


def check_dimensions(width_px: object, height_px: object, bits: object) -> tuple[int, int, int]:
    """Validate raw dimensions and bit depth; returns them as ints.

    Raises
    ------
    RawDataError
        On non-integer, non-positive or absurd (> 100000 px) sides, an unsupported depth, or
        a row length the packing cannot split (10-bit needs a multiple of 4, 12-bit of 2).
    """
    for name, v in (("width", width_px), ("height", height_px), ("bitsPerPixel", bits)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            raise RawDataError(f"raw {name} must be an integer, got {v!r}")
    w, h, b = int(width_px), int(height_px), int(bits)
    if not (1 <= w <= MAX_SIDE_PX and 1 <= h <= MAX_SIDE_PX):
        raise RawDataError(f"absurd raw dimensions {w}x{h} px (each side must be 1..{MAX_SIDE_PX})")
    if b not in SUPPORTED_BITS:
        raise RawDataError(f"unsupported raw bit depth {b} (supported: 10, 12, 16)")
    if b == 10 and (w * h) % 4:
        raise RawDataError(f"10-bit packing needs a pixel count divisible by 4, got {w}x{h}")
    if b == 12 and (w * h) % 2:
        raise RawDataError(f"12-bit packing needs an even pixel count, got {w}x{h}")
    return w, h, b


def _as_bytes(buf: bytes | bytearray | memoryview | np.ndarray, expected: int, what: str):
    arr = np.frombuffer(buf, dtype=np.uint8) if not isinstance(buf, np.ndarray) else buf
    if arr.dtype != np.uint8 or arr.ndim != 1:
        arr = np.ascontiguousarray(arr).reshape(-1).view(np.uint8)
    if arr.size != expected:
        raise RawDataError(
            f"{what}: buffer holds {arr.size} bytes, the stated dimensions need {expected}"
        )
    return arr


def unpack_12bit_be(buf, width_px: int, height_px: int) -> np.ndarray:
    """Unpack a 12-bit big-endian buffer (F01) into a ``(height, width)`` uint16 image.

    Raises
    ------
    RawDataError
        If the buffer size disagrees with the dimensions.
    """
    w, h, _ = check_dimensions(width_px, height_px, 12)
    b = _as_bytes(buf, packed_size(w, h, 12), "12-bit raw").reshape(-1, 3)
    out = np.empty((b.shape[0], 2), dtype=np.uint16)
    b0 = b[:, 0].astype(np.uint16)
    b1 = b[:, 1].astype(np.uint16)
    np.left_shift(b0, 4, out=out[:, 0])
    out[:, 0] |= b1 >> 4
    np.bitwise_and(b1, 0x0F, out=b1)
    np.left_shift(b1, 8, out=out[:, 1])
    out[:, 1] |= b[:, 2]
    return out.reshape(h, w)


def unpack_10bit_le(buf, width_px: int, height_px: int) -> np.ndarray:
    """Unpack a 10-bit little-endian buffer (Illum) into a ``(height, width)`` uint16 image.

    Raises
    ------
    RawDataError
        If the buffer size disagrees with the dimensions.
    """
    w, h, _ = check_dimensions(width_px, height_px, 10)
    b = _as_bytes(buf, packed_size(w, h, 10), "10-bit raw").reshape(-1, 5)
    n = b.shape[0]
    # Upper 8 bits: widen the first four bytes of each group in one pass, then shift.
    out = b[:, :4].astype(np.uint16)
    out <<= 2
    low = b[:, 4]
    tmp = np.empty(n, dtype=np.uint8)
    for k in range(4):
        np.right_shift(low, 2 * k, out=tmp)
        tmp &= 3
        out[:, k] |= tmp
    return out.reshape(h, w)


def unpack_16bit(buf, width_px: int, height_px: int, endianness: str = "little") -> np.ndarray:
    """Read a plain 16-bit buffer into a ``(height, width)`` native uint16 image."""
    w, h, _ = check_dimensions(width_px, height_px, 16)
    b = _as_bytes(buf, packed_size(w, h, 16), "16-bit raw")
    dt = np.dtype(">u2" if endianness == "big" else "<u2")
    return b.view(dt).astype(np.uint16).reshape(h, w)


def unpack(buf, width_px: int, height_px: int, bits: int, endianness: str) -> np.ndarray:
    """Unpack a Lytro raw buffer given its ``bitsPerPixel`` and ``endianness``.

    Raises
    ------
    RawDataError
        On an unsupported depth/endianness combination or a size mismatch.
    """
    w, h, b = check_dimensions(width_px, height_px, bits)
    endianness = str(endianness).lower()
    if b == 12 and endianness == "big":
        return unpack_12bit_be(buf, w, h)
    if b == 10 and endianness == "little":
        return unpack_10bit_le(buf, w, h)
    if b == 16 and endianness in ("big", "little"):
        return unpack_16bit(buf, w, h, endianness)
    raise RawDataError(f"unsupported packing: {b} bits, {endianness!r} endian")


def _check_values(img: np.ndarray, bits: int) -> np.ndarray:
    a = np.asarray(img)
    if a.ndim != 2:
        raise RawDataError(f"raw image must be 2-D, got shape {a.shape}")
    if a.dtype.kind not in "ui":
        raise RawDataError(f"raw image must have an integer dtype, got {a.dtype}")
    if a.size and (int(a.min()) < 0 or int(a.max()) > (1 << bits) - 1):
        raise RawDataError(f"raw values must lie in [0, {(1 << bits) - 1}] for {bits}-bit packing")
    return a.astype(np.uint16, copy=False)


def pack_12bit_be(img: np.ndarray) -> bytes:
    """Pack a 2-D image of 12-bit values as F01 12-bit big-endian bytes."""
    a = _check_values(img, 12)
    check_dimensions(a.shape[1], a.shape[0], 12)
    p = a.reshape(-1, 2)
    out = np.empty((p.shape[0], 3), dtype=np.uint8)
    out[:, 0] = p[:, 0] >> 4
    out[:, 1] = ((p[:, 0] & 0x0F) << 4) | (p[:, 1] >> 8)
    out[:, 2] = p[:, 1] & 0xFF
    return out.tobytes()


def pack_10bit_le(img: np.ndarray) -> bytes:
    """Pack a 2-D image of 10-bit values as Illum 10-bit little-endian bytes."""
    a = _check_values(img, 10)
    check_dimensions(a.shape[1], a.shape[0], 10)
    p = a.reshape(-1, 4)
    out = np.empty((p.shape[0], 5), dtype=np.uint8)
    out[:, :4] = p >> 2
    out[:, 4] = (p[:, 0] & 3) | ((p[:, 1] & 3) << 2) | ((p[:, 2] & 3) << 4) | ((p[:, 3] & 3) << 6)
    return out.tobytes()
