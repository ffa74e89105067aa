"""Benchmark: calibration time and accuracy on an Illum-size (7728×5368) hex white image.

The image comes from lfcam.calibrate.synthetic (disc micro-images, pitch 14.29 px, rotation
0.3°, natural + mechanical vignetting, shot + read noise, hot pixels) — not the project
renderer. Truth = each lens's own intensity centroid. Baselines, measured in the same run:
a plain per-lens Python loop of a windowed centroid on 2,000 lenses, extrapolated to all
lenses (what a non-vectorised refinement alone costs), and optionally PlenoptiCam's
white-image calibration (``LfpCalibrator``) run on the same image under its own interpreter.

Run:  python benchmarks/calibrate.py [--repeats 5]
      python benchmarks/calibrate.py --plenopticam /tmp/plenoenv/bin/python
(generation takes ~2 min once; cached in $TMPDIR). See docs/calibration.md for how to build
the throwaway PlenoptiCam environment (its pinned requirements do not resolve on 3.11).
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lfcam.calibrate import prepare_white  # noqa: E402
from lfcam.calibrate.grid import find_centres, fit_similarity  # noqa: E402
from lfcam.calibrate.synthetic import make_white  # noqa: E402

TARGET_S = 5.0
DRIVER = Path(__file__).resolve().with_name("plenopticam_driver.py")


def load_image() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cached Illum-size white image, its truth centres (x, y) and lattice indices."""
    cache = Path(tempfile.gettempdir()) / "lfcam_bench_illum_v1.npz"
    if cache.exists():
        z = np.load(cache)
        return z["image"], z["truth"], z["idx"]
    t = time.perf_counter()
    sw = make_white(7728, 5368, 14.29, grid="hex", rotation_rad=np.deg2rad(0.3),
                    offset_px=(3863.8, 2683.2), radius_frac=0.40, cats_eye=0.2,
                    vignetting=0.5, noise_electrons=True, read_noise=3.0,
                    hot_pixel_fraction=1e-5, rows_per_chunk=128)
    np.savez(cache, image=sw.image, truth=sw.centres_px, idx=sw.indices)
    print(f"generated in {time.perf_counter() - t:.1f} s (cached: {cache})")
    return sw.image, sw.centres_px, sw.indices


def score(centres: np.ndarray, truth: np.ndarray, hmat: np.ndarray, pitch_px: float) -> dict:
    """One-to-one nearest-neighbour match of found centres (x, y) to truth within pitch/2.

    A truth lens is *found* when its nearest centre lies within pitch/2 and that centre's
    nearest truth lens is this one. Unmatched centres within pitch/2 of a lattice node that is
    not in the truth set (a partly visible border lens) are *border* (not scored); every
    other unmatched centre (duplicates, off-lattice points) is *invented*. *Missed* = truth
    lenses (fully visible) without a match.
    """
    if len(centres) == 0:
        return {"found": 0, "rms": float("nan"), "max": float("nan"), "invented": 0,
                "missed": len(truth), "border": 0}
    lim = pitch_px / 2
    dt, it = cKDTree(centres).query(truth)
    dc, ic = cKDTree(truth).query(centres)
    k = np.arange(len(centres))
    matched = (dc < lim) & (it[ic] == k)
    err = centres[matched] - truth[ic[matched]]
    a, o = hmat[:2, :2], hmat[:2, 2]
    ij = np.rint(np.linalg.solve(a, (centres - o).T)).T
    node_d = np.linalg.norm(ij @ a.T + o - centres, axis=1)
    border = ~matched & (dc >= lim) & (node_d < lim)
    return {
        "found": int(matched.sum()),
        "rms": float(np.sqrt(np.mean(np.sum(err**2, axis=1)))) if len(err) else float("nan"),
        "max": float(np.max(np.hypot(*err.T))) if len(err) else float("nan"),
        "invented": int((~matched & ~border).sum()),
        "missed": int(len(truth) - matched.sum()),
        "border": int(border.sum()),
    }


