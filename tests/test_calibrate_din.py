"""d_in from a reference plane."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lfcam.calibrate import calibrate_white
from lfcam.calibrate.reference import (
    measure_d_in,
    paraxial_image_z_mm,
    solve_d_in,
    spacing_exact_mm,
)
from lfcam.calibrate.synthetic import make_reference_capture
from lfcam.camera import load_profile


def test_exact_spacing_matches_paraxial_for_weak_lens():
    """With a weak lens (tiny spherical aberration) the traced model reduces to the
    closed form P(1 + f_x/(d_in − z_img)); with the seed's F/2 lens it does not."""
    from lfcam.optics.paraxial import d_in_for_focus

    base = load_profile("system1")
    weak = replace(base, main_lens=replace(base.main_lens, radius_mm=1000.0, thickness_mm=3.0,
                                           pupil_diameter_mm=20.0))
    d_in = d_in_for_focus(weak.main_lens, 20000.0)
    a = 8000.0
    z = paraxial_image_z_mm(weak, a)
    p, fx = weak.mla.pitch_mm, weak.mla.focal_length_mm
    expected = p * (1 + fx / (d_in - z))
    got = spacing_exact_mm(weak, d_in, a, 0.05)
    assert abs(got - expected) / abs(expected - p) < 0.02


def test_solver_inverts_paraxial_formula():
    prof = load_profile("system1")
    a = 500.0
    z = paraxial_image_z_mm(prof, a)
    p, fx = prof.mla.pitch_mm, prof.mla.focal_length_mm
    spacing = p * (1 + fx / (104.744 - z))
    d_par, d_ex = solve_d_in(prof, a, spacing, 0.2)
    assert abs(d_par - 104.744) < 1e-9
    assert np.isfinite(d_ex)


@pytest.mark.slow
def test_rendered_reference_plane_exact_beats_paraxial():
    prof = load_profile("system1")
    d_in, a = prof.d_in_mm, 400.0
    white, cap = make_reference_capture(prof, d_in, a, period_mm=25.0 * a / 600)
    cal = calibrate_white(white)
    r = measure_d_in(cap, white, cal.centres_px, cal.indices, prof, a, window_frac=0.25,
                     max_pairs=400)
    err_par = abs(r.d_in_paraxial_mm - d_in) / d_in
    err_ex = abs(r.d_in_exact_mm - d_in) / d_in
    # measured: paraxial 5.3 %, exact 1.3 % — the 0.1 % goal is NOT met yet (see docs)
    assert err_ex < 0.02
    assert err_ex < 0.5 * err_par
