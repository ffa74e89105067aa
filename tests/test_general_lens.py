"""Every stage on the general lens: profile forms, one lens model, one tracer (issue 14)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from lfcam.camera import load_profile, profile_from_dict
from lfcam.cli.main import main
from lfcam.errors import ProfileError
from lfcam.models import POINT_MODELS, exact
from lfcam.optics.lens import Prescription
from lfcam.optics.refocus import exact_shift_for_distance
from lfcam.optics.trace import forward, trace_backward_fast, trace_source_fast
from lfcam.optics.zmx import prescription_to_toml_dict
from lfcam.sim.capture import profile_to_dict, profile_to_toml

LENSES = Path(__file__).parent / "data" / "lenses"
SEED_Z_EXIT = {"system1": 6.682788912586467, "system2": 3.337185616331423}  # behind front vertex


def _as_prescription_profile(name: str):
    """The shipped singlet profile rewritten in the prescription form (front-vertex frame)."""
    p = load_profile(name)
    lens = p.main_lens
    d = profile_to_dict(p)
    d["main_lens"] = prescription_to_toml_dict(lens.as_prescription)["main_lens"]
    d["mla"].pop("distance_mm")
    d["mla"]["gap_mm"] = p.gap_mm
    return p, profile_from_dict(d)


@pytest.mark.parametrize("name", ["system1", "system2"])
def test_singlet_keys_and_their_two_surface_prescription_give_the_same_results(name):
    p, q = _as_prescription_profile(name)
    shift = 0.5 * p.main_lens.thickness_mm  # lens centre → front vertex origin
    assert q.d_in_mm == pytest.approx(p.d_in_mm + shift, abs=1e-12)
    assert q.gap_mm == pytest.approx(p.gap_mm, abs=1e-12)
    a, b = p.main_lens, q.main_lens
    assert b.focal_length_mm == a.focal_length_mm
    assert b.pupil_diameter_mm == pytest.approx(a.pupil_diameter_mm, rel=1e-15)
    for attr in ("front_principal_z_mm", "back_principal_z_mm", "rim_z_mm", "exit_pupil_z_mm",
                 "front_vertex_z_mm", "back_vertex_z_mm"):
        assert getattr(b, attr) == pytest.approx(getattr(a, attr) + shift, abs=1e-12), attr
    assert a.exit_pupil_z_mm - a.front_vertex_z_mm == pytest.approx(SEED_Z_EXIT[name], abs=1e-12)
    dist = np.array([300.0, 1000.0, 3500.0, 1e5])
    for off in (0.0, 10.0):
        fa, fb = forward(p, None, dist, off), forward(q, None, dist, off)
        np.testing.assert_allclose(fa.y1_mm, fb.y1_mm, atol=1e-9)
        np.testing.assert_allclose(fa.y2_mm, fb.y2_mm, atol=1e-9)
        ia = exact.invert(p, None, fa.y1_mm, fa.y2_mm)
        ib = exact.invert(q, None, fa.y1_mm, fa.y2_mm)
        np.testing.assert_allclose(ia.distance_mm, dist, rtol=1e-9)
        np.testing.assert_allclose(ib.distance_mm, dist, rtol=1e-8)
    assert exact_shift_for_distance(p, 700.0) == pytest.approx(
        exact_shift_for_distance(q, 700.0), abs=1e-9)


def test_zmx_path_and_gap_in_a_profile(tmp_path):
    text = (f'[main_lens]\nzmx = "{LENSES / "cooke_triplet.zmx"}"\n'
            '[mla]\nfocal_length_mm = 0.4\npitch_mm = 0.1\ngap_mm = 45.0\n'
            '[sensor]\npixel_pitch_mm = 0.00625\nwidth_px = 64\nheight_px = 64\n')
    (tmp_path / "c.toml").write_text(text)
    p = load_profile(tmp_path / "c.toml")
    assert not p.main_lens.is_singlet
    assert p.main_lens.focal_length_mm == pytest.approx(50.0018, abs=1e-4)
    assert p.d_in_mm == pytest.approx(p.main_lens.back_vertex_z_mm + 45.0)
    assert p.gap_mm == pytest.approx(45.0)
    # written back (simulate's sidecar) it loads to the same lens and MLA
    (tmp_path / "d.toml").write_text(profile_to_toml(p))
    q = load_profile(tmp_path / "d.toml")
    assert q.main_lens.as_prescription.surfaces == p.main_lens.as_prescription.surfaces
    assert q.d_in_mm == pytest.approx(p.d_in_mm, abs=1e-12)
    with pytest.raises(ProfileError, match="one form"):
        profile_from_dict({"main_lens": {"zmx": "x.zmx", "radius_mm": 1.0}, "mla": {},
                           "sensor": {}})


@pytest.mark.parametrize("name", ["cooke_triplet", "double_gauss"])
def test_forward_and_exact_round_trip_on_multi_element_lenses(name):
    p = load_profile(name)
    for focus in (1000.0, math.inf):
        q = p.with_focus(focus)
        dist = np.array([250.0, 300.0, 750.0, 1500.0, 3500.0, 1e5])
        for off in (0.0, 4.0, -15.0):
            fw = forward(q, None, dist, off)
            assert (fw.status == 0).all()
            inv = exact.invert(q, None, fw.y1_mm, fw.y2_mm)
            assert (inv.status == 0).all()
            np.testing.assert_allclose(inv.distance_mm, dist, rtol=1e-9)
            assert np.all(np.abs(inv.offset_mm - off) <= 1e-7 * dist)


def test_closed_forms_on_a_general_lens():
    """offaxis/onaxis need the singlet's two spheres: out-of-domain; thin runs paraxially."""
    p = load_profile("cooke_triplet")
    fw = forward(p, None, np.array([500.0, 2000.0]), 2.0)
    for model in ("offaxis", "onaxis"):
        assert set(POINT_MODELS[model](p, None, fw.y1_mm, fw.y2_mm).labels()) == {
            "out-of-domain"}
    thin = POINT_MODELS["thin"](p, None, fw.y1_mm, fw.y2_mm)
    assert (thin.labels() == "ok").all()
    np.testing.assert_allclose(thin.distance_mm, [500.0, 2000.0], rtol=0.2)


