"""``lfcam info``: exit 0 on well-formed files (processed ones included), 1 + one line else."""

import json

import numpy as np
import pytest
from io_testlib import small_frame_meta

from lfcam.cli.main import main
from lfcam.io import write_lfp


def test_info_synthetic_json(tmp_path, capsys):
    f = write_lfp(tmp_path / "a.lfp", np.zeros((4, 8), np.uint16), small_frame_meta(8, 4))
    assert main(["info", str(f), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["raw_frame"] is True and d["raw"]["width_px"] == 8 and d["raw"]["bayer"] == "BGGR"
    assert [s["kind"] for s in d["sections"]] == ["LFM", "LFM", "LFM", "LFC"]
    assert d["optics"]["lens"]["focal_length_mm"] == pytest.approx(6.4)
    assert d["camera"]["model"] == "F01"


@pytest.mark.parametrize("name", ["IMG_0001-stk.lfp", "IMG_0002-stk.lfp", "IMG_0002-dm.lfp",
                                  "illum-demo.LFP"])
def test_info_real_processed(realdata, capsys, name):
    assert main(["info", str(realdata / name), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["raw_frame"] is False and "no raw sensor frame" in d["note"]


def test_info_text_illum(realdata, capsys):
    assert main(["info", str(realdata / "illum-demo.LFP")]) == 0
    out = capsys.readouterr().out
    assert "ILLUM" in out and "zoom step 123" in out and "focus step 814" in out


@pytest.mark.parametrize("payload", [b"\x89LFP\r\n\x1a\n\0\0", b"garbage", b""])
def test_info_bad_file_one_line_exit_1(tmp_path, capsys, payload):
    p = tmp_path / "bad.lfp"
    p.write_bytes(payload)
    assert main(["info", str(p)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("lfcam info: error:") and "bad.lfp" in err


def test_info_missing_file(tmp_path, capsys):
    assert main(["info", str(tmp_path / "nope.lfp")]) == 1
    assert capsys.readouterr().err.count("\n") == 1
