"""A large blur's coarse end moved onto its light (stop 74): ``fastfit._recentre_coarse``.

The capture: the Illum-size scene's 906.7 mm point (``benchmarks/many_sources.py``, scene (b),
the Illum-like profile), rendered alone on a 1 024 × 768 crop of its sensor that keeps the
optical axis where the full sensor has it, with sensor noise. Its blur lights ~1 500 lenslets.
In the scene its coarse stage ended 0.25 % long and a fifth of a pitch aside, at a misfit of
0.25 against 0.03 at its minimum; the fine steps, which take the coarse Jacobian, stayed there
(docs/distance.md, "A large blur's coarse end moved onto its light (stop 74)"). The test starts
the fit there. Truth: the renderer's source.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from crops import ILLUM_LIKE, illum_crop_capture

from lfcam.camera import load_profile
from lfcam.measure import fastfit

DISTANCE_MM = 906.6673828110515
POSITION_MM = [-15.799636702190657, -18.108248214110123]
# where scene (b)'s coarse stage ended, from the truth: log distance, x/L, y/L
COARSE_END = np.array([0.0025, 7e-5, 8e-5])


@pytest.fixture(scope="module")
def large_point():
    base = load_profile(ILLUM_LIKE)
    x0, y0 = 4582 - 512, 3507 - 384  # (the crop about the blur's centroid on the full sensor)
    axis = [0.5 * base.sensor.width_px - 0.5 - x0, 0.5 * base.sensor.height_px - 0.5 - y0]
    return illum_crop_capture(
        1024, 768, axis,
        [{"type": "point", "distance_mm": DISTANCE_MM, "position_mm": POSITION_MM}], seed=12,
        rays_per_source=200_000)[:4]


def _fit_from(prof, geom, image, region, start_q):
    mom = fastfit.region_moments(geom, image, region)
    stages = fastfit.point_fit_stages(prof, geom, image, region, mom=mom, start_q=start_q)
    next(stages)
    return next(stages), mom


def test_a_large_blurs_coarse_end_is_moved_onto_its_light(large_point, monkeypatch):
    prof, geom, image, region = large_point
    frame = fastfit.SourceFrame(prof)
    z = prof.main_lens.front_vertex_z_mm
    q_true = frame.params(np.array([*POSITION_MM, z - DISTANCE_MM]))
    fit, mom = _fit_from(prof, geom, image, region, q_true + COARSE_END)
    assert fastfit.lit_lenslets(mom) >= 1000
    polish = fastfit.LensletModel(prof, geom, mom, fastfit.POLISH_RAYS)
    at_truth = math.sqrt(fastfit.sq(polish.residual(frame.source(q_true))))
    assert fit.ok
    error = (z - fit.source_mm[2]) / DISTANCE_MM - 1.0
    assert abs(error) < 5e-4, error
    assert fit.misfit < 1.1 * at_truth, (fit.misfit, at_truth)
    # without the step the fit stays where the coarse stage left it, the polish included
    monkeypatch.setattr(fastfit, "COARSE_RECENTRE_MIN_LIT", 10**9)
    stuck, _ = _fit_from(prof, geom, image, region, q_true + COARSE_END)
    assert stuck.misfit > 2.0 * at_truth, (stuck.misfit, at_truth)
    assert abs((z - stuck.source_mm[2]) / DISTANCE_MM - 1.0) > 1e-3


def test_the_step_is_kept_only_where_it_lowers_the_misfit(large_point):
    prof, geom, image, region = large_point
    frame = fastfit.SourceFrame(prof)
    z = prof.main_lens.front_vertex_z_mm
    q_true = frame.params(np.array([*POSITION_MM, z - DISTANCE_MM]))
    mom = fastfit.region_moments(geom, image, region)
    model = fastfit.LensletModel(prof, geom, mom, fastfit.COARSE_RAYS)
    q = q_true + COARSE_END
    r = model.residual(frame.source(q))
    q2, r2, f2 = fastfit._recentre_coarse(prof, geom, mom, frame, model, q, r,
                                          fastfit.sq(r))
    # the centroid step takes the lateral offset back to within a tenth of it ...
    assert q2[0] == q[0]
    np.testing.assert_array_less(np.abs(q2[1:] - q_true[1:]), 0.15 * np.abs(COARSE_END[1:]))
    assert f2 < 0.5 * fastfit.sq(r) and f2 == pytest.approx(fastfit.sq(
        model.residual(frame.source(q2))), rel=1e-12)
    # ... and a fit already on the light is left where it is when the step does not help
    q3, r3, f3 = fastfit._recentre_coarse(prof, geom, mom, frame, model, q2, r2, 0.5 * f2)
    assert np.array_equal(q3, q2) and f3 == 0.5 * f2 and r3 is r2
