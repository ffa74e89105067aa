"""Light-field decode and refocus speed at Lytro Illum size, with peak memory.

Run from the repository root:  python benchmarks/lightfield.py [--repeat 3]

Synthetic Illum-size input: a 7728 × 5368 RGGB mosaic (uint16, random texture) and a white
image, hex grid, pitch 14.29 px, rotation 2 mrad → 15 × 15 views of 541 × 434 lenses.
Baselines measured in the same run: one full-frame bilinear ``cv2.remap`` of the raw (the
least a resampling decoder must do) and a plain angular sum of the light field (a refocus at
shift 0 with no interpolation).
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
import tracemalloc
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lfcam.calibrate import Calibration  # noqa: E402
from lfcam.decode import decode, focal_stack, refocus, to_grey  # noqa: E402

W, H, PITCH = 7728, 5368, 14.29


def best(fn, repeat):
    times = []
    out = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--planes", type=int, default=30)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    raw16 = rng.integers(64, 1023, size=(H, W), dtype=np.uint16)
    yy, xx = np.mgrid[0:H:8, 0:W:8]
    white_small = (900 * (1 - 0.3 * ((xx / W - 0.5) ** 2 + (yy / H - 0.5) ** 2))).astype(np.float32)
    white16 = cv2.resize(white_small, (W, H)).astype(np.uint16)
    grid = Calibration.from_lattice("hex", PITCH, 0.002, (7.1, 6.4))

    t_grey, raw = best(lambda: to_grey(raw16, "RGGB", 64, 1023), args.repeat)
    white = to_grey(white16, "RGGB", 64, 1023)
    ix, iy = np.meshgrid(np.arange(W, dtype=np.float32) + 0.25,
                         np.arange(H, dtype=np.float32) + 0.25)
    t_base, _ = best(lambda: cv2.remap(raw, ix, iy, cv2.INTER_LINEAR), args.repeat)

    t_dec, _ = best(lambda: decode(raw, grid, white=white), args.repeat)
    tracemalloc.start()  # one decode alone: no earlier light field alive
    lf = decode(raw, grid, white=white)
    _, peak_dec = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    nv, nu, t_count, s_count = lf.data.shape

    t_sum, _ = best(lambda: (lf.data * lf.weight).sum(axis=(0, 1)), args.repeat)
    t_one, _ = best(lambda: refocus(lf, 0.37), args.repeat)
    shifts = np.linspace(-0.5, 1.0, args.planes)
    tracemalloc.start()
    t_stack, _ = best(lambda: focal_stack(lf, shifts), 1)
    _, peak_stack = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    n_valid = int(np.count_nonzero(lf.weight.any(axis=(2, 3))))
    print(f"light field {nv}x{nu} views ({n_valid} inside the lens disk) of {s_count}x{t_count} "
          "lenses (hex→rect), "
          f"raw {W}x{H}; best of {args.repeat}; {cv2.getNumThreads()} OpenCV threads")
    print(f"{'stage':34s} {'time s':>8s} {'baseline s':>10s} {'ratio':>7s} {'target':>8s}")
    rows = [
        ("demosaic RGGB + levels (to_grey)", t_grey, None, ""),
        ("decode (with white image)", t_dec, t_base, ""),
        ("refocus, one plane", t_one, t_sum, "<= 0.2 s"),
        ("demosaic + decode", t_grey + t_dec, t_base, "<= 3 s"),
        (f"focal stack, {args.planes} planes, per plane", t_stack / args.planes, t_sum,
         "<= 0.2 s"),
    ]
    for name, t, base, target in rows:
        b = f"{base:10.3f}" if base else f"{'':10s}"
        r = f"{t / base:7.1f}" if base else f"{'':7s}"
        print(f"{name:34s} {t:8.3f} {b} {r} {target:>8s}")
    print(f"peak traced memory: decode {peak_dec / 2**20:.0f} MB (light field + weights "
          f"{2 * lf.data.nbytes / 2**20:.0f} MB), focal stack {peak_stack / 2**20:.0f} MB; "
          f"process max RSS {rss_mb:.0f} MB (includes raw, white and baselines)")


if __name__ == "__main__":
    main()
