"""Benchmark: calibration time and accuracy on an Illum-size (7728×5368) hex white image.

The image comes from lfcam.calibrate.synthetic (disc micro-images, pitch 14.29 px, rotation
0.3°, natural + mechanical vignetting, shot + read noise, hot pixels) — not the project
renderer. Truth = each lens's own intensity centroid. The baseline, measured in the same run,
is a plain per-lens Python loop of a windowed centroid on 2,000 lenses, extrapolated to all
lenses (what a non-vectorised refinement alone costs).

Run:  python benchmarks/calibrate.py   (generation takes ~2 min once; cached in $TMPDIR)
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lfcam.calibrate import prepare_white  # noqa: E402
from lfcam.calibrate.grid import find_centres, fit_similarity  # noqa: E402
from lfcam.calibrate.synthetic import make_white  # noqa: E402


def main() -> None:
    """Generate (or load) the image, calibrate, print the table."""
    cache = Path(tempfile.gettempdir()) / "lfcam_bench_illum_v1.npz"
    if cache.exists():
        z = np.load(cache)
        image, truth, idx = z["image"], z["truth"], z["idx"]
    else:
        t = time.perf_counter()
        sw = make_white(7728, 5368, 14.29, grid="hex", rotation_rad=np.deg2rad(0.3),
                        offset_px=(3863.8, 2683.2), radius_frac=0.40, cats_eye=0.2,
                        vignetting=0.5, noise_electrons=True, read_noise=3.0,
                        hot_pixel_fraction=1e-5, rows_per_chunk=128)
        image, truth, idx = sw.image, sw.centres_px, sw.indices
        np.savez(cache, image=image, truth=truth, idx=idx)
        print(f"generated in {time.perf_counter() - t:.1f} s (cached: {cache})")
    t0 = time.perf_counter()
    img, n_hot = prepare_white(image)
    t1 = time.perf_counter()
    fit = find_centres(img)
    t2 = time.perf_counter()

    d, i = cKDTree(fit.centres_px).query(truth)
    found = d < 1.0
    err = fit.centres_px[i[found]] - truth[found]
    d2, _ = cKDTree(truth).query(fit.centres_px)
    _, p_t, r_t, _ = fit_similarity(idx, truth, "hex")

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

    total = t2 - t0
    reasons = sorted(set(fit.rejected_reason))
    rows = [
        ("image", "7728x5368 hex, pitch 14.29 px (lfcam.calibrate.synthetic)"),
        ("lenses accepted / truth fully visible", f"{len(fit.centres_px)} / {len(truth)}"),
        ("lenses invented", f"{int((d2 > 1.0).sum())}"),
        ("rejected", ", ".join(f"{r} {fit.rejected_reason.count(r)}" for r in reasons)),
        ("centre RMS error (px)", f"{np.sqrt(np.mean(np.sum(err**2, axis=1))):.4f}"),
        ("pitch rel. error", f"{abs(fit.pitch_px - p_t) / p_t:.2e}"),
        ("rotation error (rad)", f"{abs(fit.rotation_rad - r_t):.2e}"),
        ("model / residual RMS (px)", f"{fit.model} / {fit.residual_rms_px:.4f}"),
        ("hot pixels replaced", f"{n_hot}"),
        ("time: prepare (s)", f"{t1 - t0:.2f}"),
        ("time: detect+refine+fit (s)", f"{t2 - t1:.2f}"),
        ("time: total (s)", f"{total:.2f}  (target <= 5 s)"),
        ("baseline per-lens loop (s, extrap.)", f"{loop_s:.1f}  (ratio {loop_s / total:.1f}x)"),
        ("cores", f"{os.cpu_count()}"),
    ]
    w = max(len(a) for a, _ in rows)
    for a, b in rows:
        print(f"{a:<{w}}  {b}")


if __name__ == "__main__":
    main()
