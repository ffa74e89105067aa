"""Ideal (paraxial) surfaces and the black-box main lens, against thin-lens algebra."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from lfcam.camera import load_profile
from lfcam.errors import ProfileError, ZmxError
from lfcam.optics import raytrace as rt
from lfcam.optics.lens import Prescription, Surface, ideal_lens
from lfcam.optics.zmx import parse_zmx, prescription_from_toml_dict, prescription_to_toml_dict

F_MM = 50.0
LENS_Z_MM = 10.0


def _single(spherical=()) -> Prescription:
    """Dummy front at z = 0, ideal surface at z = 10, stop 5 mm behind it."""
    return Prescription((
        Surface(math.inf, LENS_Z_MM, 1.0, 40.0),
        Surface(math.inf, 5.0, 1.0, 30.0, focal_length_mm=F_MM, spherical=spherical),
        Surface(math.inf, 0.0, 1.0, 10.0, stop=True),
    ))


@pytest.mark.parametrize("distance_mm", [120.0, 300.0, 1000.0, 5000.0])
@pytest.mark.parametrize("offset_mm", [0.0, 7.0, -40.0])
def test_ideal_surface_images_every_plane_perfectly(distance_mm, offset_mm):
    rx = _single()
    u = distance_mm + LENS_Z_MM  # object → ideal surface
    v = 1.0 / (1.0 / F_MM - 1.0 / u)  # thin-lens conjugate
    bundle = rt.rays_from_point(rx, np.array([3.0, offset_mm, -distance_mm]), 300)
    assert bundle.aimed.all()
    res = rt.trace(rx, bundle.origins, bundle.directions, LENS_Z_MM + v)
    assert (res.status == 0).all()
    m = -v / u
    np.testing.assert_allclose(res.points[:, 0], 3.0 * m, atol=1e-11)
    np.testing.assert_allclose(res.points[:, 1], offset_mm * m, atol=1e-11)
    # backward trace from the image points returns to the source
    back = rt.trace_backward(rx, res.points, -res.directions, -distance_mm)
    assert (back.status == 0).all()
    np.testing.assert_allclose(back.points[:, :2], [[3.0, offset_mm]] * len(back.points),
                               atol=1e-9)


def test_ideal_surface_paraxial_data_are_the_thin_lens_formulas():
    par = _single().paraxial
    assert par.efl_mm == pytest.approx(F_MM, rel=1e-14)
    assert par.front_principal_z_mm == pytest.approx(LENS_Z_MM, abs=1e-12)
    assert par.back_principal_z_mm == pytest.approx(LENS_Z_MM, abs=1e-12)
    assert par.back_focal_z_mm == pytest.approx(LENS_Z_MM + F_MM, abs=1e-12)
    # stop 5 mm behind: entrance pupil = its virtual image, 5·f/(f − 5) behind the lens,
    # magnified f/(f − 5)
    assert par.entrance_pupil_z_mm == pytest.approx(LENS_Z_MM + 5.0 * F_MM / (F_MM - 5.0))
    assert par.entrance_pupil_diameter_mm == pytest.approx(20.0 * F_MM / (F_MM - 5.0))
    assert par.exit_pupil_z_mm == pytest.approx(LENS_Z_MM + 5.0)


def test_two_ideal_surfaces_reproduce_thick_lens_cardinal_points():
    f1, f2, t = 80.0, -120.0, 15.0
    rx = Prescription((
        Surface(math.inf, t, 1.0, 30.0, focal_length_mm=f1, stop=True),
        Surface(math.inf, 0.0, 1.0, 30.0, focal_length_mm=f2),
    ))
    phi = 1.0 / f1 + 1.0 / f2 - t / (f1 * f2)
    efl = 1.0 / phi
    bfl = efl * (1.0 - t / f1)  # second surface → F′
    ffl = -efl * (1.0 - t / f2)  # first surface → F (negative: in front)
    par = rx.paraxial
    assert par.efl_mm == pytest.approx(efl, rel=1e-13)
    assert par.bfl_mm == pytest.approx(bfl, rel=1e-13)
    assert par.ffl_mm == pytest.approx(ffl, rel=1e-13)
    assert par.back_principal_z_mm == pytest.approx(t + bfl - efl, abs=1e-11)
    assert par.front_principal_z_mm == pytest.approx(ffl + efl, abs=1e-11)
    # real rays of a collimated beam meet at F′ exactly (ideal surfaces are linear)
    bundle = rt.rays_from_angle(rx, 0.0, 60)
    res = rt.trace(rx, bundle.origins, bundle.directions, t + bfl)
    np.testing.assert_allclose(res.points[:, :2], 0.0, atol=1e-11)
    # an object 400 mm in front of H images at the thick-lens conjugate behind H′
    s = 400.0
    z_obj = par.front_principal_z_mm - s
    s_img = 1.0 / (phi - 1.0 / s)
    bundle = rt.rays_from_point(rx, np.array([0.0, 5.0, z_obj]), 60)
    res = rt.trace(rx, bundle.origins, bundle.directions, par.back_principal_z_mm + s_img)
    np.testing.assert_allclose(res.points[:, 1], -5.0 * s_img / s, atol=1e-10)


def test_spherical_term_moves_the_marginal_focus():
    a1, a2 = 2e-6, -3e-9  # mm^-3, mm^-5
    rx = _single((a1, a2))
    for r in (2.0, 6.0, 9.0):
        o = np.array([[0.0, r, -5.0]])
        res = rt.trace(rx, o, np.array([[0.0, 0.0, 1.0]]), None)
        slope = res.directions[0, 1] / res.directions[0, 2]
        power = 1.0 / F_MM + a1 * r**2 + a2 * r**4
        assert slope == pytest.approx(-r * power, rel=1e-13)
    # paraxial data ignore the aberration
    assert rx.paraxial.efl_mm == pytest.approx(F_MM, rel=1e-14)


def test_ideal_surface_validation():
    with pytest.raises(ProfileError, match="flat"):
        Surface(100.0, 1.0, 1.0, 5.0, focal_length_mm=50.0)
    with pytest.raises(ProfileError, match="air"):
        Surface(math.inf, 1.0, 1.5, 5.0, focal_length_mm=50.0)
    with pytest.raises(ProfileError, match="non-zero"):
        Surface(math.inf, 1.0, 1.0, 5.0, focal_length_mm=0.0)
    with pytest.raises(ProfileError, match="only an ideal"):
        Surface(math.inf, 1.0, 1.0, 5.0, spherical=(1e-6,))
    with pytest.raises(ProfileError, match="air before"):
        Prescription((Surface(50.0, 2.0, 1.5, 5.0, stop=True),
                      Surface(math.inf, 0.0, 1.0, 5.0, focal_length_mm=40.0)))


def test_ideal_surface_toml_and_zmx():
    rx = _single((1e-6,))
    table = prescription_to_toml_dict(rx)
    assert table["main_lens"]["surfaces"][1] == {
        "focal_length_mm": F_MM, "thickness_mm": 5.0, "semi_diameter_mm": 30.0,
        "spherical": [1e-6]}
    assert prescription_from_toml_dict(table) == rx
    with pytest.raises(ProfileError, match="unknown key"):
        prescription_from_toml_dict({"surfaces": [
            {"focal_length_mm": 50.0, "thickness_mm": 0.0, "semi_diameter_mm": 5.0,
             "radius_mm": 20.0, "stop": True}]})
    zmx = "\n".join([
        "UNIT MM", "SURF 0", "  DISZ INFINITY", "SURF 1", "  STOP", "  DISZ 0", "  DIAM 10",
        "SURF 2", "  TYPE PARAXIAL", "  PARM 1 75.5", "  PARM 2 0", "  DISZ 75.5",
        "  DIAM 20", "SURF 3", "  DISZ 0", ""])
    lens = parse_zmx(zmx).prescription
    assert lens.surfaces[1].focal_length_mm == 75.5
    assert lens.paraxial.efl_mm == pytest.approx(75.5, rel=1e-14)
    with pytest.raises(ZmxError, match="PARM 1"):
        parse_zmx(zmx.replace("  PARM 1 75.5\n", ""))


BLACK_BOX = """
name = "bb"
[main_lens]
focal_length_mm = 50.0
f_number = 2.8
{extra}
[mla]
focal_length_mm = 0.5
pitch_mm = 0.1
grid = "hex"
{mla}
[sensor]
pixel_pitch_mm = 0.01
width_px = 400
height_px = 400
"""


def _write(tmp_path: Path, extra: str = "", mla: str = "") -> Path:
    p = tmp_path / "bb.toml"
    p.write_text(BLACK_BOX.format(extra=extra, mla=mla))
    return p


def test_black_box_profile_seeds_an_ideal_lens(tmp_path):
    prof = load_profile(_write(tmp_path, "exit_pupil_mm = 40.0", "distance_mm = 52.0"))
    lens = prof.main_lens
    assert lens.is_black_box
    assert lens.focal_length_mm == pytest.approx(50.0, rel=1e-14)
    assert lens.f_number == pytest.approx(2.8, rel=1e-12)
    assert prof.d_in_mm - lens.exit_pupil_z_mm == pytest.approx(40.0, abs=1e-12)
    assert lens.to_dict() == {"focal_length_mm": 50.0, "f_number": 2.8, "exit_pupil_mm": 40.0}
    # no MLA distance: the profile loads, asking for d_in says to calibrate with targets
    prof = load_profile(_write(tmp_path))
    with pytest.raises(ProfileError, match="--targets"):
        prof.d_in_mm  # noqa: B018
    # infinity-focus seed: the stop on the principal plane
    assert prof.main_lens.exit_pupil_z_mm == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("extra, match", [
    ("", "f_number"),
    ("f_number = 0.0", "positive"),
    ("f_number = 'fast'", "number"),
    ("exit_pupil_mm = 1e9\nf_number = 2.0", "implausible"),
    ("f_number = 2.0\nradius_mm = 100.0", "unknown key"),
])
def test_black_box_profile_errors(tmp_path, extra, match):
    text = BLACK_BOX.format(extra=extra, mla="").replace("f_number = 2.8\n", "", 1)
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(ProfileError, match=match):
        load_profile(p)


def test_ideal_lens_seed_f_number_and_pupils():
    for xp in (None, 20.0, -30.0, 80.0):
        rx = ideal_lens(50.0, 2.8, 12.0, xp)
        assert rx.paraxial.f_number == pytest.approx(2.8, rel=1e-12)
        assert rx.stop_pupils[2] == pytest.approx(12.0 if xp is None else xp, abs=1e-12)
    with pytest.raises(ProfileError, match="focal plane"):
        ideal_lens(50.0, 2.8, 0.0, 50.0)


def test_optics_forward_on_a_black_box_says_it_uses_the_seed(tmp_path, capsys):
    from lfcam.cli.main import main

    p = _write(tmp_path, "exit_pupil_mm = 40.0")
    assert main(["optics", "forward", "--profile", str(p), "--focus", "1000", "--distance",
                 "500", "--json"]) == 0
    captured = capsys.readouterr()
    assert "seed ideal lens" in captured.err
    # the seed: an ideal lens f = 50 on the front (z = 0), its stop (= exit pupil) placed at
    # load time 40 mm before the MLA of the profile (no MLA distance: infinity focus, z = 50),
    # radius (f/N)/2·(1 − e/f) (entrance pupil f/N). --focus 1000 moves the MLA to v(1000),
    # sensor 0.5 mm behind. The upper stop-edge ray runs from the stop edge to the image of
    # the axial source at v(500).
    v = lambda u: 50.0 * u / (u - 50.0)  # noqa: E731
    d_in = v(1000.0)
    z_stop = 50.0 - 40.0
    r_stop = 0.5 * (50.0 / 2.8) * (1.0 - z_stop / 50.0)
    z_img, z_sensor = v(500.0), d_in + 0.5
    y1 = r_stop * (z_img - z_sensor) / (z_img - z_stop)
    out = __import__("json").loads(captured.out)
    assert out["y1_mm"] == pytest.approx(y1, abs=1e-9)
    assert out["y2_mm"] == pytest.approx(-y1, abs=1e-9)