def run_lfcam(image: np.ndarray, repeats: int) -> tuple[list[float], list[float], object, float,
                                                      list[float]]:
    """Time prepare_white + find_centres: one cold run, then ``repeats`` timed runs.

    Returns (timed totals, timed prepare times, last fit, cold first-run total, CPU seconds
    of the timed runs — all threads; wall ≫ CPU/threads means other load on the machine).
    """
    totals, preps, cpus, fit = [], [], [], None
    for r in range(-1, repeats):
        c0 = time.process_time()
        t0 = time.perf_counter()
        img, _ = prepare_white(image)
        t1 = time.perf_counter()
        fit = find_centres(img)
        t2 = time.perf_counter()
        cpus.append(time.process_time() - c0)
        totals.append(t2 - t0)
        preps.append(t1 - t0)
        what = "cold first run" if r < 0 else f"run {r + 1}/{repeats}"
        print(f"lfcam {what}: {t2 - t0:.2f} s wall, {cpus[-1]:.2f} s CPU, "
              f"load {os.getloadavg()[0]:.2f}", flush=True)
    return totals[1:], preps[1:], fit, totals[0], cpus[1:]


def peak_heap_mb(image: np.ndarray) -> float:
    """Peak traced (numpy/Python) heap of one extra, untimed calibration, in MB."""
    tracemalloc.start()
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    img, _ = prepare_white(image)
    find_centres(img)
    del img
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return (peak - base) / 2**20


