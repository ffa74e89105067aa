"""Shared helpers of the loader tests: an independent reference packer and small files."""

from __future__ import annotations

from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[2]
REALDATA = REPO_ROOT.parent / "shared" / "realdata" / "lytro"


def ref_pack_bits(pixels, bits: int, big_endian: bool) -> bytes:
    """Reference packer written from the documented bit layout, one pixel at a time.

    12-bit big-endian: the pixels' 12-bit codes are written MSB first as one continuous bit
    stream (so two pixels fill 3 bytes). 10-bit little-endian (Illum): for each group of
    four pixels, four bytes with the upper 8 bits of each, then one byte holding the two
    low bits of pixel k in bit positions 2k, 2k+1.
    """
    flat = [int(v) for v in np.asarray(pixels).reshape(-1)]
    if bits == 12 and big_endian:
        stream = "".join(format(v, "012b") for v in flat)
        return bytes(int(stream[i : i + 8], 2) for i in range(0, len(stream), 8))
    if bits == 10 and not big_endian:
        out = bytearray()
        for g in range(0, len(flat), 4):
            grp = flat[g : g + 4]
            out.extend(v >> 2 for v in grp)
            out.append(sum((v & 3) << (2 * k) for k, v in enumerate(grp)))
        return bytes(out)
    raise ValueError("layout not covered by the reference packer")


def small_frame_meta(width: int, height: int, packing: str = "12bit") -> dict:
    """A minimal but complete Lytro-style frame metadata (F01 or Illum key layout)."""
    if packing == "12bit":
        raw = {"rawDetails": {
            "pixelFormat": {"rightShift": 0, "black": {c: 168 for c in ("r", "gr", "gb", "b")},
                            "white": {c: 4095 for c in ("r", "gr", "gb", "b")}},
            "pixelPacking": {"endianness": "big", "bitsPerPixel": 12},
            "mosaic": {"tile": "r,gr:gb,b", "upperLeftPixel": "b"}}}
        model, bits = "F01", 12
    else:
        raw = {"pixelFormat": {"rightShift": 0, "black": {c: 64 for c in ("r", "gr", "gb", "b")},
                               "white": {c: 1023 for c in ("r", "gr", "gb", "b")}},
               "pixelPacking": {"endianness": "little", "bitsPerPixel": 10},
               "mosaic": {"tile": "r,gr:gb,b", "upperLeftPixel": "gr"}}
        model, bits = "ILLUM", 10
    return {
        "type": "lightField",
        "image": {"width": width, "height": height, "orientation": 1,
                  "representation": "rawPacked", **raw,
                  "color": {"whiteBalanceGain": {"r": 1.25, "gr": 1.0, "gb": 1.0, "b": 1.5}}},
        "devices": {
            "sensor": {"bitsPerPixel": bits, "pixelPitch": 1.4e-6},
            "lens": {"focalLength": 0.0064, "fNumber": 2.0, "zoomStep": 100, "focusStep": 200,
                     "exitPupilOffset": {"z": 0.05}, "infinityLambda": 7},
            "mla": {"tiling": "hexUniformRowMajor", "lensPitch": 1.4e-5, "rotation": 0.001,
                    "scaleFactor": {"x": 1, "y": 1.0005},
                    "sensorOffset": {"x": -2e-6, "y": 5e-7, "z": 2.5e-5}},
        },
        "camera": {"make": "Lytro, Inc.", "model": model, "firmware": "test"},
    }
