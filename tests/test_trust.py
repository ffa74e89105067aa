"""Issue 18, remainder: calibration quality gates, profile/calibration pitch check, region
gates, batch interrupts and unreadable entries, decode through a temporary folder."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from lfcam.batch import run_batch
from lfcam.calibrate import calibrate_white_file, load_calibration
from lfcam.calibrate.quality import MAX_MISFIT, MIN_COVERAGE, assess
from lfcam.camera import load_profile
from lfcam.cli.main import main
from lfcam.distance import run_distance
from lfcam.errors import CalibrationMismatchError, CalibrationQualityError
from lfcam.io import load_capture
from lfcam.measure.verify import _same_blur

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data" / "synthetic"
CAP = "point_system2_3000mm_dh10"


def sha(p: Path) -> str:
    return hashlib.sha256(Path(p).read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def bad_white(tmp_path_factory) -> Path:
    """A system 2 white with one Monte-Carlo sample per boundary pixel (docs/robustness.md)."""
    from lfcam.sim.capture import simulate, write_capture
    from lfcam.sim.scene import scene_from_dict

    folder = tmp_path_factory.mktemp("badwhite")
    scene = {"seed": 3, "samples_per_pixel": 1, "objects": [{"type": "white"}],
             "camera": {"sensor": {"width_px": 640, "height_px": 640}}}
    raw, used, truth = simulate(load_profile("system2"), scene_from_dict(scene))
    img, _, _ = write_capture(folder / "bad.png", raw, used, truth)
    return img


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("cap")
    for ext in (".png", ".profile.toml"):
        shutil.copyfile(DATA / f"{CAP}{ext}", folder / f"cap{ext}")
    return folder / "cap.png"


def _with_quality(tmp: Path, verdict: str, accepted: bool = False) -> Path:
    d = json.loads((DATA / "calib_system2.json").read_text())
    d["quality"] = {"verdict": verdict, "reasons": ["coverage 0.323 (limit 0.9)"]
                    if verdict == "poor" else [], "accepted_poor": accepted}
    p = tmp / f"cal_{verdict}_{accepted}.json"
    p.write_text(json.dumps(d))
    return p


def test_good_white_passes_and_stores_quality(tmp_path):
    cal = calibrate_white_file(DATA / "white_system1_rect.png", output=tmp_path / "c.json")
    q = assess(cal)
    assert q.verdict == "ok" and q.coverage >= MIN_COVERAGE and q.reasons == ()
    stored = json.loads((tmp_path / "c.json").read_text())["quality"]
    assert stored["verdict"] == "ok" and stored["accepted_poor"] is False
    assert load_calibration(tmp_path / "c.json").quality["verdict"] == "ok"


def test_bad_white_is_poor_and_refused_by_calibrate(bad_white, tmp_path, capsys):
    before = sha(bad_white)
    cal = calibrate_white_file(bad_white)
    q = assess(cal)
    assert q.verdict == "poor" and q.coverage < MIN_COVERAGE
    assert q.misfit is not None and q.misfit > MAX_MISFIT
    out = tmp_path / "c.json"
    with pytest.raises(CalibrationQualityError, match="coverage"):
        calibrate_white_file(bad_white, output=out)
    assert main(["calibrate", str(bad_white), "-o", str(out), "-q"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "poor calibration" in err[0] and "--accept-poor" in err[0]
    assert not out.exists()
    assert main(["calibrate", str(bad_white), "-o", str(out), "-q", "--accept-poor"]) == 0
    assert "warning: poor calibration accepted" in capsys.readouterr().err
    q = json.loads(out.read_text())["quality"]
    assert q["verdict"] == "poor" and q["accepted_poor"] is True
    assert sha(bad_white) == before


@pytest.mark.parametrize("cmd", ["distance", "decode", "refocus", "batch"])
def test_poor_calibration_refused_unless_accepted(cmd, tmp_path, capture, capsys):
    poor = _with_quality(tmp_path, "poor")
    hashes = {p: sha(p) for p in (poor, capture)}
    extra = {"distance": ["--fast", "-o", str(tmp_path / "o")],
             "decode": ["-o", str(tmp_path / "lf")],
             "refocus": ["--shift", "0", "-o", str(tmp_path / "r.png")],
             "batch": ["--fast", "--workers", "1", "-o", str(tmp_path / "b")]}[cmd]
    src = str(capture.parent) if cmd == "batch" else str(capture)
    quiet = [] if cmd == "batch" else ["-q"]
    assert main([cmd, src, "--calibration", str(poor), *extra, *quiet]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "poor calibration" in err[0] and "coverage" in err[0]
    assert all(sha(p) == h for p, h in hashes.items())
    if cmd in ("distance", "batch"):
        accepted = _with_quality(tmp_path, "poor", accepted=True)
        with pytest.warns(UserWarning, match="accepted explicitly"):
            assert main([cmd, src, "--calibration", str(accepted), *extra, *quiet]) == 0


def test_unknown_quality_is_not_poor():
    cal = load_calibration(DATA / "calib_system2.json")  # no quality block
    assert cal.quality is None and not cal.is_poor
    cal.check_quality()


def test_invalid_quality_block(tmp_path):
    p = _with_quality(tmp_path, "poor")
    d = json.loads(p.read_text())
    d["quality"]["verdict"] = "meh"
    p.write_text(json.dumps(d))
    with pytest.raises(Exception, match="quality.verdict"):
        load_calibration(p)


def test_profile_pitch_disagreeing_with_calibration(tmp_path, capture, capsys):
    text = (capture.parent / "cap.profile.toml").read_text()
    assert "pitch_mm" in text
    import re

    bad = re.sub(r"(?m)^(\s*pitch_mm\s*=\s*).*$", r"\g<1>1000", text, count=1)
    prof_path = tmp_path / "wrong.profile.toml"
    prof_path.write_text(bad)
    prof = load_profile(prof_path)
    assert prof.mla.pitch_mm == 1000
    img = load_capture(capture, prof).grey()
    t = time.perf_counter()
    with pytest.raises(CalibrationMismatchError, match="micro-image pitch"):
        run_distance(img, prof, load_calibration(DATA / "calib_system2.json"), fast=True)
    assert time.perf_counter() - t < 5  # refused before any heavy work
    assert main(["distance", str(capture), "--calibration", str(DATA / "calib_system2.json"),
                 "--profile", str(prof_path), "-o", str(tmp_path / "o"), "-q"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "wrong profile" in err[0]


class _M:
    def __init__(self, d):
        self.distance_mm, self.offset_mm = d, 0.0


def _disc(cx: float, r: float):
    from scipy.spatial import cKDTree

    g = np.arange(-r, r + 1e-9, 1.34)
    xx, yy = np.meshgrid(g, g)
    keep = xx**2 + yy**2 <= r * r
    return cKDTree(np.column_stack([xx[keep] + cx, yy[keep]]))


def test_fragment_rule():
    # a large predicted footprint reaching the other region's light: one blur
    assert _same_blur(_disc(0.0, 5.0), _disc(20.0, 0.5), (0.0, 0.0), (5.5, 0.0),
                      ("ok", _M(300), (0, 0), 1.0), ("ok", _M(5000), (9, 0), 50.0), 1.34)
    # two small footprints far apart at different distances: two sources
    assert not _same_blur(_disc(0.0, 0.5), _disc(20.0, 0.5), (0.0, 0.0), (20.0, 0.0),
                          ("ok", _M(3000), (0, 0), 5.0), ("ok", _M(1500), (40, 0), 2.0),
                          1.34)


def test_clean_capture_stays_ok(capture):
    prof = load_profile(capture.parent / "cap.profile.toml")
    run = run_distance(load_capture(capture, prof).grey(), prof,
                       load_calibration(DATA / "calib_system2.json"), fast=True)
    assert [r.status for r in run.regions] == ["ok"]
    assert run.checks[0].explained > 0.95


# ----------------------------------------------------------------------------- batch, decode


def test_batch_dangling_symlink_and_unreadable_folder(tmp_path, capture, monkeypatch):
    src = tmp_path / "in"
    src.mkdir()
    for ext in (".png", ".profile.toml"):
        shutil.copyfile(capture.parent / f"cap{ext}", src / f"cap{ext}")
    (src / "gone.png").symlink_to(tmp_path / "nowhere.png")
    locked = src / "locked"
    locked.mkdir()
    real_scandir = os.scandir

    def scandir(path="."):
        if Path(path) == locked:
            raise PermissionError(13, "Permission denied", str(path))
        return real_scandir(path)

    monkeypatch.setattr(os, "scandir", scandir)
    res = run_batch(src, DATA / "calib_system2.json", tmp_path / "out", fast=True, workers=1)
    fails = {f.capture: f for f in res.failures}
    assert set(fails) == {"gone.png", "locked"}
    assert "dangling" in fails["gone.png"].message
    assert fails["locked"].error_class == "PermissionError"
    text = (tmp_path / "out" / "failures.csv").read_text()
    assert "gone.png" in text and "locked" in text
    assert len(res.summary) == 1


def test_ctrl_c_does_not_cut_a_workers_start_up_data():
    # a spawned batch worker's start-up data (268 kB with system 2's calibration) goes down a
    # pipe of 64 kB, so the write waits for the child to read. A Ctrl-C to the main thread in
    # that wait cut it (the child then printed "pickle data was truncated" and its traceback
    # under the batch's one-line message). Here a reader drains 300 kB after 0.3 s and SIGINT
    # reaches the main thread at 0.1 s: under _sigint_deferred the write ends whole and the
    # KeyboardInterrupt comes after it (without it: 65 536 bytes arrive)
    import threading

    from lfcam.batch import _sigint_deferred

    r, w = os.pipe()
    got = bytearray()

    def reader():
        time.sleep(0.3)
        with os.fdopen(r, "rb") as f:
            while chunk := f.read(65536):
                got.extend(chunk)

    payload = b"x" * 300_000
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    thread = threading.Thread(target=reader)
    thread.start()
    timer = threading.Timer(0.1, signal.pthread_kill,
                            (threading.main_thread().ident, signal.SIGINT))
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            with _sigint_deferred(), open(w, "wb") as f:
                f.write(payload)
    finally:
        signal.signal(signal.SIGINT, previous)
        timer.join(5)
        thread.join(5)
    assert len(got) == len(payload)


def test_local_worker_starts_with_ctrl_c_unblocked():
    # a spawned worker inherits the signal mask of the thread that started it, and
    # _sigint_deferred blocks SIGINT there: the worker's initializer unblocks it again, so a
    # worker takes Ctrl-C as before (measured: without it every worker ran with SIGINT blocked)
    import cv2

    from lfcam.batch import _init_local_worker

    threads = cv2.getNumThreads()
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        _init_local_worker((DATA / "calib_system2.json").read_bytes())
        assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, set())
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
        cv2.setNumThreads(threads)


def test_batch_sigint_writes_csvs_and_exits_130(tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    names = ["point_system2_2000mm_dh0", "point_system2_2500mm_dh5", "point_system2_3000mm_dh10",
             "point_system2_3500mm_dh0", "point_system2_2200mm_dh5", "point_system2_2800mm_dh0"]
    for n in names:
        for ext in (".png", ".profile.toml"):
            shutil.copyfile(DATA / f"{n}{ext}", src / f"{n}{ext}")
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "lfcam", "batch", str(src), "--calibration",
           str(DATA / "calib_system2.json"), "-o", str(out), "--fast", "--workers", "2"]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    # the batch starts with Ctrl-C's default disposition, as from a shell. In the full suite it
    # inherited an ignored SIGINT (still running with one capture done, it ignored the signal
    # and finished with 0); what sets the ignore is not found: Python's handler and the main
    # thread's mask were the defaults after every test
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    while (not list((out / "captures").rglob("done.json")) if (out / "captures").exists()
           else True) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    at_signal = len(list((out / "captures").rglob("done.json")))
    running = proc.poll() is None
    proc.send_signal(signal.SIGINT)
    t = time.monotonic()
    _, err = proc.communicate(timeout=60)
    assert time.monotonic() - t < 30  # prompt
    assert proc.returncode == 130, (running, at_signal, err[-500:])
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "interrupted" in lines[0] and "Traceback" not in err, err
    import csv

    summary = list(csv.DictReader(open(out / "summary.csv")))
    failures = list(csv.DictReader(open(out / "failures.csv")))
    done = sorted(p.parent.relative_to(out / "captures").as_posix()
                  for p in (out / "captures").rglob("done.json"))
    assert sorted({r["capture"] for r in summary}) == done
    assert {f["capture"] for f in failures} | set(done) == {f"{n}.png" for n in names}
    assert all(f["error_class"] == "Interrupted" for f in failures)


def test_decode_writes_through_a_temporary_folder(tmp_path, capture, monkeypatch):
    from lfcam.decode import export

    out = tmp_path / "lf"

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(export, "_write_lightfield_files", boom)
    assert main(["decode", str(capture), "--calibration", str(DATA / "calib_system2.json"),
                 "-o", str(out), "-q", "--no-png"]) == 130
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".lf")] == []
    monkeypatch.undo()
    assert main(["decode", str(capture), "--calibration", str(DATA / "calib_system2.json"),
                 "-o", str(out), "-q", "--no-png"]) == 0
    assert (out / "lightfield.json").is_file() and (out / "lightfield.npy").is_file()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".lf")] == []
    # the new folder has a mkdir's permissions, not its temporary folder's 0o700
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(out.stat().st_mode) == 0o777 & ~umask
    # an existing output folder keeps unrelated files; the light field is replaced
    (out / "notes.txt").write_text("mine")
    assert main(["decode", str(capture), "--calibration", str(DATA / "calib_system2.json"),
                 "-o", str(out), "-q", "--no-png"]) == 0
    assert (out / "notes.txt").read_text() == "mine"
    np.load(out / "lightfield.npy")
