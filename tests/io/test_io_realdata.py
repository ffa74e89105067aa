"""The real Lytro files in ../shared/realdata/lytro (skipped when absent)."""

import json

import pytest

from lfcam.errors import NoRawFrameError
from lfcam.io import load_capture, lytro_camera, raw_format, read_lfp
from lfcam.io.lytro_meta import sidecar_frame

# section counts and content read off the files by hand (hexdump) — see docs/loaders.md
EXPECTED = {
    "IMG_0001-stk.lfp": (14, None),
    "IMG_0002-stk.lfp": (4, None),
    "IMG_0002-dm.lfp": (3, None),
    "illum-demo.LFP": (12, "ILLUM"),
}


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_real_containers(realdata, name):
    n_sections, model = EXPECTED[name]
    c = read_lfp(realdata / name)  # verify="error": every sha1 must match
    assert len(c.sections) == n_sections
    assert c.sections[0].kind == "LFM"
    assert all(s.kind == "LFC" for s in c.sections[1:])
    assert not c.has_raw
    assert c.camera_metadata.get("camera", {}).get("model") == model
    with pytest.raises(NoRawFrameError, match="processed Lytro picture"):
        load_capture(realdata / name)


def test_f01_processed_references_absent_raw(realdata):
    c = read_lfp(realdata / "IMG_0001-stk.lfp")
    (fr,) = c.frames
    assert fr.image_ref == "sha1-06ae44216bf153a76fdf80ba48794c2d0d8b740b"
    assert not fr.has_image and fr.metadata == {}
    depth = c.master["picture"]["accelerationArray"][0]["vendorContent"]["depthLut"]
    assert c.section(depth["imageRef"]).length == 20 * 20 * 4  # float32 depth table


def test_illum_demo_optics(realdata):
    c = read_lfp(realdata / "illum-demo.LFP")
    fr = c.frames[0]
    cam = lytro_camera(fr.metadata, fr.private_metadata)
    o = cam.optics
    assert o.camera_model == "ILLUM" and o.serial == "45142500380"
    assert o.zoom_step == 123 and o.focus_step == 814
    assert o.focal_length_mm == pytest.approx(13.886307535794439, rel=1e-12)
    assert o.f_number == pytest.approx(2.0818971196935840418, rel=1e-12)
    assert o.exit_pupil_offset_mm == float("inf")  # file says 10000 m: the sentinel
    assert cam.mla.pitch_mm == pytest.approx(0.020, rel=1e-12)
    assert cam.mla.grid == "hex"
    assert cam.mla.rotation_rad == pytest.approx(-0.00085581338498741388321, rel=1e-12)
    assert cam.mla.offset_mm == pytest.approx((1.44067382812e-3, 6.26103496551e-3), rel=1e-9)
    assert cam.mla_separation_mm == pytest.approx(0.037, rel=1e-12)
    s = cam.sensor
    assert (s.width_px, s.height_px, s.pixel_pitch_mm) == (7728, 5368, pytest.approx(0.0014))
    assert (s.bayer, s.bit_depth, s.black_level, s.white_level) == ("GRBG", 10, 64, 1023)


def test_f01_frame_json(realdata):
    meta = json.loads((realdata / "f01-IMG_0001__frame.json").read_text())
    fmt = raw_format(meta)
    assert (fmt.width_px, fmt.height_px, fmt.bits_per_pixel, fmt.endianness) == (
        3280, 3280, 12, "big")
    assert fmt.bayer == "BGGR"  # tile r,gr:gb,b with upper-left pixel b
    assert fmt.black_level == 168 and fmt.white_level == 4095
    assert fmt.white_balance["b"] == pytest.approx(1.72265625)
    cam = lytro_camera(meta)
    assert cam.optics.camera_model == "F01"
    assert cam.optics.focal_length_mm == pytest.approx(6.4499998092651363, rel=1e-12)
    assert cam.optics.f_number == pytest.approx(1.9099999666213989, rel=1e-12)
    assert (cam.optics.zoom_step, cam.optics.focus_step) == (981, 582)
    assert cam.mla.pitch_mm == pytest.approx(0.01389859962463379, rel=1e-12)
    assert cam.sensor.pixel_pitch_mm == pytest.approx(0.0013999999761581417, rel=1e-12)
    assert cam.mla_separation_mm == pytest.approx(0.025, rel=1e-12)
    assert cam.mla_scale_factor == (1.0, pytest.approx(1.0004994869232178))


def test_illum_white_image_metadata(realdata):
    doc = json.loads((realdata / "illum-whiteimage-metadata.TXT").read_text())
    meta, priv = sidecar_frame(doc)
    cam = lytro_camera(meta, priv)
    assert cam.optics.camera_model == "B01" and cam.optics.serial == "B5143909630"
    assert (cam.optics.zoom_step, cam.optics.focus_step) == (-1040, -300)
    assert cam.optics.exit_pupil_offset_mm == pytest.approx(46.048875898122787, rel=1e-12)
    assert cam.optics.focal_length_mm == pytest.approx(77.59365439414978, rel=1e-12)
    fmt = raw_format(meta)  # F01-style rawDetails layout inside an Illum caldata file
    assert (fmt.bits_per_pixel, fmt.endianness, fmt.bayer) == (10, "little", "GRBG")
