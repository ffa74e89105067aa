"""Two sources whose blurs overlap without a waist: one region, fitted as two points, cut in
two and both measured (lfcam.measure.overlap, lfcam.distance._split_overlaps).

Truth: the renderer's distances (``lfcam.sim``, photon noise at a 20 000 e⁻ full well and
3 e⁻ read noise, as the focus grid's), the region finder's and
the lenslet fit's answers for the same capture without the cut (one region, ``poor-fit``), and
least squares on a linear problem whose solution is known (docs/distance.md, "Blurs that
overlap without a waist (stop 68)").
"""

from __future__ import annotations

import numpy as np
import pytest
from twin_points import CAMERA, NOISE, errors_by_source, render_pair

from lfcam import distance
from lfcam.camera import load_profile
from lfcam.measure import fastfit, lenslet_stats, overlap
from lfcam.measure.noise import capture_noise
from lfcam.measure.regions import find_regions, nearby_regions
from lfcam.sim.capture import simulate
from lfcam.sim.scene import scene_from_dict
from lfcam.status import RegionStatus


def _capture(apart: float, sensor: bool = True) -> tuple:
    """The pair ``apart`` (tests/twin_points.py), by default with the focus grid's sensor
    noise: 13 puts their light centroids 187 px apart (no waist: one region), 14 201 px
    (without sensor noise, the rays' own alone, a waist the lit lenslets' scatter shows in the
    wrong place: two regions, one of them poor-fit). (profile, geometry, image, lenslet
    statistics, pixel noise, truth, white level)."""
    return render_pair(apart, sensor)


def test_amplitudes_are_the_least_squares_brightnesses():
    # data = 2·m1 + 3·m2 exactly: (2, 3); data = 2·m1 − 0.5·m2 (a negative share): the
    # better of the two alone, m1's own least-squares brightness, the other at zero
    rng = np.random.default_rng(0)
    m1, m2 = rng.random((50, 4)), rng.random((50, 4))
    np.testing.assert_allclose(overlap._amplitudes(2 * m1 + 3 * m2, m1, m2), [2.0, 3.0])
    data = 2 * m1 - 0.5 * m2
    got = overlap._amplitudes(data, m1, m2)
    assert got[1] == 0.0
    assert got[0] == pytest.approx(float((m1 * data).sum() / (m1 * m1).sum()))


def _run(apart: float, monkeypatch, split: bool, sensor: bool = True, **pair):
    prof, geom, image, stats, noise, truth, white = render_pair(apart, sensor, **pair)
    monkeypatch.setattr(distance, "SPLIT_OVERLAPS", split)
    return distance.run_distance(image, prof, None, model="exact", method="lenslet",
                                 geometry=geom, jobs=1, white_value=white), truth


def _check_both(run, truth, bound: float = 1e-3):
    # measured: −0.065 / −0.033 % (13, σ 0.094 / 0.052 %), −0.016 / +0.019 % (14, σ 0.03 %)
    for k, (err, sigma) in errors_by_source(run, truth).items():
        assert abs(err) < min(3 * sigma, bound), (k, err, sigma)


def test_two_overlapping_blurs_are_cut_and_both_measured(monkeypatch):
    # one region without a waist, which the lenslet fit leaves poor-fit (as point and line)
    prof, geom, image, stats, noise, truth, white = _capture(13.0)
    regions = find_regions(stats, geom.lmap, geom.pitch_px)
    assert len(regions) == 1 and not regions[0].touching
    before, _ = _run(13.0, monkeypatch, split=False)
    assert [r.status for r in before.regions] == [RegionStatus.POOR_FIT]
    # the two-point fit places both blurs (measured: 1 401.6 and 1 501.4 mm, misfit 0.010
    # against a noise misfit of 0.030), the cut leaves a band both light out of both parts
    two = overlap.two_points(prof, geom, image, regions[0])
    d = sorted(prof.main_lens.front_vertex_z_mm - two.sources_mm[:, 2])
    np.testing.assert_allclose(d, [1400.0, 1500.0], rtol=5e-3)
    assert two.misfit < two.noise_misfit
    split = overlap.split_overlap(prof, geom, image, stats, regions[0], 1)
    assert split.cut
    parts = split.parts
    assert parts[0].region_id == 0 and parts[1].region_id == 1
    assert np.array_equal(parts[0].shared, parts[1].shared) and parts[0].shared.size > 0
    assert not np.intersect1d(parts[0].lenslets, parts[1].lenslets).size
    assert not np.intersect1d(parts[0].lenslets, parts[0].shared).size
    after, truth = _run(13.0, monkeypatch, split=True)
    _check_both(after, truth)
    assert len(after.timings_s["region_s"]) == 2


