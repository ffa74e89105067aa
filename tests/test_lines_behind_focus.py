"""Issue 16: lines behind the focused plane and d_in from a dot target behind it.

Behind a 1 m focus a 3 mm line image sits inside a 5–7 mm blur: its lenslet footprint is
barely elongated (1.2–1.4), the region is a ``spot`` and large enough to be triangulated, and
the triangulation of a line came out 27–74 % short with status ``ok``. Now every triangulated
region is rendered once as a point; a point that does not explain the pixels is tried as a
line, and a region neither model explains is ``poor-fit`` (docs/distance.md).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

import lfcam.measure.lightfield as LF
from lfcam.calibrate.reference import measure_d_in
from lfcam.camera import load_profile
from lfcam.distance import run_distance
from lfcam.measure import Measurement, noise_sigma
from lfcam.measure.lenslets import lenslet_stats
from lfcam.measure.pointfit import chief_ray_offset
from lfcam.measure.regions import find_regions
from lfcam.sim.capture import apply_overrides, simulate
from lfcam.sim.geometry import truth_geometry
from lfcam.sim.scene import scene_from_dict

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))  # focus_grid
SIZE = 1024
CAMERA = {"mla": {"focus_mm": 1000.0, "rotation_rad": 0.012},
          "sensor": {"width_px": SIZE, "height_px": SIZE}}
NOISE = {"photon_noise": True, "full_well_e": 20000, "read_noise_e": 3.0}


def _line_capture(distance, angle_deg=60.0, image_len_mm=3.0):
    base = load_profile("system2")
    prof = apply_overrides(base, CAMERA)
    u = np.array([np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))])
    a = chief_ray_offset(prof, prof.d_in_mm, distance, -0.5 * image_len_mm * u)
    b = chief_ray_offset(prof, prof.d_in_mm, distance, 0.5 * image_len_mm * u)
    scene = {"seed": 3, "camera": CAMERA, "sensor": NOISE,
             "objects": [{"type": "line", "distance_mm": distance, "start_mm": a.tolist(),
                          "end_mm": b.tolist(), "rays": 400_000}]}
    raw, used, _ = simulate(base, scene_from_dict(scene))
    return raw.astype(np.float64), used


def test_triangulated_line_is_not_an_ok_point(monkeypatch):
    """A line at 2200 mm (behind a 1 m focus) is sent to the line fit; without a line model
    that explains it, the region has no distance instead of a 49 % short one."""
    img, used = _line_capture(2200.0)
    geom = truth_geometry(used, (SIZE, SIZE))
    calls = []

    def no_line(profile, geom_, image, box, near, start_mm=None, sigma_floor_mm=None):
        calls.append(box)
        return Measurement.failed("no-solution", geom_.d_in_mm, kind="line")

    monkeypatch.setattr(LF, "measure_line", no_line)
    run = run_distance(img, used, None, model="exact", geometry=geom)
    assert calls, "the line model was never tried"
    assert run.regions and all(r.status != "ok" for r in run.regions)
    assert any(r.status == "poor-fit" for r in run.regions)


def test_line_fit_chosen_over_triangulated_point(monkeypatch):
    """When the line model fits, the region becomes a ``line`` with the line's distance."""
    img, used = _line_capture(2200.0, angle_deg=135.0)
    geom = truth_geometry(used, (SIZE, SIZE))

    def good_line(profile, geom_, image, box, near, start_mm=None, sigma_floor_mm=None):
        nan = float("nan")
        return Measurement(nan, nan, nan, 2200.0, 0.0, 1.0, "ok", geom_.d_in_mm, kind="line",
                           misfit=0.05, endpoints=((0.0, 0.0), (0.0, 0.0)))

    monkeypatch.setattr(LF, "measure_line", good_line)
    run = run_distance(img, used, None, model="exact", geometry=geom)
    best = max(run.regions, key=lambda r: r.diameter_mm if r.status == "ok" else -1)
    assert best.kind == "line" and best.status == "ok"


def test_point_behind_focus_stays_a_point():
    """A point at 2200 mm is triangulated, its render explains the pixels: no line fit."""
    base = load_profile("system2")
    scene = {"seed": 4, "camera": CAMERA, "sensor": NOISE, "rays_per_source": 300_000,
             "objects": [{"type": "point", "distance_mm": 2200.0, "position_mm": [20.0, -10.0]}]}
    raw, used, _ = simulate(base, scene_from_dict(scene))
    run = run_distance(raw.astype(np.float64), used, None, model="exact",
                       geometry=truth_geometry(used, (SIZE, SIZE)))
    ok = [r for r in run.regions if r.status == "ok"]
    assert ok and all(r.kind == "spot" for r in ok)
    best = max(ok, key=lambda r: r.diameter_mm)
    assert abs(best.distance_mm / 2200.0 - 1.0) < 0.005


