"""``lfcam batch``: discovery by content, failures, duplicates, Dask equivalence, resumption."""

from __future__ import annotations

import csv
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

from lfcam.batch import SUMMARY_COLUMNS, discover_captures, run_batch
from lfcam.calibrate import load_calibration
from lfcam.camera import load_profile
from lfcam.cli.main import main
from lfcam.distance import run_distance
from lfcam.io import load_capture
from lfcam.measure import prepare_geometry

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data" / "synthetic"
CALIB = DATA / "calib_system2.json"
# fast (triangulation-only) mode is within 1 % of the truth from 2 m on for system 2
GOOD = ["point_system2_2000mm_dh0", "point_system2_2500mm_dh5", "point_system2_3000mm_dh10",
        "point_system2_3500mm_dh0"]


def _copy(name: str, dst_dir: Path, new_name: str | None = None) -> Path:
    """Copy a synthetic capture and its sidecars, optionally renamed (``stem.ext``)."""
    dst_dir.mkdir(parents=True, exist_ok=True)
    target = dst_dir / (new_name or f"{name}.png")
    shutil.copyfile(DATA / f"{name}.png", target)
    stem = target.name.rsplit(".", 1)[0]
    shutil.copyfile(DATA / f"{name}.profile.toml", dst_dir / f"{stem}.profile.toml")
    shutil.copyfile(DATA / f"{name}.truth.json", dst_dir / f"{stem}.truth.json")
    return target


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    """4 good captures (one under a non-capture extension in a sub-folder), one duplicate,
    a truncated PNG, random bytes named .png, and files that are not captures."""
    d = tmp_path_factory.mktemp("captures")
    _copy(GOOD[0], d)
    _copy(GOOD[1], d)
    _copy(GOOD[2], d / "day2", "capture_0003.dat")  # a PNG by content, not by name
    _copy(GOOD[3], d / "day2")
    _copy(GOOD[0], d / "day2", "same_as_2000.png")  # duplicate under another name
    good = (DATA / f"{GOOD[1]}.png").read_bytes()
    (d / "truncated.png").write_bytes(good[: len(good) // 2])
    shutil.copyfile(DATA / f"{GOOD[1]}.profile.toml", d / "truncated.profile.toml")
    (d / "noise.png").write_bytes(np.random.default_rng(7).bytes(4000))
    shutil.copyfile(DATA / f"{GOOD[1]}.profile.toml", d / "noise.profile.toml")
    (d / "notes.txt").write_text("not a capture\n")
    return d


_GEOM: dict = {}


def _reference_rows(path: Path) -> list:
    """The single-capture pipeline (as ``lfcam distance --fast`` runs it), computed directly."""
    prof = load_profile(path.with_name(path.name.rsplit(".", 1)[0] + ".profile.toml"))
    cal = load_calibration(CALIB)
    cap = load_capture(path, prof)
    img = cap.grey()
    geom = _GEOM.get(prof) or _GEOM.setdefault(prof, prepare_geometry(prof, cal, img.shape))
    run = run_distance(img, prof, cal, fast=True, geometry=geom)
    return run.regions


def _read_csv(path: Path) -> list[dict]:
    with path.open(newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def local_run(folder, tmp_path_factory):
    out = tmp_path_factory.mktemp("out_local")
    return out, run_batch(folder, CALIB, out, fast=True)  # default: local, all cores


def test_discovery_by_content(folder, tmp_path):
    found = [p.relative_to(folder).as_posix() for p in discover_captures(folder)]
    assert found == ["day2/capture_0003.dat", f"day2/{GOOD[3]}.png", "day2/same_as_2000.png",
                     "noise.png", f"{GOOD[0]}.png", f"{GOOD[1]}.png", "truncated.png"]
    # an output folder inside the input folder is never scanned (its PNG/TIFF are not inputs)
    _copy(GOOD[0], tmp_path)
    for _ in range(2):
        res = run_batch(tmp_path, CALIB, tmp_path / "out", fast=True, workers=1)
        assert res.captures == [f"{GOOD[0]}.png"] and res.failures == []


def test_local_batch_summary_failures_duplicates(folder, local_run):
    out, res = local_run
    rows = _read_csv(out / "summary.csv")
    assert tuple(rows[0].keys()) == SUMMARY_COLUMNS
    by_capture = {r["capture"]: r for r in rows}
    expected = {f"{GOOD[0]}.png": GOOD[0], f"{GOOD[1]}.png": GOOD[1],
                "day2/capture_0003.dat": GOOD[2], f"day2/{GOOD[3]}.png": GOOD[3],
                "day2/same_as_2000.png": GOOD[0]}
    assert len(rows) == len(expected) == len(by_capture)  # one point source a capture
    for rel, name in expected.items():
        r = by_capture[rel]
        truth = json.loads((DATA / f"{name}.truth.json").read_text())["sources"][0]
        assert r["status"] == "ok" and r["kind"] == "spot"
        assert abs(float(r["distance_mm"]) - truth["distance_mm"]) < 0.01 * truth["distance_mm"]
        # identical to the single-capture pipeline run directly on that file
        ref = _reference_rows(folder / rel)
        assert len(ref) == 1
        assert float(r["distance_mm"]) == ref[0].distance_mm
        assert float(r["x_px"]) == ref[0].x_px and float(r["y_px"]) == ref[0].y_px
        # and the capture's own folder holds the `lfcam distance` outputs
        sub = out / "captures" / rel
        assert {p.name for p in sub.iterdir()} >= {"regions.csv", "distance.tiff",
                                                  "distance.png", "done.json"}
        assert _read_csv(sub / "regions.csv")[0]["distance_mm"] == r["distance_mm"]
    # the duplicate (the later one in path order) was not computed again, but has the same
    # outputs and says whose they are
    assert res.duplicates == {f"{GOOD[0]}.png": "day2/same_as_2000.png"}
    assert by_capture[f"{GOOD[0]}.png"]["duplicate_of"] == "day2/same_as_2000.png"
    assert by_capture["day2/same_as_2000.png"]["duplicate_of"] == ""
    # its copies are the computed files, with an ordinary file's permissions (not 0o600)
    umask = os.umask(0)
    os.umask(umask)
    for name in ("regions.csv", "distance.tiff", "distance.png"):
        copy = out / "captures" / f"{GOOD[0]}.png" / name
        assert copy.read_bytes() == (out / "captures" / "day2/same_as_2000.png" / name
                                     ).read_bytes()
        assert stat.S_IMODE(copy.stat().st_mode) == 0o666 & ~umask
    assert sorted(res.computed) == sorted(set(expected) - {f"{GOOD[0]}.png"})
    # the bad files are in failures.csv with their error class; nothing else is
    fails = {f["capture"]: f for f in _read_csv(out / "failures.csv")}
    assert set(fails) == {"truncated.png", "noise.png"}
    assert fails["noise.png"]["error_class"] == "UnsupportedFormatError"
    assert fails["truncated.png"]["error_class"] in ("UnsupportedFormatError",
                                                     "TruncatedFileError")
    assert all(f["message"] for f in fails.values())
    # the API returns the same table, typed
    assert [s["capture"] for s in res.summary] == [r["capture"] for r in rows]
    assert [s["distance_mm"] for s in res.summary] == [float(r["distance_mm"]) for r in rows]


def test_dask_local_cluster_gives_identical_summary(folder, local_run, tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    out_local, _ = local_run
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        res = run_batch(folder, CALIB, tmp_path, fast=True, scheduler=cluster.scheduler_address)
    assert (tmp_path / "summary.csv").read_bytes() == (out_local / "summary.csv").read_bytes()
    fails = [(f["capture"], f["error_class"]) for f in _read_csv(tmp_path / "failures.csv")]
    assert fails == [(f["capture"], f["error_class"])
                     for f in _read_csv(out_local / "failures.csv")]
    # the calibration was parsed once per worker process, the geometry built at most once
    assert len(res.worker_stats) == 6  # 4 distinct good captures + 2 bad ones
    assert all(s["calibration_loads"] == 1 for s in res.worker_stats)
    assert all(s["geometry_builds"] <= 1 for s in res.worker_stats)
    assert {s["pid"] for s in res.worker_stats}.isdisjoint({os.getpid()})


def _done(out: Path) -> dict[str, int]:
    """Finished captures (those with done.json) → mtime of their regions.csv."""
    return {p.parent.relative_to(out / "captures").as_posix():
            (p.parent / "regions.csv").stat().st_mtime_ns
            for p in (out / "captures").rglob("done.json")} if (out / "captures").exists() else {}


def test_interrupted_batch_resumes_without_redoing(tmp_path):
    src = tmp_path / "in"
    names = GOOD + ["point_system2_2200mm_dh5", "point_system2_2800mm_dh0"]
    for n in names:
        _copy(n, src)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "lfcam", "batch", str(src), "--calibration", str(CALIB),
           "-o", str(out), "--fast", "--workers", "1"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while not _done(out) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    before = _done(out)
    assert 1 <= len(before) < len(names), "the kill must land mid-batch"
    assert not (out / "summary.csv").exists()

    res = run_batch(src, CALIB, out, fast=True, workers=1)
    after = _done(out)
    assert sorted(res.skipped) == sorted(before)  # finished captures were not redone ...
    assert all(after[k] == v for k, v in before.items())  # ... nor rewritten
    assert sorted(res.computed) == sorted(set(after) - set(before))  # the rest was computed
    assert sorted(after) == sorted(f"{n}.png" for n in names)  # nothing lost
    assert [r["capture"] for r in _read_csv(out / "summary.csv")] == sorted(after)
    assert res.failures == []

    # an output that is no longer complete un-finishes its capture; --force redoes all
    victim = sorted(before)[0]
    regions = out / "captures" / victim / "regions.csv"
    regions.write_bytes(regions.read_bytes()[:-10])
    res2 = run_batch(src, CALIB, out, fast=True, workers=1)
    assert res2.computed == [victim]
    res3 = run_batch(src, CALIB, out, fast=True, workers=1, force=True)
    assert sorted(res3.computed) == sorted(after) and res3.skipped == []


def test_cli_exit_codes(folder, tmp_path, capsys):
    assert main(["batch", str(folder / "day2"), "--calibration", str(CALIB), "-o",
                 str(tmp_path / "a"), "--fast", "--workers", "1"]) == 0
    assert main(["batch", str(folder), "--calibration", str(CALIB), "-o",
                 str(tmp_path / "b"), "--fast", "--workers", "1", "--json"]) == 1
    err = capsys.readouterr()
    info = json.loads(err.out.strip().splitlines()[-1])
    assert info["failed"] == 2 and info["duplicates"] == 1 and info["regions"] == 5
    assert "failures.csv" in err.err
    assert main(["batch", str(tmp_path / "missing"), "--calibration", str(CALIB), "-o",
                 str(tmp_path / "c")]) == 1
    assert "input folder not found" in capsys.readouterr().err
    assert main(["batch", str(folder), "--calibration", str(tmp_path / "nope.json"), "-o",
                 str(tmp_path / "c")]) == 1
    assert "calibration" in capsys.readouterr().err


def test_progress_counts_finished_and_failed_captures(folder, tmp_path):
    calls = []
    res = run_batch(folder, CALIB, tmp_path, fast=True, workers=1,
                    progress=lambda stage, done, total: calls.append((stage, done, total)))
    todo = calls[0][2]
    failed = sum(1 for r in res.worker_stats if r.get("status") != "ok")
    assert todo == len(res.worker_stats) and failed > 0  # the folder holds broken captures
    assert [d for _, d, _ in calls] == list(range(todo + 1))  # a call a capture, from 0
    assert calls[-1][0] == f"captures ({failed} failed)"
