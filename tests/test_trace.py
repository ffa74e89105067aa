"""Exact trace: two independent implementations agree, paraxial limit, field-note figures."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lfcam import load_profile
from lfcam.camera import MainLens
from lfcam.models import thin
from lfcam.optics.trace import TraceStatus, forward, meridional_rim_heights, trace_rays


def test_meridional_and_3d_traces_agree(profile):
    lens = profile.main_lens
    z = profile.sensor_z_mm
    dist = np.geomspace(1.2 * lens.focal_length_mm, 1e6, 50)
    for off in (-10.0, 0.0, 7.5):
        fw = forward(profile, None, dist, off)  # 3-D vector trace
        along = dist + lens.rim_sag_mm
        half = 0.5 * lens.pupil_diameter_mm
        y1, ok1 = meridional_rim_heights(lens, 1.0, (half - off) / along, z)
        y2, ok2 = meridional_rim_heights(lens, -1.0, (-half - off) / along, z)
        assert ok1.all() and ok2.all() and (fw.status == 0).all()
        np.testing.assert_allclose(fw.y1_mm, y1, rtol=0, atol=1e-11)
        np.testing.assert_allclose(fw.y2_mm, y2, rtol=0, atol=1e-11)


def _with_pupil(profile, pupil_mm):
    lens = profile.main_lens
    return profile.__class__(
        name="small",
        main_lens=MainLens(lens.radius_mm, lens.thickness_mm, lens.refractive_index, pupil_mm),
        mla=profile.mla,
        sensor=profile.sensor,
    )


def _paraxial_misfit(profile, pupil_mm, offset_mm):
    small = _with_pupil(profile, pupil_mm)
    dist = np.array([300.0, 1000.0, 3500.0])
    fw = forward(small, None, dist, offset_mm)
    p1, p2 = thin.forward(small, None, dist, offset_mm)
    return np.abs((fw.y1_mm - fw.y2_mm) / (p1 - p2) - 1.0)


def test_paraxial_limit_matches_thin_lens_model():
    """Exact trace → Gaussian optics: on axis the misfit is spherical aberration (∝ D²),
    off axis the field aberrations add a term ∝ offset² that does not shrink with D."""
    base = load_profile("system1")
    on_02 = _paraxial_misfit(base, 0.2, 0.0)
    on_01 = _paraxial_misfit(base, 0.1, 0.0)
    assert on_02.max() < 1e-4
    np.testing.assert_allclose(on_02 / on_01, 4.0, rtol=0.02)
    off_2 = _paraxial_misfit(base, 0.1, 2.0)
    off_1 = _paraxial_misfit(base, 0.1, 1.0)
    assert off_2[0] / off_1[0] == pytest.approx(4.0, rel=0.05)


def test_field_note_blur_sizes_system2_focus_infinity():
    """docs/distance.md: rim spread 10.7 mm at 300 mm, 0.41 at 1500, 2.04 at 3500 (crossed)."""
    p = load_profile("system2").with_focus(math.inf)
    fw = forward(p, None, np.array([300.0, 1500.0, 3500.0]), 0.0)
    spread = fw.y1_mm - fw.y2_mm
    np.testing.assert_allclose(np.abs(spread), [10.7, 0.41, 2.04], rtol=0.01)
    assert spread[0] > 0 and spread[1] < 0 and spread[2] < 0  # rays have crossed beyond ~1 m


def test_on_axis_source_is_symmetric(profile):
    fw = forward(profile, None, np.array([500.0, 2000.0]), 0.0)
    np.testing.assert_allclose(fw.y1_mm, -fw.y2_mm, atol=1e-13)


def test_snell_invariant_at_exit():
    """n·sin(angle inside) = sin(angle outside) about the back-surface normal (3-D trace)."""
    lens = load_profile("system1").main_lens
    rng = np.random.default_rng(1)
    n = 200
    origins = np.column_stack([rng.uniform(-20, 20, n), rng.uniform(-20, 20, n),
                               np.full(n, -800.0)])
    targets = np.column_stack([rng.uniform(-15, 15, n), rng.uniform(-15, 15, n),
                               np.full(n, lens.rim_z_mm)])
    d = targets - origins
    res = trace_rays(lens, origins, d, 50.0)
    ok = res.status == 0
    assert ok.all()
    # exit point on the back sphere: step back along the outgoing ray from the plane
    c2 = np.array([0.0, 0.0, lens.back_vertex_z_mm - lens.radius_mm])
    out = res.directions
    p = res.points
    # intersect line p - s·out with the sphere, nearest to the plane
    oc = p - c2
    b = np.einsum("ij,ij->i", out, oc)
    cc = np.einsum("ij,ij->i", oc, oc) - lens.radius_mm**2
    s = b - np.sqrt(b * b - cc)
    q = p - s[:, None] * out
    normal = (q - c2) / lens.radius_mm
    sin_out = np.linalg.norm(np.cross(normal, out), axis=1)
    # inside direction: from the entry point on the front sphere to q
    entry_dir = d / np.linalg.norm(d, axis=1, keepdims=True)
    c1 = np.array([0.0, 0.0, lens.front_vertex_z_mm + lens.radius_mm])
    oc1 = origins - c1
    b1 = np.einsum("ij,ij->i", entry_dir, oc1)
    cc1 = np.einsum("ij,ij->i", oc1, oc1) - lens.radius_mm**2
    e = origins + (-b1 - np.sqrt(b1 * b1 - cc1))[:, None] * entry_dir
    inside = (q - e) / np.linalg.norm(q - e, axis=1, keepdims=True)
    sin_in = np.linalg.norm(np.cross(normal, inside), axis=1)
    np.testing.assert_allclose(lens.refractive_index * sin_in, sin_out, rtol=1e-9)
    # and at the entry: sin(incidence) = n·sin(refraction)
    n1 = (e - c1) / lens.radius_mm
    np.testing.assert_allclose(
        np.linalg.norm(np.cross(n1, entry_dir), axis=1),
        lens.refractive_index * np.linalg.norm(np.cross(n1, inside), axis=1),
        rtol=1e-9,
    )


def test_failures_carry_a_status_not_a_silent_nan():
    lens = load_profile("system1").main_lens
    origins = np.array([[0.0, 0.0, -500.0], [0.0, 0.0, -500.0], [0.0, 0.0, -500.0]])
    dirs = np.array([[0.0, 0.0, 1.0], [0.0, 0.2, 1.0], [0.0, 0.0, -1.0]])
    res = trace_rays(lens, origins, dirs, 110.0)
    assert res.status[0] == TraceStatus.OK and np.isfinite(res.points[0]).all()
    assert res.status[1] == TraceStatus.VIGNETTED  # lands 100 mm up: outside the 25 mm rim
    assert res.status[2] != TraceStatus.OK
    assert np.isnan(res.points[1:]).all()
    # TIR: a steep ray entering the rim from a near, far-off-axis source
    fw = forward(load_profile("system1"), None, np.array([1.0]), np.array([-300.0]))
    assert fw.status[0] != TraceStatus.OK and np.isnan(fw.y1_mm[0])