def test_d_in_from_a_dot_behind_focus():
    """One dot at 1500 mm behind a 1 m focus, solve started 0.4 mm off: d_in within 0.1 %
    (refused before: 0.56 px misfit, a pedestal of clipped read noise and a side basin)."""
    size = 768
    cam = {"sensor": {"width_px": size, "height_px": size}, "mla": {"focus_mm": 1000.0}}
    base = load_profile("system2")
    white, _, truth = simulate(base, scene_from_dict(
        {"seed": 1, "objects": [{"type": "white"}], "camera": cam, "rays_per_source": 100_000}))
    lenses = truth["lenses"]
    centres = np.array(lenses["centroid_px"])[np.array(lenses["complete"], dtype=bool)]
    raw, used, _ = simulate(base, scene_from_dict(
        {"seed": 2, "camera": cam, "sensor": NOISE, "rays_per_source": 200_000,
         "objects": [{"type": "point", "distance_mm": 1500.0, "position_mm": [0.0, 0.0]}]}))
    res = measure_d_in(raw.astype(np.float64), centres, used.with_d_in(used.d_in_mm + 0.4),
                       1500.0)
    assert abs(res.d_in_mm / used.d_in_mm - 1.0) < 1e-3


def _lenslet_region(img, used):
    geom = truth_geometry(used, (SIZE, SIZE))
    run = run_distance(img, used, None, model="exact", method="lenslet", geometry=geom)
    return max(run.regions, key=lambda r: r.diameter_mm if r.status == "ok" else -1)


def test_short_line_behind_focus_is_a_line():
    """A line 3 pitches long (0.75 mm on the MLA) at 2200 mm inside a ~780-lenslet blur: its
    footprint's axis is noise (90° off here), and the line fit started on it stalled at 0.74 ×
    the point's misfit, so the region was a spot 1.4 % long. Turned starts find the line."""
    img, used = _line_capture(2200.0, angle_deg=0.0, image_len_mm=0.75)
    best = _lenslet_region(img, used)
    assert best.kind == "line" and best.status == "ok"
    assert abs(best.distance_mm / 2200.0 - 1.0) < 0.005


def test_two_pitch_line_at_the_noise_is_a_line():
    """A line 2 pitches long at 2900 mm: as a point it leaves 1.6 × the misfit its noise
    alone would, as a line 0.8 × (a ratio of 0.50, not under LINE_GAIN). A line that reaches
    the noise wins (verify.line_beats); as a point the region was 1.2 % long."""
    img, used = _line_capture(2900.0, angle_deg=0.0, image_len_mm=0.5)
    best = _lenslet_region(img, used)
    assert best.kind == "line" and best.status == "ok"
    assert abs(best.distance_mm / 2900.0 - 1.0) < 0.006


def test_pixel_line_fit_starts_from_the_lenslet_line():
    """The pixel fit of a short line behind focus starts from the lenslet fit's line as well
    as from its own distance scan (whose axis, from the footprint's second moments, is noise
    here): 2200 mm, 3 pitches long, 60°: −0.62 % from the scan alone, +0.08 % now."""
    img, used = _line_capture(2200.0, angle_deg=60.0, image_len_mm=0.75)
    geom = truth_geometry(used, (SIZE, SIZE))
    regions = find_regions(lenslet_stats(img, geom.lmap), geom.lmap, geom.pitch_px)
    region = max(regions, key=lambda r: len(r.lenslets))
    m = LF.measure_lightfield(used, geom, img, region, noise_sigma(img))
    assert m.kind == "line" and m.status == "ok"
    assert abs(m.distance_mm / 2200.0 - 1.0) < 0.003


