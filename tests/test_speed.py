"""Issue 17 (speed) pieces, each against truth computed another way.

- The stencil lenslet map against a k-d tree nearest-centre search (hex lattice, overlapping
  discs, centres beyond the sensor edge, several row bands).
- Regions: halo fragments join their blur (one region per painted source), separate blurs
  stay apart.
- ``--method auto``: its error table holds the worst error of every committed benchmark CSV.
- ``lfcam distance --timings --json``: every stage's time, inside the command's own wall time.
"""

from __future__ import annotations

import csv
import json
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lfcam.measure import find_regions, lenslet_stats, lenslets
from lfcam.measure import regions as regions_module
from lfcam.measure.lenslets import build_lenslet_map
from lfcam.models.auto import METHOD_COST_ORDER, METHOD_MAX_ERROR_PCT, choose_method

DATA = Path(__file__).resolve().parents[1] / "data" / "synthetic"


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


def test_cli_reports_every_stage_time(tmp_path):
    """``--json`` carries load/geometry/regions/measure/export; ``--timings`` prints the same
    stages on stderr; together they fit inside the command's own wall time."""
    name = "point_system2_1100mm_dh5"
    t0 = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-m", "lfcam", "distance", str(DATA / f"{name}.png"), "--calibration",
         str(DATA / "calib_system2.json"), "--method", "lenslet", "--model", "exact",
         "--jobs", "1", "--json", "--timings", "-q", "-o", str(tmp_path / "o")],
        capture_output=True, text=True)
    wall = time.perf_counter() - t0
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    stages = ("load", "geometry", "regions", "measure", "export")
    t = doc["timings_s"]
    assert all(t[k] > 0 for k in stages)
    assert sum(t[k] for k in stages) < wall
    line = out.stderr.strip().splitlines()[-1]
    printed = dict(re.findall(r"(load|geometry|regions|fits|export) ([0-9.]+)", line))
    assert float(printed["fits"]) == pytest.approx(t["measure"], abs=0.006)
    assert float(printed["load"]) == pytest.approx(t["load"], abs=0.006)
    assert doc["regions"][0]["distance_mm"] == pytest.approx(1100.0, rel=0.003)


def _lenslet_image(lit: dict, n: int = 48, pitch: int = 10) -> tuple:
    """A rect lattice of ``n``² lenslets (``pitch`` px) with each (i, j) in ``lit`` painted at
    its energy over a faint noise floor."""
    g = 5.0 + pitch * np.arange(n)
    xx, yy = np.meshgrid(g, g)
    centres = np.column_stack([xx.ravel(), yy.ravel()])
    lmap = build_lenslet_map(centres, (n * pitch, n * pitch), 0.54 * pitch)
    img = np.random.default_rng(5).normal(0.0, 1e-4, (n * pitch, n * pitch))
    for (i, j), v in lit.items():
        img[j * pitch + 3 : j * pitch + 7, i * pitch + 3 : i * pitch + 7] += v / 16.0
    return lenslet_stats(img, lmap), lmap


def _disc(ci: int, cj: int, r: float, v: float) -> dict:
    return {(i, j): v for i in range(ci - 8, ci + 9) for j in range(cj - 8, cj + 9)
            if (i - ci) ** 2 + (j - cj) ** 2 <= r * r}


def test_halo_fragments_join_their_blur_and_separate_blurs_stay_apart():
    blur = _disc(14, 14, 5.0, 1.0)  # 81 lenslets
    # three fragments 6–8 lenslets from its centre, ≥ 2 pitches from its edge
    halo = {(21, 14): 0.2, (21, 15): 0.2, (21, 13): 0.2, (14, 7): 0.2, (15, 7): 0.2,
            (9, 9): 0.2, (8, 9): 0.2}
    other = _disc(36, 36, 3.0, 1.0)  # a second source, well apart: its own region
    twin_a, twin_b = _disc(36, 12, 2.0, 1.0), _disc(36, 19, 2.0, 0.15)  # 2-lenslet gap
    stats, lmap = _lenslet_image({**blur, **halo, **other, **twin_a, **twin_b})
    regions = find_regions(stats, lmap, 10.0)
    sizes = sorted((len(r.lenslets), r.parts) for r in regions)
    # the blur with its 7 halo lenslets in 3 fragments; the other source; the two small
    # neighbours (13 lenslets each, one 7× dimmer) are not fragments of each other
    assert sizes == [(13, 1), (13, 1), (29, 1), (len(blur) + len(halo), 4)]


