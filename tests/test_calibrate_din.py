"""d_in from a dot-target capture (lfcam.calibrate.reference).

Truth is the renderer's: every capture is rendered by ``lfcam.sim`` with a profile whose d_in is
known, and the solver starts from the nominal profile (d_in from focus 3500 mm). The
micro-image centres are the renderer's ray-traced white-image centroids (as in
data/synthetic/calib_system*.json), except in the CLI test, which runs the white calibration.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from lfcam.calibrate import calibrate_reference, calibrate_white
from lfcam.calibrate.reference import (
    CentreMap,
    check_distance,
    find_dots,
    measure_d_in,
)
from lfcam.camera import load_profile, profile_from_dict
from lfcam.cli.main import main
from lfcam.errors import CalibrationError
from lfcam.measure.geometry import lenslet_centres_mm
from lfcam.sim.capture import profile_to_dict, simulate, write_capture
from lfcam.sim.scene import scene_from_dict

RAYS = 200_000  # per dot: enough for centroids to ~0.01 px, a second per render


def render_target(profile, distance_mm, spacing_mm, size_px, grid=(-1, 1)):
    """(white raster, white truth centroids, dot raster, profile used) on a size² crop."""
    cam = {"sensor": {"width_px": size_px, "height_px": size_px}}
    white, _, truth = simulate(profile, scene_from_dict(
        {"seed": 1, "objects": [{"type": "white"}], "camera": cam, "rays_per_source": RAYS}))
    lenses = truth["lenses"]
    complete = np.array(lenses["complete"], dtype=bool)
    centres = np.array(lenses["centroid_px"])[complete]
    dots = [{"type": "point", "distance_mm": distance_mm, "position_mm": [i * spacing_mm,
                                                                         j * spacing_mm]}
            for i in grid for j in grid]
    raw, used, _ = simulate(profile, scene_from_dict(
        {"seed": 2, "objects": dots, "camera": cam, "rays_per_source": RAYS}))
    return white, centres, raw, used


def relative_error(value, truth):
    return abs(value - truth) / truth


@pytest.mark.parametrize(
    ("name", "distance_mm", "spacing_mm", "size_px"),
    [("system1", 400.0, 40.0, 384), ("system2", 800.0, 20.0, 512)],
)
def test_exact_route_recovers_profile_d_in(name, distance_mm, spacing_mm, size_px):
    """System 1 from the ray-traced centres; system 2 end to end, from ``calibrate_white`` on
    the rendered white image (overlapping micro-images)."""
    prof = load_profile(name)
    white, centres, raw, used = render_target(prof, distance_mm, spacing_mm, size_px)
    if name == "system2":
        centres = calibrate_white(white.astype(np.float32)).centres_px
    res = measure_d_in(raw, centres, replace(prof, sensor=used.sensor), distance_mm,
                       pupil_samples=160)
    truth = prof.d_in_mm
    assert res.n_dots >= 3
    # measured: system1 +0.022 % (truth centres), system2 −0.012 % (calibrated centres)
    assert relative_error(res.d_in_mm, truth) <= 1e-3
    # the F/2 singlet's spherical aberration defeats the paraxial algebra (measured: system1
    # +10.1 %, system2 +4.2 % with these corner dots)
    assert relative_error(res.d_in_paraxial_mm, truth) > 0.02
    assert res.d_in_paraxial_mm > truth  # the aberrated image sits nearer the MLA


def test_exact_route_recovers_perturbed_d_in_from_nominal_start():
    nominal = load_profile("system1")
    truth = nominal.d_in_mm + 0.5  # the camera's MLA sits 0.5 mm further back
    camera = nominal.with_d_in(truth)
    _, centres, raw, used = render_target(camera, 400.0, 40.0, 384)
    assert used.d_in_mm == pytest.approx(truth)
    res = measure_d_in(raw, centres, replace(nominal, sensor=used.sensor), 400.0,
                       pupil_samples=160)
    # measured +0.002 %; the nominal start is 0.48 % off
    assert relative_error(res.d_in_mm, truth) <= 1e-3
    assert abs(res.d_in_mm - truth) < 0.2 * abs(nominal.d_in_mm - truth)


def weak_profile():
    """system 1's sensor and MLA pitch behind an F/24 long-radius singlet (tiny aberrations),
    lenslets matched to it (f_x 30 mm), focused at 5 m."""
    d = profile_to_dict(load_profile("system1"))
    d["main_lens"].update(radius_mm=1000.0, thickness_mm=3.0, pupil_diameter_mm=40.0)
    d["main_lens"].pop("focal_length_mm", None)
    d["mla"].update(focal_length_mm=30.0, focus_mm=5000.0)
    d["mla"].pop("distance_mm")
    return profile_from_dict(d)


def test_paraxial_route_matches_exact_for_weak_lens():
    prof = weak_profile()
    assert prof.main_lens.f_number > 20
    _, centres, raw, used = render_target(prof, 3000.0, 20.0, 384)
    res = measure_d_in(raw, centres, replace(prof, sensor=used.sensor), 3000.0,
                       pupil_samples=160)
    truth = prof.d_in_mm
    # measured: paraxial +0.04 %, exact −0.05 % (vs +4…10 % / ≤ 0.02 % at F/2)
    assert relative_error(res.d_in_paraxial_mm, truth) <= 2e-3
    assert relative_error(res.d_in_mm, truth) <= 2e-3
    assert relative_error(res.d_in_paraxial_mm, res.d_in_mm) <= 2e-3


def test_centre_map_interpolation_matches_direct_inversion():
    prof = load_profile("system1")
    rng = np.random.default_rng(3)
    white = rng.uniform(0, 511, size=(40, 2))
    cmap = CentreMap(replace(prof, sensor=replace(prof.sensor, width_px=512, height_px=512)),
                     white)
    small = cmap.profile
    for d in (104.3, 105.07):
        direct = lenslet_centres_mm(small, d, white)
        # 0.1 µm ≈ 0.001 px; the table's own sampling noise is ~0.04 µm
        assert np.abs(cmap.raw(d) - direct).max() < 1e-4


@pytest.fixture(scope="module")
def system1_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("din")
    prof = load_profile("system1")
    cam = {"sensor": {"width_px": 384, "height_px": 384}}
    white, pw, tw = simulate(prof, scene_from_dict(
        {"seed": 1, "objects": [{"type": "white"}], "camera": cam, "rays_per_source": RAYS}))
    dots = [{"type": "point", "distance_mm": 400.0, "position_mm": [x, y]}
            for x in (-40.0, 40.0) for y in (-40.0, 40.0)]
    raw, pd, td = simulate(prof, scene_from_dict(
        {"seed": 2, "objects": dots, "camera": cam, "rays_per_source": RAYS}))
    w, wprof, _ = write_capture(folder / "white.png", white, pw, tw)
    r, _, _ = write_capture(folder / "dots.png", raw, pd, td)
    return folder, w, wprof, r, prof.d_in_mm


def test_cli_stores_d_in(system1_files, capsys):
    folder, white, profile, dots, truth = system1_files
    out = folder / "calib.json"
    rc = main(["calibrate", str(white), "--profile", str(profile), "--reference", str(dots),
               "--reference-distance", "400", "-o", str(out), "--json"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    data = json.loads(out.read_text())
    assert data["d_in_method"] == "reference-dots-exact"
    assert data["d_in_mm"] == summary["d_in_mm"]
    # centres from calibrate_white (not the ray-traced truth): measured +0.01 %
    assert relative_error(data["d_in_mm"], truth) <= 1e-3
    assert data["diagnostics"]["reference_dots"] == 4


def test_cli_reference_needs_distance_and_profile(system1_files, capsys):
    folder, white, profile, dots, _ = system1_files
    out = folder / "x.json"
    assert main(["calibrate", str(white), "--profile", str(profile), "--reference", str(dots),
                 "-o", str(out)]) == 1
    assert "--reference-distance" in capsys.readouterr().err
    assert main(["calibrate", str(white), "--reference", str(dots), "--reference-distance",
                 "400", "-o", str(out)]) == 1
    assert "--profile" in capsys.readouterr().err
    assert not out.exists()


def test_bad_distance_is_rejected():
    prof = load_profile("system1")
    for bad in (float("nan"), -5.0, 0.0, 100.0, 2e6):
        with pytest.raises(CalibrationError, match="reference distance"):
            check_distance(prof, bad)


def test_no_dots_and_size_mismatch(system1_files):
    folder, white_path, _, dots_path, _ = system1_files
    import cv2

    white = cv2.imread(str(white_path), cv2.IMREAD_UNCHANGED).astype(float)
    cal = calibrate_white(white)
    prof = load_profile("system1")
    prof = replace(prof, sensor=replace(prof.sensor, width_px=384, height_px=384))
    with pytest.raises(CalibrationError, match="no dot found"):
        find_dots(np.zeros((384, 384)), cal.centres_px, cal.pitch_px)
    with pytest.raises(CalibrationError, match="no dot found"):
        measure_d_in(white, cal.centres_px, prof, 400.0)  # a white image has no dots
    with pytest.raises(CalibrationError, match="384×384"):
        calibrate_reference(cal, np.zeros((256, 384)), prof, 400.0)


def test_wrong_distance_fails_cleanly(system1_files):
    """Dots at 400 mm declared at 300 or 200 mm: no d_in within ±20 % of the start explains
    them as point sources at that distance."""
    _, white_path, _, dots_path, _ = system1_files
    import cv2

    raw = cv2.imread(str(dots_path), cv2.IMREAD_UNCHANGED).astype(float)
    white = cv2.imread(str(white_path), cv2.IMREAD_UNCHANGED).astype(float)
    cal = calibrate_white(white)
    prof = load_profile("system1")
    prof = replace(prof, sensor=replace(prof.sensor, width_px=384, height_px=384))
    with pytest.raises(CalibrationError, match="no d_in within|no dot matches"):
        measure_d_in(raw, cal.centres_px, prof, 300.0, pupil_samples=120)
    with pytest.raises(CalibrationError, match="no d_in within|no dot matches"):
        measure_d_in(raw, cal.centres_px, prof, 200.0, pupil_samples=120)
