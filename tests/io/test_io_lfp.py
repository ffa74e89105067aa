"""LFP container: round trip, layout checks, and every documented damage case."""

import hashlib
import json
import struct

import numpy as np
import pytest
from io_testlib import ref_pack_bits, small_frame_meta

from lfcam.errors import (
    ChecksumError,
    ContainerError,
    MetadataError,
    NoRawFrameError,
    RawDataError,
    TruncatedFileError,
)
from lfcam.io import load_capture, read_lfp, write_lfp
from lfcam.io.lfp import ChecksumWarning


def _img(shape, bits, seed=0):
    return np.random.default_rng(seed).integers(0, 1 << bits, size=shape, dtype=np.uint16)


@pytest.mark.parametrize("packing,bits", [("12bit", 12), ("10bit", 10)])
def test_round_trip_pixels_and_metadata(tmp_path, packing, bits):
    img = _img((12, 16), bits)
    white = _img((12, 16), bits, seed=1)
    meta = small_frame_meta(16, 12, packing)
    priv = {"camera": {"serialNumber": "X123"}}
    f = write_lfp(tmp_path / "a.lfp", img, meta, packing=packing, private_metadata=priv,
                  white_image=white)
    c = read_lfp(f)
    np.testing.assert_array_equal(c.raw_image(), img)
    np.testing.assert_array_equal(c.raw_image(c.white_frame), white)
    lf = c.light_field_frame
    assert lf.metadata == json.loads(json.dumps(meta))  # every given key, unchanged
    assert lf.private_metadata == priv
    # the packed section is exactly the independent packer's bytes, named by its sha1
    ref = ref_pack_bits(img, bits, packing == "12bit")
    assert c.section_bytes(lf.image_ref) == ref
    assert lf.image_ref == "sha1-" + hashlib.sha1(ref).hexdigest()
    # rewriting what we read gives a byte-identical file
    g = write_lfp(tmp_path / "b.lfp", c.raw_image(), lf.metadata, packing=packing,
                  private_metadata=lf.private_metadata, white_image=white,
                  white_metadata=c.white_frame.metadata)
    assert f.read_bytes() == g.read_bytes()


def test_layout_alignment_and_header(tmp_path):
    f = write_lfp(tmp_path / "a.lfp", _img((3, 6), 12), small_frame_meta(6, 3))
    data = f.read_bytes()
    assert data[:16] == b"\x89LFP\r\n\x1a\n" + struct.pack(">II", 1, 0)
    c = read_lfp(f)
    assert [s.kind for s in c.sections] == ["LFM", "LFM", "LFM", "LFC"]
    for s in c.sections:  # each section header starts on a 16-byte boundary
        assert (s.offset - 96) % 16 == 0
    assert len(data) % 16 == 0


def test_capture_from_written_lfp(tmp_path):
    img = _img((4, 8), 10)
    f = write_lfp(tmp_path / "x.lfr", img, small_frame_meta(8, 4, "10bit"), packing="10bit")
    cap = load_capture(f)
    assert cap.source_kind == "lytro-lfp"
    assert cap.bayer == "GRBG" and cap.black_level == 64 and cap.white_level == 1023
    assert cap.white_balance == (1.0, 1.25, 1.5, 1.0)  # G R B G order of GRBG
    np.testing.assert_array_equal(cap.raw, img)
    assert not cap.raw.flags.writeable


def test_dispatch_by_content_not_extension(tmp_path):
    img = _img((2, 4), 12)
    f = write_lfp(tmp_path / "capture.png", img, small_frame_meta(4, 2))
    assert load_capture(f).source_kind == "lytro-lfp"


# ----------------------------------------------------------------------------- damage


@pytest.fixture
def good(tmp_path):
    return write_lfp(tmp_path / "good.lfp", _img((4, 8), 12), small_frame_meta(8, 4))


def _write(tmp_path, data, name="bad.lfp"):
    p = tmp_path / name
    p.write_bytes(data)
    return p


def test_wrong_magic(tmp_path, good):
    data = bytearray(good.read_bytes())
    data[1:4] = b"XYZ"
    with pytest.raises(ContainerError, match="magic"):
        read_lfp(_write(tmp_path, bytes(data)))


@pytest.mark.parametrize("cut", [10, 20, 150, -7])
def test_truncated(tmp_path, good, cut):
    data = good.read_bytes()
    with pytest.raises(TruncatedFileError):
        read_lfp(_write(tmp_path, data[:cut]))


def test_length_larger_than_file(tmp_path, good):
    data = bytearray(good.read_bytes())
    data[16 + 12 : 16 + 16] = struct.pack(">I", 0xFFFFFFF0)
    with pytest.raises(TruncatedFileError, match="announces"):
        read_lfp(_write(tmp_path, bytes(data)))