def test_pixel_line_fit_skipped_where_the_lenslet_line_explains_nothing(monkeypatch):
    """System 2's 300 mm point of the seed grid: its pixel misfit triggers the line fit, which
    always lost (10 s of pixel line fit). The lenslet fit's line leaves over 0.8 × its point's
    misfit there, so the pixel line fit does not run; the point's answer is the same."""
    from pathlib import Path

    from lfcam.calibrate import load_calibration
    from lfcam.io import load_capture
    from lfcam.measure import prepare_geometry

    data = Path(__file__).resolve().parents[1] / "data" / "synthetic"
    name = "point_system2_300mm_dh10"
    prof = load_profile(data / f"{name}.profile.toml")
    img = load_capture(data / f"{name}.png", prof).grey()
    geom = prepare_geometry(prof, load_calibration(data / "calib_system2.json"), img.shape)
    region = find_regions(lenslet_stats(img, geom.lmap), geom.lmap, geom.pitch_px)[0]
    calls = []
    monkeypatch.setattr(LF, "measure_line", lambda *a, **k: calls.append(a))
    m = LF.measure_lightfield(prof, geom, img, region, noise_sigma(img))
    assert not calls
    assert m.kind == "spot" and m.status == "ok"
    # the seed's ERROR (eq. 21): 0.009 % before and after
    assert abs(m.distance_mm - 300.0) / (300.0 + 0.5 * prof.main_lens.thickness_mm) < 5e-4


def _off_axis_line_capture(distance, angle_deg, centre_mla_mm, size=1536, rays=1_000_000):
    camera = {"mla": {"focus_mm": 1000.0, "rotation_rad": 0.012},
              "sensor": {"width_px": size, "height_px": size}}
    base = load_profile("system2")
    prof = apply_overrides(base, camera)
    u = np.array([np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))])
    c = np.asarray(centre_mla_mm, dtype=np.float64)
    a = chief_ray_offset(prof, prof.d_in_mm, distance, c - 1.5 * u)
    b = chief_ray_offset(prof, prof.d_in_mm, distance, c + 1.5 * u)
    scene = {"seed": 3, "camera": camera, "sensor": NOISE,
             "objects": [{"type": "line", "distance_mm": distance, "start_mm": a.tolist(),
                          "end_mm": b.tolist(), "rays": rays}]}
    raw, used, _ = simulate(base, scene_from_dict(scene))
    return raw.astype(np.float64), used


def test_line_off_axis_far_behind_focus():
    """A 3 mm line image at 3400 mm (focus 1 m), centred 7 mm off axis: the fine line model's
    own ray sample (5 rays a lenslet a point) rippled its misfit, and the fit stalled on a
    ripple 4.8 % long with status ``ok`` (σ 0.22 %; docs/distance.md, "Lines off axis"); with
    3 × the rays +0.51 % (σ 0.18 %). At 60° −0.52 → −0.11 %."""
    c = 7.0 * np.array([np.cos(np.radians(30.0)), np.sin(np.radians(30.0))])
    img, used = _off_axis_line_capture(3400.0, 0.0, c)
    geom = truth_geometry(used, img.shape)
    run = run_distance(img, used, None, model="exact", method="lenslet", geometry=geom)
    best = max(run.regions, key=lambda r: r.diameter_mm if r.status == "ok" else -1)
    assert best.kind == "line" and best.status == "ok"
    assert abs(best.distance_mm / 3400.0 - 1.0) < 0.008


def _field_line(cam, distance_mm: float, field: float, angle_deg: float, rays: int):
    """``benchmarks/focus_grid.py --lines``' capture (:meth:`focus_grid.Camera.line`)."""
    img, _, _ = cam.render([cam.line(distance_mm, angle_deg, field, rays)], seed=3, rays=rays)
    return img


def test_line_across_the_field_stretch(tmp_path):
    """System 1, a 3 mm line image at 1500 mm (focus 1 m) centred at 60 % of the half-field
    and turned 135°, across the radius along which vignetting stretches a point's footprint
    (``benchmarks/focus_grid.py --lines --line-field 0.6``'s capture and calibration): the
    line fit started only along the footprint's (radial) axis and ended as a spot 23.7 % long
    with status ``ok``. Started also along the footprint less the point's own it is a line at
    −0.014 % (docs/distance.md, "Lines across the field's stretch")."""
    import focus_grid as fg

    cam = fg.Camera("system1", 1000.0, None, tmp_path, False)
    img = _field_line(cam, 1500.0, 0.6, 135.0, 1_000_000)
    run = run_distance(img, cam.used, None, model="exact", method="lenslet",
                       geometry=cam.geom)
    best = max(run.regions, key=lambda r: r.diameter_mm if r.status == "ok" else -1)
    assert best.kind == "line" and best.status == "ok"
    assert abs(best.distance_mm / 1500.0 - 1.0) < 0.003


