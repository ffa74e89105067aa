"""Benchmark: white-image calibration of touching / overlapping micro-images, old vs new.

Cases (full size; images cached in $TMPDIR after the first run):

* ``illum-touching`` — 7728×5368 hex, pitch 14.29 px, disc radius 0.46 pitch with erfc edges
  (σ 0.5 px), 45 % radial vignetting, shot + 3 e⁻ read noise (``benchmarks/whites.py``).
* ``illum-dark-gap`` — the dark-gap Illum-size image of ``benchmarks/calibrate.py``
  (``lfcam.calibrate.synthetic``; takes the circle window, unchanged code path).
* ``f01-touching`` — 3280×3280 hex, pitch 9.9 px, otherwise as ``illum-touching``.
* ``system2-full`` — the renderer's (``lfcam.sim``) system 2 white at its full 1536² sensor,
  hex, photon + read noise: overlapping micro-images (R ≈ 0.55 pitch).

Truth: generator cases — the centroid of each fully visible lens's own noise-free light;
rendered case — ``lenses.centroid_px`` of the lenses the renderer marks ``complete``.
Columns: wall and CPU time of ``prepare_white`` + ``find_centres`` (measured inside a fresh
subprocess, so both implementations pay the same imports and first-touch costs; image
generation excluded), centre RMS / max error (px) over matched truth lenses (one-to-one
nearest neighbour within pitch/4), found / fully visible, missed, invented (returned centres
farther than pitch/4 from every lens that lights the sensor).

"old" is the code at ``--baseline`` (default: the commit before the fast own-light fit),
extracted with ``git archive`` into a temporary directory; "new" is a copy of this working
tree's ``lfcam`` taken at the start.
Both run in the same invocation on the same image, each first once untimed (its compiled
kernels' disk cache: the extracted old code has none and would compile inside its first
timed run; ``--cold`` skips that), then the new code ``--repeats`` times (with
``--old-repeats`` the old code as often, the two alternating).

``--critical-path`` adds an idle-machine wall-time estimate for 2 threads from CPU times
(:func:`critical_path`; for a loaded machine); ``--plenopticam PYTHON`` runs PlenoptiCam's
``LfpCalibrator`` on each case too (``benchmarks/plenopticam_driver.py``, micro-image size
preset to the pitch by default), scored the same way; "vs new wall" is each row's wall time
over the new code's (the median of its runs).

Run:  python benchmarks/calibrate_touching.py [--cases illum-touching f01-touching ...]
      [--skip-old] [--baseline REV] [--repeats N] [--old-repeats] [--cold] [--critical-path]
      [--plenopticam PYTHON]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

BASELINE = "7706da8"
CASES = ("illum-touching", "illum-dark-gap", "f01-touching", "system2-full")


def worker(impl_root: str, image_path: str, out_path: str) -> None:
    """Subprocess body: calibrate one image with the lfcam found at ``impl_root``."""
    sys.path.insert(0, impl_root)
    from lfcam.calibrate import prepare_white
    from lfcam.calibrate.grid import find_centres

    image = np.load(image_path)
    c0, t0 = time.process_time(), time.perf_counter()
    img, _ = prepare_white(image)
    fit = find_centres(img)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    crit = critical_path(image) if os.environ.get("LFCAM_BENCH_CRITICAL") else {}
    np.savez(out_path, centres=fit.centres_px, wall=wall, cpu=cpu, pitch=fit.pitch_px,
             method=fit.diagnostics.get("centroid_method", "?"),
             crit=np.array([crit.get(t, np.nan) for t in (1, 2, 4)]))


def critical_path(image: np.ndarray) -> dict:
    """Idle-machine wall-time estimate of ``prepare_white`` + ``find_centres`` for 1, 2 and 4
    threads, measured on a loaded machine.

    The calibration runs once more, single-threaded (OpenCV too), with
    :mod:`lfcam.calibrate.parallel`'s chunk and band runners replaced by serial ones that
    record each chunk's thread CPU time. Estimate = CPU outside those loops + for each loop
    the makespan of its chunks on T threads (longest first, greedy). CPU time is what other
    processes on the machine do not inflate (much); the estimate ignores memory-bandwidth
    contention between the threads, so it is a lower bound of the idle wall time.
    Empty when the code at hand has no ``lfcam.calibrate.parallel``.
    """
    try:
        import lfcam.calibrate.parallel as par
    except ImportError:
        return {}
    import cv2

    import lfcam.calibrate.grid as grid_mod
    import lfcam.calibrate.image as image_mod
    import lfcam.calibrate.microimage as micro_mod

    calls: list[list[float]] = []

    def chunks(fn, n, chunk):
        out, ts = [], []
        for s in range(0, n, chunk):
            t = time.thread_time()
            out.append(fn(slice(s, min(n, s + chunk))))
            ts.append(time.thread_time() - t)
        calls.append(ts)
        return out

    def bands(fn, height, min_rows=256):
        nb = max(1, min(2 * 2, height // max(1, min_rows)))  # as run_bands with 2 threads
        edges = [round(i * height / nb) for i in range(nb + 1)]
        out, ts = [], []
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            t = time.thread_time()
            out.append(fn(a, b))
            ts.append(time.thread_time() - t)
        calls.append(ts)
        return out

    def makespan(ts: list[float], threads: int) -> float:
        load = [0.0] * threads
        for x in sorted(ts, reverse=True):
            load[int(np.argmin(load))] += x
        return max(load)

    cv2.setNumThreads(1)
    for mod in (par, micro_mod):
        if hasattr(mod, "run_chunks"):
            mod.run_chunks = chunks
    for mod in (par, grid_mod, image_mod):
        if hasattr(mod, "run_bands"):
            mod.run_bands = bands
    t0 = time.thread_time()
    img, _ = image_mod.prepare_white(image)
    grid_mod.find_centres(img)
    total = time.thread_time() - t0
    looped = sum(sum(c) for c in calls)
    return {t: total - looped + sum(makespan(c, t) for c in calls) for t in (1, 2, 4)}


def load(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Image, truth centres of the fully visible lenses, positions of every lit lens."""
    from lfcam.calibrate.grid import fit_similarity

    if name in ("illum-touching", "f01-touching"):
        from whites import load_case

        sw = load_case(name)
        return sw.image, sw.centres_px, _lattice_nodes(sw.image.shape, sw.indices,
                                                       sw.lattice_px, sw.grid)
    if name == "illum-dark-gap":
        from calibrate import load_image

        image, truth, idx = load_image()
        hmat, *_ = fit_similarity(idx, truth, "hex")
        return image, truth, _lattice_nodes(image.shape, idx, truth, "hex", hmat)
    if name == "system2-full":
        cache = Path(tempfile.gettempdir()) / "lfcam_bench_system2_full_hex_v1.npz"
        if not cache.exists():
            from calibrate_rendered import render

            t = time.perf_counter()
            image, truth = render("system2", "hex", 0.0, (0.0, 0.0), True, None)
            lenses = truth["lenses"]
            np.savez(cache, image=image, centroid=np.asarray(lenses["centroid_px"], float),
                     complete=np.asarray(lenses["complete"], bool))
            print(f"system2-full rendered in {time.perf_counter() - t:.0f} s", flush=True)
        z = np.load(cache)
        lit = z["centroid"][np.isfinite(z["centroid"]).all(axis=1)]
        return z["image"], z["centroid"][z["complete"]], lit
    raise ValueError(name)


