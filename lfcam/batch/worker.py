"""The worker side of :mod:`lfcam.batch`: one capture through the distance pipeline.

A worker process parses the batch's calibration once (:func:`init_worker`, the pool
initializer or the Dask worker plugin of :mod:`lfcam.batch.dask_plugin`) and prepares the
lenslet geometry once per (profile, sensor size); :func:`process_capture` never raises for a
bad capture. :func:`is_finished` is the resumability rule (docs/batch.md).
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2

from lfcam.atomic import atomic_write_text, sha256_file
from lfcam.calibrate.model import calibration_from_bytes
from lfcam.distance import run_distance, write_outputs
from lfcam.errors import BatchError
from lfcam.io import load_capture
from lfcam.io.grey import GREY_WHITE
from lfcam.io.profiles import profile_for_capture
from lfcam.measure import prepare_geometry

OUTPUT_FILES = ("regions.csv", "distance.tiff", "distance.png")
DONE_FILE = "done.json"


@dataclass(frozen=True)
class Settings:
    """Pipeline options shared by every capture of a batch (recorded in ``done.json``)."""

    model: str = "auto"
    method: str = "lightfield"
    tolerance_pct: float | None = None
    fast: bool = False
    profile: str | None = None  # name or path; None: each capture's .profile.toml sidecar


@dataclass(frozen=True)
class Job:
    """One capture to compute (picklable; sent to the workers)."""

    capture: str  # absolute path
    rel: str  # path relative to the input folder (posix), as written in the CSVs
    outdir: str
    sha256: str
    calibration_sha256: str
    settings: Settings


_STATE_LOCK = threading.Lock()
_CALIBRATIONS: dict[str, Any] = {}  # calibration sha256 -> Calibration (one per process)
_GEOMETRIES: dict[tuple, Any] = {}  # (calibration sha, profile, shape) -> Geometry
_STATS = {"calibration_loads": 0, "geometry_builds": 0}


def init_worker(calibration_bytes: bytes, single_thread: bool = True) -> None:
    """Parse the calibration once in this process (pool initializer / Dask worker plugin).

    With ``single_thread`` OpenCV runs on one thread: a worker is one core, parallelism comes
    from running several workers.

    Parameters
    ----------
    calibration_bytes : bytes
        The calibration file's content (:func:`lfcam.calibrate.calibration_from_bytes`).
    single_thread : bool
    """
    if single_thread:
        cv2.setNumThreads(1)
    _undo_malloc_trim()

    key = hashlib.sha256(calibration_bytes).hexdigest()
    with _STATE_LOCK:
        if key in _CALIBRATIONS:
            return
        _CALIBRATIONS[key] = calibration_from_bytes(calibration_bytes)
        _STATS["calibration_loads"] += 1


def _undo_malloc_trim() -> None:
    """Undo a small ``MALLOC_TRIM_THRESHOLD_`` (Dask sets 65536 in its workers by default).

    With it, glibc returns every large freed block to the system and maps it again on the
    next allocation; the pipeline allocates many full-frame temporaries and ran 3× slower
    (measured: 2.0 → 6.0 s a capture). Restores large fixed thresholds, glibc only.
    """
    if "MALLOC_TRIM_THRESHOLD_" not in os.environ or not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 32 << 20)  # M_MMAP_THRESHOLD: full frames stay on the heap
        libc.mallopt(-1, 64 << 20)  # M_TRIM_THRESHOLD
    except (OSError, AttributeError):  # not glibc: nothing to undo
        pass


def _geometry(cal_key: str, profile, shape: tuple[int, int]):
    key = (cal_key, profile, shape)
    with _STATE_LOCK:
        geom = _GEOMETRIES.get(key)
        if geom is None:
            geom = prepare_geometry(profile, _CALIBRATIONS[cal_key], shape)
            _GEOMETRIES[key] = geom
            _STATS["geometry_builds"] += 1
    return geom


def write_done(outdir: Path, job: Job, duplicate_of: str = "") -> None:
    outputs = {}
    for name in OUTPUT_FILES:
        p = outdir / name
        outputs[name] = {"bytes": p.stat().st_size, "sha256": sha256_file(p)}
    record = {
        "capture": job.rel, "sha256": job.sha256, "calibration_sha256": job.calibration_sha256,
        "settings": job.settings.__dict__, "duplicate_of": duplicate_of, "outputs": outputs,
    }
    atomic_write_text(outdir / DONE_FILE, json.dumps(record, indent=1) + "\n")


def process_capture(job: Job) -> dict:
    """Compute one capture and write its outputs; never raises for a bad capture.

    Returns a dict with ``status`` (``ok`` | ``failed``), the capture's ``rel`` path, the
    worker's ``pid``, its calibration-load and geometry-build counters, and for a failure
    ``error_class`` and ``message``.

    Parameters
    ----------
    job : Job

    Returns
    -------
    dict
    """
    t0 = time.perf_counter()
    out = {"rel": job.rel, "pid": os.getpid()}
    try:
        if job.calibration_sha256 not in _CALIBRATIONS:
            raise BatchError("this worker has no calibration (worker not initialised)")
        s = job.settings
        path = Path(job.capture)
        profile = profile_for_capture(path, s.profile)
        cap = load_capture(path, profile)
        image = cap.grey()
        from lfcam.calibrate.lensfit import resolve_profile

        geom = _geometry(job.calibration_sha256,
                         resolve_profile(profile, _CALIBRATIONS[job.calibration_sha256]),
                         image.shape)
        run = run_distance(image, profile, _CALIBRATIONS[job.calibration_sha256],
                           model=s.model, method=s.method, tolerance_pct=s.tolerance_pct,
                           fast=s.fast, geometry=geom, white_value=GREY_WHITE)
        outdir = Path(job.outdir)
        (outdir / DONE_FILE).unlink(missing_ok=True)
        write_outputs(outdir, run, f"{job.rel}  model {s.model}, method {s.method}"
                      f"{' (fast)' if s.fast else ''}")
        write_done(outdir, job)
        out.update(status="ok", regions=len(run.regions))
    except Exception as exc:  # noqa: BLE001 - one bad capture must never stop the batch
        msg = " ".join(str(exc).split()) or repr(exc)
        out.update(status="failed", error_class=type(exc).__name__, message=msg)
    out.update(seconds=time.perf_counter() - t0, **_STATS)
    return out


def is_finished(job: Job) -> bool:
    """Whether ``job``'s outputs are complete for this capture, calibration and settings.

    Parameters
    ----------
    job : Job

    Returns
    -------
    bool
        True when ``done.json`` matches and every output it lists is intact.
    """
    outdir = Path(job.outdir)
    try:
        rec = json.loads((outdir / DONE_FILE).read_text(encoding="utf-8"))
        if (rec["sha256"] != job.sha256 or rec["calibration_sha256"] != job.calibration_sha256
                or rec["settings"] != job.settings.__dict__):
            return False
        for name in OUTPUT_FILES:
            want = rec["outputs"][name]
            p = outdir / name
            if p.stat().st_size != want["bytes"] or sha256_file(p) != want["sha256"]:
                return False
    except (OSError, ValueError, KeyError, TypeError):
        return False
    return True
