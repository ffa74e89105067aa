"""Two sources whose blurs touch: one cluster of lit lenslets, cut at its waist into two regions,
each measured with the other as its neighbour and the lenslets both light left out, and
refitted without the light the other's fitted source puts past the band.

Truth: the renderer's distances (``lfcam.sim``, the rays' own noise: 10⁶ a source, no sensor
noise), and the region finder's old answer for the same capture (one ``multiple`` region, no
distance) as the case the cut is for (docs/distance.md, "Touching blurs cut at their waist
(stop 67)"); for the neighbour's light, each source rendered alone, and the same captures'
answers without it taken out (docs/distance.md, "A touching blur's light taken out (stop
71)").
"""

from __future__ import annotations

import numpy as np
import pytest
from twin_points import errors_by_source, render_pair

from lfcam import distance
from lfcam.measure import fastfit, overlap
from lfcam.measure import regions as regions_module
from lfcam.measure.regions import find_regions, nearby_regions
from lfcam.status import RegionStatus, unsupported


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


@pytest.mark.parametrize("line_mm, apart, lit", [
    (0.0, 14.0, 1),  # a point pair (measured: the 1 500 mm point +0.348 → +0.053 %, σ 0.05 %)
    (10.0, 12.0, 0),  # a 14 mm line beside a point (the line +0.786 → −0.000 %, σ 0.12 %;
    #                   refitted from scratch, not from its first answer: −0.024 %)
])
def test_a_touching_blurs_light_is_taken_out(line_mm, apart, lit, monkeypatch):
    prof, geom, image, stats, noise, truth, white = render_pair(apart, True,
                                                                first_line_mm=line_mm)
    regions = find_regions(stats, geom.lmap, geom.pitch_px)
    assert len(regions) == 2 and all(r.touching for r in regions)
    runs = {}
    for out in (False, True):
        monkeypatch.setattr(distance, "NEIGHBOURS_OUT", out)
        run = distance.run_distance(image, prof, None, model="exact", method="lenslet",
                                    geometry=geom, jobs=1, white_value=white)
        runs[out] = errors_by_source(run, truth)
    # source ``lit`` reads the other's light past the band as its own: long, by ~3σ
    err, sigma = runs[False][lit]
    assert err > max(3e-3, 2.5 * sigma), runs[False]
    for k in (0, 1):
        err, sigma = runs[True][k]
        assert abs(err) < min(3 * sigma, 1.5e-3), (k, runs[True])
    # the other side, which ``lit``'s light past the band does not reach, is not refitted
    assert runs[True][1 - lit] == runs[False][1 - lit]


def test_neighbour_light_is_the_sources_own():
    # the light the 1 400 mm point's fitted source puts on the 1 500 mm point's lenslets
    # against that point rendered alone (the renderer's rays, scaled to the pair's data on
    # its own region)
    prof, geom, image, stats, noise, truth, white = render_pair(14.0, True)
    alone = render_pair(14.0, False, only=0)[2]  # (no sensor noise: the rays' own alone)
    regions = find_regions(stats, geom.lmap, geom.pitch_px)
    near = nearby_regions(regions)
    c1 = np.array(truth["sources"][0]["centroid_px"])
    b = int(np.argmin([np.hypot(*(np.array(r.centroid_px) - c1)) for r in regions]))
    a = 1 - b
    meas = fastfit.measure_lenslet(prof, geom, image, regions[b], noise, others=near[b])
    assert meas.method == "lenslet" and len(meas.fitted_mm) == 1
    mom = fastfit.region_moments(geom, image, regions[a], near[a])
    light = overlap.neighbour_light(prof, geom, image, mom, [(regions[b], near[b], meas)])
    # the renderer's: the point alone, on the same lenslets, scaled by its own region's data
    own = fastfit.region_moments(geom, image, regions[b], near[b]).data
    own_alone = fastfit.region_moments(geom, alone, regions[b], near[b]).data
    scale = float((own * own_alone).sum() / (own_alone * own_alone).sum())
    truth_light = scale * fastfit.region_moments(geom, alone, regions[a], near[a]).data
    # 2.5 % of the region's own light (norms of the moments); the model's misses the
    # renderer's by 4.0 % of it (the rays' noise of both in it), its norm by +1.0 %
    share = np.linalg.norm(truth_light) / mom.norm
    assert 0.015 < share < 0.04, share
    miss = np.linalg.norm(light - truth_light) / np.linalg.norm(truth_light)
    assert miss < 0.06, miss


