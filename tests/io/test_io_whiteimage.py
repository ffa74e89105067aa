"""White-image lookup in a caldata folder built from the real Illum MOD metadata."""

import json

import pytest

from lfcam.errors import WhiteImageNotFoundError
from lfcam.io import find_white_image, white_image_for


def _caldata(tmp_path, realdata, entries):
    doc = json.loads((realdata / "illum-whiteimage-metadata.TXT").read_text())
    fr = doc["master"]["picture"]["frameArray"][0]["frame"]
    root = tmp_path / "caldata-B5143909630" / "C"
    root.mkdir(parents=True)
    for i, (serial, zoom, focus) in enumerate(entries):
        fr["privateMetadata"]["camera"]["serialNumber"] = serial
        fr["metadata"]["devices"]["lens"]["zoomStep"] = zoom
        fr["metadata"]["devices"]["lens"]["focusStep"] = focus
        (root / f"MOD_{i:04d}.TXT").write_text(json.dumps(doc))
        (root / f"MOD_{i:04d}.RAW").write_bytes(b"")
    return tmp_path


def test_serial_then_zoom_then_focus(tmp_path, realdata):
    folder = _caldata(tmp_path, realdata, [
        ("B5143909630", -1040, -300),   # 0: the real file's values
        ("B5143909630", -1040, 500),    # 1
        ("B5143909630", -600, 120),     # 2
        ("OTHER", 123, 814),            # 3: exact match but another camera
    ])
    pick = find_white_image(folder, "B5143909630", 123, 814)
    # zoom: |-600-123| = 723 beats |-1040-123| = 1163, even though focus 120 is far
    assert pick.raw_path.name == "MOD_0002.RAW"
    pick = find_white_image(folder, "B5143909630", -1000, 300)
    assert pick.raw_path.name == "MOD_0001.RAW"  # zoom -1040 tie, focus 500 nearest 300
    pick = find_white_image(folder, "B5143909630", -1040, -310)
    assert pick.raw_path.name == "MOD_0000.RAW" and pick.zoom_step == -1040
    meta = {"frame": {"devices": {"lens": {"zoomStep": 123, "focusStep": 814}}},
            "privateMetadata": {"camera": {"serialNumber": "OTHER"}}}
    assert white_image_for(meta, folder).raw_path.name == "MOD_0003.RAW"


def test_errors(tmp_path, realdata):
    folder = _caldata(tmp_path, realdata, [("A1", 0, 0), ("B2", 0, 0)])
    with pytest.raises(WhiteImageNotFoundError, match="no white image of camera C3.*A1, B2"):
        find_white_image(folder, "C3", 0, 0)
    with pytest.raises(WhiteImageNotFoundError, match="2 cameras"):
        find_white_image(folder, None, 0, 0)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(WhiteImageNotFoundError, match="no white images"):
        find_white_image(empty, "A1", 0, 0)
