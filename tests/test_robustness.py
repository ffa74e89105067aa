"""Bad input, handled: every case of docs/robustness.md, with its error class, and inputs
left byte-identical."""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import shutil
import struct
import zlib
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import tifffile

from lfcam.atomic import check_output_dir, refuse_overwrite
from lfcam.cli.main import build_parser, main
from lfcam.errors import (
    CalibrationError,
    ChecksumError,
    LfcamError,
    OutputPathError,
    ProfileError,
    RawDataError,
    ResourceLimitError,
    SaturatedCaptureError,
    SceneError,
)
from lfcam.io import limits

ROOT = Path(__file__).resolve().parents[1]
SYN = ROOT / "data" / "synthetic"
CAPTURE = "point_system1_1100mm_dh0"


def digest(*paths: Path) -> list[str]:
    return [hashlib.sha256(Path(p).read_bytes()).hexdigest() for p in paths]


def run(argv: list[str]):
    """Parse and run one command, letting its LfcamError propagate (main() prints it)."""
    args = build_parser().parse_args(argv)
    return args.func(args)


def one_line_error(capsys, argv: list[str], needle: str) -> str:
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and needle in err, err
    return err


@pytest.fixture()
def work(tmp_path, monkeypatch):
    """A capture, its profile sidecar, the system-1 calibration, a CSV; cwd = tmp_path."""
    shutil.copy(SYN / f"{CAPTURE}.png", tmp_path / "cap.png")
    shutil.copy(SYN / f"{CAPTURE}.profile.toml", tmp_path / "cap.profile.toml")
    shutil.copy(SYN / "calib_system1.json", tmp_path / "calib.json")
    (tmp_path / "c.csv").write_text("y1_mm,y2_mm\n0.1,-0.1\n")
    monkeypatch.chdir(tmp_path)
    return tmp_path


CAL = ["--calibration", "calib.json", "--profile", "cap.profile.toml"]


# ----------------------------------------------------------------------------- 1 overwrite


def test_refuse_overwrite_paths(tmp_path):
    a = tmp_path / "a.png"
    a.write_bytes(b"x")
    os.link(a, tmp_path / "hard.png")
    (tmp_path / "sym.png").symlink_to(a)
    (tmp_path / "sub").mkdir()
    for out in (a, tmp_path / "hard.png", tmp_path / "sym.png", tmp_path / "sub" / ".." / "a.png",
                os.path.relpath(a)):
        with pytest.raises(OutputPathError, match="would overwrite input"):
            refuse_overwrite([None, a], [out])
    refuse_overwrite([a, None], [tmp_path / "new.png", None])  # different file: fine


@pytest.mark.parametrize("out", ["cap.png", "hard.png", "sym.png"])
def test_refocus_never_replaces_the_capture(work, capsys, out):
    if out == "hard.png":
        os.link("cap.png", "hard.png")
    elif out == "sym.png":
        Path("sym.png").symlink_to(work / "cap.png")
    before = digest("cap.png")
    with pytest.raises(OutputPathError, match=f"output {out} would overwrite input cap.png"):
        run(["refocus", "cap.png", *CAL, "--shift", "0", "-o", out])
    one_line_error(capsys, ["refocus", "cap.png", *CAL, "--shift", "0", "-o", out],
                   "would overwrite")
    assert digest("cap.png") == before


def test_optics_inverse_input_is_not_output(work):
    before = digest("c.csv")
    with pytest.raises(OutputPathError, match="c.csv"):
        run(["optics", "inverse", "--profile", "system1", "--model", "exact",
             "--input", "c.csv", "--output", "c.csv"])
    assert digest("c.csv") == before


def test_simulate_keeps_scene_and_profile(work):
    scene = {"rays_per_source": 2000, "objects": [{"type": "point", "distance_mm": 1000.0}]}
    Path("x.truth.json").write_text(json.dumps(scene))
    prof = "# my notes\n" + (ROOT / "calibration" / "system1.toml").read_text()
    Path("y.profile.toml").write_text(prof)
    Path("scene.json").write_text(json.dumps(scene))
    before = digest("x.truth.json", "y.profile.toml")
    with pytest.raises(OutputPathError, match="x.truth.json would overwrite input"):
        run(["simulate", "--profile", "system1", "--scene", "x.truth.json", "-o", "x.png"])
    with pytest.raises(OutputPathError, match="y.profile.toml would overwrite input"):
        run(["simulate", "--profile", "y.profile.toml", "--scene", "scene.json", "-o", "y.png"])
    assert digest("x.truth.json", "y.profile.toml") == before
    assert not Path("x.png").exists() and not Path("y.png").exists()


