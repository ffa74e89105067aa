"""load_capture dispatch: bare .raw + sidecar, camera raw (synthetic DNG via rawpy), PNG/TIFF."""

import json

import cv2
import numpy as np
import pytest
import tifffile
from io_testlib import ref_pack_bits, small_frame_meta

from lfcam.camera import load_profile
from lfcam.errors import (
    MetadataError,
    RawDataError,
    UnsupportedFormatError,
)
from lfcam.io import load_capture


def test_bare_raw_real_f01_sidecar(tmp_path, realdata):
    # the real F01 frame metadata, unmodified, as sidecar of a synthetic 3280x3280 raw
    meta = (realdata / "f01-IMG_0001__frame.json").read_bytes()
    img = np.random.default_rng(3).integers(0, 4096, size=(3280, 3280), dtype=np.uint16)
    (tmp_path / "IMG_0001.json").write_bytes(meta)
    p = tmp_path / "IMG_0001.raw"
    # vectorised form of the reference layout (the per-pixel packer is too slow at 10.8 Mpx)
    a, b = img[:, 0::2].astype(np.uint32), img[:, 1::2].astype(np.uint32)
    packed = np.stack([a >> 4, ((a & 15) << 4) | (b >> 8), b & 255], axis=-1).astype(np.uint8)
    assert packed[0, :2].tobytes() == ref_pack_bits(img[0, :4], 12, True)
    p.write_bytes(packed.tobytes())
    cap = load_capture(p)
    assert cap.source_kind == "lytro-raw" and cap.bayer == "BGGR"
    assert (cap.black_level, cap.white_level) == (168, 4095)
    np.testing.assert_array_equal(cap.raw, img)


def test_bare_raw_illum_caldata_sidecar(tmp_path, realdata):
    doc = json.loads((realdata / "illum-whiteimage-metadata.TXT").read_text())
    fm = doc["master"]["picture"]["frameArray"][0]["frame"]["metadata"]["image"]
    fm["width"], fm["height"] = 16, 6  # a small frame with the real key layout
    (tmp_path / "MOD_0000.TXT").write_text(json.dumps(doc))
    img = np.random.default_rng(4).integers(0, 1024, size=(6, 16), dtype=np.uint16)
    (tmp_path / "MOD_0000.RAW").write_bytes(ref_pack_bits(img, 10, False))
    cap = load_capture(tmp_path / "MOD_0000.RAW")
    assert cap.bayer == "GRBG" and cap.black_level == 64
    assert cap.metadata["privateMetadata"]["camera"]["serialNumber"] == "B5143909630"
    np.testing.assert_array_equal(cap.raw, img)


def test_bare_raw_errors(tmp_path):
    p = tmp_path / "a.raw"
    p.write_bytes(b"\0" * 48)
    with pytest.raises(MetadataError, match="without metadata"):
        load_capture(p)
    (tmp_path / "a.json").write_text(json.dumps(small_frame_meta(8, 6)))
    with pytest.raises(RawDataError, match="needs 72"):
        load_capture(p)
    (tmp_path / "a.json").write_bytes(b"{\"image\": \xff}")
    with pytest.raises(MetadataError, match="UTF-8"):
        load_capture(p)
    (tmp_path / "a.json").write_text('{"image": {}, "devices": {}}')
    with pytest.raises(MetadataError, match="missing key image.width"):
        load_capture(p)


def _dng(path, img, cfa=(0, 1, 1, 2), black=64, white=4095):
    tags = [
        (254, "I", 1, 0, True),
        (33421, "H", 2, (2, 2), True),        # CFARepeatPatternDim
        (33422, "B", 4, cfa, True),           # CFAPattern (0=R, 1=G, 2=B)
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50708, "s", 0, "lfcam synthetic", True),
        (50714, "H", 1, (black,), True),      # BlackLevel
        (50717, "H", 1, (white,), True),      # WhiteLevel
        (50721, "2i", 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 1, 1, 0, 1), True),
    ]
    tifffile.imwrite(path, img, photometric=32803, extratags=tags)


@pytest.mark.parametrize("cfa,name", [((0, 1, 1, 2), "RGGB"), ((1, 0, 2, 1), "GRBG"),
                                      ((2, 1, 1, 0), "BGGR")])
def test_camera_raw_synthetic_dng(tmp_path, cfa, name):
    img = np.random.default_rng(5).integers(100, 4000, size=(32, 48), dtype=np.uint16)
    p = tmp_path / "shot.dng"
    _dng(p, img, cfa, black=72, white=4000)
    cap = load_capture(p)
    assert cap.source_kind == "camera-raw" and cap.bayer == name
    assert (cap.black_level, cap.white_level) == (72, 4000)
    np.testing.assert_array_equal(cap.raw, img)


def test_dng_dispatch_by_content(tmp_path):
    img = np.random.default_rng(6).integers(0, 4000, size=(32, 32), dtype=np.uint16)
    p = tmp_path / "shot.tif"  # a DNG with a .tif name is still read as a camera raw
    _dng(p, img)
    assert load_capture(p).source_kind == "camera-raw"


def test_damaged_camera_raw(tmp_path):
    p = tmp_path / "broken.nef"
    p.write_bytes(b"II*\x00" + b"\x00" * 60)
    with pytest.raises(UnsupportedFormatError, match="LibRaw"):
        load_capture(p)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_png(tmp_path, dtype):
    img = np.random.default_rng(7).integers(0, np.iinfo(dtype).max, size=(10, 14), dtype=dtype)
    p = tmp_path / "a.png"
    cv2.imwrite(str(p), img)
    cap = load_capture(p)
    assert cap.source_kind == "png" and cap.bayer == "none"
    assert cap.white_level == np.iinfo(dtype).max
    np.testing.assert_array_equal(cap.raw, img)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_tiff(tmp_path, dtype):
    img = (np.random.default_rng(8).random((9, 11)) * 200).astype(dtype)
    p = tmp_path / "a.tiff"
    tifffile.imwrite(p, img)
    cap = load_capture(p)
    assert cap.source_kind == "tiff"
    np.testing.assert_array_equal(cap.raw, img)


def test_tiff_with_profile(tmp_path):
    prof = load_profile("system1")
    s = prof.sensor
    img = np.zeros((s.height_px, s.width_px), dtype=np.uint16)
    p = tmp_path / "a.tiff"
    tifffile.imwrite(p, img)
    cap = load_capture(p, profile=prof)
    assert cap.profile is prof and cap.bayer == s.bayer and cap.white_level == s.white_level
    tifffile.imwrite(p, img[:-1])
    with pytest.raises(RawDataError, match="sensor"):
        load_capture(p, profile=prof)


def test_raster_errors(tmp_path):
    p = tmp_path / "rgb.png"
    cv2.imwrite(str(p), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(RawDataError, match="single-channel"):
        load_capture(p)
    q = tmp_path / "nan.tiff"
    tifffile.imwrite(q, np.full((3, 3), np.nan, np.float32))
    with pytest.raises(RawDataError, match="NaN"):
        load_capture(q)
    r = tmp_path / "trunc.png"
    r.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 10)
    with pytest.raises(UnsupportedFormatError):
        load_capture(r)


def test_unknown_format(tmp_path):
    p = tmp_path / "x.bin"
    p.write_bytes(b"hello world")
    with pytest.raises(UnsupportedFormatError, match="unsupported"):
        load_capture(p)