def test_a_side_the_band_took_is_no_blur(monkeypatch):
    # two lines in a T (system 2, 1 400 mm across, 1 500 mm along the pair's line, 12 ‰
    # apart): the band about the waist takes 395 lenslets, most of the 1 500 mm line's blur,
    # and leaves its side 8. That rim is reported as `multiple` (no distance), not as a
    # `near-focus` blur; the other side's line is measured (1 399.8 mm)
    prof, geom, image, stats, noise, truth, white = render_pair(12.0, True, first_line_mm=10.0,
                                                                second_line_mm=10.0)
    regions = find_regions(stats, geom.lmap, geom.pitch_px)
    assert sorted(r.kind for r in regions) == ["line", "multiple"]
    sliver = next(r for r in regions if r.kind == "multiple")
    assert sliver.lenslets.size < regions_module.SLIVER_SHARE * sliver.shared.size
    run = distance.run_distance(image, prof, None, model="exact", method="lenslet",
                                geometry=geom, jobs=1, white_value=white)
    got = {r.kind: r for r in run.regions}
    assert got["multiple"].status == unsupported("multiple")
    line = got["line"]
    assert line.status == RegionStatus.OK
    assert abs(line.distance_mm / 1400.0 - 1) < min(3 * line.uncertainty_mm / 1400.0, 2e-3)
    # the rule off: the same lenslets, fitted, read as a blur near focus
    monkeypatch.setattr(regions_module, "SLIVER_SHARE", 0.0)
    run = distance.run_distance(image, prof, None, model="exact", method="lenslet",
                                geometry=geom, jobs=1, white_value=white)
    assert sorted(r.status for r in run.regions) == [RegionStatus.NEAR_FOCUS, RegionStatus.OK]


def _unmeasured_without(switch: str, capture: tuple, monkeypatch):
    """The distance run of a capture of one region with ``lfcam.distance``'s ``switch`` on,
    after checking that with it off the region is ``poor-fit``."""
    prof, geom, image, stats, _, _, white = capture
    assert len(find_regions(stats, geom.lmap, geom.pitch_px)) == 1
    runs = []
    for on in (False, True):
        monkeypatch.setattr(distance, switch, on)
        runs.append(distance.run_distance(image, prof, None, model="exact", method="lenslet",
                                          geometry=geom, jobs=1, white_value=white))
    assert [r.status for r in runs[0].regions] == [RegionStatus.POOR_FIT]
    return runs[1]


@pytest.mark.parametrize("apart", [4.0, 8.0])
def test_a_point_and_a_line_in_one_region_are_both_measured(apart, monkeypatch):
    # a 14 mm line at 1 400 mm and a point at 1 500 mm, 4 and 8 ‰ of their distance from the
    # axis on either side: one region that no point, line or two points explain (poor-fit,
    # both sources unmeasured); fitted by turns as a point and a line, each source is
    # measured (seed 7: the line +0.014 / +0.025 %, the point +0.024 / -0.042 %)
    capture = render_pair(apart, True, first_line_mm=10.0)
    run = _unmeasured_without("POINT_AND_LINE", capture, monkeypatch)
    errors = errors_by_source(run, capture[5])
    assert {r.kind for r in run.regions} == {"spot", "line"}
    # the line is source 0 (its region the `line` one), the point source 1
    assert next(r for r in run.regions if r.kind == "line").distance_mm < 1450.0
    for k in (0, 1):
        err, sigma = errors[k]
        assert abs(err) < min(3 * sigma, 2e-3), (k, errors)


def test_a_refit_starts_from_the_first_answer():
    """The refit without the neighbour's light, started from the region's first answer (no
    point fit, scan or race for a line; no scan for a point), reads the truth as the refit
    from scratch does, and traces under three quarters of its rays (a count, not a time)."""
    prof, geom, image, stats, noise, truth, _ = render_pair(12.0, True, first_line_mm=10.0)
    regions = find_regions(stats, geom.lmap, geom.pitch_px)
    near = nearby_regions(regions)
    first = [fastfit.measure_lenslet(prof, geom, image, r, noise, others=n)
             for r, n in zip(regions, near, strict=True)]
    centroids = np.array([s["centroid_px"] for s in truth["sources"]])
    for k, region in enumerate(regions):
        j = int(np.argmin(np.hypot(*(centroids - np.array(region.centroid_px)).T)))
        truth_mm = truth["sources"][j]["distance_mm"]
        mom = fastfit.region_moments(geom, image, region, near[k])
        light = overlap.neighbour_light(prof, geom, image, mom,
                                        [(regions[1 - k], near[1 - k], first[1 - k])])
        spent = {}
        for warm in (False, True):
            with fastfit.counting_rays() as rays:
                m = fastfit.measure_lenslet(prof, geom, image, region, noise, others=near[k],
                                            light=light, start=first[k] if warm else None)
            spent[warm] = rays[0]
            err = m.distance_mm / truth_mm - 1.0
            assert m.status == "ok" and m.kind == first[k].kind, (k, warm, m.status)
            # measured: the line -0.024 % from scratch, -0.000 % from its first answer (+0.79 %;
            # sigma 0.12 %); the point -0.064 % and -0.029 % (sigma 0.08 %)
            assert abs(err) < min(3.0 * m.sigma_distance_mm / truth_mm, 1.5e-3), (k, warm, err)
        # measured: the line 1.94 -> 1.34 million rays (no point fit, scan or race; one coarse
        # Jacobian, then the fine stage), the point 1.23 -> 0.60 (no scan or summary matching)
        assert spent[True] < 0.75 * spent[False], (first[k].kind, spent)