def test_distance_decode_calibrate_batch_outputs(work):
    # an input that sits where an output file goes
    Path("out").mkdir()
    shutil.copy("cap.png", "out/distance.png")
    shutil.copy("calib.json", "out/lightfield.json")
    shutil.copy("calib.json", "out/summary.csv")
    shutil.copy("cap.png", "w.json")  # a PNG whatever its name: calibrate reads by content
    files = ["out/distance.png", "out/lightfield.json", "out/summary.csv", "w.json"]
    before = digest(*files)
    with pytest.raises(OutputPathError, match="distance.png"):
        run(["distance", "out/distance.png", *CAL, "-o", "out"])
    with pytest.raises(OutputPathError, match="lightfield.json"):
        run(["decode", "cap.png", "--calibration", "out/lightfield.json", "-o", "out"])
    with pytest.raises(OutputPathError, match="w.json"):
        run(["calibrate", "w.json", "-o", "w.json"])
    with pytest.raises(OutputPathError, match="summary.csv"):
        run(["batch", ".", "--calibration", "out/summary.csv", "-o", "out"])
    assert digest(*files) == before


def test_unwritable_output_folder_fails_before_work(work, monkeypatch):
    import lfcam.distance

    def boom(*a, **k):  # pragma: no cover - must not be reached
        raise AssertionError("computed before checking the output folder")

    monkeypatch.setattr(lfcam.distance, "run_distance", boom)
    Path("file").write_text("x")
    with pytest.raises(OutputPathError, match="not a directory"):
        run(["distance", "cap.png", *CAL, "-o", "file/out"])
    with pytest.raises(OutputPathError, match="not writable"):
        run(["distance", "cap.png", *CAL, "-o", "/proc/lfcam-out"])
    with pytest.raises(OutputPathError):
        run(["refocus", "cap.png", *CAL, "--shift", "0", "-o", "file/r.png"])


def test_check_output_dir_leaves_nothing(tmp_path):
    check_output_dir(tmp_path / "a" / "b")
    assert not (tmp_path / "a").exists()
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- 2 resources


def _png(path: Path, width: int, height: int, depth: int = 8, payload: bytes = b"\0" * 64):
    def chunk(kind, body):
        return struct.pack(">I", len(body)) + kind + body + struct.pack(
            ">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", width, height, depth, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
                     + chunk(b"IDAT", zlib.compress(payload)) + chunk(b"IEND", b""))
    return path


def _loaders():
    from lfcam.io import load_capture
    from lfcam.io.info import describe_file

    return [load_capture, describe_file]


def test_png_header_over_pixel_limit(tmp_path, capsys):
    p = _png(tmp_path / "huge.png", 60000, 60000)
    before = digest(p)
    for load in _loaders():
        with pytest.raises(ResourceLimitError, match="huge.png.*60000x60000.*250 Mpx"):
            load(p)
    one_line_error(capsys, ["info", str(p)], "over lfcam's limit")
    assert digest(p) == before


def test_png_forged_size_and_bytes_limit(tmp_path, monkeypatch):
    # 20000 x 10000 8-bit = 200 Mpx (under the pixel limit) in a file of ~100 bytes
    p = _png(tmp_path / "forged.png", 20000, 10000)
    for load in _loaders():
        with pytest.raises(RawDataError, match="more than deflate can compress"):
            load(p)
    q = _png(tmp_path / "ok.png", 64, 48, 16, b"\0" * (48 * 129))
    monkeypatch.setattr(limits, "MAX_DECODED_BYTES", 1000)
    with pytest.raises(ResourceLimitError, match="MiB"):
        _loaders()[0](q)


