"""``lfcam optics`` end to end, in a subprocess like a user (exit codes, one-line errors)."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import pytest

from lfcam import load_profile
from lfcam.optics.trace import forward


def run(*args):
    return subprocess.run([sys.executable, "-m", "lfcam", *args], capture_output=True, text=True)


def test_forward_json_matches_library():
    out = run("optics", "forward", "--profile", "system2", "--focus", "inf", "--distance", "300",
              "--json")
    assert out.returncode == 0, out.stderr
    data = json.loads(out.stdout)
    assert data["diameter_mm"] == pytest.approx(10.7, rel=0.01)  # docs/distance.md
    assert data["y1_mm"] == pytest.approx(-data["y2_mm"], abs=1e-12)


def test_inverse_round_trip_via_cli():
    p = load_profile("system1")
    fw = forward(p, None, 1234.5, 6.0)
    out = run("optics", "inverse", "--profile", "system1", "--model", "exact",
              "--y1", repr(float(fw.y1_mm)), "--y2", repr(float(fw.y2_mm)), "--json")
    data = json.loads(out.stdout)
    assert data["status"] == "ok"
    assert data["distance_mm"] == pytest.approx(1234.5, rel=1e-9)
    assert data["offset_mm"] == pytest.approx(6.0, abs=1e-6)


def test_batch_forward_then_inverse(tmp_path):
    cases = tmp_path / "cases.csv"
    cases.write_text("distance_mm,offset_mm\n300,0\n1500,5\n3500,10\n", encoding="utf-8")
    heights = tmp_path / "heights.csv"
    assert run("optics", "forward", "--profile", "system1", "--input", str(cases),
               "--output", str(heights)).returncode == 0
    back = tmp_path / "back.csv"
    res = run("optics", "inverse", "--profile", "system1", "--model", "exact", "--input",
              str(heights), "--output", str(back))
    assert res.returncode == 0, res.stderr
    rows = list(csv.DictReader(back.open()))
    assert [r["status"] for r in rows] == ["ok"] * 3
    for r, d in zip(rows, (300, 1500, 3500), strict=True):
        assert float(r["distance_mm"]) == pytest.approx(d, rel=1e-9)


def test_refocus_distance_reference_figure():
    out = run("optics", "refocus-distance", "--pp", "0.009", "--fs", "2.75", "--pm", "0.125",
              "--dA", "111.0324", "--fU", "193.2935", "--HH", "-65.5563", "--df", "inf",
              "--a", "1", "--M", "13.9523", "--json")
    data = json.loads(out.stdout)
    assert data["distance_mm"] == pytest.approx(962.7459, abs=1e-4)
    assert data["dof_far_mm"] == pytest.approx(1098.2788, abs=1e-4)


@pytest.mark.parametrize(
    "args",
    [
        ("optics", "forward", "--profile", "nosuch", "--distance", "300"),
        ("optics", "forward", "--profile", "system1"),
        ("optics", "inverse", "--profile", "system1", "--model", "exact", "--input", "/nope.csv",
         "--output", "/tmp/x.csv"),
        ("optics", "forward", "--profile", "system1", "--focus", "10", "--distance", "300"),
    ],
)
def test_bad_input_is_one_line_and_exit_1(args):
    out = run(*args)
    assert out.returncode == 1
    assert out.stderr.count("\n") == 1 and "Traceback" not in out.stderr


def test_bad_csv_cell_names_row_and_column(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("y1_mm,y2_mm\n1.0,2.0\n1.0,abc\n", encoding="utf-8")
    out = run("optics", "inverse", "--profile", "system1", "--model", "offaxis", "--input",
              str(bad), "--output", str(tmp_path / "o.csv"))
    assert out.returncode == 1 and "row 3" in out.stderr and "y2_mm" in out.stderr
    assert not (tmp_path / "o.csv").exists()


def test_usage_error_exit_2():
    assert run("optics", "inverse", "--profile", "system1", "--model", "bogus").returncode == 2
