"""The Lytro route: camera metadata → camera profile, and rendered captures written as LFR.

Truth: the numbers written in real Lytro metadata (F01 frame JSON, Illum processed picture,
Illum caldata white-frame metadata), and an independent paraxial y–nu trace of the lens.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from lfcam.camera import load_profile, profile_from_dict
from lfcam.io import load_capture
from lfcam.io import lytro_meta as lm
from lfcam.io.lfp import merged_metadata, read_lfp
from lfcam.io.profiles import profile_for_capture
from lfcam.sim.capture import profile_to_dict, simulate
from lfcam.sim.lytro import lytro_metadata, write_lytro_capture
from lfcam.sim.scene import scene_from_dict

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata" / "lytro"


@pytest.fixture
def realdata() -> Path:
    if not REALDATA.is_dir():
        pytest.skip(f"real Lytro files not present at {REALDATA}")
    return REALDATA


def test_profile_dict_from_real_f01(realdata):
    meta = json.loads((realdata / "f01-IMG_0001__frame.json").read_text())
    d = lm.profile_dict_from_lytro(lm.lytro_camera(meta))
    # devices.lens.focalLength 0.0064499998092651363 m, fNumber 1.9099999666213989,
    # exitPupilOffset.z 10000 (the "infinity" sentinel: no exit pupil key)
    assert d["main_lens"] == pytest.approx({"focal_length_mm": 6.4499998092651363,
                                            "f_number": 1.9099999666213989})
    assert d["name"] == "lytro-f01-zoom981-focus582"
    assert d["mla"]["pitch_mm"] == pytest.approx(1.389859962463379e-02, rel=1e-12)
    assert d["mla"]["grid"] == "hex"
    assert d["mla"]["rotation_rad"] == pytest.approx(0.0019290975760668516, rel=1e-12)
    s = d["sensor"]
    assert (s["width_px"], s["height_px"], s["bit_depth"], s["bayer"]) == (3280, 3280, 12, "BGGR")
    assert (s["black_level"], s["white_level"]) == (168, 4095)
    assert s["pixel_pitch_mm"] == pytest.approx(1.3999999761581417e-03, rel=1e-12)


def test_profile_dict_from_real_illum_picture(realdata):
    merged = merged_metadata(read_lfp(realdata / "illum-demo.LFP"))
    d = lm.profile_dict_from_lytro(lm.lytro_camera(merged["frame"], merged["privateMetadata"]))
    assert d["main_lens"] == pytest.approx({"focal_length_mm": 13.886307535794439,
                                            "f_number": 2.081897119693584})
    assert d["name"] == "lytro-illum-zoom123-focus814"
    m = d["mla"]
    assert (m["grid"], m["pitch_mm"], m["focal_length_mm"]) == ("hex", pytest.approx(0.02),
                                                                 pytest.approx(0.037))
    assert m["offset_mm"] == pytest.approx([1.440673828125e-03, 6.261034965515137e-03])
    s = d["sensor"]
    assert (s["width_px"], s["height_px"], s["bit_depth"], s["bayer"]) == (7728, 5368, 10, "GRBG")
    assert (s["black_level"], s["white_level"]) == (64, 1023)


def test_profile_dict_from_real_illum_white_keeps_exit_pupil(realdata):
    doc = json.loads((realdata / "illum-whiteimage-metadata.TXT").read_text())
    meta, priv = lm.sidecar_frame(doc)
    lens = meta["devices"]["lens"]
    d = lm.profile_dict_from_lytro(lm.lytro_camera(meta, priv))
    # a finite exitPupilOffset (metres) becomes the black box's exit pupil → MLA distance
    assert math.isfinite(lens["exitPupilOffset"]["z"]) and lens["exitPupilOffset"]["z"] < 1.0
    assert d["main_lens"]["exit_pupil_mm"] == pytest.approx(lens["exitPupilOffset"]["z"] * 1e3,
                                                            rel=1e-12)
    assert d["main_lens"]["focal_length_mm"] == pytest.approx(lens["focalLength"] * 1e3,
                                                              rel=1e-12)


def _ynu_efl_and_epd(rows: list[dict]) -> tuple[float, float]:
    """EFL and entrance-pupil diameter by a hand-written paraxial y–nu trace (test's own)."""
    def trace(y, u):  # through every surface; returns heights at surfaces, final angle
        n, ys = 1.0, []
        for r in rows:
            c = 0.0 if math.isinf(r["radius_mm"]) else 1.0 / r["radius_mm"]
            n2 = r["refractive_index"]
            ys.append(y)
            u = (n * u - y * (n2 - n) * c) / n2
            n = n2
            y = y + r["thickness_mm"] * u
        return ys, u
    _, u_out = trace(1.0, 0.0)
    efl = -1.0 / u_out
    stop = next(k for k, r in enumerate(rows) if r.get("stop"))
    ys, _ = trace(1.0, 0.0)  # marginal ray height at the stop per unit entrance height
    epd = 2.0 * rows[stop]["semi_diameter_mm"] / abs(ys[stop])
    return efl, epd


def _illum_like(width_px: int = 160, height_px: int = 120) -> object:
    """The shipped double Gauss with an Illum-like MLA and sensor (hex, 10 bit, RGGB)."""
    d = profile_to_dict(load_profile("double_gauss"))
    d["mla"] = {"focal_length_mm": 0.037, "pitch_mm": 0.02, "grid": "hex", "focus_mm": 1000.0,
                "rotation_rad": 0.002, "offset_mm": [0.003, -0.004]}
    d["sensor"] = {"pixel_pitch_mm": 0.0014, "width_px": width_px, "height_px": height_px,
                   "bit_depth": 10, "bayer": "RGGB", "black_level": 64, "white_level": 1023}
    return profile_from_dict(d)


def test_lytro_metadata_numbers_are_the_lens(tmp_path):
    prof = _illum_like()
    meta = lytro_metadata(prof, zoom_step=-297, focus_step=814)
    rows = profile_to_dict(load_profile("double_gauss"))["main_lens"]["surfaces"]
    efl, epd = _ynu_efl_and_epd(rows)
    lens = meta["devices"]["lens"]
    assert lens["focalLength"] == pytest.approx(efl * 1e-3, rel=1e-9)
    assert lens["fNumber"] == pytest.approx(efl / epd, rel=1e-9)
    assert 95.0 < efl < 105.0 and 3.5 < efl / epd < 4.5  # "f 100 mm, F/4" of the file
    # exit pupil → MLA: positive, shorter than the back focal distance + gap of the layout
    assert 0.0 < lens["exitPupilOffset"]["z"] < 0.2
    assert meta["devices"]["mla"]["sensorOffset"] == pytest.approx(
        {"x": 3e-6, "y": -4e-6, "z": 3.7e-5})


def test_rendered_lfr_round_trip(tmp_path):
    prof = _illum_like()
    raw, used, _ = simulate(prof, scene_from_dict({
        "seed": 5, "rays_per_source": 20_000, "sensor": {"photon_noise": True},
        "objects": [{"type": "point", "distance_mm": 600, "offset_mm": 0.4}]}))
    assert raw.max() <= 1023 and raw.min() >= 64
    path = write_lytro_capture(tmp_path / "scene.lfr", raw, used, zoom_step=-297)
    cap = load_capture(path)
    assert cap.source_kind == "lytro-lfp" and cap.bayer == "RGGB"
    assert (cap.black_level, cap.white_level) == (64.0, 1023.0)
    np.testing.assert_array_equal(cap.raw, raw)
    # the metadata read back describes the rendering camera
    cam = lm.lytro_camera(cap.metadata["frame"], cap.metadata["privateMetadata"])
    assert cam.mla.grid == "hex" and cam.mla.pitch_mm == pytest.approx(0.02)
    assert cam.mla.rotation_rad == pytest.approx(0.002)
    assert cam.mla_separation_mm == pytest.approx(0.037)
    assert cam.sensor.pixel_pitch_mm == pytest.approx(0.0014)
    assert cam.optics.zoom_step == -297
    assert cam.optics.focal_length_mm == pytest.approx(used.main_lens.focal_length_mm, rel=1e-12)
    assert cam.optics.exit_pupil_offset_mm == pytest.approx(
        used.mla_z_mm - used.main_lens.exit_pupil_z_mm, rel=1e-12)
    # no --profile and no sidecar: the camera comes from the metadata, the lens as a black box
    got = profile_for_capture(path, None)
    assert got.main_lens.focal_length_mm == pytest.approx(used.main_lens.focal_length_mm,
                                                          rel=1e-9)
    assert got.main_lens.f_number == pytest.approx(used.main_lens.f_number, rel=1e-9)
    assert got.mla.distance_mm is None and got.mla.focus_mm is None  # the calibration's job
    assert (got.mla.grid, got.mla.pitch_mm, got.mla.focal_length_mm) == (
        "hex", pytest.approx(0.02), pytest.approx(0.037))
    # (a Lytro container holds no full well: the simulator's profile states the one it drew
    # photon noise with, the metadata's profile none)
    assert got.sensor.full_well_e is None and used.sensor.full_well_e is not None
    assert got.sensor == replace(used.sensor, full_well_e=None)


def test_lytro_writer_refuses_what_lytro_cannot_hold(tmp_path):
    from lfcam.errors import SceneError

    prof = load_profile("double_gauss")  # rect grid, 16 bit
    with pytest.raises(SceneError, match="10- or 12-bit"):
        lytro_metadata(prof)
    d = profile_to_dict(_illum_like())
    d["mla"]["grid"] = "rect"
    with pytest.raises(SceneError, match="hexagonal"):
        lytro_metadata(profile_from_dict(d))


def test_calibrate_targets_without_profile_needs_one_unless_lytro(tmp_path, capsys):
    import cv2

    from lfcam.cli.main import main

    cv2.imwrite(str(tmp_path / "white.png"), np.full((32, 32), 1000, np.uint16))
    (tmp_path / "targets.csv").write_text("capture,distance_mm\nwhite.png,500\n")
    code = main(["calibrate", str(tmp_path / "white.png"), "--targets",
                 str(tmp_path / "targets.csv"), "-o", str(tmp_path / "c.json")])
    assert code == 1
    assert "--targets needs --profile" in capsys.readouterr().err
    assert not (tmp_path / "c.json").exists()