def test_line_refitted_where_its_ray_sample_moves_it(tmp_path, monkeypatch):
    """System 1, a 3 mm line image at 3400 mm (focus 1 m) centred at 80 % of the half-field,
    turned 135°, noise-free (16 M rays), the renderer's lenslet centres: nothing but the fit
    is left to err. The fine line model (~5 000 rays a point on this ~180-lenslet blur) put
    it +1.90 % long at a σ of 0.43 % (4.4σ): far behind focus the blur grows by ~0.4 % for
    1 % of distance, and the model's own ray sample moved the minimum. A Gauss–Newton step
    through a turned pupil sample measures that shift (0.015 in log distance here) and the
    line is refitted with 4× the rays: −0.05 % (docs/distance.md, "A line's settled test").

    Since each point of the line turns its own pupil sample (half the rays: 3 333 a point;
    a refit with 8× them), the same fit is −0.002 % with the settled test (σ 0.11 %), +0.50 %
    without it (σ 0.31 %), and +1.13 % (3.5σ) with neither (docs/distance.md, "A line's points,
    each with its own turn of the pupil sample"). Without the settled test the answer is the
    fine sample's own minimum and so depends on the fit's path: +0.32 % (σ 0.28 %) before
    Levenberg–Marquardt stopped re-trying near-identical steps (stop 48), the settled answer
    −0.005 % then."""
    import focus_grid as fg

    import lfcam.measure.fastfit as ff

    monkeypatch.setitem(fg.NOISE, "photon_noise", False)
    monkeypatch.setitem(fg.NOISE, "read_noise_e", 0.0)
    cam = fg.Camera("system1", 1000.0, 1024, tmp_path, True)
    img = _field_line(cam, 3400.0, 0.8, 135.0, 16_000_000)

    def line_error(tolerance_pct: float | None = None) -> tuple[float, float]:
        run = run_distance(img, cam.used, None, model="exact", method="lenslet",
                           geometry=cam.geom, jobs=1, tolerance_pct=tolerance_pct)
        best = max(run.regions, key=lambda r: r.diameter_mm if r.status == "ok" else -1)
        assert best.kind == "line" and best.status == "ok"
        return best.distance_mm / 3400.0 - 1.0, best.uncertainty_mm / 3400.0

    def line_error_with(name: str, value) -> tuple[float, float]:
        # line_error() with one fastfit constant set to value, then restored
        kept = getattr(ff, name)
        monkeypatch.setattr(ff, name, value)
        try:
            return line_error()
        finally:
            monkeypatch.setattr(ff, name, kept)

    paused = []
    lm = ff.levenberg_marquardt

    def spied(*a, pause=None, **k):  # (whether the fine fit stopped for the settled test)
        if pause is not None:
            def pause_spied(*b):
                paused.append(pause(*b))
                return paused[-1]
            return lm(*a, pause=pause_spied, **k)
        return lm(*a, **k)

    monkeypatch.setattr(ff, "levenberg_marquardt", spied)
    err, sigma = line_error()
    assert abs(err) < 0.003 and abs(err) < 3.0 * sigma  # measured +0.021 %, σ 0.175 %
    # The settled test read before the fine fit's last iteration sends the line to the refit
    # from there (LINE_REFIT_EARLY: measured +0.150 %, σ 0.18 %); the old path, the test after
    # the last iteration and the refit from its end, lands as near the truth (measured
    # +0.102 %) and within 0.5σ of it (docs/distance.md, "The settled test before the fine
    # fit's last iteration (stop 58)")
    assert paused == [False, True]  # (called after the first iteration, and the second)
    # the fine stage's four Gauss–Newton steps on the coarse Jacobian before its
    # Levenberg–Marquardt, as before stop 80 (LINE_RAYS_FINE_GN): within half a σ (measured
    # −0.018 %, σ 0.174 %; docs/distance.md, "A ray-sampled line's fine stage without the
    # coarse Jacobian's steps (stop 80)")
    err_gn, sigma_gn = line_error_with("LINE_RAYS_FINE_GN", True)
    assert abs(err_gn) < 3.0 * sigma_gn and abs(err - err_gn) < 0.5 * sigma
    # the fine Jacobian's columns along the line from every point shifted, as before stop 80
    # (LINE_FINE_ENDS): +0.189 %, σ 0.184 %, 1.0σ from this one's answer, both within 3σ of
    # the truth (docs/distance.md, "The fine Jacobian from the line's ends off super-cells
    # (stop 80)")
    err_fine_points, sigma_fine_points = line_error_with("LINE_FINE_ENDS", False)
    assert abs(err_fine_points) < 3.0 * sigma_fine_points
    # the refit's Jacobian along the line from its two ends (LINE_REFIT_ENDS) against every
    # point shifted, the three traces it replaces: within half a σ (docs/distance.md, "The
    # refit's Jacobian from the line's ends (stop 78)": measured +0.085 %, σ 0.19 %, against
    # +0.150 %, σ 0.18 %; since stop 80 +0.021 %, σ 0.175 %, against +0.025 %, σ 0.170 %)
    err_points, sigma_points = line_error_with("LINE_REFIT_ENDS", False)
    assert abs(err_points) < 3.0 * sigma_points and abs(err - err_points) < 0.5 * sigma
    # the refit's first step by its own Jacobian taken unevaluated (LINE_REFIT_TRUSTED)
    # against its steps evaluated, as before stop 79: here, noise-free, the evaluated path
    # takes a second step (0.062 % in distance) that the linear model of the first does not
    # ask for: +0.085 % (σ 0.190 %) against +0.147 % (σ 0.190 %), within half a σ
    # (docs/distance.md, "The refit's step by its own Jacobian, not evaluated (stop 79)";
    # since stop 80 −0.029 %, σ 0.175 %, against +0.021 %, σ 0.175 %)
    err_evaluated, sigma_evaluated = line_error_with("LINE_REFIT_TRUSTED", False)
    assert abs(err_evaluated) < 3.0 * sigma_evaluated and abs(err - err_evaluated) < 0.5 * sigma
    assert abs(sigma / sigma_evaluated - 1.0) < 0.05
    err_old, sigma_old = line_error_with("LINE_REFIT_EARLY", False)
    assert abs(err_old) < 3.0 * sigma_old and abs(err - err_old) < 0.5 * sigma
    # A tolerance the fine fit cannot meet with the shift in its σ keeps the refit; one it
    # meets skips it and reports that σ (docs/distance.md, "A line's refit only where the
    # tolerance needs it"): the unrefitted answer, with a σ that covers its error
    assert line_error(1.0) == (err, sigma)
    err_quick, sigma_quick = line_error(10.0)
    monkeypatch.setattr(ff, "LINE_SETTLED_LOG", np.inf)  # without the settled test
    err_turned, sigma_turned = line_error()
    # the points' turned samples alone: within 3σ. Without the settled test the answer is
    # the fine sample's own minimum, where the fit's path leaves it: +0.50 % (1.6σ) at stop
    # 58, +0.286 % (1.1σ) at stop 79, +0.340 % (1.3σ) since stop 80 (+0.623 %, 2.3σ, with
    # stop 80's first change alone, no fine steps on the coarse Jacobian)
    assert abs(err_turned) < 3.0 * sigma_turned
    # the unrefitted answer with the shift in its σ: within 2σ (+0.286 % at σ 0.430 % at stop
    # 79, 0.67σ; +0.340 % at σ 0.435 % since stop 80, 0.78σ; 1.37σ with stop 80's first
    # change alone, whose three Levenberg–Marquardt iterations from a start 9.4 % long ended
    # 0.13 % beyond the fine model's minimum)
    assert err_quick == err_turned and abs(err_quick) < 2.0 * sigma_quick
    # the shift is in it (the difference of the two samples' steps, read before the last
    # iteration: 0.0033 in log distance; 0.015 read after it, with the last step still to go
    # in it): σ 0.43 % against 0.26 % (0.435 % against 0.259 % since stop 80)
    assert sigma_quick > 1.5 * sigma_turned
    monkeypatch.setattr(ff, "LINE_TURNS", False)  # ... and one pupil sample for every point
    err_unsettled, sigma_unsettled = line_error()
    # measured +1.13 % at stop 58, +7.47 % (7.1σ) at stop 79, +9.79 % (7.2σ) since stop 80:
    # the turns at least halve the error in σ
    assert err_unsettled > 0.01 and err_unsettled > 3.0 * sigma_unsettled
    assert abs(err_turned) / sigma_turned < 0.5 * err_unsettled / sigma_unsettled


