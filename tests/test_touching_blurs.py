"""Two sources whose blurs touch: one cluster of lit lenslets, cut at its waist into two regions,
each measured with the other as its neighbour and the lenslets both light left out.

Truth: the renderer's distances (``lfcam.sim``, the rays' own noise: 10⁶ a source, no sensor
noise), and the region finder's old answer for the same capture (one ``multiple`` region, no
distance) as the case the cut is for (docs/distance.md, "Touching blurs cut at their waist
(stop 67)").
"""

from __future__ import annotations

import numpy as np
import pytest

from lfcam import distance
from lfcam.camera import load_profile
from lfcam.measure import fastfit, lenslet_stats
from lfcam.measure import regions as regions_module
from lfcam.measure.noise import capture_noise
from lfcam.measure.regions import find_regions, nearby_regions
from lfcam.sim.capture import apply_overrides, simulate
from lfcam.sim.geometry import truth_geometry
from lfcam.sim.scene import scene_from_dict

SIZE = 1024
CAMERA = {"mla": {"focus_mm": 1000.0}, "sensor": {"width_px": SIZE, "height_px": SIZE}}


def _capture(apart: float) -> tuple:
    """System 2 focused at 1 m, two points behind focus (1 400 and 1 500 mm, blurs ~290 and
    ~305 px across) placed ``apart`` × 1/1000 of their distance off the axis on either side:
    18 puts their light centroids 259 px apart, 16.5 237 px (the blurs overlap by ~40 and
    ~60 px). (profile, geometry, image, its lenslet statistics, pixel noise, truth)."""
    base = load_profile("system2")
    prof = apply_overrides(base, CAMERA)
    prof = prof.with_d_in(prof.d_in_mm)
    objects = [{"type": "point", "distance_mm": d, "position_mm": [0.0, s * apart * d / 1000]}
               for d, s in ((1400.0, -1.0), (1500.0, 1.0))]
    scene = {"seed": 7, "rays_per_source": 1_000_000, "camera": CAMERA,
             "exposure": {"peak": 0.5}, "objects": objects}
    raw, used, truth = simulate(base, scene_from_dict(scene))
    image = raw.astype(np.float64) - used.sensor.black_level
    geom = truth_geometry(prof, (SIZE, SIZE))
    white = float(used.sensor.white_level - used.sensor.black_level)
    stats = lenslet_stats(image, geom.lmap)
    capture_noise(image, geom.lmap, geom.pitch_px, stats,
                  sensor_gain=distance.sensor_gain(prof, white))
    return prof, geom, image, stats, distance.noise_sigma(image), truth


@pytest.mark.parametrize("apart", [18.0, 16.5])
def test_touching_points_each_measured(apart, monkeypatch):
    prof, geom, image, stats, noise, truth = _capture(apart)
    regions = find_regions(stats, geom.lmap, geom.pitch_px)
    assert len(regions) == 2 and all(r.touching for r in regions)
    assert np.array_equal(regions[0].shared, regions[1].shared)
    assert not np.intersect1d(regions[0].lenslets, regions[1].lenslets).size
    centroids = np.array([s["centroid_px"] for s in truth["sources"]])
    found = set()
    for region, near in zip(regions, nearby_regions(regions), strict=True):
        k = int(np.argmin(np.hypot(*(centroids - np.array(region.centroid_px)).T)))
        found.add(k)
        m = fastfit.measure_lenslet(prof, geom, image, region, noise, others=near)
        truth_mm = truth["sources"][k]["distance_mm"]
        err = m.distance_mm / truth_mm - 1.0
        assert m.status == "ok" and m.kind == "spot", (apart, k, m.status)
        # measured: +0.004 / -0.005 % (18), -0.019 / +0.007 % (16.5), sigma 0.031-0.034 %
        assert abs(err) < min(3.0 * m.sigma_distance_mm / truth_mm, 1.5e-3), (apart, k, err)
    assert found == {0, 1}
    # the same capture without the cut: one region no method measures
    monkeypatch.setattr(regions_module, "SPLIT_TOUCHING", False)
    assert [r.kind for r in find_regions(stats, geom.lmap, geom.pitch_px)] == ["multiple"]