def test_tiff_limits_from_tags(tmp_path, monkeypatch):
    p = tmp_path / "t.tiff"
    tifffile.imwrite(p, np.zeros((48, 64), np.uint16))
    monkeypatch.setattr(limits, "MAX_PIXELS", 1000)
    for load in _loaders():
        with pytest.raises(ResourceLimitError, match="t.tiff"):
            load(p)
    monkeypatch.setattr(limits, "MAX_PIXELS", 10**9)
    assert limits.check_raster(p).pixels == 48 * 64


# ----------------------------------------------------------------------------- 3 JSON depth


def test_json_depth_and_nan(tmp_path):
    import lfcam.calibrate
    from lfcam.sim.scene import load_scene

    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(CalibrationError, match="nested 100000 levels deep"):
        lfcam.calibrate.load_calibration(deep)
    with pytest.raises(SceneError, match="nested"):
        load_scene(deep)
    nan = tmp_path / "nan.json"
    nan.write_text('{"objects": [{"type": "point", "distance_mm": NaN}]}')
    with pytest.raises(SceneError, match="NaN is not a JSON number"):
        load_scene(nan)
    brackets_in_strings = tmp_path / "s.json"
    brackets_in_strings.write_text(json.dumps({"objects": [], "comment": "[" * 1000}))
    assert load_scene(brackets_in_strings).objects == ()


# ----------------------------------------------------------------------------- 4 simulate


def test_ray_budget(work, capsys):
    from lfcam.camera import load_profile
    from lfcam.sim.capture import simulate
    from lfcam.sim.scene import check_ray_budget, ray_count, scene_from_dict

    many = {"objects": [{"type": "point", "distance_mm": 1000.0, "rays": 500_000_000}] * 2000}
    scene = scene_from_dict(many)
    assert ray_count(scene, 1) >= 2000 * 500_000_000
    with pytest.raises(SceneError, match="over the budget"):
        check_ray_budget(scene, 1)
    with pytest.raises(SceneError, match="--max-rays"):
        simulate(load_profile("system1"), scene)
    Path("many.json").write_text(json.dumps(many))
    one_line_error(capsys, ["simulate", "--profile", "system1", "--scene", "many.json",
                            "-o", "m.png"], "over the budget")
    small = {"rays_per_source": 4000, "objects": [{"type": "point", "distance_mm": 900.0}]}
    Path("small.json").write_text(json.dumps(small))
    with pytest.raises(SceneError, match="budget of 100"):
        run(["simulate", "--profile", "system1", "--scene", "small.json", "-o", "s.png",
             "--max-rays", "100"])
    assert main(["simulate", "--profile", "system1", "--scene", "small.json", "-o",
                 "s.png"]) == 0


@pytest.mark.parametrize("obj", [
    {"type": "point", "distance_mm": -5.0},
    {"type": "point", "distance_mm": 1e3, "intensity": -1},
    {"type": "point", "distance_mm": 1e3, "rays": 0},
    {"type": "line", "distance_mm": 1e3, "start_mm": [0, 0], "end_mm": [0, 1e400]},
])
def test_scene_numbers(obj):
    from lfcam.sim.scene import scene_from_dict

    with pytest.raises(SceneError):
        scene_from_dict({"objects": [obj]})


# ----------------------------------------------------------------------------- 5 CLI


def test_negative_numbers_are_values(capsys):
    for y1 in ("-1e-12", "-.5e-3", "-0.001", "-1E-3"):
        assert main(["optics", "inverse", "--profile", "system1", "--model", "exact",
                     "--y1", y1, "--y2", "0.01", "--json"]) == 0
        assert "distance_mm" in capsys.readouterr().out
    args = build_parser().parse_args(["optics", "refocus-distance", "--profile", "system1",
                                      "--a", "-2.5e-1"])
    assert args.a == -0.25


