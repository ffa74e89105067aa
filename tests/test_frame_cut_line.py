"""A line whose blur the frame's top edge cuts (stop 69): the line fit's distance scan starts
each segment where its model's light centroid on the region's lenslets is the data's
(``fastfit.LINE_SCAN_RECENTRE``).

The capture: scene (b)'s 1 131.5 mm line (``benchmarks/many_sources.py``, the Illum-like
profile), rendered on a 1 024 × 768 crop of its sensor that keeps the frame's top edge and the
optical axis where the full sensor has them (the line's light centroid 211 px from the edge,
its ~280 px blur cut by about a third). Truth: the renderer's distance. Without the recentred
scan the fit starts 16 % long and ends ``poor-fit`` (docs/distance.md, "A line the frame's
edge cuts (stop 69)").
"""

from __future__ import annotations

import pytest
from crops import illum_crop_capture

from lfcam.measure import fastfit
from lfcam.status import RegionStatus

DISTANCE_MM = 1131.4944225535191


@pytest.fixture(scope="module")
def cut_line():
    return illum_crop_capture(
        1024, 768, [511.5, 2683.5],
        [{"type": "line", "distance_mm": DISTANCE_MM,
          "start_mm": [-0.44753421223058815, 65.81645799890462],
          "end_mm": [0.44753421223058815, 69.71502857227283]}], seed=7,
        rays_per_source=1_000_000)


def test_the_frame_cuts_the_region(cut_line):
    prof, geom, image, region, _ = cut_line
    assert region.box_px[1] == 0  # (the top edge)
    assert fastfit._frame_cut(region, image.shape, geom.pitch_px)


def test_a_line_the_frame_cuts_is_measured(cut_line, monkeypatch):
    prof, geom, image, region, noise = cut_line
    monkeypatch.setattr(fastfit, "LINE_SCAN_RECENTRE", 0)
    before = fastfit.measure_lenslet(prof, geom, image, region, noise)
    assert before.status == RegionStatus.POOR_FIT
    monkeypatch.undo()
    got = fastfit.measure_lenslet(prof, geom, image, region, noise)
    assert got.kind == "line" and got.status == RegionStatus.OK
    # measured: +0.031 % (σ 0.10 %), misfit 0.040 against a noise misfit of 0.040
    err = got.distance_mm / DISTANCE_MM - 1
    assert abs(err) < min(3 * got.sigma_distance_mm / DISTANCE_MM, 2e-3), (err, got)