def test_line_whose_point_fit_runs_to_the_far_bound_is_still_tried(tmp_path):
    """System 2 at 1536² (focus 1 m), a 3 mm line image at 380 mm, in front of focus, centred
    at 60 % of the half-field at 0° (``benchmarks/focus_grid.py --lines --systems system2
    --size 1536 --line-field 0.6``'s capture and calibration). Its point fit, on the lenslet
    cells, runs out to the far bound (`no-solution`, a misfit of 0.65); the region was given
    up there without a line being tried. The line is tried now and answers within 0.05 %
    (measured −0.015 %: docs/distance.md, "Large point blurs on the cells (stop 44)")."""
    import focus_grid as fg

    import lfcam.measure.fastfit as ff

    cam = fg.Camera("system2", 1000.0, 1536, tmp_path, False)
    img = _field_line(cam, 380.0, 0.6, 0.0, 1_000_000)
    run = run_distance(img, cam.used, None, model="exact", method="lenslet",
                       geometry=cam.geom, jobs=1)
    best = max(run.regions, key=lambda r: r.diameter_mm if r.status == "ok" else -1)
    assert best.kind == "line" and best.status == "ok"
    assert abs(best.distance_mm / 380.0 - 1.0) < 5e-4
    # (the case this is about: the point fit alone reaches the far bound)
    regions = find_regions(lenslet_stats(img, cam.geom.lmap), cam.geom.lmap, cam.geom.pitch_px)
    region = max(regions, key=lambda r: len(r.lenslets))
    first = next(ff.point_fit_stages(cam.used, cam.geom, img, region))
    assert not first.ok and first.reason == "no-solution" and first.misfit > 0.3


