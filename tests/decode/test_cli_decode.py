"""``lfcam decode`` and ``lfcam refocus`` on PNG raws (truth: tests/decode/synth)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import tifffile

from lfcam.cli.main import main
from tests.decode.synth import encode, lattice

PITCH, LENSES = 16.0, 20
SYSTEM1_SMALL = """
name = "small1"
[main_lens]
radius_mm = 100.0
thickness_mm = 14.35
refractive_index = 1.515
pupil_diameter_mm = 50.0
[mla]
focal_length_mm = 2.749
pitch_mm = 1.34
grid = "rect"
focus_mm = 3500.0
[sensor]
pixel_pitch_mm = 0.08375
width_px = 320
height_px = 320
bit_depth = 16
"""


def _texture(s, t):
    return 0.4 + 0.2 * np.sin(2 * np.pi * s / 6.3) + 0.15 * np.cos(2 * np.pi * t / 8.1)


@pytest.fixture()
def capture(tmp_path):
    """A plane whose view (du, dv) is the texture shifted by −(du, dv) lenslets (a = 1)."""
    cx, cy, sp, tp = lattice("rect", PITCH, 0.0, (8.0, 8.0), LENSES, LENSES)
    raw = encode(lambda du, dv, s, t: _texture(s - du, t - dv), (320, 320), cx, cy, sp, tp,
                 0.0, 8.0)
    png = tmp_path / "raw.png"
    cv2.imwrite(str(png), np.round(raw * 65535).astype(np.uint16))
    calib = tmp_path / "calib.json"
    calib.write_text(json.dumps({"grid": "rect", "pitch_px": PITCH, "rotation_rad": 0.0,
                                 "offset_px": [8.0, 8.0], "residual_rms_px": 0.0}))
    prof = tmp_path / "small1.toml"
    prof.write_text(SYSTEM1_SMALL)
    return png, calib, prof


def test_decode_writes_views_and_arrays(capture, tmp_path):
    png, calib, _ = capture
    out = tmp_path / "lf"
    assert main(["decode", str(png), "--calibration", str(calib), "--views", "5",
                 "-o", str(out)]) == 0
    lf = np.load(out / "lightfield.npy")
    assert lf.shape == (5, 5, LENSES, LENSES)
    ss, tt = np.meshgrid(np.arange(LENSES), np.arange(LENSES))
    # view (v, u) = texture at (s − du, t − dv); 16-bit quantisation bounds the error
    np.testing.assert_allclose(lf[2, 2], _texture(ss, tt), atol=2e-4)
    np.testing.assert_allclose(lf[2, 4], _texture(ss - 2, tt), atol=2e-4)
    assert tifffile.imread(out / "views.tiff").shape == (25, LENSES, LENSES)
    assert len(list((out / "views").glob("*.png"))) == 25
    assert json.loads((out / "lightfield.json").read_text())["shape"] == [5, 5, LENSES, LENSES]


def test_refocus_by_shift_realigns_and_distance_matches_shift(capture, tmp_path):
    png, calib, prof = capture
    t1 = tmp_path / "a1.tiff"
    assert main(["refocus", str(png), "--calibration", str(calib), "--views", "5",
                 "--shift", "-1", "-o", str(t1)]) == 0
    img = tifffile.imread(t1)
    ss, tt = np.meshgrid(np.arange(LENSES), np.arange(LENSES))
    inner = (slice(3, -3), slice(3, -3))
    np.testing.assert_allclose(img[inner], _texture(ss, tt)[inner], atol=2e-4)

    from lfcam.camera import load_profile
    from lfcam.decode import shift_for_distance

    a = float(shift_for_distance(load_profile(prof), 700.0))
    t2, t3 = tmp_path / "d.tiff", tmp_path / "s.tiff"
    assert main(["refocus", str(png), "--calibration", str(calib), "--profile", str(prof),
                 "--distance", "700", "-o", str(t2)]) == 0
    assert main(["refocus", str(png), "--calibration", str(calib), "--shift", repr(a),
                 "-o", str(t3)]) == 0
    np.testing.assert_array_equal(tifffile.imread(t2), tifffile.imread(t3))
    p = tmp_path / "d.png"
    assert main(["refocus", str(png), "--calibration", str(calib), "--shift", "0.3",
                 "-o", str(p)]) == 0
    assert cv2.imread(str(p), cv2.IMREAD_UNCHANGED).dtype == np.uint16


@pytest.mark.parametrize(
    "extra, msg",
    [
        (["--distance", "700"], "pass --profile"),
        (["--shift", "1", "-o", "x.jpg"], ".png"),
    ],
)
def test_refocus_errors_are_one_line(capture, tmp_path, capsys, extra, msg):
    png, calib, _ = capture
    args = ["refocus", str(png), "--calibration", str(calib)] + extra
    if "-o" not in extra:
        args += ["-o", str(tmp_path / "o.tiff")]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert msg in err and err.count("\n") == 1


def test_refocus_nan_shift_is_a_usage_error(capture, tmp_path, capsys):
    png, calib, _ = capture
    with pytest.raises(SystemExit) as exc:
        main(["refocus", str(png), "--calibration", str(calib), "--shift", "nan",
              "-o", str(tmp_path / "o.tiff")])
    assert exc.value.code == 2
    assert "--shift: must be a finite number" in capsys.readouterr().err


def test_missing_calibration_is_one_line(capture, tmp_path, capsys):
    png, _, _ = capture
    assert main(["decode", str(png), "--calibration", str(tmp_path / "none.json"),
                 "-o", str(tmp_path / "o")]) == 1
    assert "calibration file not found" in capsys.readouterr().err
