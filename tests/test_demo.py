"""``lfcam demo``: the whole pipeline with no arguments; its regions hit the rendered truth."""

from __future__ import annotations

import csv
import json

import numpy as np

from lfcam.cli.main import main


def test_demo_end_to_end(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "-o", str(out)]) == 0
    for name in ("regions.csv", "distance.tiff", "distance.png", "calibration.json",
                 "capture.png", "capture.truth.json", "capture.profile.toml"):
        assert (out / name).is_file(), name
    rows = list(csv.DictReader((out / "regions.csv").open()))
    truth = json.loads((out / "capture.truth.json").read_text())["sources"]
    assert len(rows) == len(truth) == 6
    kinds = sorted(r["kind"] for r in rows)
    assert kinds == ["line"] + ["spot"] * 5
    for r in rows:
        assert r["status"] == "ok"
        src = min(truth, key=lambda s: np.hypot(s["centroid_px"][0] - float(r["x_px"]),
                                                s["centroid_px"][1] - float(r["y_px"])))
        err = abs(float(r["distance_mm"]) - src["distance_mm"])
        assert err <= 0.01 * src["distance_mm"], (r, src["distance_mm"])
    printed = capsys.readouterr().out
    assert "mean |error|" in printed and "seed closed form" in printed