def _measured_worst_pct() -> dict:
    """Worst ERROR % per (kind, method) in the committed benchmark CSVs (calibrated path,
    model ``exact``)."""
    res = Path(__file__).resolve().parents[1] / "docs" / "results"
    worst: dict = {}

    def note(kind, method, value):
        worst[(kind, method)] = max(worst.get((kind, method), 0.0), value)

    with open(res / "tradeoff.csv", newline="", encoding="utf-8") as fh:
        for row in csv.DictReader(fh):
            if row["model"] == "exact" and row["method"] in METHOD_COST_ORDER:
                note("spot" if row["source"] == "point" else "line", row["method"],
                     float(row["max_error_pct"]))
    for name, method in (("focus_grid.csv", "lightfield"), ("focus_grid_lenslet.csv", "lenslet")):
        with open(res / name, newline="", encoding="utf-8") as fh:
            for row in csv.DictReader(fh):
                if row["centres"] == "calibrated" and row["status"] == "ok":
                    note("line" if row["mode"].startswith("line") else "spot", method,
                         float(row["error_pct"]))
    return worst


def test_auto_method_table_never_understates_a_measured_worst_error():
    """``--method auto --tolerance`` trusts METHOD_MAX_ERROR_PCT: it must hold the worst
    error any benchmark measured, or auto would pick a method that misses the tolerance."""
    worst = _measured_worst_pct()
    assert len(worst) == 6  # every kind × method has a measurement
    for (kind, method), value in worst.items():
        assert METHOD_MAX_ERROR_PCT[kind][method] >= value - 1e-3, (kind, method, value)
    # and the choice is the cheapest whose table entry meets the tolerance
    for tol in (0.5, 1.0, 2.0, 3.0, 9.0, 50.0):
        want = next((m for m in METHOD_COST_ORDER if worst[("spot", m)] <= tol), None)
        if want is not None and METHOD_MAX_ERROR_PCT["spot"][want] <= tol:
            assert choose_method(tol, "spot") == want


def test_touching_blurs_are_cut_at_their_waist_and_a_line_blur_is_not(monkeypatch):
    """Two discs that touch (two sources whose blurs touch) have a waist: each disc is a region
    of its own, and the lenslet both light is in neither, left out of both fits' data
    (``Region.shared``); the stadium a line source makes has no waist. Without the cut
    (``SPLIT_TOUCHING`` off) the pair is one ``multiple`` region, which no method measures."""
    disc_a, disc_b = _disc(10, 12, 6.0, 1.0), _disc(22, 12, 6.0, 1.0)  # (16, 12) in both
    stadium = {(i, j): 1.0 for i in range(8, 40) for j in range(28, 45)
               if (j - 36) ** 2 + max(0, 14 - i, i - 33) ** 2 <= 16}
    stats, lmap = _lenslet_image({**disc_a, **disc_b, **stadium})
    regions = find_regions(stats, lmap, 10.0)

    def cells(ids):  # lattice (i, j) of lenslet indices (_lenslet_image's row-major order)
        return {(int(k) % 48, int(k) // 48) for k in ids}

    assert sorted(r.kind for r in regions) == ["line", "spot", "spot"]
    line = next(r for r in regions if r.kind == "line")
    assert cells(line.lenslets) == set(stadium) and not line.touching
    a, b = sorted((r for r in regions if r.kind == "spot"), key=lambda r: r.centroid_px[0])
    both = set(disc_a) & set(disc_b)
    assert a.touching and b.touching and cells(a.shared) == cells(b.shared) == both
    assert cells(a.lenslets) == set(disc_a) - both
    assert cells(b.lenslets) == set(disc_b) - both
    monkeypatch.setattr(regions_module, "SPLIT_TOUCHING", False)
    kinds = sorted((r.kind, len(r.lenslets)) for r in find_regions(stats, lmap, 10.0))
    assert kinds == [("line", len(stadium)), ("multiple", len({**disc_a, **disc_b}))]
