"""Touching micro-images (real Lytro whites): the fixed-point own-light fit against the truth.

The white comes from ``benchmarks/whites.py`` (soft discs that share their seams, radial
vignetting), whose truth is each lens's own light, independent of the calibration code.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lfcam.calibrate import prepare_white
from lfcam.calibrate.grid import find_centres, fit_similarity
from lfcam.calibrate.microimage import DiscModel, fixed_point_applies, own_light_fit

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from whites import make_touching_white  # noqa: E402


def _match(centres, truth, pitch):
    d, i = cKDTree(truth).query(centres)
    _, j = cKDTree(centres).query(truth)
    matched = (d < 0.25 * pitch) & (j[i] == np.arange(len(centres)))
    err = np.hypot(*(centres[matched] - truth[i[matched]]).T)
    return matched, err


@pytest.mark.parametrize("pitch, noisy", [(14.29, True), (9.9, False)])
def test_fixed_point_matches_truth(pitch, noisy):
    sw = make_touching_white(560, 420, pitch, rotation_rad=np.deg2rad(0.7), noise=noisy,
                             read_noise=3.0 if noisy else 0.0, vignetting=0.45)
    img, _ = prepare_white(sw.image)
    t0 = time.perf_counter()
    fit = find_centres(img)
    assert time.perf_counter() - t0 < 10.0
    assert fit.diagnostics["centroid_method"] == "micro-image model"
    assert fit.diagnostics["model_solver"] == "fixed point"
    matched, err = _match(fit.centres_px, sw.centres_px, pitch)
    assert matched.sum() >= len(sw.centres_px) - 2
    # nothing invented: every reported centre is a lens the generator drew. (The generator's
    # "fully visible" asks for its whole erfc tail, R + 4.5σ, on the sensor; calibration asks
    # for the fitted disc support, so a few border lenses are reported but not in the truth.)
    design = np.column_stack([sw.indices, np.ones(len(sw.indices))])
    sol, *_ = np.linalg.lstsq(design, sw.lattice_px, rcond=None)
    ij = np.mgrid[-60:61, -60:61].reshape(2, -1).T
    sites = np.column_stack([ij, np.ones(len(ij))]) @ sol
    d_site, _ = cKDTree(sites).query(fit.centres_px[~matched])
    assert (d_site < 0.1).all()
    rms = float(np.sqrt(np.mean(err**2)))
    # photon noise alone gives ~0.014 px; the seam attribution (linear edge ramp against the
    # erfc edges) adds ~0.01 px, more on this small, steeply vignetted image
    assert rms < (0.023 if noisy else 0.015), rms
    _, pitch_t, rot_t, _ = fit_similarity(sw.indices, sw.centres_px, "hex")
    assert abs(fit.pitch_px - pitch_t) / pitch_t < 1e-4
    assert abs(fit.rotation_rad - rot_t) < 1e-4


def test_fixed_point_converges_from_rough_start():
    """Starts half a pixel off still reach the own-light centroids the converged fit gives."""
    sw = make_touching_white(400, 320, 14.29, rotation_rad=0.01, noise=False, read_noise=0.0)
    model = DiscModel(0.46 * 14.29, 0.9, 0.0)
    assert fixed_point_applies(model, 14.29)
    rng = np.random.default_rng(1)
    start = sw.lattice_px + rng.uniform(-0.3, 0.3, sw.lattice_px.shape)
    own, flux, disc, conv = own_light_fit(sw.image, start, model, 14.29, tol_px=1e-4,
                                          iterations=20)
    assert conv.all()
    assert (flux > 0).all()
    ref, *_ = own_light_fit(sw.image, sw.lattice_px, model, 14.29, tol_px=1e-4, iterations=20)
    # lenses away from the border (the partly visible lenses are not modelled here, so the
    # outermost row's seams are not reproducible)
    h, w = sw.image.shape
    x, y = sw.lattice_px.T
    inner = (x > 22) & (x < w - 23) & (y > 22) & (y < h - 23)
    # the same fixed point up to the brightness planes, which are fitted on a core disc about
    # each start's nearest pixel (a few thousandths of a pixel at most)
    diff = np.hypot(*(own - ref)[inner].T)
    assert np.sqrt(np.mean(diff**2)) < 4e-3 and diff.max() < 0.015
    assert np.sqrt(np.mean(np.sum((own - sw.centres_px)[inner] ** 2, axis=1))) < 0.012
    # the disc centres land near the lattice sites the discs were drawn at (a model
    # parameter: the linear edge ramp only approximates the erfc edges)
    assert np.sqrt(np.mean(np.sum((disc - sw.lattice_px)[inner] ** 2, axis=1))) < 0.03


def test_overlapping_discs_keep_gauss_newton():
    assert not fixed_point_applies(DiscModel(8.79, 0.5, 0.0), 16.1)  # system 2
    assert fixed_point_applies(DiscModel(7.96, 0.6, 0.0), 16.4)  # system 1


def test_threads_give_the_serial_result(monkeypatch):
    """The chunked loops on threads (``lfcam.calibrate.parallel``) give the serial result:
    small chunks, so a 560×420 white has 9–36 of them per loop, on 1 and on 3 threads."""
    import lfcam.calibrate.microimage as micro

    sw = make_touching_white(560, 420, 14.29, rotation_rad=np.deg2rad(0.7), noise=True,
                             read_noise=3.0, vignetting=0.45)
    monkeypatch.setattr(micro, "CHUNK", 128)
    out = {}
    for threads in ("1", "3"):
        monkeypatch.setenv("LFCAM_THREADS", threads)
        img, n_hot = prepare_white(sw.image)
        out[threads] = (find_centres(img), n_hot)
    (f1, h1), (f3, h3) = out["1"], out["3"]
    assert h1 == h3
    assert np.array_equal(f1.indices, f3.indices)
    # the model image is summed in another order on threads (float32): a few 1e-6 px at most
    assert np.abs(f1.centres_px - f3.centres_px).max() < 1e-4
    matched, err = _match(f3.centres_px, sw.centres_px, 14.29)
    assert matched.sum() >= len(sw.centres_px) - 2
    assert float(np.sqrt(np.mean(err**2))) < 0.023


def test_candidates_do_not_depend_on_the_bands(monkeypatch):
    """The candidate filters in row bands of at most ``BAND_ROWS`` rows (each with a margin of
    the filters' reach) give the one-band result exactly, on 1 and 3 threads."""
    import lfcam.calibrate.grid as grid

    sw = make_touching_white(300, 260, 14.29, rotation_rad=np.deg2rad(0.7), noise=True,
                             read_noise=3.0, vignetting=0.45)
    img, _ = prepare_white(sw.image)
    monkeypatch.setenv("LFCAM_THREADS", "1")
    monkeypatch.setattr(grid, "BAND_ROWS", 10**6)
    pts1, val1 = grid.find_candidates(img, 14.29)
    for threads in ("1", "3"):
        monkeypatch.setenv("LFCAM_THREADS", threads)
        monkeypatch.setattr(grid, "BAND_ROWS", 37)  # 8 bands, each shorter than two margins
        pts, val = grid.find_candidates(img, 14.29)
        order1, order = np.lexsort(pts1.T), np.lexsort(pts.T)
        assert np.array_equal(pts1[order1], pts[order])
        assert np.array_equal(val1[order1], val[order])
    assert len(pts1) >= 371  # one or more for each of its 371 fully visible lenses