def _lattice_nodes(shape, idx, pts, grid, hmat=None) -> np.ndarray:
    """Every lattice node within one pitch of the sensor (the lenses that can light it)."""
    from lfcam.calibrate.grid import apply_homography, fit_similarity

    if hmat is None:
        hmat, *_ = fit_similarity(idx, pts, grid)
    lo, hi = idx.min(axis=0) - 3, idx.max(axis=0) + 3
    gi, gj = np.mgrid[lo[0]:hi[0] + 1, lo[1]:hi[1] + 1]
    nodes = apply_homography(hmat, np.column_stack([gi.ravel(), gj.ravel()]))
    h, w = shape
    pitch = float(np.sqrt(abs(np.linalg.det(hmat[:2, :2]))))
    keep = ((nodes[:, 0] > -pitch) & (nodes[:, 0] < w + pitch) & (nodes[:, 1] > -pitch)
            & (nodes[:, 1] < h + pitch))
    return nodes[keep]


def match_one_to_one(centres: np.ndarray, truth: np.ndarray, lim: float):
    """Pair centres with truth points that are each other's nearest neighbour within ``lim``.

    Returns
    -------
    matched : (N,) bool
        Per centre: paired.
    index : (N,) int
        Per centre: its nearest truth point.
    err : (M,) float
        Distance of every pair (px).
    """
    dc, ic = cKDTree(truth).query(centres)
    _, it = cKDTree(centres).query(truth)
    matched = (dc < lim) & (it[ic] == np.arange(len(centres)))
    err = np.hypot(*(centres[matched] - truth[ic[matched]]).T)
    return matched, ic, err