def test_a_waist_in_the_wrong_place_is_cut_again(monkeypatch):
    prof, geom, image, stats, noise, truth, white = _capture(14.0, sensor=False)
    regions = find_regions(stats, geom.lmap, geom.pitch_px)
    assert len(regions) == 2 and all(r.touching for r in regions)
    before, _ = _run(14.0, monkeypatch, split=False, sensor=False)
    assert RegionStatus.POOR_FIT in [r.status for r in before.regions]
    after, truth = _run(14.0, monkeypatch, split=True, sensor=False)
    assert sorted(r.region_id for r in after.regions) == [0, 1]
    _check_both(after, truth)


def test_one_source_is_not_cut():
    # a single point's region: two points cannot explain it better than one (the second
    # takes no light, or both light the same lenslets and no part is left): no cut
    prof, geom, image, stats, noise, truth, white = _capture(13.0)
    base = load_profile("system2")
    scene = {"seed": 3, "rays_per_source": 1_000_000, "camera": CAMERA, "sensor": NOISE,
             "exposure": {"peak": 0.5},
             "objects": [{"type": "point", "distance_mm": 1500.0, "position_mm": [0.0, 5.0]}]}
    raw, used, _ = simulate(base, scene_from_dict(scene))
    img = raw.astype(np.float64) - used.sensor.black_level
    st = lenslet_stats(img, geom.lmap)
    capture_noise(img, geom.lmap, geom.pitch_px, st,
                  sensor_gain=distance.sensor_gain(prof, white))
    (region,) = find_regions(st, geom.lmap, geom.pitch_px)
    assert fastfit.measure_lenslet(prof, geom, img, region, distance.noise_sigma(img),
                                   others=nearby_regions([region])[0]).status == "ok"
    assert overlap.split_overlap(prof, geom, img, st, region, 1) is None


def test_the_light_field_fit_measures_both_parts():
    # measure_lightfield on each part of the cut, the other its neighbour: its lenslet starts
    # read the part as measure_lenslet does (band and neighbour left out: fastfit.
    # region_moments); with the box's own moments both parts were poor-fit after ~20 s each
    from lfcam.measure import measure_lightfield

    prof, geom, image, stats, noise, truth, white = _capture(13.0)
    (region,) = find_regions(stats, geom.lmap, geom.pitch_px)
    parts = overlap.split_overlap(prof, geom, image, stats, region, 1).parts
    found = set()
    for part, other in ((parts[0], parts[1]), (parts[1], parts[0])):
        m = measure_lightfield(prof, geom, image, part, noise, nearby=(other,))
        k = int(np.argmin([np.hypot(part.centroid_px[0] - s["centroid_px"][0],
                                    part.centroid_px[1] - s["centroid_px"][1])
                           for s in truth["sources"]]))
        d = truth["sources"][k]["distance_mm"]
        assert m.status == RegionStatus.OK, (k, m.status)
        # measured: −0.032 % and +0.008 % (σ 0.10-0.11 %), 4.1 s each
        assert abs(m.distance_mm / d - 1) < min(3 * m.sigma_distance_mm / d, 1e-3), (k, m)
        found.add(k)
    assert found == {0, 1}