def test_two_lines_in_one_region_are_both_measured(monkeypatch):
    # a 14 mm line at 1 400 mm across the pair's line and a 15 mm line at 1 500 mm along it (a
    # T), 14 ‰ of their distance from the axis on either side: one region that no point, line,
    # two points or point and line explain (poor-fit); fitted by turns as two lines, each first
    # on the lenslets the other's light leaves nearly alone, both are measured (seed 7: the
    # 1 400 mm line +0.008 %, the 1 500 mm one -0.005 %, sigma 0.11 %)
    capture = render_pair(14.0, True, first_line_mm=10.0, second_line_mm=10.0)
    run = _unmeasured_without("TWO_LINES", capture, monkeypatch)
    assert [r.kind for r in run.regions] == ["line", "line"]
    errors = errors_by_source(run, capture[5])
    for k in (0, 1):
        err, sigma = errors[k]
        assert abs(err) < min(3 * sigma, 2e-3), (k, errors)


def test_two_lines_are_not_tried_on_a_round_region(monkeypatch):
    # two points 1 ‰ of their distance apart in front of focus (300 and 320 mm): one round
    # region (elongation 1.0) that no fit explains; two lines are not tried there (the try
    # failed and cost ~0.3 s), as they are on the T's region (elongation 2.0)
    prof, geom, image, stats, noise, truth, white = render_pair(1.0, True,
                                                                distances=(300.0, 320.0))
    regions = find_regions(stats, geom.lmap, geom.pitch_px)
    assert len(regions) == 1 and regions[0].elongation < distance.TWO_LINES_ELONGATION
    seconds = []
    by_turns = overlap.by_turns

    def logged(*args, second="spot", **kwargs):
        seconds.append(second)
        return by_turns(*args, second=second, **kwargs)

    monkeypatch.setattr(overlap, "by_turns", logged)
    run = distance.run_distance(image, prof, None, model="exact", method="lenslet",
                                geometry=geom, jobs=1, white_value=white)
    assert [r.status for r in run.regions] == [RegionStatus.POOR_FIT]
    assert seconds == ["spot"]


@pytest.mark.parametrize("rho", [0.0, 0.5, 0.9])
def test_marginal_over_own_is_the_widening_a_correlation_gives(rho):
    # two parameters whose Jacobian columns correlate by ρ, each in a block with a nuisance
    # column orthogonal to everything: the σ of each with both free is its σ with the other
    # held fixed over √(1 − ρ²) (the Schur complement of a 2 × 2 normal matrix)
    rng = np.random.default_rng(5)
    basis, _ = np.linalg.qr(rng.normal(size=(400, 4)))
    a, b, n1, n2 = basis.T
    jac = np.c_[3.0 * a, 0.5 * (rho * a + np.sqrt(1.0 - rho * rho) * b), n1, 2.0 * n2]
    f = overlap.marginal_over_own(jac, [[0, 2], [1, 3]])
    assert f == pytest.approx((1.0 / np.sqrt(1.0 - rho * rho),) * 2, rel=1e-9)
    # a singular problem (one column twice) widens nothing it cannot state
    assert overlap.marginal_over_own(np.c_[a, a], [[0], [1]]) == (1.0, 1.0)


def test_a_point_and_a_line_by_turns_state_their_coupling(monkeypatch):
    # system 1's point beside a line 12 ‰ apart (34 px in ~106 px blurs), fitted by turns:
    # each fit's own σ holds the other's light fixed, but the two trade light (the line reads
    # long where the point reads short); with both free each σ is 1.2-1.4 × wider
    # (docs/distance.md, "Two sources' σ with both free (stop 74)")
    capture = render_pair(12.0, True, system="system1", first_line_mm=10.0)
    prof, geom, image, stats, noise, truth, white = capture
    sigmas = []
    for on in (False, True):
        monkeypatch.setattr(overlap, "PL_COUPLED_SIGMA", on)
        run = distance.run_distance(image, prof, None, model="exact", method="lenslet",
                                    geometry=geom, jobs=1, white_value=white)
        assert sorted(r.kind for r in run.regions) == ["line", "spot"]
        errors = errors_by_source(run, truth)
        sigmas.append([errors[k][1] for k in (0, 1)])
        if on:
            for k in (0, 1):
                err, sigma = errors[k]
                assert abs(err) < min(3 * sigma, 4e-3), (k, errors)
    ratio = np.array(sigmas[1]) / np.array(sigmas[0])
    assert np.all((ratio > 1.1) & (ratio < 1.6)), ratio