def test_general_tracer_paths_agree_forward_and_backward():
    """Rays traced forward from a source and back from where they land return to the source
    line; the renderer's pupil map keeps samples on the real stop."""
    p = load_profile("double_gauss")
    lens = p.main_lens
    rng = np.random.default_rng(3)
    r = 0.5 * lens.pupil_diameter_mm * np.sqrt(rng.random(4000))
    a = 2 * np.pi * rng.random(4000)
    src = (5.0, -8.0, lens.front_vertex_z_mm - 900.0)
    f = trace_source_fast(lens, src, r * np.cos(a), r * np.sin(a), p.d_in_mm)
    assert f.ok.mean() > 0.9  # samples mapped onto the real pupil: few clipped
    b = trace_backward_fast(lens, f.x[f.ok], f.y[f.ok], p.d_in_mm, f.dx[f.ok] / f.dz[f.ok],
                            f.dy[f.ok] / f.dz[f.ok])
    assert b.ok.all()
    t = (src[2] - b.z) / b.dz
    np.testing.assert_allclose(b.x + t * b.dx, src[0], atol=1e-7)
    np.testing.assert_allclose(b.y + t * b.dy, src[1], atol=1e-7)
    rb = trace_backward_fast(lens, f.x[f.ok], f.y[f.ok], p.d_in_mm, f.dx[f.ok] / f.dz[f.ok],
                             f.dy[f.ok] / f.dz[f.ok], ratio=True)
    assert (rb.rho <= 1.0 + 1e-9).all() and rb.ok.all()


def test_stop_pupils_of_a_flat_stop_are_the_paraxial_pupils():
    rx = load_profile("double_gauss").main_lens.as_prescription
    enp_z, enp_d, exp_z, exp_d = rx.stop_pupils
    par = rx.paraxial
    assert (enp_z, exp_z) == pytest.approx((par.entrance_pupil_z_mm, par.exit_pupil_z_mm))
    assert (enp_d, exp_d) == pytest.approx((par.entrance_pupil_diameter_mm,
                                            par.exit_pupil_diameter_mm))
    assert isinstance(rx, Prescription)


def test_lens_import_and_info(tmp_path, capsys):
    out = tmp_path / "dg.toml"
    assert main(["lens", "import", str(LENSES / "double_gauss.zmx"), "-o", str(out),
                 "--focus", "1500"]) == 0
    p = load_profile(out)
    assert p.main_lens.focus_for_d_in(p.d_in_mm) == pytest.approx(1500.0, rel=1e-9)
    assert p.main_lens.f_number == pytest.approx(5.0, abs=1e-3)
    png = tmp_path / "dg.png"
    assert main(["lens", "info", str(out), "--png", str(png), "--json"]) == 0
    text = capsys.readouterr().out
    assert '"efl_mm": 100.00' in text and png.stat().st_size > 1000
    assert main(["lens", "info", "system1"]) == 0


def test_optics_forward_and_inverse_cli_on_a_prescription(capsys):
    import json

    assert main(["optics", "forward", "--profile", "cooke_triplet", "--focus", "1000",
                 "--distance", "600", "--offset", "3", "--json"]) == 0
    fw = json.loads(capsys.readouterr().out)
    assert main(["optics", "inverse", "--profile", "cooke_triplet", "--focus", "1000",
                 "--model", "exact", "--y1", repr(fw["y1_mm"]), "--y2", repr(fw["y2_mm"]),
                 "--json"]) == 0
    inv = json.loads(capsys.readouterr().out)
    assert inv["status"] == "ok"
    assert inv["distance_mm"] == pytest.approx(600.0, rel=1e-9)
    assert inv["offset_mm"] == pytest.approx(3.0, abs=1e-6)
