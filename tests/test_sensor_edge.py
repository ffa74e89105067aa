"""Issue 16: lenses cut by the sensor edge reach the distance stage.

The white calibration measures only whole micro-images; the distance geometry adds every lens
whose micro-image reaches the sensor, placed by the calibration's lattice model. Truth: the
renderer's own lenslets (chief-ray micro-image centres) and the rendered source distance.
Before the change this capture (a 1.4 mm blur at 90 % of the field, cut by the right edge)
had 41 lenslets instead of the renderer's 49 and was refused ``poor-fit``.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lfcam.calibrate import calibrate_white
from lfcam.camera import load_profile
from lfcam.distance import run_distance
from lfcam.measure import prepare_geometry
from lfcam.measure.geometry import sensor_lenses
from lfcam.measure.pointfit import chief_ray_offset
from lfcam.sim.capture import apply_overrides, simulate
from lfcam.sim.geometry import truth_geometry
from lfcam.sim.scene import scene_from_dict

SIZE = 384  # px: 24 × 24 lenslets
CAMERA = {"mla": {"focus_mm": 1000.0}, "sensor": {"width_px": SIZE, "height_px": SIZE}}
DISTANCE_MM = 500.0


@pytest.fixture(scope="module")
def setup():
    base = load_profile("system2")
    prof = apply_overrides(base, CAMERA)
    prof = prof.with_d_in(prof.d_in_mm)
    white, _, _ = simulate(base, scene_from_dict(
        {"seed": 5, "objects": [{"type": "white"}], "camera": CAMERA}))
    cal = calibrate_white(white.astype(np.float32)).with_d_in(prof.d_in_mm, "profile")
    return base, prof, cal


def _lit_lenses(geom):
    """Centres (px) of the lenses the lenslet map gives at least one pixel."""
    lab = geom.lmap.labels
    return geom.lmap.centres_px[np.unique(lab[lab >= 0])]


def test_edge_lenses_match_renderer(setup):
    _, prof, cal = setup
    shape = (SIZE, SIZE)
    geom = prepare_geometry(prof, cal, shape)
    truth = _lit_lenses(truth_geometry(prof, shape))
    ours = _lit_lenses(geom)
    assert len(ours) == len(truth) > cal.n_lenses  # 25² vs 23² measured
    d, k = cKDTree(truth).query(ours)
    assert d.max() < 0.1 * geom.pitch_px and len(np.unique(k)) == len(truth)
    # the measured lenses come first, unchanged
    centres, _, n = sensor_lenses(cal, shape, geom.lmap.radius_px)
    assert n == cal.n_lenses
    np.testing.assert_array_equal(geom.lmap.centres_px[:n], cal.centres_px)


def test_blur_cut_by_sensor_edge(setup):
    base, prof, cal = setup
    mag = 1 + prof.mla.focal_length_mm / (prof.d_in_mm - prof.main_lens.exit_pupil_z_mm)
    half_mm = 0.5 * SIZE * prof.sensor.pixel_pitch_mm
    xy = chief_ray_offset(prof, prof.d_in_mm, DISTANCE_MM, np.array([0.9 * half_mm, 0.0]) / mag)
    scene = {"seed": 4, "rays_per_source": 400_000, "camera": CAMERA,
             "sensor": {"photon_noise": True, "full_well_e": 20000, "read_noise_e": 3.0},
             "objects": [{"type": "point", "distance_mm": DISTANCE_MM,
                          "position_mm": [float(xy[0]), float(xy[1])]}]}
    raw, _, truth = simulate(base, scene_from_dict(scene))
    assert truth["sources"][0]["distance_mm"] == pytest.approx(DISTANCE_MM)
    run = run_distance(raw.astype(np.float64), prof, cal, model="exact", jobs=1)
    ok = [r for r in run.regions if r.status == "ok"]
    assert len(ok) == 1
    # the region reaches the last pixel column: the blur is cut by the sensor edge
    assert ok[0].bbox_px[2] == SIZE
    assert abs(ok[0].distance_mm / DISTANCE_MM - 1.0) < 0.01
