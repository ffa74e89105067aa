"""General lens model and exact tracer: ray-optics reference figures, legacy singlet, statuses,
ray aiming, zmx / TOML lens files."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from lfcam import load_profile
from lfcam.errors import OpticsError, ProfileError, ZmxError
from lfcam.optics import raytrace as rt
from lfcam.optics.lens import Prescription, Surface
from lfcam.optics.raytrace import RayStatus, best_focus_object_distance, best_focus_z
from lfcam.optics.trace import TraceStatus, forward, trace_backward_fast, trace_rays
from lfcam.optics.zmx import (
    GLASS_ND,
    load_zmx,
    parse_zmx,
    prescription_from_toml_dict,
    prescription_to_toml_dict,
)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

DATA = Path(__file__).parent / "data"
LENSES = ("seed_singlet", "cooke_triplet", "double_gauss")
REFERENCE = json.loads((DATA / "lens_reference.json").read_text())


@pytest.fixture(scope="module")
def lenses() -> dict[str, Prescription]:
    return {name: load_zmx(DATA / "lenses" / f"{name}.zmx").prescription for name in LENSES}


@pytest.fixture(scope="module")
def singlet_profile():
    return load_profile("system1")


@pytest.fixture(scope="module")
def singlet(singlet_profile) -> Prescription:
    lens = singlet_profile.main_lens
    return Prescription.from_singlet(
        lens.radius_mm, lens.thickness_mm, lens.refractive_index, lens.pupil_diameter_mm
    )


# ----------------------------------------------------------------------------- ray-optics


@pytest.mark.parametrize("name", LENSES)
def test_first_order_data_match_ray_optics(lenses, name):
    ref = REFERENCE["lenses"][name]
    lens = lenses[name]
    assert lens.stop_index == ref["stop_index"]
    assert [s.refractive_index for s in lens.surfaces] == ref["indices_after_surface"]
    par = lens.paraxial
    efl = ref["first_order"]["efl_mm"]
    for key, value in ref["first_order"].items():
        # positions may be ~0 (singlet entrance pupil): relative to max(|value|, EFL)
        tol = 1e-6 * max(abs(value), abs(efl)) if key.endswith("z_mm") else 1e-6 * abs(value)
        assert getattr(par, key) == pytest.approx(value, abs=tol), key
    for row in ref["finite_objects"]:
        gap = lens.image_distance_for(row["object_distance_mm"])
        assert gap == pytest.approx(row["image_gap_mm"], rel=1e-9)


@pytest.mark.parametrize("name", LENSES)
def test_real_ray_intercepts_match_ray_optics(lenses, name):
    ref = REFERENCE["lenses"][name]
    origins = np.array([r["origin_mm"] for r in ref["rays"]])
    directions = np.array([r["direction"] for r in ref["rays"]])
    expected = np.array([r["image_xy_mm"] for r in ref["rays"]])
    res = rt.trace(lenses[name], origins, directions, ref["image_plane_z_mm"], clip=False)
    assert (res.status == RayStatus.OK).all()
    assert np.abs(res.points[:, :2] - expected).max() < 1e-6
    assert np.any(np.abs(origins[:, 0]) > 0)  # the grid has skew rays


def test_glass_table_indices_in_reference_files(lenses):
    # the triplet's and double Gauss's named glasses come from lfcam's SCHOTT nd table
    assert lenses["cooke_triplet"].surfaces[0].refractive_index == GLASS_ND["N-LAK9"]
    assert lenses["double_gauss"].surfaces[3].refractive_index == GLASS_ND["F5"]


# ----------------------------------------------------------------------------- legacy singlet


def test_singlet_zmx_equals_from_singlet(lenses, singlet):
    zmx = lenses["seed_singlet"]
    for a, b in zip(zmx.surfaces[:1], singlet.surfaces[:1], strict=True):
        assert a == b
    assert zmx.surfaces[1].semi_diameter_mm == pytest.approx(singlet.surfaces[1].semi_diameter_mm)
    assert singlet.stop_index == 0 and singlet.surfaces[0].semi_diameter_mm == 25.0


def test_singlet_paraxial_matches_main_lens(singlet_profile, singlet):
    lens = singlet_profile.main_lens
    shift = 0.5 * lens.thickness_mm  # legacy origin = lens centre; prescription = front vertex
    par = singlet.paraxial
    assert par.efl_mm == pytest.approx(lens.focal_length_mm, rel=1e-13)
    assert par.back_principal_z_mm == pytest.approx(lens.back_principal_z_mm + shift, abs=1e-12)
    assert par.front_principal_z_mm == pytest.approx(lens.front_principal_z_mm + shift, abs=1e-12)
    assert singlet.f_number == pytest.approx(lens.f_number, rel=1e-13)
    for focus in (300.0, 3500.0, math.inf):
        z = singlet.image_plane_z_for(focus)
        assert z == pytest.approx(lens.d_in_for_focus(focus) + shift, abs=1e-9)
        assert singlet.object_distance_for(z) == pytest.approx(
            lens.focus_for_d_in(z - shift), rel=1e-9
        )
    assert singlet.object_distance_for(singlet.paraxial.back_focal_z_mm - 1.0) == math.inf
    with pytest.raises(OpticsError, match="front focal point"):
        singlet.image_plane_z_for(50.0)


def test_singlet_marginal_heights_match_legacy_forward(singlet_profile, singlet):
    shift = 0.5 * singlet_profile.main_lens.thickness_mm
    dist = np.array([150.0, 300.0, 1000.0, 3500.0, 1e6, math.inf])
    for off in (-12.0, 0.0, 7.5):
        legacy = forward(singlet_profile, None, dist, off)
        new = rt.marginal_heights(singlet, dist, off, singlet_profile.sensor_z_mm + shift)
        assert (legacy.status == TraceStatus.OK).all() and (new.status == RayStatus.OK).all()
        np.testing.assert_allclose(new.y1_mm, legacy.y1_mm, rtol=0, atol=1e-9)
        np.testing.assert_allclose(new.y2_mm, legacy.y2_mm, rtol=0, atol=1e-9)


def test_singlet_skew_rays_match_legacy_trace_rays(singlet_profile, singlet):
    lens = singlet_profile.main_lens
    shift = 0.5 * lens.thickness_mm
    rng = np.random.default_rng(3)
    n = 2000
    src = np.column_stack(
        [rng.uniform(-30, 30, n), rng.uniform(-30, 30, n), -rng.uniform(50, 5e3, n)]
    )
    aim = np.column_stack([rng.uniform(-30, 30, n), rng.uniform(-30, 30, n), np.zeros(n)])
    d = aim - src
    z_plane = singlet_profile.sensor_z_mm
    legacy = trace_rays(lens, src - [0, 0, shift], d, z_plane)
    new = rt.trace(singlet, src, d, z_plane + shift)
    ok = legacy.status == TraceStatus.OK
    assert 0.3 < ok.mean() < 0.9  # both passing and vignetted rays in the sample
    np.testing.assert_array_equal(new.status == RayStatus.OK, ok)
    np.testing.assert_allclose(new.points[ok, :2], legacy.points[ok, :2], rtol=0, atol=1e-9)
    np.testing.assert_allclose(new.directions[ok], legacy.directions[ok], rtol=0, atol=1e-12)
    vig = legacy.status == TraceStatus.VIGNETTED
    assert (new.status[vig] == RayStatus.VIGNETTED).all() and (new.surface[vig] == 0).all()


def test_backward_trace_matches_legacy_and_reverses_forward(singlet_profile, singlet):
    lens = singlet_profile.main_lens
    shift = 0.5 * lens.thickness_mm
    rng = np.random.default_rng(4)
    n = 500
    z = singlet_profile.sensor_z_mm
    x, y = rng.uniform(-20, 20, n), rng.uniform(-20, 20, n)
    sx, sy = rng.uniform(-0.25, 0.25, n), rng.uniform(-0.25, 0.25, n)
    legacy = trace_backward_fast(lens, x, y, z, sx, sy)
    origins = np.column_stack([x, y, np.full(n, z + shift)])
    dirs = -np.column_stack([sx, sy, np.ones(n)])
    new = rt.trace_backward(singlet, origins, dirs, None)
    np.testing.assert_array_equal(new.status == RayStatus.OK, legacy.ok)
    ok = legacy.ok
    assert ok.mean() > 0.3
    np.testing.assert_allclose(new.points[ok, 0], legacy.x[ok], atol=1e-9)
    np.testing.assert_allclose(new.points[ok, 2], legacy.z[ok] + shift, atol=1e-9)
    np.testing.assert_allclose(new.directions[ok, 1], legacy.dy[ok], atol=1e-12)
    # reversibility: the object-side rays traced forward again land on the start points
    again = rt.trace(singlet, new.points[ok] + new.directions[ok], -new.directions[ok], z + shift)
    np.testing.assert_allclose(again.points[:, :2], origins[ok, :2], atol=1e-9)


# ----------------------------------------------------------------------------- statuses


def test_status_codes_and_failing_surface(lenses):
    tri = lenses["cooke_triplet"]
    # vignetted at the front surface, and at the stop (surface 2) for a ray through the front
    b = rt.aim_rays(tri, [[0.0, 1.05], [0.0, 0.5]], field_directions=[0.0, 0.0, 1.0])
    res = rt.trace(
        tri, np.vstack([[0, 12.0, -5.0], b.origins]), np.vstack([[0, 0, 1.0], b.directions]), 60
    )
    assert res.status.tolist() == [RayStatus.VIGNETTED, RayStatus.VIGNETTED, RayStatus.OK]
    assert res.surface.tolist() == [0, 2, -1]
    assert np.isnan(res.points[:2]).all() and np.isfinite(res.points[2]).all()
    # missed (line passes outside the sphere) and backward rays
    ball = Prescription((Surface(10.0, 5.0, 1.5, 9.99, stop=True), Surface(-10.0, 0.0, 1.0, 9.0)))
    res = rt.trace(
        ball,
        [[0, 11.0, -5], [0, 0, -5], [0, 0, 5.0]],
        [[0, 0, 1], [0, 0, -1], [0, 0, 1]],
        40,
        clip=False,
    )
    assert res.status.tolist() == [RayStatus.MISSED, RayStatus.BACKWARD, RayStatus.BACKWARD]
    assert res.surface.tolist() == [0, 0, 0]
    # total internal reflection leaving a hemisphere far off axis
    hemi = Prescription(
        (Surface(math.inf, 10.0, 1.5, 9.9, stop=True), Surface(-10.0, 0.0, 1.0, 9.99))
    )
    res = rt.trace(hemi, [[0, 9.0, -1.0], [0, 1.0, -1.0]], [[0, 0, 1.0]] * 2, 30)
    assert res.status.tolist() == [RayStatus.TIR, RayStatus.OK]
    assert res.surface.tolist() == [1, -1]


# ----------------------------------------------------------------------------- ray aiming


def test_ray_aiming_is_uniform_over_the_real_stop_off_axis(lenses):
    dg = lenses["double_gauss"]
    sd = dg.surfaces[dg.stop_index].semi_diameter_mm
    bundle = rt.rays_from_angle(dg, 14.0, 400)
    assert bundle.aimed.all()
    x, y = rt._stop_hits(dg, bundle.origins, bundle.directions)
    np.testing.assert_allclose(np.column_stack([x, y]), bundle.pupil_xy * sd, rtol=0, atol=1e-9)
    # the paraxial guess alone lands visibly off (pupil aberration): aiming matters here
    par = dg.paraxial
    guess = rt.aim_rays(
        dg, bundle.pupil_xy, field_directions=rt._field_direction(14.0), max_iterations=0
    )
    gx, gy = rt._stop_hits(dg, guess.origins, guess.directions)
    assert np.hypot(gx - x, gy - y).max() > 1e-3 * sd and par.entrance_pupil_diameter_mm > 0
    # a finite off-axis point on the triplet: also exact on its stop, and all rays pass
    tri = lenses["cooke_triplet"]
    pts = rt.rays_from_point(tri, [3.0, -40.0, -300.0], 97, pattern="hex")
    assert len(pts.pupil_xy) == 127 and pts.aimed.all()
    x, y = rt._stop_hits(tri, pts.origins, pts.directions)
    np.testing.assert_allclose(
        np.column_stack([x, y]), pts.pupil_xy * tri.surfaces[2].semi_diameter_mm, atol=1e-9
    )
    assert (rt.trace(tri, pts.origins, pts.directions, 60.0).status == RayStatus.OK).all()


def testpupil_patterns():
    fib = rt.pupil_pattern(100)
    assert fib.shape == (100, 2) and np.hypot(*fib.T).max() < 1
    assert np.abs(fib.mean(axis=0)).max() < 0.02
    assert len(rt.pupil_pattern(7, "hex")) == 7 and len(rt.pupil_pattern(8, "hex")) == 19
    st = rt.pupil_pattern(50, "stratified")
    assert st.shape == (64, 2) and np.hypot(*st.T).max() <= 1.0
    with pytest.raises(OpticsError, match="unknown pupil pattern"):
        rt.pupil_pattern(5, "spiral")


def test_marginal_rays_through_stop_edges(lenses):
    tri = lenses["cooke_triplet"]
    mr = rt.marginal_rays(tri, [[0.0, 5.0, -500.0], [0.0, -20.0, -2000.0]])
    sd = tri.surfaces[2].semi_diameter_mm
    for bundle, sign in ((mr.upper, 1.0), (mr.lower, -1.0)):
        x, y = rt._stop_hits(tri, bundle.origins, bundle.directions)
        np.testing.assert_allclose(y, sign * sd, atol=1e-9)
        np.testing.assert_allclose(x, 0.0, atol=1e-9)
    h = rt.marginal_heights(tri, [500.0, math.inf], [5.0, 0.0], tri.image_plane_z_for(500.0))
    assert (h.status == 0).all() and h.y1_mm[0] < h.y2_mm[0] + 0.5  # near focus: rays cross


# ----------------------------------------------------------------------------- exact focus


def test_exact_focus_is_least_rms_and_inverts(singlet):
    z_best = best_focus_z(singlet, 3500.0)
    # brute force: RMS spot of a 2-D aimed bundle on planes around the optimum
    bundle = rt.rays_from_point(singlet, [0.0, 0.0, -3500.0], 3000)
    res = rt.trace(singlet, bundle.origins, bundle.directions, z_best)
    slope = res.directions[:, :2] / res.directions[:, 2:]

    def rms(dz):
        return np.sqrt(np.mean(np.sum((res.points[:, :2] + dz * slope) ** 2, axis=1)))

    dzs = np.linspace(-0.05, 0.05, 201)
    assert abs(dzs[np.argmin([rms(d) for d in dzs])]) <= 0.0015
    assert z_best < singlet.image_plane_z_for(3500.0) - 1.0  # spherical aberration: focus moves in
    assert best_focus_object_distance(singlet, z_best) == pytest.approx(3500.0, rel=1e-7)
    assert best_focus_object_distance(singlet, z_best - 20.0) == math.inf
    small = Prescription.from_singlet(100.0, 14.35, 1.515, 0.5)
    assert best_focus_z(small, 1000.0) == pytest.approx(
        small.image_plane_z_for(1000.0), abs=2e-3
    )


# ----------------------------------------------------------------------------- files, validation


def test_prescription_validation_names_surfaces():
    s = Surface(50.0, 5.0, 1.5, 10.0)
    with pytest.raises(ProfileError, match="exactly one surface must be the stop, found 0"):
        Prescription((s, Surface(-50.0, 0.0, 1.0, 10.0)))
    with pytest.raises(ProfileError, match=r"found 2 \(surfaces \[0, 1\]\)"):
        Prescription(
            (Surface(50.0, 5.0, 1.5, 10.0, stop=True), Surface(-50.0, 0, 1.0, 10.0, stop=True))
        )
    with pytest.raises(ProfileError, match="beyond the edge"):
        Surface(10.0, 1.0, 1.5, 10.5)
    with pytest.raises(ProfileError, match="radius_mm must be non-zero"):
        Surface(0.0, 1.0, 1.5, 1.0)
    with pytest.raises(ProfileError, match="D/2"):
        Prescription.from_singlet(100.0, 2.0, 1.5, 60.0)


def test_toml_round_trip_and_errors(lenses):
    stop_row = (
        "{ radius_mm = inf, thickness_mm = 8.3, refractive_index = 1.0, semi_diameter_mm = 11.0,"
        " stop = true },"
    )
    text = f"""
