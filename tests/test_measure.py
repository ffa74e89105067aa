"""The measure modules one at a time, each against truth computed another way.

- lenslets: pixel → lenslet labels against a brute-force nearest-centre search; energies and
  centroids against direct sums.
- regions: clusters of a painted energy map; the lit threshold against its normal-noise
  definition.
- pointfit: spot centroids of analytic Gaussian spots; line triangulation against a known
  point; the lattice lookup against brute force.
- linefit: image moments of a drawn segment against its analytic length and direction.
- geometry: white-centroid → lenslet-centre inversion against the renderer's lenslet centres.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lfcam.camera import load_profile
from lfcam.measure import find_regions, lenslet_stats
from lfcam.measure.geometry import (
    lenslet_centres_mm,
    regularise_to_lattice,
    white_centroids_px,
)
from lfcam.measure.lenslets import build_lenslet_map
from lfcam.measure.linefit import _moments
from lfcam.measure.pointfit import LocalLattice, find_spots, triangulate_lines
from lfcam.measure.regions import NOISE_SIGMAS, lit_threshold

DATA = Path(__file__).resolve().parents[1] / "data" / "synthetic"


def _grid(n: int, pitch: float, origin: float = 0.0) -> np.ndarray:
    g = origin + pitch * np.arange(n)
    xx, yy = np.meshgrid(g, g)
    return np.column_stack([xx.ravel(), yy.ravel()])


def test_lenslet_map_matches_brute_force_nearest_centre():
    rng = np.random.default_rng(1)
    centres = _grid(6, 10.0, 5.0) + rng.uniform(-0.3, 0.3, (36, 2))
    lmap = build_lenslet_map(centres, (60, 60), 5.4)
    yy, xx = np.mgrid[0:60, 0:60]
    pix = np.column_stack([xx.ravel(), yy.ravel()]).astype(float)
    d = np.hypot(*(pix[:, None, :] - centres[None]).transpose(2, 0, 1))
    want = np.where(d.min(axis=1) <= 5.4, d.argmin(axis=1), -1)
    np.testing.assert_array_equal(lmap.labels.ravel(), want)


def test_lenslet_stats_are_the_sums_over_each_micro_image():
    centres = _grid(4, 10.0, 5.0)
    lmap = build_lenslet_map(centres, (40, 40), 5.0)
    rng = np.random.default_rng(2)
    img = rng.uniform(0, 1, (40, 40))
    stats = lenslet_stats(img, lmap)
    yy, xx = np.mgrid[0:40, 0:40]
    for k in (0, 5, 15):
        m = lmap.labels == k
        assert stats.energy[k] == pytest.approx(img[m].sum(), rel=1e-12)
        cx = (img[m] * xx[m]).sum() / img[m].sum()
        assert stats.centroid_px[k, 0] == pytest.approx(cx, rel=1e-12)


def test_lit_threshold_is_median_plus_k_normal_sigmas():
    rng = np.random.default_rng(3)
    e = rng.normal(100.0, 2.0, 200_000)
    assert lit_threshold(e) == pytest.approx(100.0 + NOISE_SIGMAS * 2.0, rel=2e-3)


def test_regions_separate_two_blurs_and_call_the_long_one_a_line():
    centres = _grid(30, 10.0, 5.0)
    lmap = build_lenslet_map(centres, (300, 300), 5.4)
    img = np.random.default_rng(4).normal(0.0, 1e-3, (300, 300))
    img[41:80, 41:80] += 1.0  # a 4×4-lenslet spot (lenslets 45…75), symmetric about 60
    img[201:209, 101:259] += 1.0  # a 16×1-lenslet line
    regions = find_regions(lenslet_stats(img, lmap), lmap, 10.0)
    kinds = sorted((r.kind, len(r.lenslets)) for r in regions)
    assert kinds == [("line", 16), ("spot", 16)]
    spot = next(r for r in regions if r.kind == "spot")
    assert spot.centroid_px == pytest.approx((60.0, 60.0), abs=0.01)
    line = next(r for r in regions if r.kind == "line")
    assert abs(line.axis_dir[0]) == pytest.approx(1.0, abs=1e-9)


def test_find_spots_recovers_gaussian_centroids():
    yy, xx = np.mgrid[0:64, 0:64].astype(float)
    truth = [(12.3, 20.7, 2.0), (45.8, 40.1, 3.0)]
    img = sum(a * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.5**2)) for x, y, a in truth)
    spots, energy = find_spots(img, np.ones_like(img, bool), 1e-9)
    order = np.argsort(spots[:, 0])
    np.testing.assert_allclose(spots[order], [(x, y) for x, y, _ in truth], atol=1e-6)
    np.testing.assert_allclose(energy[order], [a * 2 * np.pi * 1.5**2 for *_, a in truth],
                               rtol=1e-6)


def test_triangulate_lines_meets_at_the_source():
    rng = np.random.default_rng(5)
    source = np.array([3.0, -2.0, -1500.0])
    points = np.column_stack([rng.uniform(-20, 20, (40, 2)), np.zeros(40)])
    dirs = source - points
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    s, cov, rms = triangulate_lines(points, dirs, np.ones(40))
    np.testing.assert_allclose(s, source, atol=1e-6)
    assert rms < 1e-9


def test_local_lattice_lookup_matches_brute_force():
    ang = 0.02
    rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    basis = 0.25 * rot @ np.array([[1.0, 0.5], [0.0, np.sqrt(3) / 2]])
    ij = np.array([(i, j) for i in range(-6, 7) for j in range(-6, 7)])
    centres = ij @ basis.T + np.array([0.03, -0.01])
    lat = LocalLattice.fit(centres, 0.25)
    assert lat is not None
    rng = np.random.default_rng(6)
    pts = rng.uniform(-0.8, 0.8, (2000, 2))
    got = lat.nearest(pts[:, 0], pts[:, 1])
    _, want = cKDTree(centres).query(pts)
    np.testing.assert_array_equal(got, want)


def test_line_moments_give_length_and_direction():
    img = np.zeros((80, 80))
    t = np.linspace(-25, 25, 2001)
    ang = np.deg2rad(30.0)
    x = np.round(40 + t * np.cos(ang)).astype(int)
    y = np.round(40 + t * np.sin(ang)).astype(int)
    img[y, x] = 1.0
    centre, variances, direction = _moments(img)
    assert tuple(centre) == pytest.approx((40.0, 40.0), abs=0.05)
    # a uniform segment of length L has variance L²/12 along it
    assert variances[1] == pytest.approx(50.0**2 / 12.0, rel=0.03)
    assert variances[0] < 0.5
    assert abs(abs(np.dot(direction, (np.cos(ang), np.sin(ang)))) - 1.0) < 1e-3


def _white_lenses(name: str):
    """A committed white's truth and profile, and its fully visible lenslets' renderer
    centroids (px), centres (mm) and lattice indices."""
    truth = json.loads((DATA / f"{name}.truth.json").read_text(encoding="utf-8"))
    profile = load_profile(DATA / f"{name}.profile.toml")
    lenses = truth["lenses"]
    ok = np.asarray(lenses["complete"], bool)
    return (truth, profile, np.asarray(lenses["centroid_px"], float)[ok],
            np.asarray(lenses["centre_mm"], float)[ok], np.asarray(lenses["index_ij"])[ok])


@pytest.mark.parametrize("name", ["white_system1_rect", "white_system2_rect"])
def test_white_centroids_of_the_true_lenslets_match_the_renderer(name):
    # the forward map (benchmarks' prediction at the renderer's lenslets): the renderer's own
    # ray-derived centroids within 0.002 pitch RMS (measured 0.00086 and 0.00053), and
    # lenslet_centres_mm takes it back to the lenslets within 0.1 µm (measured 0.018, 0.003)
    truth, profile, centroids, lens_mm, _ = _white_lenses(name)
    got = white_centroids_px(profile, truth["d_in_mm"], lens_mm)
    err_mm = np.hypot(*(got - centroids).T) * profile.sensor.pixel_pitch_mm
    assert np.sqrt(np.mean(err_mm**2)) < 0.002 * profile.mla.pitch_mm
    back = lenslet_centres_mm(profile, truth["d_in_mm"], got)
    assert np.abs(back - lens_mm).max() < 1e-4


@pytest.mark.parametrize("name", ["white_system1_rect", "white_system2_rect"])
def test_lenslet_centres_from_white_centroids_match_the_renderer(name):
    truth, profile, centroids, want, index_ij = _white_lenses(name)
    got = lenslet_centres_mm(profile, truth["d_in_mm"], centroids)
    err_um = 1e3 * np.hypot(*(got - want).T)
    pitch_um = 1e3 * profile.mla.pitch_mm
    assert np.sqrt(np.mean(err_um**2)) < 0.002 * pitch_um  # sub-µm on a 1.34 mm / 250 µm pitch
    reg, rms = regularise_to_lattice(got, index_ij, profile.mla.pitch_mm)
    assert rms < 0.002
    assert np.sqrt(np.mean(np.hypot(*(reg - want).T) ** 2)) <= np.sqrt(
        np.mean((got - want) ** 2) * 2) + 1e-12
