"""Exporters: float32 TIFF round trip, CSV columns, PNG preview, atomic writes."""

from __future__ import annotations

import csv
from types import SimpleNamespace

import cv2
import numpy as np
import tifffile

from lfcam.export import (
    REGION_COLUMNS,
    RegionResult,
    paint_region,
    write_csv,
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


def test_paint_region_fills_its_lenslets_and_the_gaps_between_them():
    # two 4-px micro-images of lenslets 0 and 1 with a 2-px gap, a third lenslet 2 not painted
    labels = np.full((20, 30), -1, np.int64)
    labels[5:9, 5:9], labels[5:9, 11:15], labels[5:9, 20:24] = 0, 1, 2
    region = SimpleNamespace(box_px=(0, 0, 30, 20), lenslets=np.array([0, 1]))
    dmap = np.full((20, 30), np.nan, np.float32)
    paint_region(dmap, region, SimpleNamespace(labels=labels), 5.0, 1500.0)
    assert dmap[6, 6] == np.float32(1500.0) and dmap[6, 13] == np.float32(1500.0)
    assert dmap[6, 10] == np.float32(1500.0)  # the gap between the two is closed
    assert np.isnan(dmap[6, 21]) and np.isnan(dmap[15, 6])  # other lenslets, background


def test_distance_map_tiff_round_trip(tmp_path):
    dmap = np.full((64, 64), np.nan, np.float32)
    dmap[15:26, 5:17] = 1500.0
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
    write_distance_png(tmp_path / "distance.png", dmap, _regions(), title="cap.png  exact")
    img = cv2.imread(str(tmp_path / "distance.png"))
    top, left = 24, 44  # title band and y-axis labels
    assert img.shape[0] == 100 + top + 22 and img.shape[1] > left + 120 + 16
    near, far = img[top + 25, left + 25].astype(int), img[top + 75, left + 80].astype(int)
    assert near[0] > near[2] and far[2] > far[0]  # turbo: near blue, far red
    assert tuple(img[top + 95, left + 5]) == (40, 40, 40)  # NaN background
    assert (img[:top] < 128).any()  # the title is drawn


def test_nice_ticks():
    from lfcam.export import nice_ticks

    assert nice_ticks(500, 3000) == [500, 1000, 1500, 2000, 2500, 3000]
    assert nice_ticks(0, 1023, 4) == [0, 500, 1000]
    assert nice_ticks(1423.7, 1576.3) == [1450, 1500, 1550]


def test_csv_cells_with_commas_and_quotes_round_trip(tmp_path):
    rows = [("a,b", 'say "x"', 1.5, float("nan")), ("plain", "failed: ValueError", 2.0, 3.0)]
    write_csv(tmp_path / "t.csv", ("c1", "c2", "c3", "c4"), rows)
    back = list(csv.reader((tmp_path / "t.csv").open(newline="")))
    assert back[1] == ["a,b", 'say "x"', "1.5", ""]
    assert back[2] == ["plain", "failed: ValueError", "2.0", "3.0"]
