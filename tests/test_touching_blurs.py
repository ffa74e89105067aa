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
from twin_points import render_pair

from lfcam.measure import fastfit
from lfcam.measure import regions as regions_module
from lfcam.measure.regions import find_regions, nearby_regions


def _capture(apart: float) -> tuple:
    """The pair ``apart`` (tests/twin_points.py, the rays' own noise): 18 puts their light
    centroids 259 px apart, 16.5 237 px (the blurs overlap by ~40 and ~60 px). (profile,
    geometry, image, its lenslet statistics, pixel noise, truth)."""
    return render_pair(apart)[:6]


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
