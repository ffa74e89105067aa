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
Both run in the same invocation, one after the other, on the same image.

Run:  python benchmarks/calibrate_touching.py [--cases illum-touching f01-touching ...]
      [--skip-old] [--repeats N]
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
    np.savez(out_path, centres=fit.centres_px, wall=wall, cpu=cpu, pitch=fit.pitch_px,
             method=fit.diagnostics.get("centroid_method", "?"))


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


def score(centres: np.ndarray, truth: np.ndarray, lit: np.ndarray, pitch: float) -> dict:
    """Match returned centres to truth one-to-one (nearest neighbour within pitch/4)."""
    lim = 0.25 * pitch
    dc, ic = cKDTree(truth).query(centres)
    _, it = cKDTree(centres).query(truth)
    matched = (dc < lim) & (it[ic] == np.arange(len(centres)))
    err = np.hypot(*(centres[matched] - truth[ic[matched]]).T)
    d_lit, _ = cKDTree(lit).query(centres)
    return {"found": int(matched.sum()), "truth": len(truth),
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
    args = ap.parse_args()

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
                for label, root in impls:
                    for _ in range(args.repeats if label == "new" else 1):
                        r = run(root, image_file)
                        s = score(r["centres"], truth, lit, float(r["pitch"]))
                        rows.append((name, label, str(r["method"]), float(r["wall"]),
                                     float(r["cpu"]), s))
                        print(f"{name} {label}: {float(r['wall']):.1f} s wall, "
                              f"{float(r['cpu']):.1f} s CPU, rms {s['rms']:.4f}, "
                              f"load {os.getloadavg()[0]:.1f}", flush=True)

    print(f"\ncores {os.cpu_count()}, load avg (1 min) at the end {os.getloadavg()[0]:.2f}")
    fmt = "{:<15} {:<15} {:<18} {:>8} {:>8} {:>7} {:>8} {:>8} {:>15} {:>6} {:>8}"
    print(fmt.format("case", "code", "method", "wall s", "CPU s", "ratio", "RMS px", "max px",
                     "found/visible", "missed", "invented"))
    for name, label, method, wall, cpu, s in rows:
        old = [r for r in rows if r[0] == name and r[1].startswith("old")]
        ratio = f"{old[0][3] / wall:.1f}x" if old and label == "new" else "-"
        print(fmt.format(name, label, method, f"{wall:.1f}", f"{cpu:.1f}", ratio,
                         f"{s['rms']:.4f}", f"{s['max']:.4f}", f"{s['found']}/{s['truth']}",
                         s["missed"], s["invented"]))


if __name__ == "__main__":
    main()
