"""Throughput of ``lfcam batch``: captures per minute on 1 and 2 workers, local and Dask.

Run: ``python benchmarks/batch.py [--captures 8] [--fast]`` from the repository root.
Builds a folder of distinct synthetic system-2 captures (``data/synthetic``), then times a
whole batch (``force=True``, fresh output folder) for: the local default with 1 worker (in
process) and 2 worker processes, and a ``dask.distributed.LocalCluster`` with 1 and 2 worker
processes (cluster start-up not timed; worker set-up — calibration, geometry — is). Scaling
efficiency = rate(2 workers) / (2 × rate(1 worker)) of the same back-end. Wall time includes
discovery, hashing, summary writing and the one-off geometry preparation in each worker.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

# one core a worker everywhere, the in-process 1-worker baseline included (Dask and the local
# pool set the same for their worker processes)
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from lfcam.batch import run_batch  # noqa: E402

DATA = ROOT / "data" / "synthetic"
CALIB = DATA / "calib_system2.json"


def make_folder(dst: Path, n: int) -> list[str]:
    """``n`` distinct system-2 point captures (with their profile sidecars)."""
    names = sorted(p.name[:-4] for p in DATA.glob("point_system2_*mm_dh*.png")
                   if int(p.name.split("_")[2][:-2]) >= 1500)[:n]
    for name in names:
        shutil.copyfile(DATA / f"{name}.png", dst / f"{name}.png")
        shutil.copyfile(DATA / f"{name}.profile.toml", dst / f"{name}.profile.toml")
    return names


def timed(src: Path, out: Path, fast: bool, **kw) -> float:
    t0 = time.perf_counter()
    res = run_batch(src, CALIB, out, fast=fast, force=True, progress=False, **kw)
    dt = time.perf_counter() - t0
    if res.failures or len(res.computed) != len(res.captures):
        raise SystemExit(f"benchmark batch failed: {res.failures}")
    return dt


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--captures", type=int, default=8)
    ap.add_argument("--fast", action="store_true", help="triangulation only (default: full fit)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="lfcam-bench-batch-") as tmp:
        src = Path(tmp) / "in"
        src.mkdir()
        n = len(make_folder(src, args.captures))
        rows = []
        for w in (1, 2):
            dt = timed(src, Path(tmp) / f"local{w}", args.fast, workers=w)
            rows.append(("local", w, dt))
        try:
            from dask.distributed import LocalCluster
        except ImportError:
            print("dask.distributed not installed: LocalCluster rows skipped", file=sys.stderr)
        else:
            for w in (1, 2):
                with LocalCluster(n_workers=w, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
                    dt = timed(src, Path(tmp) / f"dask{w}", args.fast,
                               scheduler=cluster.scheduler_address)
                rows.append(("dask LocalCluster", w, dt))
    mode = "fast (triangulation only)" if args.fast else "full light-field fit"
    print(f"lfcam batch: {n} captures, system 2 (1536x1536 px), {mode}; "
          f"{os.cpu_count()} cores, load average before run {os.getloadavg()[0]:.2f}")
    print(f"{'back-end':<18} {'workers':>7} {'wall s':>8} {'captures/min':>13} "
          f"{'efficiency':>10}")
    base = {}
    for backend, w, dt in rows:
        rate = 60.0 * n / dt
        if w == 1:
            base[backend] = rate
        eff = rate / (w * base[backend])
        print(f"{backend:<18} {w:>7} {dt:>8.1f} {rate:>13.1f} {eff:>10.0%}")


if __name__ == "__main__":
    main()