[main_lens]
surfaces = [   # front to back; refractive_index = medium AFTER the surface
  {{ radius_mm = 85.5,  thickness_mm = 11.6, refractive_index = 1.744, semi_diameter_mm = 38.0 }},
  {stop_row}
  {{ radius_mm = -204.96, thickness_mm = 0.0, refractive_index = 1.0,  semi_diameter_mm = 26.0 }},
]   # radius inf = flat; exactly one stop; last thickness ignored
[mla]
gap_mm = 65.43   # last lens vertex -> MLA (or focus_mm)
"""
    p = prescription_from_toml_dict(tomllib.loads(text))
    assert p.stop_index == 1 and math.isinf(p.surfaces[1].radius_mm)
    for lens in lenses.values():
        d = prescription_to_toml_dict(lens, gap_mm=50.0)
        assert d["mla"] == {"gap_mm": 50.0}
        assert prescription_from_toml_dict(d).surfaces == lens.surfaces
    bad = tomllib.loads(text)
    del bad["main_lens"]["surfaces"][2]["semi_diameter_mm"]
    with pytest.raises(ProfileError, match=r"surfaces\[2\]: missing semi_diameter_mm"):
        prescription_from_toml_dict(bad)
    bad = tomllib.loads(text)
    bad["main_lens"]["surfaces"][0]["curv"] = 1.0
    with pytest.raises(ProfileError, match=r"surfaces\[0\]: unknown key\(s\) curv"):
        prescription_from_toml_dict(bad)
    bad = tomllib.loads(text)
    bad["main_lens"]["surfaces"][1]["refractive_index"] = 0.5
    with pytest.raises(ProfileError, match=r"surfaces\[1\]\.refractive_index"):
        prescription_from_toml_dict(bad)
    with pytest.raises(ProfileError, match="missing"):
        prescription_from_toml_dict({"main_lens": {}})


def _zmx(surfaces: str, unit: str = "MM") -> str:
    return (
        f"VERS 1\nMODE SEQ\nNAME test lens\nUNIT {unit} X W X CM MR CPMM\n"
        "SURF 0\n  TYPE STANDARD\n  CURV 0.0\n  DISZ INFINITY\n"
        f"{surfaces}"
        "SURF 9\n  TYPE STANDARD\n  CURV 0\n  DISZ 0\n  DIAM 10\n"
    )


GOOD = (
    "SURF 1\n  STOP\n  TYPE STANDARD\n  CURV 0.02 0 0\n  DISZ 5\n"
    "  GLAS ___BLANK 1 0 1.5168 64.17 0 0 0\n  DIAM 10 1 0\n  CONI -0.5\n"
    "SURF 2\n  TYPE STANDARD\n  CURV -0.01\n  DISZ 90.5\n  DIAM 10\n"
)


def test_zmx_parse_and_encodings(tmp_path):
    z = parse_zmx(_zmx(GOOD))
    s0, s1 = z.prescription.surfaces
    assert (s0.radius_mm, s0.refractive_index, s0.conic, s0.stop) == (50.0, 1.5168, -0.5, True)
    assert (s1.radius_mm, s1.refractive_index, z.image_gap_mm, z.name) == (
        -100.0,
        1.0,
        90.5,
        "test lens",
    )
    assert math.isinf(z.object_distance_mm)
    for enc in ("utf-16", "utf-8"):  # "utf-16" writes a BOM
        path = tmp_path / f"lens_{enc}.zmx"
        path.write_bytes(_zmx(GOOD).replace("\n", "\r\n").encode(enc))
        assert load_zmx(path).prescription == z.prescription


@pytest.mark.parametrize(
    ("surfaces", "unit", "message"),
    [
        (GOOD, "IN", "only UNIT MM"),
        (
            GOOD.replace("___BLANK 1 0 1.5168 64.17 0 0 0", "UNOBTAINIUM 0 0 1.6 40"),
            "MM",
            "SURF 1: glass 'UNOBTAINIUM' is not in lfcam's table",
        ),
        (
            GOOD.replace("SURF 2\n  TYPE STANDARD", "SURF 2\n  TYPE EVENASPH"),
            "MM",
            "SURF 2: surface TYPE EVENASPH is not supported",
        ),
        (GOOD.replace("  DIAM 10\n", ""), "MM", "SURF 2: needs a positive DIAM"),
        (GOOD.replace("  STOP\n", ""), "MM", "exactly one surface must be the stop"),
        (
            GOOD.replace("GLAS ___BLANK 1 0 1.5168 64.17 0 0 0", "GLAS MIRROR"),
            "MM",
            "SURF 1: mirrors are not supported",
        ),
        (GOOD.replace("CURV -0.01", "CURV abc"), "MM", "SURF 2: CURV 'abc' is not a number"),
    ],
)
def test_zmx_errors(surfaces, unit, message):
    with pytest.raises(ZmxError, match=message):
        parse_zmx(_zmx(surfaces, unit))
    assert issubclass(ZmxError, ProfileError)


def test_forward_then_backward_round_trip_on_double_gauss(lenses):
    dg = lenses["double_gauss"]
    bundle = rt.rays_from_angle(dg, (4.0, 10.0), 200)
    z_img = dg.paraxial.back_focal_z_mm
    fwd = rt.trace(dg, bundle.origins, bundle.directions, z_img)
    assert (fwd.status == RayStatus.OK).all()
    back = rt.trace_backward(dg, fwd.points, -fwd.directions, bundle.origins[0, 2])
    assert (back.status == RayStatus.OK).all()
    np.testing.assert_allclose(back.points, bundle.origins, rtol=0, atol=1e-9)
    np.testing.assert_allclose(back.directions, -bundle.directions, rtol=0, atol=1e-12)
