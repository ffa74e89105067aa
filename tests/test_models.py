"""Distance models against the exact forward trace, the seed's findings and Hahne's figures."""

from __future__ import annotations

import math

import numpy as np
import pytest
from seed_grid import SEED_DISTANCES_MM, SEED_OFFSETS_MM, seed_error_pct

from lfcam import load_profile
from lfcam.errors import ModelError
from lfcam.models import exact, hahne, line, offaxis, onaxis, point_model, thin
from lfcam.models.base import Status
from lfcam.optics.trace import forward

EXACT_RTOL = 1e-9


def _seed_errors(profile, model):
    """ERROR (%) of ``model`` on the seed grid, fed exact rim-ray heights; shape (3, 16)."""
    rows = []
    for dh in SEED_OFFSETS_MM:
        fw = forward(profile, None, SEED_DISTANCES_MM, dh)
        inv = model(profile, None, fw.y1_mm, fw.y2_mm)
        assert (inv.status == Status.OK).all()
        thickness = profile.main_lens.thickness_mm
        rows.append(seed_error_pct(SEED_DISTANCES_MM, inv.distance_mm, thickness))
    return np.array(rows)


@pytest.mark.parametrize("name", ["system1", "system2"])
@pytest.mark.parametrize("focus", [300.0, 1000.0, 3500.0, math.inf])
def test_exact_round_trip_over_the_domain(name, focus):
    p = load_profile(name).with_focus(focus)
    f, d = p.main_lens.focal_length_mm, p.main_lens.pupil_diameter_mm
    dist = np.geomspace(1.2 * f, 1e6, 60)
    off = np.linspace(-0.45 * d, 0.45 * d, 7)
    dist, off = np.meshgrid(dist, off)
    fw = forward(p, None, dist, off)
    assert (fw.status == 0).all()
    inv = exact.invert(p, None, fw.y1_mm, fw.y2_mm)
    assert (inv.status == Status.OK).all()
    np.testing.assert_allclose(inv.distance_mm, dist, rtol=EXACT_RTOL)
    assert (np.abs(inv.offset_mm - off) <= EXACT_RTOL * dist).all()


def test_field_note_1_offaxis_reproduces_seed_level_errors():
    """docs/models.md: eqs. 1–17 on exact heights, focus 3.5 m: 5.55 % (sys 1), 2.16 % (sys 2)."""
    e1 = _seed_errors(load_profile("system1"), offaxis.invert)
    e2 = _seed_errors(load_profile("system2"), offaxis.invert)
    assert e1.mean() == pytest.approx(5.55, abs=0.01)
    assert e2.mean() == pytest.approx(2.16, abs=0.01)


@pytest.mark.parametrize("name", ["system1", "system2"])
def test_table2_qualitative_finding(name):
    """Seed Table 2: offaxis error grows with distance; exact has none."""
    p = load_profile(name)
    e = _seed_errors(p, offaxis.invert)
    # SEED_DISTANCES_MM runs from far to near: error must fall monotonically along it
    assert (np.diff(e, axis=1) < 0).all()
    assert e[:, 0].min() > 3.0 * e[:, -1].max()
    assert _seed_errors(p, exact.invert).max() * 1e-2 <= EXACT_RTOL


def test_system1_worse_than_system2_as_in_the_seed():
    e1 = _seed_errors(load_profile("system1"), offaxis.invert)
    e2 = _seed_errors(load_profile("system2"), offaxis.invert)
    assert (e1.mean(axis=0) > e2.mean(axis=0)).all()


def test_offaxis_answers_are_symmetric_in_offset(profile):
    a = forward(profile, None, SEED_DISTANCES_MM, 7.0)
    b = forward(profile, None, SEED_DISTANCES_MM, -7.0)
    ia = offaxis.invert(profile, None, a.y1_mm, a.y2_mm)
    ib = offaxis.invert(profile, None, b.y1_mm, b.y2_mm)
    np.testing.assert_allclose(ia.distance_mm, ib.distance_mm, rtol=1e-12)
    np.testing.assert_allclose(ia.offset_mm, -ib.offset_mm, rtol=1e-9)


def test_onaxis_equals_offaxis_for_on_axis_sources(profile):
    fw = forward(profile, None, SEED_DISTANCES_MM, 0.0)
    a = onaxis.invert(profile, None, fw.y1_mm, fw.y2_mm)
    b = offaxis.invert(profile, None, fw.y1_mm, fw.y2_mm)
    np.testing.assert_allclose(a.distance_mm, b.distance_mm, rtol=1e-12)
    assert (a.offset_mm == 0).all()