def test_a_trusted_refit_step_ends_at_the_least_squares_minimum():
    """:func:`lfcam.measure.solve.gauss_newton_fixed` with ``trusted`` (a refit's, a cells
    line's fine step) on a linear residual ``r(q) = A·q − b``: its unevaluated step lands on
    the least-squares solution (numpy's ``lstsq``, an SVD) and its predicted residual is the
    one evaluated there; a step longer than the trust bound is evaluated, and one under the
    refit's least trial (or the cells' shortest step) is not taken."""
    import lfcam.measure.fastfit as ff
    from lfcam.measure.solve import gauss_newton_fixed

    rng = np.random.default_rng(5)
    a = rng.normal(size=(400, 5))
    b = rng.normal(size=400)
    q_min = np.linalg.lstsq(a, b, rcond=None)[0]
    calls: list = []

    def fun(q):
        calls.append(1)
        return a @ q - b

    def refit(start, **rule):
        calls.clear()
        rule = rule or {"min_trial": ff.LINE_REFIT_MIN_TRIAL_LOG}
        return gauss_newton_fixed(fun, start, a @ start - b, a, ff.LINE_REFIT_STEPS,
                                  trusted=ff.LINE_REFIT_TRUST_LOG, **rule)

    start = q_min + np.array([0.004, 0.01, -0.02, 0.003, 0.0])  # 0.4 % in log distance
    q, r, f = refit(start)
    assert not calls  # (not evaluated)
    assert np.allclose(q, q_min, rtol=0, atol=1e-9)
    assert np.allclose(r, a @ q - b, rtol=0, atol=1e-9)
    assert abs(f - float((a @ q_min - b) @ (a @ q_min - b))) < 1e-9
    far = q_min + np.array([2.0 * ff.LINE_REFIT_TRUST_LOG, 0.0, 0.0, 0.0, 0.0])
    q_f, _, _ = refit(far)
    assert calls and np.allclose(q_f, q_min, rtol=0, atol=1e-9)  # (evaluated steps instead)
    near = q_min + np.array([0.5 * ff.LINE_REFIT_MIN_TRIAL_LOG, 0.0, 0.0, 0.0, 0.0])
    q_n, r_n, f_n = refit(near)
    assert not calls and np.array_equal(q_n, near)
    assert abs(f_n - float(r_n @ r_n)) < 1e-9 * f_n
    # the cells' fine step (LINE_CELLS_TRUSTED) with its own shortest step: taken over it
    cells = q_min + np.array([2.0 * ff.LINE_CELLS_FINE_STEP_LOG, 0.0, 0.0, 0.0, 0.0])
    q_c, _, _ = refit(cells, skip_below=ff.LINE_CELLS_FINE_STEP_LOG)
    assert not calls and np.allclose(q_c, q_min, rtol=0, atol=1e-9)
    q_s, _, _ = refit(cells, skip_below=3.0 * ff.LINE_CELLS_FINE_STEP_LOG)
    assert not calls and np.array_equal(q_s, cells)
