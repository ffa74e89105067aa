"""A sensor gain from the camera profile where a capture cannot measure its own (stop 49).

A capture of one small sharp blur has too few interior lenslets for
:func:`lfcam.measure.noise.photon_gain`, which then returns 0: its noise model counted no
photon noise, and its point misfit read as 2.6–7.5 × that noise, over the line trigger. The
profile's ``sensor.full_well_e`` gives the gain there. Truth: the renderer's own sensor
(20 000 e⁻ at the white level, 3 e⁻ read noise), noise drawn again around its noise-free render
(Monte Carlo), and the source's distance (docs/distance.md, "A sensor gain for captures that
cannot measure one (stop 49)").
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from lfcam.camera import load_profile, profile_from_dict
from lfcam.distance import run_distance, sensor_gain
from lfcam.errors import ProfileError
from lfcam.measure import find_regions, lenslet_stats
from lfcam.measure.fastfit import _region_box, data_moments
from lfcam.measure.noise import capture_noise, photon_gain
from lfcam.measure.pointfit import chief_ray_offset
from lfcam.sim.capture import apply_overrides, profile_to_dict, profile_to_toml, simulate
from lfcam.sim.geometry import truth_geometry
from lfcam.sim.scene import scene_from_dict

FULL_WELL_E = 20000.0
READ_E = 3.0
WHITE = 65535.0
CROP_PX = 320


def test_profile_full_well_is_optional_and_checked():
    prof = load_profile("system1")
    assert prof.sensor.full_well_e is None
    d = profile_to_dict(prof)
    d["sensor"]["full_well_e"] = 25000
    got = profile_from_dict(d)
    assert got.sensor.full_well_e == 25000.0
    assert profile_from_dict(profile_to_dict(got)).sensor.full_well_e == 25000.0
    assert "full_well_e = 25000.0" in profile_to_toml(got)
    for bad in (0, -5.0, "lots", math.inf):
        d["sensor"]["full_well_e"] = bad
        with pytest.raises(ProfileError, match="full_well_e"):
            profile_from_dict(d)
    # the gain in image units: white level 1 (Capture.grey) or raw counts; 0 when unknown
    assert sensor_gain(got, 1.0) == pytest.approx(1.0 / 25000.0)
    assert sensor_gain(got, WHITE) == pytest.approx(WHITE / 25000.0)
    assert sensor_gain(got, None) == 0.0 and sensor_gain(prof, 1.0) == 0.0


def _scene(noise: bool) -> tuple[np.ndarray, object]:
    """System 1 at a 1 m focus, a point 300 mm away at the field centre (a blur of ~45
    lenslets in front of focus), on a crop of the sensor; raw counts (white 65 535)."""
    cam = {"mla": {"focus_mm": 1000.0},
           "sensor": {"width_px": CROP_PX, "height_px": CROP_PX}}
    prof = apply_overrides(load_profile("system1"), cam)
    prof = prof.with_d_in(prof.d_in_mm)
    xy = chief_ray_offset(prof, prof.d_in_mm, 300.0, np.zeros(2))
    sensor = ({"photon_noise": True, "full_well_e": FULL_WELL_E, "read_noise_e": READ_E}
              if noise else {"photon_noise": False, "read_noise_e": 0.0})
    raw, used, _ = simulate(load_profile("system1"), scene_from_dict({
        "seed": 3, "rays_per_source": 1_000_000, "camera": cam, "sensor": sensor,
        "exposure": {"peak": 0.8},
        "objects": [{"type": "point", "distance_mm": 300.0,
                     "position_mm": [float(xy[0]), float(xy[1])]}]}))
    return raw.astype(np.float64), used.with_d_in(used.d_in_mm)


def test_small_blur_noise_is_counted_with_the_profiles_full_well(monkeypatch):
    import lfcam.distance
    from lfcam.measure import fastfit

    img, prof = _scene(noise=True)
    geom = truth_geometry(prof, img.shape)
    stats = lenslet_stats(img, geom.lmap)
    assert photon_gain(stats, geom.lmap, geom.pitch_px) == 0.0  # the case: no gain measured

    # the noise misfit of the region's moments, against noise drawn again (Poisson electrons
    # and Gaussian read noise) around the noise-free render: with the sensor's gain it is the
    # noise's; without, the read noise alone, a fraction of it
    clean, clean_prof = _scene(noise=False)
    region = max(find_regions(stats, geom.lmap, geom.pitch_px), key=lambda r: len(r.lenslets))
    box = _region_box(geom, region, img.shape)
    ref = data_moments(geom, clean, box)
    g = WHITE / FULL_WELL_E
    rng = np.random.default_rng(11)
    drift = []
    for _ in range(40):
        noisy = g * (rng.poisson(clean / g) + READ_E * rng.standard_normal(clean.shape))
        drift.append(float(((data_moments(geom, noisy, box).data - ref.data) ** 2).sum()))
    observed = math.sqrt(np.mean(drift)) / ref.norm
    mom = data_moments(geom, img, box)
    with_gain = capture_noise(img.copy(), geom.lmap, geom.pitch_px, stats, sensor_gain=g)
    without = capture_noise(img.copy(), geom.lmap, geom.pitch_px, stats)
    assert with_gain.gain == g and without.gain == 0.0
    assert with_gain.moments_misfit_of(mom.noise_sums, mom.norm) == pytest.approx(observed,
                                                                                  rel=0.15)
    assert without.moments_misfit_of(mom.noise_sums, mom.norm) < 0.4 * observed

    # measured: no line fit is tried (a line could not win: its point misfit is the noise),
    # and the answer is the point's; without a full well the noise trigger falls under the
    # point's misfit (below)
    tries = []
    line_fit = fastfit.fit_lenslet_line
    monkeypatch.setattr(fastfit, "fit_lenslet_line",
                        lambda *a, **k: tries.append(1) or line_fit(*a, **k))
    triggers, misfits = [], []
    noise_trigger, measure = fastfit.line_trigger, lfcam.distance.measure_lenslet
    monkeypatch.setattr(fastfit, "line_trigger",
                        lambda *a, **k: triggers.append(noise_trigger(*a, **k)) or triggers[-1])
    monkeypatch.setattr(lfcam.distance, "measure_lenslet",
                        lambda *a, **k: misfits.append(measure(*a, **k)) or misfits[-1])
    # (the simulator's profile states its sensor's full well when it draws photon noise)
    assert prof.sensor.full_well_e == FULL_WELL_E
    assert clean_prof.sensor.full_well_e is None
    run = run_distance(img.copy(), prof, None, model="exact", method="lenslet", geometry=geom,
                       white_value=WHITE)
    best = max(run.regions, key=lambda r: r.diameter_mm if r.status == "ok" else -1.0)
    assert best.kind == "spot" and best.status == "ok"
    assert abs(best.distance_mm / 300.0 - 1.0) < 0.003
    assert not tries
    assert len(misfits) == len(triggers) == 1  # (the scene's one region)
    point, with_well = misfits[0].misfit, triggers[0]
    # the profile without a full well: the read noise alone sets the noise trigger, under
    # the point's misfit (measured 0.0018 against 0.0039; 0.0061 with the full well). Until
    # stop 53 that tried a line here; since the rays' shares lost the box's variance the
    # point models' own disagreement on this small blur (0.0022, twice that the model gate)
    # keeps it from being tried too
    triggers.clear()
    unknown = replace(prof, sensor=replace(prof.sensor, full_well_e=None))
    run_distance(img.copy(), unknown, None, model="exact", method="lenslet", geometry=geom,
                 white_value=WHITE)
    assert len(triggers) == 1 and triggers[0] < 0.6 * point < 0.8 * with_well
