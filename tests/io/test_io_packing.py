"""Packed raw layouts: our vectorised unpackers against an independent per-pixel packer."""

import numpy as np
import pytest
from io_testlib import ref_pack_bits

from lfcam.errors import RawDataError
from lfcam.io.packing import (
    pack_10bit_le,
    pack_12bit_be,
    unpack,
    unpack_10bit_le,
    unpack_12bit_be,
)


def test_12bit_hand_example():
    # 0xABC, 0x123 → AB C1 23 (big-endian nibble order)
    assert ref_pack_bits([0xABC, 0x123], 12, True) == bytes([0xAB, 0xC1, 0x23])
    img = unpack_12bit_be(bytes([0xAB, 0xC1, 0x23]), 2, 1)
    assert img.tolist() == [[0xABC, 0x123]]


def test_10bit_hand_example():
    # 1023, 0, 512, 3 → high bytes FF 00 80 00; low bits 3 (pixel 0) and 3<<6 (pixel 3)
    raw = bytes([0xFF, 0x00, 0x80, 0x00, 0xC3])
    assert ref_pack_bits([1023, 0, 512, 3], 10, False) == raw
    assert unpack_10bit_le(raw, 4, 1).tolist() == [[1023, 0, 512, 3]]


@pytest.mark.parametrize("shape", [(6, 8), (5, 12), (1, 4), (3, 20)])
def test_12bit_random_against_reference(shape):
    rng = np.random.default_rng(sum(shape))
    img = rng.integers(0, 4096, size=shape, dtype=np.uint16)
    buf = ref_pack_bits(img, 12, True)
    out = unpack_12bit_be(buf, shape[1], shape[0])
    assert out.dtype == np.uint16 and out.shape == shape
    np.testing.assert_array_equal(out, img)
    assert pack_12bit_be(img) == buf


@pytest.mark.parametrize("shape", [(6, 8), (5, 12), (1, 4), (4, 5)])
def test_10bit_random_against_reference(shape):
    rng = np.random.default_rng(7 + sum(shape))
    img = rng.integers(0, 1024, size=shape, dtype=np.uint16)
    buf = ref_pack_bits(img, 10, False)
    out = unpack_10bit_le(buf, shape[1], shape[0])
    np.testing.assert_array_equal(out, img)
    assert pack_10bit_le(img) == buf


def test_extremes_every_bit():
    # each single bit set once: catches any swapped or dropped bit position
    for bits, big, fn in ((12, True, unpack_12bit_be), (10, False, unpack_10bit_le)):
        vals = np.array([1 << k for k in range(bits)] + [0, (1 << bits) - 1], dtype=np.uint16)
        vals = np.concatenate([vals, vals[::-1]])[: (len(vals) * 2 // 4) * 4]
        img = vals.reshape(1, -1)
        np.testing.assert_array_equal(fn(ref_pack_bits(img, bits, big), img.shape[1], 1), img)


def test_16bit_endianness():
    img = np.array([[1, 258, 65535, 4096]], dtype=np.uint16)
    np.testing.assert_array_equal(unpack(img.astype(">u2").tobytes(), 4, 1, 16, "big"), img)
    np.testing.assert_array_equal(unpack(img.astype("<u2").tobytes(), 4, 1, 16, "little"), img)


@pytest.mark.parametrize(
    "args",
    [
        (b"\0" * 5, 2, 2, 12, "big"),          # buffer too short (needs 6)
        (b"\0" * 7, 2, 2, 12, "big"),          # too long
        (b"\0" * 6, 4, 2, 10, "little"),       # 10-bit 4x2 needs 10 bytes
        (b"\0" * 6, 0, 4, 12, "big"),          # zero width
        (b"\0" * 6, 200_000, 1, 12, "big"),    # absurd width
        (b"\0" * 6, 2, 2, 14, "big"),          # unsupported depth
        (b"\0" * 6, 2, 2, 12, "little"),       # wrong endianness for 12-bit
        (b"\0" * 6, 3, 1, 10, "little"),       # 10-bit count not divisible by 4
        (b"\0" * 6, 2.0, 2, 12, "big"),        # non-integer width
    ],
)
def test_bad_buffers_raise_rawdataerror(args):
    with pytest.raises(RawDataError):
        unpack(*args)


def test_pack_rejects_out_of_range():
    with pytest.raises(RawDataError):
        pack_10bit_le(np.full((1, 4), 1024, dtype=np.uint16))
    with pytest.raises(RawDataError):
        pack_12bit_be(np.zeros((2, 2, 2), dtype=np.uint16))
