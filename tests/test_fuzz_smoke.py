"""A fast slice of the loader fuzz campaign (benchmarks/fuzz.py): 300 seeded cases, run as
the command a user reruns."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_fuzz_smoke():
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "fuzz.py"), "--seed", "20261123",
         "--cases", "300"], capture_output=True, text=True, timeout=600, cwd=ROOT)
    # exit 0 = every case raised only LfcamError subclasses, within time and memory
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "300 cases" in proc.stdout
    assert "finding(s):" not in proc.stdout
