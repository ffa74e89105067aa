"""Camera profiles: Table 1 focal lengths, principal planes, validation messages."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lfcam import load_profile
from lfcam.camera import profile_from_dict
from lfcam.errors import OpticsError, ProfileError


def _abcd_thick_lens(r, t, n):
    """System matrix (front vertex → back vertex) built from refraction/translation matrices."""
    refr1 = np.array([[1.0, 0.0], [-(n - 1.0) / (r * n), 1.0 / n]])
    trans = np.array([[1.0, t], [0.0, 1.0]])
    refr2 = np.array([[1.0, 0.0], [-(1.0 - n) / (-r), n]])
    return refr2 @ trans @ refr1


@pytest.mark.parametrize(("name", "table1_mm"), [("system1", 99.515), ("system2", 98.088)])
def test_focal_length_reproduces_table1(name, table1_mm):
    lens = load_profile(name).main_lens
    assert lens.focal_length_mm == pytest.approx(table1_mm, abs=5e-4)


@pytest.mark.parametrize("name", ["system1", "system2"])
def test_principal_planes_match_matrix_optics(name):
    lens = load_profile(name).main_lens
    m = _abcd_thick_lens(lens.radius_mm, lens.thickness_mm, lens.refractive_index)
    (a, b), (c, d) = m
    f = -1.0 / c
    assert f == pytest.approx(lens.focal_length_mm, rel=1e-12)
    # back focal distance = -a/c from the back vertex; H2 lies f before the back focus
    bfd = -a / c
    assert lens.back_vertex_z_mm + bfd - f == pytest.approx(lens.back_principal_z_mm, abs=1e-9)


def test_contract_d_in_for_system1_focus_3500():
    # docs/profiles.md example: focus 3500 mm ↔ distance_mm = 104.743
    assert load_profile("system1").d_in_mm == pytest.approx(104.743, abs=5e-4)


@pytest.mark.parametrize("focus", [300.0, 1000.0, 3500.0, 1e5])
def test_focus_round_trip(focus):
    lens = load_profile("system2").main_lens
    assert lens.focus_for_d_in(lens.d_in_for_focus(focus)) == pytest.approx(focus, rel=1e-10)


def test_infinity_focus_puts_mla_at_back_focal_plane():
    lens = load_profile("system1").main_lens
    d_in = lens.d_in_for_focus(math.inf)
    assert d_in == pytest.approx(lens.back_principal_z_mm + lens.focal_length_mm, rel=1e-15)


def test_focus_inside_focal_length_is_an_error():
    with pytest.raises(OpticsError, match="front focal point"):
        load_profile("system1").main_lens.d_in_for_focus(50.0)


BASE = {
    "name": "t",
    "main_lens": {"radius_mm": 100.0, "thickness_mm": 14.35, "refractive_index": 1.515,
                  "pupil_diameter_mm": 50.0},
    "mla": {"focal_length_mm": 2.749, "pitch_mm": 1.34, "focus_mm": 3500.0},
    "sensor": {"pixel_pitch_mm": 0.08375, "width_px": 64, "height_px": 64},
}


def _with(section, key, value):
    data = {k: (dict(v) if isinstance(v, dict) else v) for k, v in BASE.items()}
    if value is None:
        del data[section][key]
    else:
        data[section][key] = value
    return data


@pytest.mark.parametrize(
    ("section", "key", "value", "needle"),
    [
        ("main_lens", "radius_mm", None, "main_lens.radius_mm"),
        ("main_lens", "thickness_mm", -1.0, "main_lens.thickness_mm"),
        ("main_lens", "pupil_diameter_mm", 200.0, "main_lens.pupil_diameter_mm"),
        ("main_lens", "pupil_diameter_mm", 80.0, "main_lens.pupil_diameter_mm"),  # past the edge
        ("main_lens", "refractive_index", float("nan"), "main_lens.refractive_index"),
        ("main_lens", "focal_length_mm", 99.0, "main_lens.focal_length_mm"),
        ("mla", "pitch_mm", "wide", "mla.pitch_mm"),
        ("mla", "grid", "triangle", "mla.grid"),
        ("mla", "focus_mm", 20.0, "focal point"),
        ("sensor", "width_px", 0, "sensor.width_px"),
        ("sensor", "bayer", "XYZW", "sensor.bayer"),
        ("sensor", "pixel_pitch_mm", None, "sensor.pixel_pitch_mm"),
        ("sensor", "colour", 1, "sensor.colour"),
    ],
)
def test_bad_profiles_name_the_key(section, key, value, needle):
    with pytest.raises((ProfileError, OpticsError), match=needle.replace(".", r"\.")):
        profile_from_dict(_with(section, key, value))


def test_good_profile_and_stated_focal_length_within_tolerance():
    p = profile_from_dict(_with("main_lens", "focal_length_mm", 99.515))
    assert p.main_lens.focal_length_mm == pytest.approx(99.515, abs=5e-4)


def test_missing_table_and_unknown_name(tmp_path):
    with pytest.raises(ProfileError, match=r"\[sensor\]"):
        profile_from_dict({k: v for k, v in BASE.items() if k != "sensor"})
    with pytest.raises(ProfileError, match="no profile named"):
        load_profile("system9")
    bad = tmp_path / "bad.toml"
    bad.write_text("name = [", encoding="utf-8")
    with pytest.raises(ProfileError, match="invalid TOML"):
        load_profile(bad)


def test_unknown_d_in_is_explained():
    data = _with("mla", "focus_mm", None)
    p = profile_from_dict(data)
    with pytest.raises(ProfileError, match="d_in"):
        _ = p.d_in_mm
