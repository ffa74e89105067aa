"""Issue 17 (speed) pieces, each against truth computed another way.

- The stencil lenslet map against a k-d tree nearest-centre search (hex lattice, overlapping
  discs, centres beyond the sensor edge, several row bands).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from lfcam.measure import lenslets
from lfcam.measure.lenslets import build_lenslet_map


def _hex_centres(h: int, w: int, pitch: float, rng) -> np.ndarray:
    a1 = np.array([pitch, 0.0])
    a2 = np.array([0.5 * pitch, 0.5 * np.sqrt(3.0) * pitch])
    i, j = np.meshgrid(np.arange(-int(w / pitch) - 3, int(2 * w / pitch) + 3),
                       np.arange(-3, int(h / (0.86 * pitch)) + 3))
    c = i.ravel()[:, None] * a1 + j.ravel()[:, None] * a2
    c += rng.uniform(-0.3, 0.3, c.shape)
    keep = (c[:, 0] > -pitch) & (c[:, 0] < w + pitch) & (c[:, 1] > -pitch) & (c[:, 1] < h + pitch)
    return c[keep]


def test_stencil_lenslet_map_equals_kdtree_nearest_centre(monkeypatch):
    # small bands so that several bands and centre chunks are exercised
    monkeypatch.setattr(lenslets, "BAND_PIXELS", 4000)
    rng = np.random.default_rng(7)
    h, w, pitch = 173, 211, 9.3
    centres = _hex_centres(h, w, pitch, rng)
    radius = 0.6 * pitch  # neighbouring discs overlap: the nearer centre must win
    lmap = build_lenslet_map(centres, (h, w), radius)
    yy, xx = np.mgrid[0:h, 0:w]
    dist, idx = cKDTree(centres).query(np.column_stack([xx.ravel(), yy.ravel()]))
    want = np.where(dist <= radius, idx, -1).reshape(h, w)
    assert (want >= 0).mean() > 0.9  # the test covers the discs, not just the gaps
    np.testing.assert_array_equal(lmap.labels, want)