def test_thin_inverts_its_own_forward_and_is_paraxially_right(profile):
    dist = np.geomspace(150.0, 1e5, 40)
    y1, y2 = thin.forward(profile, None, dist, 4.0)
    inv = thin.invert(profile, None, y1, y2)
    np.testing.assert_allclose(inv.distance_mm, dist, rtol=1e-10)
    np.testing.assert_allclose(inv.offset_mm, 4.0, rtol=1e-8)


def test_thin_reports_no_solution_where_aberration_defeats_it():
    """At F/2 the marginal rays of a far source cross before the paraxial focus."""
    p = load_profile("system1")
    fw = forward(p, None, np.array([3500.0]), 0.0)
    inv = thin.invert(p, None, fw.y1_mm, fw.y2_mm)
    assert inv.status[0] == Status.NO_SOLUTION and np.isnan(inv.distance_mm[0])


def test_line_model_on_ten_mm_lines(profile):
    a = forward(profile, None, SEED_DISTANCES_MM, -5.0)
    b = forward(profile, None, SEED_DISTANCES_MM, 5.0)
    inv = line.invert(profile, None, a.y1_mm, a.y2_mm, b.y1_mm, b.y2_mm)
    assert (inv.status == Status.OK).all()
    err = seed_error_pct(SEED_DISTANCES_MM, inv.distance_mm, profile.main_lens.thickness_mm)
    point = _seed_errors(profile, offaxis.invert).mean(axis=0)
    # eq. 20 inherits eq. 14's approximation: same error level as the point model (±10 %)
    np.testing.assert_allclose(err, point, rtol=0.1)
    np.testing.assert_allclose(inv.offset_mm, 0.0, atol=1e-6)


def test_line_model_flags_cancellation_for_short_lines():
    p = load_profile("system1")
    a = forward(p, None, np.array([2000.0, 2000.0]), np.array([3.0, -5.0]))
    b = forward(p, None, np.array([2000.0, 2000.0]), np.array([3.0 + 1e-7, 5.0]))
    inv = line.invert(p, None, a.y1_mm, a.y2_mm, b.y1_mm, b.y2_mm)
    assert inv.status[0] == Status.ILL_CONDITIONED and np.isnan(inv.distance_mm[0])
    assert inv.status[1] == Status.OK


def test_bad_heights_get_a_status(profile):
    # NaN, inf, and rim rays crossed by two metres (a source 'beyond infinity')
    y1 = np.array([np.nan, np.inf, -1e3, 3.0, 0.0])
    y2 = np.array([0.0, 0.0, 1e3, 3.0, 0.0])
    for name in ("exact", "offaxis", "onaxis", "thin"):
        inv = point_model(name)(profile, None, y1, y2)
        assert (inv.status[:3] != Status.OK).all(), name
        bad = inv.status != Status.OK
        assert np.isnan(inv.distance_mm[bad]).all() and np.isfinite(inv.distance_mm[~bad]).all()


def test_unknown_model_is_a_clear_error():
    with pytest.raises(ModelError, match="exact"):
        point_model("magic")


HAHNE_REF = dict(pp=0.009, fs=2.75, pm=0.125, dA=111.0324, fU=193.2935, HH=-65.5563, M=13.9523)


def test_hahne_reference_figures():
    res = hahne.refocus_distance(hahne.HahneParameters(df=math.inf, **HAHNE_REF), 1.0)
    assert float(res.distance_mm) == pytest.approx(962.7459, abs=1e-4)
    assert float(res.far_mm) == pytest.approx(1098.2788, abs=1e-4)
    assert float(res.near_mm) == pytest.approx(846.6410, abs=1e-4)
    at_focus = hahne.refocus_distance(hahne.HahneParameters(df=4000.0, **HAHNE_REF), 0.0)
    assert float(at_focus.distance_mm) == pytest.approx(4000.0, rel=1e-12)


def test_hahne_closed_form_inverse_agrees_with_ray_pairs():
    params = hahne.HahneParameters(df=4000.0, **HAHNE_REF)
    shifts = np.array([-0.2, 0.0, 0.5, 1.0, 1.5, 2.0])
    d = hahne.refocus_distance(params, shifts).distance_mm
    np.testing.assert_allclose(hahne.shift_for_distance(params, d), shifts, atol=1e-9)
    assert (np.diff(d) < 0).all()  # larger shifts focus closer


def test_hahne_parameters_of_our_camera_refocus_at_focus(profile):
    params = hahne.parameters_for(profile)
    at_zero = float(hahne.refocus_distance(params, 0.0).distance_mm)
    expected = profile.mla.focus_mm + hahne.mla_to_front_vertex_mm(profile)
    assert at_zero == pytest.approx(expected, rel=1e-9)
