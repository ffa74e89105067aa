"""Stability report (benchmarks/stability.py): the facts docs/stability.md states."""

from __future__ import annotations

import csv
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lfcam import load_profile
from lfcam.models import POINT_MODELS, line
from lfcam.models.base import Status
from lfcam.optics.trace import forward

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    """The report as a user makes it: ``python benchmarks/stability.py`` (its CSV and curves)."""
    out = tmp_path_factory.mktemp("stability")
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "stability.py"), "--out",
                    str(out), "--no-figures", "--curves", str(out / "curves.pkl")],
                   check=True, capture_output=True, timeout=900, cwd=ROOT)
    with (out / "stability.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    plots = pickle.loads((out / "curves.pkl").read_bytes())
    return {(r["case"], r["system"], r["model"], r["note"]): r for r in rows}, plots


def test_far_field_and_infinity():
    """tan φ → 0: exact stays exact out to 1e6 mm and says no-solution at ∞ (parallel rays)."""
    prof = load_profile("system1")
    dist = np.array([1e4, 1e5, 1e6, np.inf])
    fw = forward(prof, None, dist, 0.0)
    inv = POINT_MODELS["exact"](prof, None, fw.y1_mm, fw.y2_mm)
    assert list(inv.status) == [Status.OK] * 3 + [Status.NO_SOLUTION]
    np.testing.assert_allclose(inv.distance_mm[:3], dist[:3], rtol=1e-7)
    assert np.isnan(inv.distance_mm[3])


def test_float32_heights_within_rounding_bound(report):
    """float32 rounding of the heights moves the answer by no more than half an ulp times the
    propagated sensitivity (× √2 for two inputs)."""
    _, plots = report
    for out in plots["float32"].values():
        for _name, (_dist, rel, pred) in out.items():
            ok = np.isfinite(rel) & np.isfinite(pred)
            assert ok.sum() > 20
            assert np.all(rel[ok] <= np.sqrt(2) * pred[ok] * 1.05 + 1e-12)


def test_noise_propagation_matches_monte_carlo(report):
    """First-order propagation agrees with 2000-draw Monte Carlo (sampling error ~2 %)."""
    _, plots = report
    for series in plots["noise"].values():
        for _name, _sigma, _dist, mc, pred in series:
            np.testing.assert_allclose(mc, pred, rtol=0.08)


def test_short_lines_flagged_where_eq20_cancels(report):
    """Lines whose eq. 20 amplification exceeds the threshold are ill-conditioned, others ok;
    the amplification grows as 1/length (halving the line doubles it)."""
    _, plots = report
    length, amp, _err, _spread, status = plots["shortline"]
    big = amp > line.DEFAULT_MAX_AMPLIFICATION
    assert big.any() and (~big).any()
    assert np.all(status[big] == Status.ILL_CONDITIONED)
    assert np.all(status[~big] == Status.OK)
    slope = np.polyfit(np.log(length), np.log(amp), 1)[0]
    assert slope == pytest.approx(-1.0, abs=0.02)


def test_sign_of_focus_matters():
    """Swapping the rim heights (the diameter method's side-of-focus ambiguity) turns a near
    source into a far one: the sign carries the information, the diameter alone does not."""
    prof = load_profile("system1")
    fw = forward(prof, None, 325.0, 5.0)
    right = POINT_MODELS["exact"](prof, None, fw.y1_mm, fw.y2_mm)
    wrong = POINT_MODELS["exact"](prof, None, fw.y2_mm, fw.y1_mm)
    assert right.distance_mm == pytest.approx(325.0, rel=1e-9)
    assert wrong.status == Status.OK and wrong.distance_mm > 10_000.0
