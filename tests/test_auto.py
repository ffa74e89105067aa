"""Uncertainty propagation (vs Monte Carlo) and ``--model auto`` (vs the exact truth)."""

from __future__ import annotations

import numpy as np
import pytest

from lfcam import load_profile
from lfcam.models import POINT_MODELS, auto
from lfcam.optics.trace import forward


@pytest.mark.parametrize("model", ["exact", "offaxis"])
def test_propagated_sigma_matches_monte_carlo(model):
    p = load_profile("system1")
    dist = np.array([500.0, 1500.0, 3000.0])
    fw = forward(p, None, dist, 4.0)
    sigma_y = 0.003  # mm, a few hundredths of a pixel
    _, sigma = auto.propagate(model, p, None, fw.y1_mm, fw.y2_mm, sigma_y, sigma_y)
    rng = np.random.default_rng(7)
    n = 4000
    y1 = fw.y1_mm[None, :] + rng.normal(0, sigma_y, (n, 3))
    y2 = fw.y2_mm[None, :] + rng.normal(0, sigma_y, (n, 3))
    mc = POINT_MODELS[model](p, None, y1, y2).distance_mm.std(axis=0)
    np.testing.assert_allclose(sigma, mc, rtol=0.08)  # MC std has ~1.1 % sampling error


def test_auto_defaults_to_exact():
    p = load_profile("system2")
    fw = forward(p, None, np.array([400.0, 3000.0]), 0.0)
    models, inv, _ = auto.choose(p, None, fw.y1_mm, fw.y2_mm, 1e-3, 1e-3)
    assert list(models) == ["exact", "exact"]
    np.testing.assert_allclose(inv.distance_mm, [400.0, 3000.0], rtol=1e-9)


@pytest.mark.parametrize("tolerance_pct", [0.5, 1.0, 3.0])
def test_auto_meets_its_tolerance_and_is_cheap_where_it_can_be(tolerance_pct):
    p = load_profile("system2")
    rng = np.random.default_rng(3)
    dist = rng.uniform(300.0, 3500.0, 300)
    off = rng.uniform(-10.0, 10.0, 300)
    fw = forward(p, None, dist, off)
    models, inv, _ = auto.choose(p, None, fw.y1_mm, fw.y2_mm, 1e-4, 1e-4, tolerance_pct)
    err = np.abs(inv.distance_mm / dist - 1) * 100
    assert (err <= tolerance_pct * 1.02).all()
    if tolerance_pct >= 1.0:
        assert (models != "exact").sum() > 30  # closed forms used where good enough
