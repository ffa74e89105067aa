"""Centre detection and lattice fit against the independent synthetic generator's truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lfcam.calibrate import calibrate_white
from lfcam.calibrate.grid import fit_similarity
from lfcam.calibrate.synthetic import make_white
from lfcam.errors import CalibrationError
from lfcam.optics.mla import lattice_basis, rotation_matrix


def _score(sw, cal, w, h):
    truth = sw.centres_px
    hx = 0.5 * cal.pitch_px
    hy = hx if sw.grid == "rect" else np.sqrt(3) * cal.pitch_px / 4
    visible = ((truth[:, 0] - hx >= 0) & (truth[:, 0] + hx <= w - 1)
               & (truth[:, 1] - hy >= 0) & (truth[:, 1] + hy <= h - 1))
    d, i = cKDTree(cal.centres_px).query(truth)
    found = d < 1.0
    err = cal.centres_px[i[found]] - truth[found]
    # every lattice position the generator drew (partial lenses included)
    a = sw.pitch_px * rotation_matrix(sw.rotation_rad) @ lattice_basis(sw.grid)
    ij = np.mgrid[-80:81, -80:81].reshape(2, -1).T
    drawn = sw.offset_px + ij @ a.T
    d2, _ = cKDTree(drawn).query(cal.centres_px)
    _, pitch_t, rot_t, _ = fit_similarity(sw.indices, truth, sw.grid)
    return {
        "rms": float(np.sqrt(np.mean(np.sum(err**2, axis=1)))),
        "missed": int((visible & ~found).sum()),
        "invented": int((d2 > 1.5).sum()),
        "pitch_rel": abs(cal.pitch_px - pitch_t) / pitch_t,
        "rot_err": abs(cal.rotation_rad - rot_t),
    }


@pytest.mark.parametrize("grid", ["rect", "hex"])
@pytest.mark.parametrize("noisy", [False, True])
def test_synthetic_white_accuracy(grid, noisy):
    w, h = 640, 480
    pitch = 16.0 if grid == "rect" else 14.3
    sw = make_white(w, h, pitch, grid=grid, rotation_rad=np.deg2rad(-1.7 if noisy else 1.9),
                    offset_px=(320.37, 240.81), radius_frac=0.42 if grid == "rect" else 0.40,
                    cats_eye=0.3, vignetting=0.5, noise_electrons=noisy,
                    read_noise=3.0 if noisy else 0.0, hot_pixel_fraction=1e-4 if noisy else 0.0,
                    background=50.0 if noisy else 0.0, seed=3)
    cal = calibrate_white(sw.image)
    s = _score(sw, cal, w, h)
    assert cal.grid == grid
    assert s["rms"] <= (0.05 if noisy else 0.02), s
    assert s["missed"] == 0 and s["invented"] == 0, s
    assert s["pitch_rel"] <= 1e-4, s
    assert s["rot_err"] <= 1e-4, s
    assert cal.residual_rms_px < 0.05


def test_symmetric_discs_recover_generator_lattice():
    """Without vignetting the centroid lattice is the drawn lattice itself."""
    sw = make_white(500, 400, 15.3, grid="rect", rotation_rad=np.deg2rad(0.7),
                    offset_px=(250.23, 199.61), vignetting=0.0)
    cal = calibrate_white(sw.image)
    assert abs(cal.pitch_px - 15.3) / 15.3 < 1e-5
    assert abs(cal.rotation_rad - np.deg2rad(0.7)) < 1e-5
    # offset is the lattice point (0, 0) nearest the image centre: a lattice position
    f = np.linalg.solve(15.3 * rotation_matrix(np.deg2rad(0.7)),
                        np.array(cal.offset_px) - (250.23, 199.61))
    assert np.abs(f - np.round(f)).max() < 1e-3


def test_shadowed_lenses_rejected_not_invented():
    w, h = 480, 480
    sw = make_white(w, h, 16.0, vignetting=0.0, offset_px=(240.4, 240.2))
    img = sw.image.copy()
    img[:, :93] = 0.0  # a field stop cutting the column of discs at x = 96.4 ± 6.7
    cal = calibrate_white(img)
    cut = sum(v for k, v in cal.rejected.items() if k != "edge")
    assert cut == 29  # the whole cut column (29 lenses) is rejected, with a reason
    assert cal.centres_px[:, 0].min() > 105
    d, _ = cKDTree(sw.disc_centres_px).query(cal.centres_px)
    assert d.max() < 0.02  # every accepted centre is a real, unbiased lens


def test_not_a_white_image():
    rng = np.random.default_rng(0)
    with pytest.raises(CalibrationError):
        calibrate_white(rng.normal(100, 10, (200, 200)))
    with pytest.raises(CalibrationError):
        calibrate_white(np.zeros((100, 100)))
    with pytest.raises(CalibrationError):
        calibrate_white(np.full((100, 100), np.nan))


def _lattice(radial, noise_px, seed=0):
    """Points of a rotated, slightly projective hex lattice, optionally radially distorted."""
    from lfcam.calibrate.grid import predict_lattice

    rng = np.random.default_rng(seed)
    ij = np.mgrid[-40:41, -30:31].reshape(2, -1).T
    a = 14.3 * rotation_matrix(0.01) @ lattice_basis("hex")
    h = np.array([[a[0, 0], a[0, 1], 1000.0], [a[1, 0], a[1, 1], 700.0], [2e-6, -1e-6, 1.0]])
    pts = predict_lattice(h, radial, ij) + rng.normal(0.0, noise_px, (len(ij), 2))
    return ij, pts, h


def test_radial_term_recovered_and_only_when_warranted():
    """The radial lattice term is fitted to a known distortion and rejected when absent
    (truth: the generating parameters; the decision is the F-test plus a 0.01 px effect)."""
    from lfcam.calibrate.grid import (
        _richer_warranted,
        _rss,
        fit_projective,
        fit_radial,
        predict_lattice,
    )

    truth = (1010.0, 690.0, -2.0e-3, 1.5e-3)
    for radial, expect in ((truth, True), (None, False)):
        ij, pts, h = _lattice(radial, 0.01)
        w = np.ones(len(ij))
        h_p, w_p = fit_projective(ij, pts, w, h)
        h_r, rad, _ = fit_radial(ij, pts, w_p, h_p, np.array([1000.0, 700.0]))
        shift = float(np.abs(predict_lattice(h_r, rad, ij) - predict_lattice(h_p, None, ij)).max())
        use, _ = _richer_warranted(_rss(h_p, ij, pts, w_p), _rss(h_r, ij, pts, w_p, rad), 8, 12,
                                   float(w_p.sum()), shift)
        assert use is expect
        if expect:
            # the distortion is recovered: predictions within the 0.01 px noise level
            err = predict_lattice(h_r, rad, ij) - predict_lattice(h, truth, ij)
            assert float(np.sqrt(np.mean(np.sum(err**2, axis=1)))) < 0.005


def test_nearest_measured_is_the_kd_tree_query():
    """The lattice sites' nearest measured lens by table lookup (sites with a lens) and a k-d
    tree for the rest, and the sites dropped far off the sensor, against a full query."""
    from scipy.spatial import cKDTree

    from lfcam.calibrate.grid import _nearest_measured

    rng = np.random.default_rng(4)
    pitch = 14.0
    affine = np.array([[pitch, 0.5 * pitch, 30.0], [0.0, 0.866 * pitch, 25.0]])
    gi, gj = np.mgrid[-3:40, -3:30]
    sites = np.column_stack([gi.ravel(), gj.ravel()])
    idx = sites[(sites >= 0).all(axis=1) & (sites[:, 0] < 35) & (sites[:, 1] < 26)]
    idx = idx[rng.random(len(idx)) > 0.1]  # some lenses missed
    shape = (int(0.866 * pitch * 26) + 40, int(pitch * 48) + 40)
    kept, near = _nearest_measured(sites, idx, affine, shape, 2.0 * pitch)
    full = cKDTree(idx).query(sites)[1]
    where = {tuple(s): k for k, s in enumerate(map(tuple, sites))}
    rows = np.array([where[tuple(s)] for s in kept])
    dist_got = np.hypot(*(idx[near] - kept).T)
    dist_ref = np.hypot(*(idx[full[rows]] - kept).T)
    assert np.array_equal(dist_got, dist_ref)  # nearest (ties may pick another of equal reach)
    occupied = (idx[near] == kept).all(axis=1)
    assert occupied.sum() == len(idx)  # every measured lens's own site maps to it
    xy = np.delete(sites, rows, axis=0) @ affine[:, :2].T + affine[:, 2]
    off = np.maximum.reduce([-xy[:, 0], xy[:, 0] - (shape[1] - 1), -xy[:, 1],
                             xy[:, 1] - (shape[0] - 1)])
    assert len(xy) > 0 and np.all(off >= 2.0 * pitch)  # only sites far off the sensor dropped


def test_lattice_fits_recover_their_lattice():
    """The similarity fit's normal equations from weighted sums against a generic weighted
    least squares of its (2N × 4) rows, and the projective fit (compiled normal equations)
    recovering the homography that made the points (truth: the generating parameters)."""
    from lfcam.calibrate.grid import _robust_weights, fit_projective, predict_lattice

    ij, pts, h = _lattice(None, 0.02, seed=3)
    h_p, _ = fit_projective(ij, pts, np.ones(len(ij)), h + np.diag([0.05, -0.05, 0.0]))
    err = predict_lattice(h_p, None, ij) - predict_lattice(h, None, ij)
    assert float(np.sqrt(np.mean(np.sum(err**2, axis=1)))) < 0.002  # 0.02 px noise, 5 000 pts
    # the similarity fit, one round, against np.linalg.lstsq on its rows
    rng = np.random.default_rng(4)
    idx = np.mgrid[-30:31, -20:21].reshape(2, -1).T
    a = 14.29 * rotation_matrix(0.0052) @ lattice_basis("rect")
    xy = idx @ a.T + [3863.0, 2684.0] + rng.normal(0.0, 0.03, (len(idx), 2))
    w0 = rng.uniform(0.2, 1.0, len(idx))
    hs, pitch, rot, wts = fit_similarity(idx, xy, "rect", w0)
    u = idx.astype(float) @ lattice_basis("rect").T
    w = w0
    for _ in range(4):  # the fit's own four rounds, by lstsq
        rows = np.zeros((2 * len(u), 4))
        rows[: len(u), 0], rows[len(u):, 1] = 1.0, 1.0
        rows[: len(u), 2], rows[: len(u), 3] = u[:, 0], -u[:, 1]
        rows[len(u):, 2], rows[len(u):, 3] = u[:, 1], u[:, 0]
        sw = np.sqrt(np.concatenate([w, w]))
        rhs = np.concatenate([xy[:, 0], xy[:, 1]])
        sol = np.linalg.lstsq(rows * sw[:, None], rhs * sw, rcond=None)[0]
        w = _robust_weights(xy - (rows @ sol).reshape(2, -1).T)
    assert pitch == pytest.approx(float(np.hypot(sol[2], sol[3])), rel=1e-12)
    assert rot == pytest.approx(float(np.arctan2(sol[3], sol[2])), abs=1e-12)
    np.testing.assert_allclose(hs[:2, 2], sol[:2], rtol=1e-12)
    np.testing.assert_allclose(wts, w, atol=1e-9)
    assert pitch == pytest.approx(14.29, abs=2e-4) and rot == pytest.approx(0.0052, abs=2e-5)