def score(centres: np.ndarray, truth: np.ndarray, lit: np.ndarray, pitch: float) -> dict:
    """Match returned centres to truth one-to-one (nearest neighbour within pitch/4)."""
    lim = 0.25 * pitch
    matched, _, err = match_one_to_one(centres, truth, lim)
    d_lit, _ = cKDTree(lit).query(centres)
    return {"found": int(matched.sum()), "truth": len(truth), "pitch": pitch,
            "missed": int(len(truth) - matched.sum()),
            "invented": int(np.sum(d_lit > lim)),
            "rms": float(np.sqrt(np.mean(err**2))) if err.size else float("nan"),
            "max": float(err.max()) if err.size else float("nan")}


def run(impl_root: Path, image_file: Path) -> dict:
    """Calibrate in a fresh subprocess; returns its saved result."""
    with tempfile.TemporaryDirectory(prefix="lfcam_bt_") as tmp:
        out = Path(tmp) / "out.npz"
        subprocess.run([sys.executable, __file__, "--worker", str(impl_root), str(image_file),
                        str(out)], check=True, env={**os.environ, "PYTHONPATH": ""})
        z = np.load(out)
        return {k: z[k] for k in z.files}


def main() -> None:
    """Print the old-vs-new table."""
    if len(sys.argv) == 5 and sys.argv[1] == "--worker":
        worker(*sys.argv[2:])
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    ap.add_argument("--baseline", default=BASELINE, help="git revision of the old code")
    ap.add_argument("--skip-old", action="store_true", help="run the new code only")
    ap.add_argument("--repeats", type=int, default=1, help="runs of the new code per case")
    ap.add_argument("--old-repeats", action="store_true",
                    help="as many runs of the old code, alternating with the new")
    ap.add_argument("--cold", action="store_true",
                    help="no discarded first run per implementation and case (the old code, "
                         "extracted afresh, then compiles its kernels inside its first timed "
                         "runs)")
    ap.add_argument("--critical-path", action="store_true",
                    help="also estimate the idle-machine wall time (see critical_path)")
    ap.add_argument("--plenopticam", metavar="PYTHON",
                    help="interpreter of a venv with plenopticam installed; runs it on each case")
    ap.add_argument("--plenopticam-m", default="pitch", metavar="M",
                    help="micro-image size handed to PlenoptiCam: 'pitch' (the case's pitch, "
                         "rounded), 'auto' (its own estimate) or pixels")
    ap.add_argument("--plenopticam-timeout", type=float, default=1800.0, metavar="S")
    args = ap.parse_args()
    if args.critical_path:
        os.environ["LFCAM_BENCH_CRITICAL"] = "1"

    with (tempfile.TemporaryDirectory(prefix="lfcam_old_") as old_root,
          tempfile.TemporaryDirectory(prefix="lfcam_new_") as new_root):
        # snapshot of the working tree, so that editing it during the run changes nothing
        shutil.copytree(ROOT / "lfcam", Path(new_root) / "lfcam")
        impls = [("new", Path(new_root))]
        if not args.skip_old:
            archive = subprocess.run(["git", "-C", str(ROOT), "archive", args.baseline, "lfcam"],
                                     check=True, capture_output=True).stdout
            subprocess.run(["tar", "-x", "-C", old_root], input=archive, check=True)
            impls.insert(0, (f"old ({args.baseline})", Path(old_root)))
        rows = []
        for name in args.cases:
            image, truth, lit = load(name)
            with tempfile.TemporaryDirectory(prefix="lfcam_bt_img_") as tmp:
                image_file = Path(tmp) / "image.npy"
                np.save(image_file, image)
                if not args.cold:
                    for _label, root in impls:
                        run(root, image_file)  # (discarded: compiles or loads the caches)
                order = [(label, root) for rep in range(args.repeats) for label, root in
                         (impls if rep % 2 == 0 else impls[::-1])
                         if label == "new" or rep == 0 or args.old_repeats]
                for label, root in order:
                    r = run(root, image_file)
                    s = score(r["centres"], truth, lit, float(r["pitch"]))
                    crit = r["crit"] if "crit" in r else np.full(3, np.nan)
                    rows.append((name, label, str(r["method"]), float(r["wall"]),
                                 float(r["cpu"]), s, crit))
                    print(f"{name} {label}: {float(r['wall']):.1f} s wall, "
                          f"{float(r['cpu']):.1f} s CPU, critical path 2 threads "
                          f"{crit[1]:.1f} s, rms {s['rms']:.4f}, "
                          f"load {os.getloadavg()[0]:.1f}", flush=True)
            if args.plenopticam:
                from calibrate import run_plenopticam

                m_px = (str(int(round(float(rows[-1][5]["pitch"]))))
                        if args.plenopticam_m == "pitch" else args.plenopticam_m)
                pc = run_plenopticam(args.plenopticam, image, "area", m_px,
                                     args.plenopticam_timeout)
                if "error" in pc:
                    rows.append((name, f"PlenoptiCam M={m_px}", pc["error"], np.nan, np.nan,
                                 None, np.full(3, np.nan)))
                else:
                    cen = np.asarray(pc["centres_xy"], float).reshape(-1, 2)
                    s = (score(cen, truth, lit, float(rows[-1][5]["pitch"])) if len(cen)
                         else {"found": 0, "truth": len(truth), "missed": len(truth),
                               "invented": 0, "rms": np.nan, "max": np.nan})
                    rows.append((name, f"PlenoptiCam M={m_px}", "area",
                                 float(pc["total_s"]), np.nan, s, np.full(3, np.nan)))
                print(f"{name} PlenoptiCam: {rows[-1][3]:.1f} s, {rows[-1][2]}, load "
                      f"{os.getloadavg()[0]:.1f}", flush=True)

    print(f"\ncores {os.cpu_count()}, load avg (1 min) at the end {os.getloadavg()[0]:.2f}")
    fmt = ("{:<15} {:<19} {:<18} {:>8} {:>8} {:>9} {:>12} {:>8} {:>8} {:>15} {:>6} "
           "{:>8}")
    print(fmt.format("case", "code", "method", "wall s", "CPU s", "crit. 2t", "vs new wall",
                     "RMS px", "max px", "found/visible", "missed", "invented"))
    for name, label, method, wall, cpu, s, crit in rows:
        new = [r for r in rows if r[0] == name and r[1] == "new"]
        ratio = (f"{wall / float(np.median([r[3] for r in new])):.1f}x"
                 if new and label != "new" else "-")
        if s is None:
            print(fmt.format(name, label, method[:18], "-", "-", "-", "-", "-", "-", "-", "-",
                             "-"))
            continue
        print(fmt.format(name, label, method[:18], f"{wall:.1f}", f"{cpu:.1f}",
                         f"{crit[1]:.1f}", ratio, f"{s['rms']:.4f}", f"{s['max']:.4f}",
                         f"{s['found']}/{s['truth']}", s["missed"], s["invented"]))


if __name__ == "__main__":
    main()
