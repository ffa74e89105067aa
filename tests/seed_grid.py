"""The seed paper's evaluation grid and error measure, shared by the tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
# Table 2 / 3 of the seed: actual distances Ad (mm) and offsets Δh (mm)
SEED_DISTANCES_MM = np.array(
    [3500, 3250, 3000, 2800, 2500, 2200, 2000, 1800, 1500, 1300, 1100, 900, 750, 600, 450, 300],
    dtype=np.float64,
)
SEED_OFFSETS_MM = (0.0, 5.0, 10.0)


def seed_error_pct(true_mm, estimated_mm, thickness_mm):
    """The seed's eq. 21: |Ad − Ed| / (Ad + T/2), in percent."""
    return np.abs(true_mm - estimated_mm) / (true_mm + 0.5 * thickness_mm) * 100.0
