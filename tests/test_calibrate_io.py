"""Calibration file round trip, validation, CLI, real microscope frames, d_in solver."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from lfcam.calibrate import calibrate_white, load_calibration, save_calibration
from lfcam.calibrate.model import CALIBRATION_TABLES
from lfcam.calibrate.synthetic import make_white
from lfcam.cli.main import main
from lfcam.errors import CalibrationError
from lfcam.io import load_capture
from lfcam.validate import parse_json_bytes

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "realdata" / "microscope"
REAL = REAL if REAL.is_dir() else Path("/work/shared/realdata/microscope")


@pytest.fixture(scope="module")
def small_cal():
    sw = make_white(320, 240, 15.0, offset_px=(160.3, 120.6))
    return calibrate_white(sw.image)


def test_round_trip(tmp_path, small_cal):
    p = save_calibration(small_cal.with_d_in(104.7, "test"), tmp_path / "c.json")
    back = load_calibration(p)
    assert back.grid == small_cal.grid and back.n_lenses == small_cal.n_lenses
    assert np.abs(back.centres_px - small_cal.centres_px).max() <= 5e-6
    assert back.d_in_mm == 104.7
    assert abs(back.residual_rms_px - small_cal.residual_rms_px) < 1e-12
    assert not back.centres_px.flags.writeable


@pytest.mark.parametrize("edit,msg", [
    (lambda d: d.pop("pitch_px"), "pitch_px"),
    (lambda d: d.update(grid="tri"), "grid"),
    (lambda d: d.update(centres_px=d["centres_px"][:-1]), "indices"),
    (lambda d: d.update(pitch_px=-1), "positive"),
    (lambda d: d.update(lattice_matrix=[[1, 0], [0, 1]]), "lattice_matrix"),
    (lambda d: d.update(white_sha256="xyz"), "sha256"),
    (lambda d: d.update(format="other"), "format"),
    (lambda d: d["indices"].__setitem__(5, d["indices"][2]), "share one lattice index"),
])
def test_invalid_files(tmp_path, small_cal, edit, msg):
    p = save_calibration(small_cal, tmp_path / "c.json")
    d = json.loads(p.read_text())
    edit(d)
    p.write_text(json.dumps(d))
    with pytest.raises(CalibrationError, match=msg):
        load_calibration(p)


def _compact(d: dict) -> str:
    return json.dumps(d, separators=(",", ":"))


def test_tables_read_by_numpy_equal_json(tmp_path, small_cal):
    """The numeric tables of a calibration file, read by numpy, are the values ``json.loads``
    reads, to the bit; the rest of the file is the same mapping."""
    p = save_calibration(small_cal.with_d_in(104.7, "test"), tmp_path / "c.json")
    raw = p.read_bytes()
    fast = parse_json_bytes(raw, CalibrationError, "c", tables=CALIBRATION_TABLES)
    ref = json.loads(raw)
    for key in CALIBRATION_TABLES:
        assert isinstance(fast[key], np.ndarray)  # the numpy path ran
        assert np.array_equal(fast[key], np.array(ref[key], dtype=float))
    assert {k: v for k, v in fast.items() if k not in CALIBRATION_TABLES} == {
        k: v for k, v in ref.items() if k not in CALIBRATION_TABLES}
    # a key of that name inside a string, and the sentinel itself, change nothing
    d = dict(ref, diagnostics={"note": '"centres_px":[[1,2]] @lfcam-numeric-table'})
    p.write_text(_compact(d))
    back = load_calibration(p)
    assert np.array_equal(back.centres_px, np.array(ref["centres_px"]))


@pytest.mark.parametrize("edit,msg", [
    (lambda d: d["centres_px"].__setitem__(3, [1.0]), "centres_px"),  # ragged
    (lambda d: d["centres_px"].__setitem__(3, [1.0, 2.0, 3.0]), "centres_px"),
    (lambda d: d["indices"].__setitem__(3, [d["indices"][3][0], 0.5]), "integers"),
])
def test_malformed_compact_tables(tmp_path, small_cal, edit, msg):
    p = save_calibration(small_cal, tmp_path / "c.json")
    d = json.loads(p.read_text())
    edit(d)
    p.write_text(_compact(d))
    with pytest.raises(CalibrationError, match=msg):
        load_calibration(p)
    # an empty number in a compact table is not JSON, on either path
    p.write_text(_compact(json.loads(p.read_text()) | {"indices": [[0, 0]]}).replace(
        '"indices":[[0,0]]', '"indices":[[0,,0]]'))
    with pytest.raises(CalibrationError, match="JSON"):
        load_calibration(p)


def test_not_json(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text("{nope")
    with pytest.raises(CalibrationError, match="JSON"):
        load_calibration(p)


def test_cli(tmp_path, capsys):
    sw = make_white(300, 260, 14.0, grid="hex", offset_px=(150.2, 130.4), radius_frac=0.4,
                    vignetting=0.0)
    white = tmp_path / "white.png"
    cv2.imwrite(str(white), np.clip(sw.image * 60, 0, 65535).astype(np.uint16))
    out = tmp_path / "calib.json"
    assert main(["calibrate", str(white), "-o", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    cal = load_calibration(out)
    assert summary["grid"] == "hex" == cal.grid
    assert abs(cal.pitch_px - 14.0) < 1e-3
    assert len(cal.white_sha256) == 64
    assert main(["calibrate", str(tmp_path / "missing.png"), "-o", str(out)]) == 1
    assert "not found" in capsys.readouterr().err


def _fft_period(img: np.ndarray) -> float:
    """Independent pitch reference: row/column-averaged spectrum peak, zero-padded 16×."""
    periods = []
    for prof in (img.mean(axis=0), img.mean(axis=1)):
        prof = (prof - prof.mean()) * np.hanning(len(prof))
        n = 16 * len(prof)
        spec = np.abs(np.fft.rfft(prof, n))
        f = np.fft.rfftfreq(n)
        spec[f < 1 / 40] = 0
        periods.append(1 / f[np.argmax(spec)])
    return float(np.mean(periods))


@pytest.mark.skipif(not REAL.is_dir(), reason="real microscope data absent")
@pytest.mark.parametrize("folder,white,dark,nominal,shape", [
    ("guv", "Radiometry_GUVExperim1.tif", "DarkFrame_GUVExperim1.tif", 100 / 6.5, (28, 28)),
    ("seaurchin", "radiometry_frame.tif", "dark_frame.tif", 125 / 7.4, (119, 118)),
])
def test_real_microscope(folder, white, dark, nominal, shape):
    w = np.asarray(load_capture(REAL / folder / white).raw, np.float32)
    d = np.asarray(load_capture(REAL / folder / dark).raw, np.float32)
    cal = calibrate_white(w, d)
    assert cal.grid == "rect"
    ref = _fft_period(w - d)
    assert abs(cal.pitch_px - ref) / ref < 2e-3  # agrees with a detector-free period
    span = tuple(int(v) for v in np.ptp(cal.indices, axis=0) + 1)
    assert span == shape
    if folder == "guv":
        assert abs(cal.pitch_px - nominal) / nominal < 0.01
        assert cal.n_lenses == 28 * 28 and cal.residual_rms_px < 0.05
    else:  # 1.8 % above the unit-magnification nominal: the relay is not exactly 1:1
        assert 0.015 < (cal.pitch_px - nominal) / nominal < 0.021
        # dim, vignetted corners bend the centroid lattice radially: the radial term is
        # selected and halves the residual (projective alone: 0.33 px, corners 1.1 px)
        assert cal.model == "projective+radial"
        assert cal.residual_rms_px < 0.2


def test_radial_model_round_trip_and_validation(tmp_path, small_cal):
    from dataclasses import replace

    cal = replace(small_cal, model="projective+radial",
                  lattice_radial=(150.0, 130.0, -1e-3, 2e-4))
    p = save_calibration(cal, tmp_path / "r.json")
    back = load_calibration(p)
    assert back.lattice_radial == cal.lattice_radial
    np.testing.assert_allclose(back.predict(cal.indices), cal.predict(cal.indices), atol=1e-9)
    d = json.loads(p.read_text())
    d["lattice_radial"] = None
    p.write_text(json.dumps(d))
    with pytest.raises(CalibrationError, match="lattice_radial"):
        load_calibration(p)
