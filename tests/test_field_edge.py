"""Issue 16, both sides of focus and the full field, against the renderer's truth.

``method="lenslet"``: off-axis points at 80 % of system 1's half-field are points (F/2 coma
stretches their blur, the region finder calls them elongated); lines stay lines behind focus.
``method="lightfield"``: the image fit bins rays like the sensor (1–2 px spots behind focus)
and starts from the lenslet fit (a side basin at the field edge).

Each capture is a small crop of the sensor around the source (``sensor.axis_px`` moves the
optical axis off the crop), rendered by ``lfcam.sim`` with photon and read noise; distances are
checked against the scene's truth (issue 16 targets: max ERROR 1 % for points, 2 % for lines).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from crops import crop_camera, source_at

from lfcam.camera import load_profile
from lfcam.distance import run_distance
from lfcam.sim.capture import simulate
from lfcam.sim.geometry import truth_geometry
from lfcam.sim.scene import scene_from_dict

CROP_PX = 320
HALF_FIELD_MM = 0.5 * 1024 * 0.08375  # system 1's full sensor


def _measure(cam, prof, objects, seed=3, method="lenslet"):
    scene = {"seed": seed, "rays_per_source": 1_000_000, "camera": cam,
             "exposure": {"peak": 0.8},
             "sensor": {"photon_noise": True, "full_well_e": 20000, "read_noise_e": 3.0},
             "objects": objects}
    raw, used, _ = simulate(load_profile(prof.name), scene_from_dict(scene))
    img = raw.astype(np.float64)
    return run_distance(img, used, None, model="exact", method=method,
                        geometry=truth_geometry(used, img.shape))


@pytest.mark.parametrize(("focus", "distance", "shape"), [
    (math.inf, 3500.0, "line"),  # was a `line`, −8.8 %
    (1000.0, 700.0, "line"),  # was a `line`, −1.3 %
    (1500.0, 3500.0, "spot"),  # behind focus, was −1.1 %
])
def test_off_axis_point_at_80_percent_is_a_point(focus, distance, shape, monkeypatch):
    """A point, read within 0.3 % (measured −0.05, −0.02 and −0.02 %), whatever the shape the
    region finder gives its region. The first two regions are `line`-shaped (coma and
    vignetting), but their point fits leave under the line trigger: no line is tried (on the
    focus grids every such try lost, 17-55 ms each; docs/distance.md, "Line-shaped point
    regions (stop 49)"). Before stop 49 the region's shape alone sent them to a line fit."""
    import lfcam.distance as distance_mod
    from lfcam.measure import fastfit

    shapes, tries = [], []
    measure = distance_mod.measure_lenslet
    monkeypatch.setattr(distance_mod, "measure_lenslet", lambda p, g, i, region, *a, **k: (
        shapes.append(region.kind) or measure(p, g, i, region, *a, **k)))
    line_fit = fastfit.fit_lenslet_line
    monkeypatch.setattr(fastfit, "fit_lenslet_line",
                        lambda *a, **k: tries.append(1) or line_fit(*a, **k))
    az = math.radians(30.0)
    at = 0.8 * HALF_FIELD_MM * np.array([math.cos(az), math.sin(az)])
    cam, prof = crop_camera(focus, at, CROP_PX)
    run = _measure(cam, prof, [{"type": "point", "distance_mm": distance,
                                "position_mm": source_at(prof, distance, at)}])
    best = max(run.regions, key=lambda r: r.diameter_mm if r.status == "ok" else -1.0)
    assert best.kind == "spot" and best.status == "ok"
    assert abs(best.distance_mm / distance - 1.0) < 0.003
    assert shapes == [shape]  # (the case each is for)
    assert not tries


def test_line_behind_focus_is_a_line():
    """A line 3 mm long on the MLA, 2200 mm behind a 1 m focus, at the field centre."""
    cam, prof = crop_camera(1000.0, np.zeros(2), 384)
    mag = 1 + prof.mla.focal_length_mm / (prof.d_in_mm - prof.main_lens.exit_pupil_z_mm)
    u = np.array([math.cos(math.radians(60.0)), math.sin(math.radians(60.0))])
    a = source_at(prof, 2200.0, -1.5 * mag * u)
    b = source_at(prof, 2200.0, 1.5 * mag * u)
    run = _measure(cam, prof, [{"type": "line", "distance_mm": 2200.0, "start_mm": a,
                                "end_mm": b}])
    best = max(run.regions, key=lambda r: r.diameter_mm if r.status == "ok" else -1.0)
    assert best.kind == "line" and best.status == "ok"
    assert abs(best.distance_mm / 2200.0 - 1.0) < 0.02



@pytest.mark.parametrize(("system", "focus", "distance", "field", "limit"), [
    ("system1", 1000.0, 2200.0, 0.0, 0.005),  # 1–2 px spots behind focus: was −1.34 %
    ("system2", math.inf, 3500.0, 0.8, 0.01),  # side basin at the field edge: was −2.4 %
])
def test_image_fit_behind_focus_and_at_the_edge(system, focus, distance, field, limit):
    half = 0.5 * load_profile(system).sensor.width_px * load_profile(system).sensor.pixel_pitch_mm
    az = math.radians(30.0)
    at = field * half * np.array([math.cos(az), math.sin(az)])
    cam, prof = crop_camera(focus, at, CROP_PX, system)
    run = _measure(cam, prof, [{"type": "point", "distance_mm": distance,
                                "position_mm": source_at(prof, distance, at)}],
                   method="lightfield")
    best = max(run.regions, key=lambda r: r.diameter_mm if r.status == "ok" else -1.0)
    assert best.kind == "spot" and best.status == "ok"
    assert abs(best.distance_mm / distance - 1.0) < limit
