"""docs/guide.md's shipped-data workflow, run verbatim in a temporary folder (issue 18)."""

from __future__ import annotations

import csv
import json
import os
import re
import stat
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def guide_workflow() -> str:
    """The bash block of the guide's "Workflow on the shipped data" section."""
    text = (REPO / "docs" / "guide.md").read_text(encoding="utf-8")
    section = text.split("## Workflow on the shipped data", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```bash\n(.*?)```", section, flags=re.S)
    assert len(blocks) == 1
    return blocks[0]


def test_guide_workflow_runs_verbatim(tmp_path):
    script = guide_workflow()
    assert "lfcam calibrate" in script and "lfcam distance" in script
    (tmp_path / "data").symlink_to(REPO / "data")
    bindir = tmp_path / "bin"
    bindir.mkdir()
    shim = bindir / "lfcam"
    shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m lfcam "$@"\n')
    shim.chmod(shim.stat().st_mode | stat.S_IXUSR)
    env = dict(os.environ, PATH=f"{bindir}{os.pathsep}{os.environ['PATH']}",
               PYTHONPATH=str(REPO))
    proc = subprocess.run(["bash", "-e", "-c", script], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    truth = json.loads((REPO / "data/synthetic/point_system1_1500mm_dh5.truth.json")
                       .read_text())["sources"][0]["distance_mm"]
    with open(tmp_path / "o" / "regions.csv", newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["status"] == "ok"]
    assert len(rows) == 1
    assert abs(float(rows[0]["distance_mm"]) - truth) / truth < 0.01
    assert json.loads((tmp_path / "c.json").read_text())["quality"]["verdict"] == "ok"