def run_plenopticam(python: str, image: np.ndarray, method: str, m_px: str,
                    timeout_s: float) -> dict:
    """Run PlenoptiCam's LfpCalibrator on ``image`` in a subprocess; centres, times, memory."""
    with tempfile.TemporaryDirectory(prefix="lfcam_pcam_") as tmp:
        src, out = Path(tmp) / "white.npy", Path(tmp) / "out.npz"
        np.save(src, image)
        print(f"running PlenoptiCam ({python}, method {method}, M {m_px}, "
              f"timeout {timeout_s:.0f} s) ...", flush=True)
        t0 = time.perf_counter()
        try:
            proc = subprocess.run([python, str(DRIVER), str(src), str(out), method, m_px],
                                  timeout=timeout_s, cwd=tmp, stderr=subprocess.PIPE, text=True)
        except subprocess.TimeoutExpired:
            return {"error": f"timed out after {timeout_s:.0f} s"}
        except OSError as exc:
            return {"error": f"cannot start {python}: {exc}"}
        wall = time.perf_counter() - t0
        if proc.returncode != 0 or not out.exists():
            tail = (proc.stderr or "").strip().splitlines()[-1:] or ["no output"]
            return {"error": f"exit {proc.returncode}: {tail[0]}"}
        z = np.load(out)
        res = {k: z[k] for k in z.files}
    res["wall_s"] = wall
    # ru_maxrss of the largest waited-for child (KiB on Linux)
    res["maxrss_mb"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return res


def main() -> None:
    """Generate (or load) the image, calibrate, print the tables."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5,
                    help="timed lfcam repeats after one cold run (default 5)")
    ap.add_argument("--plenopticam", metavar="PYTHON",
                    help="interpreter of a venv with plenopticam installed; runs it too")
    ap.add_argument("--plenopticam-method", default="area",
                    help="PlenoptiCam cal_meth: area (its default), peak, grid-fit, ...")
    ap.add_argument("--plenopticam-timeout", type=float, default=1200.0, metavar="S")
    ap.add_argument("--plenopticam-m", action="append", metavar="M",
                    help="micro-image size (px) preset for PlenoptiCam, or 'auto' for its own "
                         "estimate; repeat to run several variants (default: auto)")
    ap.add_argument("--plenopticam-input", choices=("raw", "prepared"), default="raw",
                    help="image given to PlenoptiCam: the same raw image lfcam gets (default) "
                         "or the image after lfcam's hot-pixel removal")
    args = ap.parse_args()

    image, truth, idx = load_image()
    hmat, p_t, r_t, _ = fit_similarity(idx, truth, "hex")
    totals, preps, fit, cold_s, cpus = run_lfcam(image, max(1, args.repeats))
    heap_mb = peak_heap_mb(image)
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    img, n_hot = prepare_white(image)
    lf = score(fit.centres_px, truth, hmat, p_t)
    t_lf = float(np.mean(totals))

    c = fit.centres_px
    inner = (c.min(axis=1) > 20) & (c[:, 0] < img.shape[1] - 20) & (c[:, 1] < img.shape[0] - 20)
    sample = c[inner][:2000]
    h = 8
    ys, xs = np.mgrid[-h:h + 1, -h:h + 1]
    t3 = time.perf_counter()
    for x, y in sample:
        cx, cy = int(round(x)), int(round(y))
        for _ in range(4):
            patch = img[cy - h:cy + h + 1, cx - h:cx + h + 1]
            s = patch.sum()
            _ = (patch * xs).sum() / s, (patch * ys).sum() / s
    loop_s = (time.perf_counter() - t3) / len(sample) * len(fit.centres_px)

    pcs = []
    if args.plenopticam:
        src = img if args.plenopticam_input == "prepared" else image
        for m_px in args.plenopticam_m or ["auto"]:
            pcs.append((m_px, run_plenopticam(args.plenopticam, src, args.plenopticam_method,
                                              m_px, args.plenopticam_timeout)))

    reasons = sorted(set(fit.rejected_reason))
    spread = (f"median {np.median(totals):.2f}, min {min(totals):.2f}, max {max(totals):.2f}; "
              f"cold first run {cold_s:.2f}")
    ok = "MET" if t_lf <= TARGET_S else "MISSED"
    rows = [
        ("image", "7728x5368 hex, pitch 14.29 px (lfcam.calibrate.synthetic)"),
        ("lenses accepted / truth fully visible", f"{len(fit.centres_px)} / {len(truth)}"),
        ("rejected", ", ".join(f"{r} {fit.rejected_reason.count(r)}" for r in reasons)),
        ("centre RMS / max error (px)", f"{lf['rms']:.4f} / {lf['max']:.4f}"),
        ("pitch rel. error", f"{abs(fit.pitch_px - p_t) / p_t:.2e}"),
        ("rotation error (rad)", f"{abs(fit.rotation_rad - r_t):.2e}"),
        ("model / residual RMS (px)", f"{fit.model} / {fit.residual_rms_px:.4f}"),
        ("hot pixels replaced", f"{n_hot}"),
        ("time: prepare (s, mean)", f"{np.mean(preps):.2f}"),
        ("time: detect+refine+fit (s, mean)", f"{t_lf - np.mean(preps):.2f}"),
        (f"time: total (s, mean of {len(totals)} warm)", f"{t_lf:.2f}  ({spread})"),
        (f"target <= {TARGET_S:.0f} s (on the mean)", f"{ok}"),
        ("CPU time per run (s, mean, all threads)", f"{np.mean(cpus):.2f}"),
        ("peak traced heap of one run (MB)", f"{heap_mb:.0f}"),
        ("process max RSS (MB, incl. image+truth)", f"{rss_mb:.0f}"),
        ("baseline per-lens loop (s, extrap.)", f"{loop_s:.1f}  (ratio {loop_s / t_lf:.1f}x)"),
        ("cores / load avg (1 min)", f"{os.cpu_count()} / {os.getloadavg()[0]:.2f}"),
    ]
    w = max(len(a) for a, _ in rows)
    for a, b in rows:
        print(f"{a:<{w}}  {b}")

    print("\nmatch: one-to-one nearest neighbour within pitch/2; truth = "
          f"{len(truth)} fully visible lenses")
    head = ("tool", "time s", "ratio", "found", "RMS px", "invented", "missed", "border")
    fmt = "{:<28} {:>8} {:>7} {:>7} {:>8} {:>9} {:>7} {:>7}"
    print(fmt.format(*head))
    print(fmt.format("lfcam", f"{t_lf:.2f}", "1.0", lf["found"], f"{lf['rms']:.4f}",
                     lf["invented"], lf["missed"], lf["border"]))
    for m_px, pc in pcs:
        name = f"plenopticam M={m_px}"
        if "error" in pc:
            print(f"{name:<28} not run: {pc['error']}")
            continue
        for label, key in ((name, "centres_xy"), ("  refined, before sorting", "refined_xy")):
            s = score(pc[key], truth, hmat, p_t)
            final = key == "centres_xy"
            t = f"{float(pc['total_s']):.1f}" if final else "-"
            r = f"{float(pc['total_s']) / t_lf:.0f}x" if final else "-"
            print(fmt.format(label, t, r, s["found"], f"{s['rms']:.4f}", s["invented"],
                             s["missed"], s["border"]))
        stages = ", ".join(f"{n or '(blank)'} {float(x):.1f}" for n, x in
                           zip(pc["stage_names"], pc["stage_s"], strict=True))
        print(f"  stages (s): {stages}")
        print(f"  M used {int(pc['m_used'])} px; method {args.plenopticam_method}; input "
              f"{args.plenopticam_input}; tool error flag {bool(pc['tool_error'])}; subprocess "
              f"wall {pc['wall_s']:.1f} s (incl. imports, image load); max RSS of largest child "
              f"so far {pc['maxrss_mb']:.0f} MB; plenopticam {pc['version']}")


if __name__ == "__main__":
    main()