def test_spread_of_two_equal_discs_is_their_separation():
    # two uniform discs (radius 1) 0.6 apart along a 30° axis, sampled on a fine grid: the
    # second moments place the two points at their centres (analytic: the variance along the
    # axis exceeds the variance across it by a quarter of the separation squared)
    g = np.arange(-3, 3, 0.01)
    xx, yy = np.meshgrid(g, g)
    pos = np.column_stack([xx.ravel(), yy.ravel()]) + [0.4, -0.2]
    axis = np.array([np.cos(np.pi / 6), np.sin(np.pi / 6)])
    centres = np.array([[0.4, -0.2] - 0.3 * axis, [0.4, -0.2] + 0.3 * axis])
    w = sum((np.hypot(*(pos - c).T) <= 1.0).astype(float) for c in centres)
    got = overlap._spread(pos, w)
    if (got[0] - got[1]) @ (centres[0] - centres[1]) < 0:
        got = got[::-1]
    np.testing.assert_allclose(got, centres, atol=5e-3)


def test_near_coincident_sources_are_two_answers_not_one_line(monkeypatch):
    # system 1, 1 400 and 1 500 mm a tenth of a blur apart (light centroids 11 px, blurs
    # ~106 / 110 px): one region, which a short line explains to 2.7-2.9 × its noise misfit
    # (1 440.9 mm, +2.9 % from the nearer source at 7.9σ); two points leave under the noise
    # misfit, and too nearly one blur to cut: both answers are the joint fit's
    pair = {"system": "system1"}
    before, truth = _run(4.0, monkeypatch, split=False, **pair)
    (line,) = before.regions
    assert line.kind == "line" and line.status == RegionStatus.OK
    assert min(abs(line.distance_mm / s["distance_mm"] - 1) for s in truth["sources"]) > 0.02
    after, truth = _run(4.0, monkeypatch, split=True, **pair)
    # measured: +0.148 % (0.8σ) and −0.074 % (0.4σ)
    _check_both(after, truth, bound=5e-3)


def test_a_pair_in_front_of_focus_is_found_from_its_spread(monkeypatch):
    # system 2, 300 and 320 mm in front of a 1 m focus, 42 px apart (blurs ~800 lenslets,
    # ~95 % overlap): the footprint's halves start the two-point fit in a wrong basin
    # (259 / 251 mm, misfit 0.53 against a noise misfit of 0.027); two points as far apart as
    # the second moments say find both (misfit 0.018); the cut's crescents fail their own
    # fits, and the joint fit's answers stand
    pair = {"system": "system2", "distances": (300.0, 320.0)}
    prof, geom, image, stats, noise, truth, white = render_pair(3.0, True, **pair)
    (region,) = find_regions(stats, geom.lmap, geom.pitch_px)
    halves = overlap.two_points(prof, geom, image, region, starts="halves")
    spread = overlap.two_points(prof, geom, image, region, starts="spread")
    assert halves.misfit > 10 * halves.noise_misfit
    assert spread.misfit < spread.noise_misfit
    before, _ = _run(3.0, monkeypatch, split=False, **pair)
    assert [r.status for r in before.regions] == [RegionStatus.POOR_FIT]
    after, truth = _run(3.0, monkeypatch, split=True, **pair)
    # measured: −0.002 % and +0.004 % (σ 0.03 %, its floor)
    _check_both(after, truth, bound=1e-3)


def test_a_joint_answer_without_a_finite_sigma_is_refused():
    # a singular Jacobian leaves a distance's σ infinite: that source is poor-fit, the other
    # keeps its answer (its distance from the front vertex, σ with the 0.03 % floor)
    prof = load_profile("system2")
    z = prof.main_lens.front_vertex_z_mm
    src = np.array([[0.0, 0.0, z - 1400.0], [0.0, 0.0, z - 1500.0]])
    answer = overlap.JointAnswer(src, np.array([np.inf, 1.0]), 0.01)
    two = overlap.TwoPoints(src, 0.01, np.ones((2, 3)), np.arange(3), 0.02, lambda: answer)
    geom = type("G", (), {"d_in_mm": prof.d_in_mm})()
    first, second = overlap.joint_measurements(prof, geom, two)
    assert first.status == RegionStatus.POOR_FIT
    assert second.status == RegionStatus.OK
    assert second.distance_mm == pytest.approx(1500.0, rel=1e-9)
    floor_mm = fastfit.SIGMA_FLOOR_REL * 1500.0
    assert second.sigma_distance_mm == pytest.approx(np.hypot(1.0, floor_mm), rel=1e-9)
