"""Many captures at once: ``lfcam batch`` and its Python API :func:`run_batch`.

Every capture found under an input folder (recursively, recognised by content) is run through
the distance pipeline (:mod:`lfcam.distance`) and gets its own output folder
``OUT/captures/<relative path>/`` with the ``lfcam distance`` outputs plus a completion record
``done.json``. ``OUT/summary.csv`` has one row a region of every finished capture,
``OUT/failures.csv`` one row a capture that failed.

Resumability rule: a capture counts as finished only when its ``done.json`` exists, was
written for the same capture content (sha256), the same calibration content and the same
settings, and every output it lists exists with the recorded size and sha256. Each output is
written atomically and ``done.json`` last, so a batch killed at any point leaves only
finished captures (skipped on the next run) and unfinished ones (redone).

Captures with identical content and identical profile are computed once; the copies get the
same outputs (``duplicate_of`` names the capture that was computed).

Parallelism: local worker processes by default; with ``scheduler`` (or ``client``) the
captures go to a Dask distributed cluster (optional extra ``lfcam[dask]``). In both cases the
calibration is parsed once per worker process and the lenslet geometry is prepared once per
worker and (profile, sensor size); the captures and the output folder must be visible to the
workers at the same paths (shared file system).
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import os
import signal
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lfcam.atomic import atomic_copy, sha256_file
from lfcam.batch.worker import (
    DONE_FILE,
    OUTPUT_FILES,
    Job,
    Settings,
    init_worker,
    is_finished,
    process_capture,
    write_done,
)
from lfcam.calibrate.model import load_calibration
from lfcam.camera import load_profile
from lfcam.errors import BatchError, InputFileError
from lfcam.export import REGION_COLUMNS, write_csv
from lfcam.io.capture import RAW_EXTENSIONS
from lfcam.measure import METHODS
from lfcam.models import check_distance_model
from lfcam.progress import Progress, TerminalProgress

SUMMARY_COLUMNS = ("capture", "duplicate_of", *REGION_COLUMNS)
FAILURE_COLUMNS = ("capture", "error_class", "message")
CAPTURES_DIR = "captures"
# files with these extensions are reported as failures when their content is not a capture;
# files with any other extension are silently skipped unless their content is a capture
CAPTURE_EXTENSIONS = {".png", ".tif", ".tiff", ".lfp", ".lfr", ".raw", *RAW_EXTENSIONS}
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
_INT_COLUMNS = {"region_id"}
_FLOAT_COLUMNS = {"x_px", "y_px", "distance_mm", "offset_mm", "diameter_mm", "uncertainty_mm"}


# ----------------------------------------------------------------------------- jobs


@dataclass(frozen=True)
class Failure:
    """A capture that could not be processed (a row of ``failures.csv``)."""

    capture: str
    error_class: str
    message: str


@dataclass
class BatchResult:
    """What :func:`run_batch` did.

    ``summary`` holds one dict a region (keys :data:`SUMMARY_COLUMNS`; numbers as float/int,
    NaN for empty cells), in capture order; ``failures`` one :class:`Failure` a capture.
    """

    summary: list[dict[str, Any]]
    failures: list[Failure]
    captures: list[str]
    computed: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    duplicates: dict[str, str] = field(default_factory=dict)
    worker_stats: list[dict] = field(default_factory=list)
    elapsed_s: float = 0.0


def discover_captures(input_dir: str | Path, exclude: Iterable[str | Path] = (),
                      problems: list | None = None) -> list[Path]:
    """Every file under ``input_dir`` that is, or claims to be, a capture (sorted).

    A file is taken when its content is a supported capture (``lfcam.io.sniff_kind``) whatever
    its name, or when its extension is a capture extension (``.png``, ``.lfp``, ``.raw``,
    camera raws, …) whatever its content — such a file that is not readable becomes a failure
    rather than being ignored. Hidden files and folders, and the ``exclude`` folders (the
    output folder), are skipped. A folder that cannot be listed and a dangling symbolic link
    are appended to ``problems`` (when given) as ``(path, OSError)``: they become failures.

    Parameters
    ----------
    input_dir : str or Path
    exclude : iterable of paths
    problems : list, optional

    Returns
    -------
    list of Path
        Sorted by path relative to ``input_dir``.
    """
    from lfcam.io import sniff_kind

    root = Path(input_dir)
    if not root.is_dir():
        raise BatchError(f"input folder not found: {root}")
    excl = [Path(e).resolve() for e in exclude]
    found: list[Path] = []
    def unreadable(exc: OSError) -> None:
        if problems is not None and exc.filename is not None:
            problems.append((Path(exc.filename), exc))

    for dirpath, dirnames, filenames in os.walk(root, onerror=unreadable):
        d = Path(dirpath)
        dirnames[:] = sorted(n for n in dirnames if not n.startswith(".")
                             and not any((d / n).resolve() == e for e in excl))
        for name in sorted(filenames):
            if name.startswith("."):
                continue
            p = d / name
            if p.is_symlink() and not p.exists():
                if problems is not None:
                    problems.append((p, FileNotFoundError(
                        2, f"dangling symbolic link (to {os.readlink(p)})", str(p))))
                continue
            if not p.is_file():
                continue
            try:
                sniff_kind(p)
            except InputFileError:
                if p.suffix.lower() not in CAPTURE_EXTENSIONS:
                    continue
            found.append(p)
    return sorted(found, key=lambda q: q.relative_to(root).as_posix())


# ----------------------------------------------------------------------------- coordinator


def _copy_outputs(src: Job, dst: Job) -> None:
    """Give the duplicate ``dst`` the outputs computed for ``src`` (atomic per file)."""
    sdir, ddir = Path(src.outdir), Path(dst.outdir)
    ddir.mkdir(parents=True, exist_ok=True)
    (ddir / DONE_FILE).unlink(missing_ok=True)
    for name in OUTPUT_FILES:
        atomic_copy(sdir / name, ddir / name)
    write_done(ddir, dst, duplicate_of=src.rel)


def _profile_fingerprint(capture: Path, profile: str | None) -> str:
    """What decides the capture's profile: ``--profile`` or the sidecar's content."""
    if profile:
        return "profile:" + profile
    side = capture.with_name(capture.stem + ".profile.toml")
    try:
        return "sidecar:" + sha256_file(side)
    except OSError:
        return "sidecar:none"


def _read_rows(job: Job, duplicate_of: str) -> list[list[str]]:
    with (Path(job.outdir) / "regions.csv").open(encoding="utf-8", newline="") as f:
        rows = list(csv.reader(f))
    if not rows or tuple(rows[0]) != REGION_COLUMNS:
        raise InputFileError(f"{job.outdir}/regions.csv: unexpected header")
    return [[job.rel, duplicate_of, *r] for r in rows[1:]]


def _typed(row: list[str]) -> dict[str, Any]:
    d: dict[str, Any] = {}
    for k, v in zip(SUMMARY_COLUMNS, row, strict=True):
        if k in _INT_COLUMNS:
            d[k] = int(v)
        elif k in _FLOAT_COLUMNS:
            d[k] = float(v) if v else float("nan")
        else:
            d[k] = v
    return d


def _captures_progress(progress: Progress | bool | None, total: int):
    """(report(ok), close()) that tell ``progress`` — a :data:`lfcam.progress.Progress`, or a
    flag for the terminal line — how many captures are finished and how many failed."""
    term = None
    if not callable(progress):
        term = TerminalProgress(enabled=progress)
        progress = term
    n = {"ok": 0, "failed": 0}

    def report(ok: bool | None = None) -> None:
        if ok is not None:
            n["ok" if ok else "failed"] += 1
        stage = f"captures ({n['failed']} failed)" if n["failed"] else "captures"
        progress(stage, n["ok"] + n["failed"], total)

    return report, (term.close if term is not None else (lambda: None))


@contextlib.contextmanager
def _sigint_deferred():
    """Hold Ctrl-C (SIGINT) off the main thread while workers are spawned; it is delivered
    when the block ends.

    A spawned worker's start-up data (the calibration in the initializer's arguments: 268 kB
    for system 2's) is written down a pipe that holds 64 kB, so the write waits for the
    child's interpreter to start reading it. A Ctrl-C in that wait cut the write short and
    the child printed ``UnpicklingError: pickle data was truncated`` with its traceback under
    the batch's one-line message (seen once in the suite, 1 capture of 6 done). Threads
    started inside inherit the mask; a signal taken meanwhile by another thread is raised in
    the main thread once the write returns whole."""
    if (threading.current_thread() is not threading.main_thread()
            or not hasattr(signal, "pthread_sigmask")):  # (no signal masks on Windows)
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _init_local_worker(cal_bytes: bytes) -> None:
    """A local worker's start: Ctrl-C unblocked again (a spawned process inherits the signal
    mask :func:`_sigint_deferred` held while it was started), then :func:`init_worker`."""
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    init_worker(cal_bytes)


def _run_local(jobs: list[Job], cal_bytes: bytes, workers: int, on_result) -> None:
    if workers <= 1 or len(jobs) <= 1:
        import cv2

        n_cv = cv2.getNumThreads()
        try:
            init_worker(cal_bytes)
            for job in jobs:
                on_result(process_capture(job))
        finally:
            cv2.setNumThreads(n_cv)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    ctx = mp.get_context("spawn")
    # (created before _sigint_deferred: starting multiprocessing's resource tracker unblocks
    # SIGINT, and creating the pool starts it)
    pool = ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=ctx,
                               initializer=_init_local_worker, initargs=(cal_bytes,))
    try:
        # spawned workers start on the first submit: single-threaded numerical libraries
        saved = {k: os.environ.get(k) for k in _THREAD_VARS}
        os.environ.update(dict.fromkeys(_THREAD_VARS, "1"))
        try:
            with _sigint_deferred():
                futures = {pool.submit(process_capture, j): j for j in jobs}
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        for fut in as_completed(futures):
            try:
                on_result(fut.result())
            except BrokenProcessPool as exc:  # a worker died (e.g. out of memory)
                on_result({"rel": futures[fut].rel, "status": "failed",
                           "error_class": type(exc).__name__,
                           "message": "a worker process died while processing this capture"})
    except BaseException:  # Ctrl-C: drop the queued captures, stop the running ones
        procs = list((getattr(pool, "_processes", None) or {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for proc in procs:
            if proc.is_alive():
                proc.terminate()
        for proc in procs:
            proc.join(timeout=5)
        # The pool's manager thread closes its wake-up pipe as it ends: let it end here. At
        # exit, Python 3.11's concurrent.futures wakes every manager still alive, and a wake-up
        # racing that close printed "Exception ignored … Bad file descriptor" and a traceback
        # after the one-line message (seen once in CI, under load)
        manager = getattr(pool, "_executor_manager_thread", None)
        if manager is not None:
            manager.join(timeout=5)
        raise
    pool.shutdown(wait=True)


def _run_dask(jobs: list[Job], cal_bytes: bytes, scheduler: str | None, client, on_result):
    try:
        from dask.distributed import Client, as_completed
    except ImportError:
        raise BatchError("--scheduler needs Dask: pip install 'lfcam[dask]'") from None
    own = client is None
    if own:
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError, ValueError) as exc:
            raise BatchError(f"cannot reach the Dask scheduler {scheduler}: {exc}") from None
    try:
        from lfcam.batch.dask_plugin import CalibrationPlugin

        plugin = CalibrationPlugin(cal_bytes)
        name = f"lfcam-calibration-{jobs[0].calibration_sha256[:16]}"
        if hasattr(client, "register_plugin"):
            client.register_plugin(plugin, name=name)
        else:  # older distributed
            client.register_worker_plugin(plugin, name=name)
        futures = [client.submit(process_capture, j, pure=False, key=f"lfcam-{i}-{j.sha256[:12]}")
                   for i, j in enumerate(jobs)]
        by_key = {f.key: j for f, j in zip(futures, jobs, strict=True)}
        try:
            for fut in as_completed(futures):
                try:
                    on_result(fut.result())
                except Exception as exc:  # noqa: BLE001 - e.g. KilledWorker: record, go on
                    on_result({"rel": by_key[fut.key].rel, "status": "failed",
                               "error_class": type(exc).__name__,
                               "message": " ".join(str(exc).split())})
        except KeyboardInterrupt:  # Ctrl-C: the cluster drops what has not finished
            client.cancel(futures)
            raise
    finally:
        if own:
            client.close()


def run_batch(
    input_dir: str | Path,
    calibration: str | Path,
    output_dir: str | Path,
    profile: str | None = None,
    *,
    model: str = "auto",
    method: str = "lightfield",
    tolerance_pct: float | None = None,
    fast: bool = False,
    workers: int | None = None,
    scheduler: str | None = None,
    client: Any = None,
    force: bool = False,
    progress: Progress | bool | None = None,
    on_result: Callable[[dict], None] | None = None,
) -> BatchResult:
    """Run the distance pipeline on every capture under ``input_dir``.

    Parameters
    ----------
    input_dir : str or Path
        Folder searched recursively (see :func:`discover_captures`).
    calibration : str or Path
        Calibration JSON (``lfcam calibrate``), used for every capture.
    output_dir : str or Path
        Receives ``summary.csv``, ``failures.csv`` and ``captures/<relative path>/``.
    profile : str, optional
        Camera profile name or path for every capture; default: each capture's
        ``<stem>.profile.toml`` sidecar.
    model, method, tolerance_pct, fast
        As for :func:`lfcam.distance.run_distance`.
    workers : int, optional
        Local worker processes (default: ``os.cpu_count()``); 1 runs in this process.
    scheduler : str, optional
        Address of a Dask scheduler (``tcp://host:8786``): the captures run on that cluster.
    client : dask.distributed.Client, optional
        An existing Dask client (instead of ``scheduler``).
    force : bool
        Recompute every capture, even finished ones.
    progress : Progress or bool, optional
        A :data:`lfcam.progress.Progress` told ``("captures", finished, to do)``, or a flag
        for the progress line on stderr (default: when stderr is a terminal).
    on_result : callable, optional
        Called with each worker result dict as it arrives (coordinator side).

    Returns
    -------
    BatchResult

    Raises
    ------
    BatchError
        Missing input folder, output folder inside a capture path, unreachable scheduler.
    CalibrationError
        Unreadable or invalid calibration (checked once, before any capture runs).
    """
    t0 = time.perf_counter()
    check_distance_model(model)
    if method not in METHODS:
        raise BatchError(f"unknown method {method!r} (choose from {', '.join(METHODS)})")
    root = Path(input_dir).resolve()
    out = Path(output_dir).resolve()
    # fail early, with the calibration's own message; a poor one is refused unless accepted
    load_calibration(calibration).check_quality()
    cal_bytes = Path(calibration).read_bytes()
    cal_sha = hashlib.sha256(cal_bytes).hexdigest()
    if profile is not None:
        load_profile(profile)  # a wrong --profile is a usage error, not N failures
    settings = Settings(model, method, tolerance_pct, bool(fast), profile)
    problems: list = []
    paths = discover_captures(root, exclude=[out], problems=problems)
    out.mkdir(parents=True, exist_ok=True)

    failures: list[Failure] = []
    for p, exc in problems:  # unreadable folders, dangling links: failures, not silence
        rel = p.relative_to(root).as_posix() if p.is_relative_to(root) else str(p)
        failures.append(Failure(rel, type(exc).__name__, str(exc.strerror or exc)))
    jobs: list[Job] = []
    for p in paths:
        rel = p.relative_to(root).as_posix()
        try:
            sha = sha256_file(p)
        except OSError as exc:
            failures.append(Failure(rel, type(exc).__name__, str(exc.strerror or exc)))
            continue
        jobs.append(Job(str(p), rel, str(out / CAPTURES_DIR / rel), sha, cal_sha, settings))

    # duplicates: same content and same profile -> computed once
    first: dict[tuple[str, str], Job] = {}
    dup_of: dict[str, Job] = {}
    for j in jobs:
        key = (j.sha256, _profile_fingerprint(Path(j.capture), profile))
        if key in first:
            dup_of[j.rel] = first[key]
        else:
            first[key] = j
    originals = [j for j in jobs if j.rel not in dup_of]
    todo = [j for j in originals if force or not is_finished(j)]
    skipped = [j.rel for j in originals if j not in todo]

    bar, close_bar = _captures_progress(progress, len(todo))
    bar()
    computed: list[str] = []
    failed: dict[str, Failure] = {}
    worker_stats: list[dict] = []

    def handle(res: dict) -> None:
        ok = res.get("status") == "ok"
        if ok:
            computed.append(res["rel"])
        else:
            failed[res["rel"]] = Failure(res["rel"], res.get("error_class", "Error"),
                                         res.get("message", ""))
        worker_stats.append(res)
        bar(ok)
        if on_result is not None:
            on_result(res)

    interrupted = False
    try:
        if todo:
            if scheduler or client is not None:
                _run_dask(todo, cal_bytes, scheduler, client, handle)
            else:
                _run_local(todo, cal_bytes, workers or os.cpu_count() or 1, handle)
    except KeyboardInterrupt:  # Ctrl-C: no new capture; still write what finished
        interrupted = True
    finally:
        close_bar()
    if interrupted:
        done = set(computed) | set(failed)
        for j in todo:
            if j.rel in done:
                continue
            if is_finished(j):  # finished on disk, its result not yet reported back
                computed.append(j.rel)
            else:
                failed[j.rel] = Failure(j.rel, "Interrupted",
                                        "not processed: the batch was interrupted")

    duplicates: dict[str, str] = {}
    for j in jobs:
        src = dup_of.get(j.rel)
        if src is None:
            continue
        duplicates[j.rel] = src.rel
        if src.rel in failed:
            f = failed[src.rel]
            failed[j.rel] = Failure(j.rel, f.error_class, f"duplicate of {src.rel}: {f.message}")
        elif (force or not is_finished(j)) and is_finished(src):
            _copy_outputs(src, j)

    failures += [failed[j.rel] for j in jobs if j.rel in failed]
    failures.sort(key=lambda f: f.capture)
    rows: list[list[str]] = []
    for j in jobs:
        if j.rel in failed:
            continue
        src = dup_of.get(j.rel)
        try:
            rows += _read_rows(j, src.rel if src else "")
        except (OSError, InputFileError) as exc:
            failures.append(Failure(j.rel, type(exc).__name__, str(exc)))
    write_csv(out / "summary.csv", SUMMARY_COLUMNS, rows)
    write_csv(out / "failures.csv", FAILURE_COLUMNS,
              ([f.capture, f.error_class, f.message] for f in failures))
    if interrupted:
        n_done = len(computed) + len(skipped)
        raise BatchInterrupted(f"interrupted: {n_done} of {len(originals)} captures finished; "
                               f"{out / 'summary.csv'} and failures.csv list them")
    return BatchResult(
        summary=[_typed(r) for r in rows], failures=failures, captures=[j.rel for j in jobs],
        computed=sorted(computed), skipped=skipped, duplicates=duplicates,
        worker_stats=worker_stats, elapsed_s=time.perf_counter() - t0,
    )


class BatchInterrupted(KeyboardInterrupt):
    """A batch stopped by Ctrl-C/SIGINT after writing summary.csv and failures.csv."""


__all__ = [
    "BatchError", "BatchInterrupted", "BatchResult", "Failure", "Job", "Settings",
    "discover_captures",
    "init_worker", "is_finished", "process_capture", "run_batch",
]