@pytest.mark.parametrize("argv", [
    ["distance", "c.png", "--calibration", "x", "-o", "o", "--tolerance", "nan"],
    ["distance", "c.png", "--calibration", "x", "-o", "o", "--tolerance", "-5"],
    ["distance", "c.png", "--calibration", "x", "-o", "o", "--tolerance", "inf"],
    ["refocus", "c.png", "--calibration", "x", "-o", "o.png", "--distance", "9", "--d-in=-5"],
    ["refocus", "c.png", "--calibration", "x", "-o", "o.png", "--distance", "nan"],
    ["decode", "c.png", "--calibration", "x", "-o", "o", "--views", "0"],
    ["optics", "forward", "--profile", "system1", "--distance", "-100"],
    ["optics", "forward", "--profile", "system1", "--distance", "1e3", "--focus", "nan"],
    ["optics", "inverse", "--profile", "system1", "--model", "exact", "--y1", "nan"],
    ["calibrate", "w.png", "-o", "c.json", "--reference", "r.png",
     "--reference-distance", "-1"],
    ["simulate", "--profile", "system1", "--scene", "s", "-o", "x.png", "--seed", "-1"],
    ["batch", "in", "--calibration", "c", "-o", "o", "--tolerance", "0"],
])
def test_bad_numbers_are_usage_errors(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(argv)
    assert exc.value.code == 2
    assert "error: argument" in capsys.readouterr().err


def test_focus_inf_still_allowed():
    args = build_parser().parse_args(["optics", "forward", "--profile", "system1",
                                      "--distance", "1e3", "--focus", "inf"])
    assert args.focus == float("inf")


def _all_parsers():
    out = []

    def walk(p, name):
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for n, sp in a.choices.items():
                    out.append((f"{name} {n}", sp))
                    walk(sp, f"{name} {n}")

    walk(build_parser(), "lfcam")
    return out


def test_every_subcommand_has_a_description():
    parsers = _all_parsers()
    assert len(parsers) >= 12
    assert [n for n, p in parsers if not p.description] == []


def _sha1_mismatch_lfp(path: Path) -> Path:
    import sys

    sys.path.insert(0, str(ROOT / "tests" / "io"))
    from io_testlib import small_frame_meta

    from lfcam.io import read_lfp, write_lfp

    write_lfp(path, (np.arange(64 * 48) % 4000).astype(np.uint16).reshape(48, 64),
              small_frame_meta(64, 48))
    data = bytearray(path.read_bytes())
    data[read_lfp(path).sections[-1].offset] ^= 1
    path.write_bytes(bytes(data))
    return path


@pytest.mark.filterwarnings("ignore::lfcam.io.lfp.ChecksumWarning")
def test_checksum_message_names_only_existing_flags(work, capsys):
    _sha1_mismatch_lfp(work / "bad.lfp")
    flags = {n: {o for a in p._actions for o in a.option_strings} for n, p in _all_parsers()}
    for cmd in (["distance", "bad.lfp", *CAL, "-o", "o"],
                ["decode", "bad.lfp", "--calibration", "calib.json", "-o", "o"],
                ["info", "bad.lfp"],
                ["calibrate", "bad.lfp", "-o", "c.json"]):
        assert main(cmd) == 1
        err = capsys.readouterr().err
        assert "sha1 mismatch" in err and err.count("\n") == 1
        if "--no-verify" in err:
            assert "--no-verify" in flags[f"lfcam {cmd[0]}"], cmd[0]
    assert "--no-verify" in flags["lfcam distance"] and "--no-verify" in flags["lfcam decode"]
    with pytest.raises(ChecksumError):
        run(["distance", "bad.lfp", *CAL, "-o", "o"])
    # with the flag, the checksum no longer stops it (the 64x48 frame fails later, elsewhere)
    with pytest.raises(LfcamError) as exc:
        run(["distance", "bad.lfp", *CAL, "-o", "o", "--no-verify"])
    assert not isinstance(exc.value, ChecksumError)


def test_profile_errors_name_the_file(tmp_path, capsys):
    from lfcam.camera import load_profile

    bad = tmp_path / "bad.toml"
    bad.write_text((ROOT / "calibration" / "system1.toml").read_text()
                   .replace("pitch_mm = 1.34", "pitch_mm = -1.34"))
    with pytest.raises(ProfileError, match=r"bad\.toml: mla\.pitch_mm"):
        load_profile(bad)
    one_line_error(capsys, ["optics", "forward", "--profile", str(bad), "--distance", "1e3"],
                   "bad.toml")


def test_dot_calibration_prints_no_nan(work, capsys, monkeypatch):
    import lfcam.calibrate

    cal = SimpleNamespace(grid="rect", pitch_px=16.4, rotation_rad=0.0, offset_px=(1.0, 2.0),
                          n_lenses=9, model="projective", residual_rms_px=0.01, rejected={},
                          d_in_mm=104.7, d_in_method="reference", is_poor=False, quality=None)
    din = SimpleNamespace(d_in_mm=104.7, sigma_mm=float("nan"), d_in_paraxial_mm=float("nan"),
                          n_dots=1, distance_mm=1000.0)
    monkeypatch.setattr(lfcam.calibrate, "calibrate_white_file", lambda *a, **k: cal)
    monkeypatch.setattr(lfcam.calibrate, "calibrate_reference_file", lambda *a, **k: (cal, din))
    monkeypatch.setattr(lfcam.calibrate, "save_calibration", lambda c, p: p)
    shutil.copy("cap.png", "ref.png")
    argv = ["calibrate", "cap.png", "--profile", "system1", "--reference", "ref.png",
            "--reference-distance", "1000", "-o", "c.json"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "nan" not in out.lower() and "d_in 104.7000 mm from 1 dots" in out
    assert main([*argv, "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)  # strict JSON: no NaN token
    assert summary["d_in_sigma_mm"] is None


# ----------------------------------------------------------------------------- 6 progress


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_terminal_progress_renderer():
    from lfcam.progress import TerminalProgress

    buf = _Tty()
    with TerminalProgress(stream=buf, min_interval_s=0.0) as bar:
        bar("regions", 1, 4)
        bar("centroids", 500, 1000)
        bar("writing", 1, 1)
    text = buf.getvalue()
    assert "regions" in text and " 25.0%" in text and "centroids" in text
    assert "100.0%" in text and text.endswith("\n")
    quiet = io.StringIO()  # not a terminal: nothing
    with TerminalProgress(stream=quiet) as bar:
        bar("x", 1, 2)
    assert quiet.getvalue() == ""


def test_progress_on_a_terminal_and_quiet(work, monkeypatch, capsys):
    Path("s.json").write_text(json.dumps({"rays_per_source": 4000, "objects": [
        {"type": "point", "distance_mm": 900.0}, {"type": "point", "distance_mm": 1500.0}]}))
    for quiet in (False, True):
        tty = _Tty()
        monkeypatch.setattr("sys.stderr", tty)
        argv = ["simulate", "--profile", "system1", "--scene", "s.json", "-o", "s.png"]
        assert main(argv + (["--quiet"] if quiet else [])) == 0
        if quiet:
            assert tty.getvalue() == ""
        else:
            assert "rendering" in tty.getvalue() and "100.0%" in tty.getvalue()
    tty = _Tty()
    monkeypatch.setattr("sys.stderr", tty)
    assert main(["distance", "cap.png", *CAL, "--fast", "-o", "out"]) == 0
    assert "regions" in tty.getvalue() and "loading" in tty.getvalue()
    capsys.readouterr()
    for cmd in ("distance", "calibrate", "simulate", "decode"):
        assert "--quiet" in dict(_all_parsers())[f"lfcam {cmd}"].format_help()


# ----------------------------------------------------------------------------- 7 saturation


def test_saturated_frame_is_refused(work, capsys):
    from lfcam.io import load_capture
    from lfcam.io.capture import check_saturation

    img = np.full((1024, 1024), 65535, np.uint16)
    cv2.imwrite("sat.png", img)
    before = digest("sat.png")
    with pytest.raises(SaturatedCaptureError, match=r"sat.png: 100.0 % of the pixels"):
        run(["distance", "sat.png", *CAL, "--fast", "-o", "out"])
    one_line_error(capsys, ["decode", "sat.png", "--calibration", "calib.json", "-o", "o"],
                   "white level")
    assert digest("sat.png") == before
    img[: 400] = 1000  # 61 % saturated: refused; 39 %: accepted
    cv2.imwrite("part.png", img)
    with pytest.raises(SaturatedCaptureError):
        check_saturation(load_capture("part.png"))
    img[: 625] = 1000
    cv2.imwrite("part.png", img)
    assert 0.38 < check_saturation(load_capture("part.png")) < 0.40
