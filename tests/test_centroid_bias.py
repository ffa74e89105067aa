"""The centroid estimator's bias on touching micro-images, learnt on a model white
(lfcam.calibrate.bias), against a white from the second rendering path.

docs/calibration.md, "Own-light centroids of touching whites at the field's rim (stop 64)".
"""

from __future__ import annotations

import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from whites_analytic import analytic_white_truth  # noqa: E402

from lfcam.calibrate.bias import _learn, centroid_bias, model_strip  # noqa: E402
from lfcam.calibrate.grid import _model_centroids  # noqa: E402
from lfcam.calibrate.microimage import DiscModel  # noqa: E402
from lfcam.camera import load_profile  # noqa: E402

# system 1 focused at infinity: its white's micro-images touch (R = 8.18 px, half the pitch
# 8.20 px, edge half-width 0.56 px; the calibration of its 1024² white, benchmarks/.cache)
DISC = DiscModel(8.184, 0.563, 0.0)
PITCH_PX = 16.4095
SENSOR = (1024, 1024)


@pytest.fixture(scope="module")
def camera():
    base = load_profile(ROOT / "calibration" / "system1.toml")
    profile = replace(base, sensor=replace(base.sensor, width_px=SENSOR[1],
                                           height_px=SENSOR[0], axis_px=None))
    return profile.with_d_in(profile.main_lens.d_in_for_focus(math.inf))


def test_the_bias_learnt_on_a_model_white_matches_a_white_rendered_without_lfcam_sim(camera):
    """The bias ``_learn`` fits on ``lfcam.sim``'s strip against the estimator's error on the
    same strip rendered by ``benchmarks/whites_analytic.py`` (its own per-pixel integral, no
    shared rendering code), measured there against that path's own truth centroids: at 70–100 %
    of the reach, where the error is 0.02–0.06 px inward, the two agree within 0.006 px; a
    bias that were zero would miss by 0.02 px or more."""
    bias = _learn(camera, SENSOR, DISC.radius_px, DISC.edge_px, PITCH_PX, "rect", 0.0)
    assert bias is not None and bias.lenses >= 150
    # the same strip, from the analytic path (noise-free)
    strip, axis, reach = model_strip(camera, SENSOR, PITCH_PX)
    assert reach == pytest.approx(math.hypot(511.5, 511.5))  # the corner, from the centre
    white, truth = analytic_white_truth(strip, samples=16, noise=False)
    cand = np.rint(truth["centroid_px"][truth["complete"]])
    centres, _, conv, at_edge = _model_centroids(white, cand, DISC, PITCH_PX, "rect", 0.0,
                                                 lambda *a: None)
    got = centres[conv & ~at_edge]
    ref = truth["centroid_px"][truth["complete"]]
    dist, k = cKDTree(ref).query(got)
    got, ref = got[dist < 3.0], ref[k[dist < 3.0]]
    d = ref - np.asarray(axis)
    r = np.hypot(d[:, 0], d[:, 1])
    error = ((got - ref) * d / r[:, None]).sum(axis=1)
    outer = (r > 0.7 * reach) & (r < reach)
    assert outer.sum() >= 40
    # the analytic white's error, averaged in bins of 0.1 reach, against the learnt bias
    for lo in (0.7, 0.8, 0.9):
        sel = (r >= lo * reach) & (r < (lo + 0.1) * reach)
        measured = float(error[sel].mean())
        learnt = float(bias.radial_px(r[sel]).mean())
        assert measured < -0.015
        assert abs(measured - learnt) < 0.006


def test_no_bias_where_the_micro_images_leave_gaps(camera):
    """A white whose neighbours' edge ramps overlap by less than a half-width (system 1 at a
    1 m focus: R = 7.40 px of a 16.37 px pitch) has no seam to split: no bias is learnt and
    the centroids are used as measured."""
    from lfcam.calibrate.model import Calibration

    cal = Calibration.from_lattice("rect", 16.3733)
    cal = replace(cal, diagnostics={"centroid_method": "micro-image model",
                                    "disc_radius_px": 7.398, "disc_edge_px": 0.541})
    assert centroid_bias(camera, camera.d_in_mm, cal, SENSOR) is None
    touching = replace(cal, diagnostics={**cal.diagnostics, "disc_radius_px": 8.184,
                                         "disc_edge_px": 0.563}, pitch_px=PITCH_PX)
    got = centroid_bias(camera, camera.d_in_mm, touching, SENSOR)
    assert got is not None
    # it moves a rim centroid inward-measured one outward, and leaves the axis alone
    ax, ay = camera.sensor.axis_xy_px
    rim = np.array([[ax + 0.9 * 700.0, ay]])
    assert got.correct(rim)[0, 0] > rim[0, 0] + 0.01
    assert np.allclose(got.correct(np.array([[ax, ay]])), [[ax, ay]])
