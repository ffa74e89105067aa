"""``lfcam demo`` runs with no arguments and its exact-model rows hit the truth."""

from __future__ import annotations

import csv

from lfcam.cli.main import main


def test_demo_writes_regions_and_exact_rows_are_exact(tmp_path, capsys):
    assert main(["demo", "-o", str(tmp_path / "demo")]) == 0
    rows = list(csv.DictReader((tmp_path / "demo" / "regions.csv").open()))
    exact = [r for r in rows if r["model"] == "exact"]
    assert len(exact) == 5
    for r in exact:
        true = float(r["true_distance_mm"])
        assert abs(float(r["distance_mm"]) - true) <= 1e-9 * true
    seed = [r for r in rows if r["model"] == "offaxis"]
    errs = [abs(float(r["distance_mm"]) / float(r["true_distance_mm"]) - 1) for r in seed]
    assert 1e-3 < max(errs) < 0.06  # eq. 14's approximation error, system 2 (seed: up to ~4 %)
    assert "regions.csv" in capsys.readouterr().out
