"""A fast slice of the loader fuzz campaign (benchmarks/fuzz.py): 300 seeded cases."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _fuzz():
    spec = importlib.util.spec_from_file_location("lfcam_fuzz", ROOT / "benchmarks" / "fuzz.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def test_fuzz_smoke():
    fuzz = _fuzz()
    stats, findings = fuzz.campaign(seed=20261123, cases=300, verbose=False)
    assert sum(s.cases for s in stats.values()) == 300
    assert all(s.cases > 0 for s in stats.values())
    # only LfcamError subclasses, within time and memory
    assert findings == [], [(f["case"], f["why"], f["where"]) for f in findings]
    assert max(s.max_s for s in stats.values()) < fuzz.MAX_SECONDS
