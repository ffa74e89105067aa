"""Decoding recovers a known light field from a raw encoded independently (tests/decode/synth)."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from lfcam.calibrate import Calibration, load_calibration
from lfcam.calibrate.model import calibration_from_dict
from lfcam.decode import decode, to_grey
from lfcam.errors import CalibrationError, InputFileError
from tests.decode.synth import encode, lattice


def _linear_field(du, dv, s, t):
    # linear in the angular offset inside a lens, so bilinear sampling is exact
    return 0.3 + 0.01 * du - 0.007 * dv + 0.002 * s + 0.003 * t + 0.0005 * s * t


@pytest.mark.parametrize("grid", ["rect", "hex"])
def test_decode_recovers_linear_field_at_subpixel_rotated_centres(grid):
    pitch, rot, off = 11.37, 0.013, (7.31, 6.62)
    cx, cy, sp, tp = lattice(grid, pitch, rot, off, 24, 24)
    raw = encode(_linear_field, (230, 240), cx, cy, sp, tp, rot, 0.5 * pitch)
    lf = decode(raw, Calibration.from_lattice(grid, pitch, rot, off), n_views=9, hex_to_rect=False)
    assert lf.first_t == 0 and lf.first_s == (-1 if grid == "hex" else 0)
    vc, uc = lf.angular_centre
    checked = 0
    for v in range(9):
        for u in range(9):
            du, dv = u - uc, v - vc
            if math.hypot(du, dv) > 0.5 * pitch - 1.5:
                continue  # the 2x2 pixel neighbourhood may straddle two lenses
            rows, cols = lf.data.shape[2:]
            tt, ss = np.meshgrid(np.arange(rows) + lf.first_t, np.arange(cols) + lf.first_s,
                                 indexing="ij")
            s_pos = ss + (0.5 * (tt % 2) if grid == "hex" else 0.0)
            t_pos = tt * (math.sqrt(3) / 2 if grid == "hex" else 1.0)
            truth = _linear_field(du, dv, s_pos, t_pos)
            ok = (lf.weight[v, u] > 0) & (ss >= 0) & (ss < 24) & (tt < 24)
            assert ok.sum() > 300
            np.testing.assert_allclose(lf.data[v, u][ok], truth[ok], atol=2e-6)
            checked += 1
    assert checked >= 49


def test_measured_centres_override_the_lattice():
    pitch, rot, off = 10.0, 0.0, (5.2, 5.4)
    cx, cy, sp, tp = lattice("rect", pitch, rot, off, 20, 20)
    rng = np.random.default_rng(3)
    jx, jy = cx + rng.uniform(-0.4, 0.4, cx.size), cy + rng.uniform(-0.4, 0.4, cy.size)
    raw = encode(_linear_field, (200, 200), jx, jy, sp, tp, rot, 5.0)
    truth_c = _linear_field(0.0, 0.0, sp, tp).reshape(20, 20)
    plain = decode(raw, Calibration.from_lattice("rect", pitch, rot, off), n_views=5)
    cal = Calibration.from_lattice("rect", pitch, rot, off, np.column_stack([jx, jy]))
    measured = decode(raw, cal, n_views=5)
    err_plain = np.abs(plain.data[2, 2] - truth_c).max()
    err_meas = np.abs(measured.data[2, 2] - truth_c).max()
    assert err_meas < 1e-5
    assert err_plain > 1e-3  # the jitter is visible when ignored: the test can fail


def test_hex_to_rect_aligns_odd_rows():
    pitch = 10.0
    cx, cy, sp, tp = lattice("hex", pitch, 0.0, (5.0, 5.0), 20, 20)
    raw = encode(lambda du, dv, s, t: 0.1 + 0.02 * s + 0.01 * t, (180, 210), cx, cy, sp, tp,
                 0.0, 5.0)
    lf = decode(raw, Calibration.from_lattice("hex", pitch, 0.0, (5.0, 5.0)), n_views=5)
    assert lf.spacing_px == pytest.approx((10.0, 10.0 * math.sqrt(3) / 2))
    c = lf.data[2, 2]
    ok = lf.weight[2, 2] > 0
    tt, ss = np.meshgrid(np.arange(c.shape[0]) + lf.first_t, np.arange(c.shape[1]) + lf.first_s,
                         indexing="ij")
    ok &= (ss >= 1) & (ss < 20) & (tt < 20)  # s = 0 of odd rows needs the absent lens s = −1
    truth = 0.1 + 0.02 * ss + 0.01 * tt * math.sqrt(3) / 2  # every row at integer s now
    np.testing.assert_allclose(c[ok], truth[ok], atol=1e-5)
    assert lf.weight[2, 2, 1, 0] == 0  # odd row, no left neighbour to interpolate from


def test_white_image_devignettes_and_weights():
    pitch = 10.0
    cx, cy, sp, tp = lattice("rect", pitch, 0.0, (5.0, 5.0), 16, 16)
    vignet = encode(lambda du, dv, s, t: 1.0 - 0.015 * (du**2 + dv**2), (160, 160), cx, cy,
                    sp, tp, 0.0, 5.0)
    scene = encode(lambda du, dv, s, t: 0.2 + 0.01 * s + 0 * du, (160, 160), cx, cy, sp, tp,
                   0.0, 5.0)
    grid = Calibration.from_lattice("rect", pitch, 0.0, (5.0, 5.0))
    lf = decode(scene * vignet, grid, white=vignet,
                n_views=7, white_threshold=0.5)
    ok = lf.weight > 0
    truth = np.broadcast_to(0.2 + 0.01 * np.arange(16.0), lf.data.shape)
    # sampling a product bilinearly is not exact: 1 % of the value is the bound
    np.testing.assert_allclose(lf.data[ok], truth[ok], rtol=0.01)
    # the corner views (r = 4.2 px: white 0.73) keep reduced weight; centre has full weight
    assert lf.weight[3, 3, 5, 5] == pytest.approx(1.0, abs=1e-6)
    assert lf.weight[0, 0, 5, 5] == pytest.approx(1 - 0.015 * 18, abs=0.02)


def test_to_grey_demosaics_rggb():
    rgb = np.zeros((8, 8, 3))
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 1000.0, 2000.0, 4000.0
    mosaic = np.zeros((8, 8), np.uint16)
    mosaic[0::2, 0::2] = rgb[0::2, 0::2, 0]
    mosaic[0::2, 1::2] = rgb[0::2, 1::2, 1]
    mosaic[1::2, 0::2] = rgb[1::2, 0::2, 1]
    mosaic[1::2, 1::2] = rgb[1::2, 1::2, 2]
    grey = to_grey(mosaic, "RGGB", black_level=0, white_level=10000)
    expected = (0.299 * 1000 + 0.587 * 2000 + 0.114 * 4000) / 10000
    assert grey[3:5, 3:5] == pytest.approx(np.full((2, 2), expected), rel=1e-3)
    assert cv2.COLOR_BayerBG2BGR  # the mapping used for RGGB exists


@pytest.mark.parametrize(
    "data, msg",
    [
        ({"grid": "tri", "pitch_px": 10, "offset_px": [0, 0]}, "grid"),
        ({"grid": "rect", "pitch_px": "x", "offset_px": [0, 0]}, "pitch_px"),
        ({"grid": "rect", "pitch_px": 1e9, "offset_px": [0, 0]}, "pitch_px"),
        ({"grid": "rect", "pitch_px": 10, "offset_px": [0]}, "offset_px"),
        ({"grid": "rect", "pitch_px": 10, "offset_px": [0, 0], "centres_px": [1, 2, 3]},
         "centres_px"),
        ([], "object"),
    ],
)
def test_bad_calibration_is_a_calibration_error(data, msg):
    with pytest.raises(CalibrationError, match=msg):
        calibration_from_dict(data)


def test_minimal_calibration_form_reads_contract_keys(tmp_path):
    p = tmp_path / "c.json"
    p.write_text(json.dumps({"grid": "hex", "pitch_px": 14.3, "rotation_rad": 0.001,
                             "offset_px": [3.0, 4.0], "centres_px": [[3.0, 4.0]],
                             "residual_rms_px": 0.01}))
    g = load_calibration(p)
    assert (g.grid, g.pitch_px, g.offset_px) == ("hex", 14.3, (3.0, 4.0))
    assert g.model == "similarity" and g.indices.tolist() == [[0, 0]]
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(CalibrationError, match="JSON"):
        load_calibration(tmp_path / "bad.json")


def test_bad_raw_inputs():
    g = Calibration.from_lattice("rect", 10.0, 0.0, (5.0, 5.0))
    with pytest.raises(InputFileError, match="2-D"):
        decode(np.zeros((4, 4, 3)), g)
    with pytest.raises(InputFileError, match="differ"):
        decode(np.zeros((50, 50)), g, white=np.ones((40, 40)))
    with pytest.raises(InputFileError, match="n_views"):
        decode(np.zeros((50, 50)), g, n_views=0)
    with pytest.raises(InputFileError, match="NaN"):
        to_grey(np.full((4, 4), np.nan))
