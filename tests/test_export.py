"""Exporters: float32 TIFF round trip, CSV columns, PNG preview, atomic writes."""

from __future__ import annotations

import csv

import cv2
import numpy as np
import tifffile

from lfcam.export import (
    REGION_COLUMNS,
    RegionResult,
    distance_map,
    write_distance_png,
    write_distance_tiff,
    write_regions_csv,
)


def _regions():
    return [
        RegionResult(0, 10.5, 20.25, "spot", "exact", 1500.0, 2.0, 0.4, 3.1, "ok", (5, 15, 17, 26)),
        RegionResult(1, 40.0, 40.0, "line", "line", float("nan"), float("nan"), 0.2, float("nan"),
                     "ill-conditioned", (35, 35, 46, 46)),
    ]


def test_distance_map_tiff_round_trip(tmp_path):
    regions = _regions()
    dmap = distance_map((64, 64), regions)
    assert np.isnan(dmap[0, 0]) and dmap[20, 10] == np.float32(1500.0)
    assert np.isnan(dmap[40, 40])  # not-ok region leaves NaN
    write_distance_tiff(tmp_path / "distance.tiff", dmap)
    back = tifffile.imread(tmp_path / "distance.tiff")
    assert back.dtype == np.float32 and back.shape == (64, 64)
    np.testing.assert_array_equal(np.isnan(back), np.isnan(dmap))
    assert [p.name for p in tmp_path.iterdir()] == ["distance.tiff"]  # no temp file left


def test_regions_csv_has_contract_columns(tmp_path):
    write_regions_csv(tmp_path / "regions.csv", _regions())
    rows = list(csv.DictReader((tmp_path / "regions.csv").open()))
    assert tuple(rows[0]) == REGION_COLUMNS
    assert float(rows[0]["distance_mm"]) == 1500.0 and rows[1]["distance_mm"] == ""
    assert rows[1]["status"] == "ill-conditioned"


def test_preview_png_has_colours_outline_and_bar(tmp_path):
    dmap = np.full((100, 120), np.nan, np.float32)
    dmap[10:40, 10:40] = 500.0
    dmap[60:90, 60:110] = 3000.0
    write_distance_png(tmp_path / "distance.png", dmap, _regions())
    img = cv2.imread(str(tmp_path / "distance.png"))
    assert img.shape[0] == 100 and img.shape[1] > 120 + 16  # map + colour bar + labels
    near, far = img[25, 25].astype(int), img[75, 80].astype(int)
    assert near[0] > near[2] and far[2] > far[0]  # turbo: near blue, far red
    assert tuple(img[0, 0]) == (40, 40, 40)  # NaN background