def test_header_length_larger_than_file(tmp_path, good):
    data = bytearray(good.read_bytes())
    data[12:16] = struct.pack(">I", 1 << 31)
    with pytest.raises(ContainerError, match="header length"):
        read_lfp(_write(tmp_path, bytes(data)))


def test_sha1_mismatch_error_and_warning(tmp_path, good):
    data = bytearray(good.read_bytes())
    c = read_lfp(good)
    s = c.sections[-1]
    data[s.offset] ^= 0x01
    bad = _write(tmp_path, bytes(data))
    with pytest.raises(ChecksumError, match="sha1 mismatch"):
        read_lfp(bad)
    with pytest.warns(ChecksumWarning):
        c2 = read_lfp(bad, verify="warn")
    assert c2.checksum_failures == (s.name,)
    assert int(c2.raw_image()[0, 0]) != int(c.raw_image()[0, 0])


def _rebuild(tmp_path, master: bytes | None = None, frame_meta: bytes | None = None,
             image: bytes | None = None):
    """A container assembled by hand (independent of write_lfp) from raw section payloads."""
    def sec(magic, payload):
        name = ("sha1-" + hashlib.sha1(payload).hexdigest()).encode().ljust(80, b"\0")
        body = magic + struct.pack(">II", 0, len(payload)) + name + payload
        return name.rstrip(b"\0").decode(), body + b"\0" * (-len(body) % 16)

    fm = frame_meta if frame_meta is not None else json.dumps(small_frame_meta(8, 4)).encode()
    im = image if image is not None else ref_pack_bits(_img((4, 8), 12), 12, True)
    mname, mblob = sec(b"\x89LFM\r\n\x1a\n", fm)
    iname, iblob = sec(b"\x89LFC\r\n\x1a\n", im)
    if master is None:
        master = json.dumps({"picture": {"frameArray": [
            {"frame": {"metadataRef": mname, "imageRef": iname}}]}}).encode()
    _, master_blob = sec(b"\x89LFM\r\n\x1a\n", master)
    data = b"\x89LFP\r\n\x1a\n" + struct.pack(">II", 1, 0) + master_blob + mblob + iblob
    return _write(tmp_path, data)


def test_hand_built_container_reads(tmp_path):
    f = _rebuild(tmp_path)
    np.testing.assert_array_equal(read_lfp(f).raw_image(), _img((4, 8), 12))


def test_non_utf8_metadata(tmp_path):
    with pytest.raises(MetadataError, match="UTF-8"):
        read_lfp(_rebuild(tmp_path, frame_meta=b'{"a": "\xff\xfe"}'))


def test_malformed_json(tmp_path):
    with pytest.raises(MetadataError, match="malformed"):
        read_lfp(_rebuild(tmp_path, master=b'{"picture": [1, 2'))


def test_deeply_nested_json(tmp_path):
    with pytest.raises(MetadataError):
        read_lfp(_rebuild(tmp_path, master=b"[" * 100000 + b"]" * 100000))


def test_missing_key(tmp_path):
    meta = small_frame_meta(8, 4)
    del meta["image"]["rawDetails"]["pixelPacking"]["bitsPerPixel"]
    f = _rebuild(tmp_path, frame_meta=json.dumps(meta).encode())
    with pytest.raises(MetadataError, match="bitsPerPixel"):
        load_capture(f)


def test_wrong_type_key(tmp_path):
    meta = small_frame_meta(8, 4)
    meta["image"]["width"] = "8"
    with pytest.raises(MetadataError, match="image.width"):
        load_capture(_rebuild(tmp_path, frame_meta=json.dumps(meta).encode()))


def test_absurd_dimensions(tmp_path):
    meta = small_frame_meta(8, 4)
    meta["image"]["width"] = 10**9
    with pytest.raises(RawDataError, match="absurd"):
        load_capture(_rebuild(tmp_path, frame_meta=json.dumps(meta).encode()))


def test_wrong_buffer_size(tmp_path):
    meta = small_frame_meta(8, 6)  # claims 6 rows, the buffer holds 4
    with pytest.raises(RawDataError, match="bad.lfp: raw frame .* need 72"):
        load_capture(_rebuild(tmp_path, frame_meta=json.dumps(meta).encode()))


def test_no_raw_frame_is_clear(tmp_path):
    master = json.dumps({"picture": {"frameArray": [
        {"frame": {"metadataRef": "sha1-" + "0" * 40, "imageRef": "sha1-" + "1" * 40}}]}})
    f = _rebuild(tmp_path, master=master.encode())
    c = read_lfp(f)
    assert not c.has_raw
    with pytest.raises(NoRawFrameError, match="no raw sensor frame"):
        load_capture(f)
