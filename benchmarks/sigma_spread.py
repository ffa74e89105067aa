"""Does a method's stated σ match the spread of its answers? Noise draws of one 12-source scene.

The 12-source scene of ``benchmarks/focus_grid.py --scene12`` (one system and focus) is
rendered once without sensor noise and with many rays a source (``--rays``, default 8 M: the
renderer's own ray noise ~3× below the photon noise of the faintest source). Then ``--draws``
captures are made from it by drawing the sensor's noise the way ``lfcam.sim.sensor`` does
(Poisson electrons at 20 000 e full well, 3 e read noise, rounded, clipped at 0), and each is
measured with ``run_distance(method=--method, model="exact")``. Per source it prints the
mean error, the standard deviation of the answers over the draws, the mean stated σ and
their ratio (spread / σ: 1 is an honest σ, > 1 an understated one).

With 8 draws the spread itself is known to ~±25 %: ratios of 0.75–1.33 are consistent with 1.

Run::

    python benchmarks/sigma_spread.py --system system1 --focus inf --draws 8
    python benchmarks/sigma_spread.py --system system1 --focus inf --draws 8 --method lightfield

Cost: one render (~40 s at 8 M rays) and per draw one capture's measurement (lenslet ~2 s,
lightfield ~100 s on system 1).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import focus_grid as fg  # noqa: E402

from lfcam.sim.scene import scene_from_dict  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--system", default="system1")
    ap.add_argument("--focus", default="inf", help="focus distance, mm, or inf")
    ap.add_argument("--draws", type=int, default=8)
    ap.add_argument("--rays", type=int, default=8_000_000, help="rays per source")
    ap.add_argument("--method", default="lenslet", choices=("lenslet", "lightfield"))
    ap.add_argument("--cache", type=Path, default=Path("/tmp/lfcam_focus_grid_cache"),
                    help="calibrations of the rendered whites (as focus_grid.py)")
    args = ap.parse_args()
    fg.METHOD[0] = args.method
    args.cache.mkdir(parents=True, exist_ok=True)
    cam = fg.Camera(args.system, float(args.focus), None, args.cache, False)
    grid = [(fx, fy) for fy in (-0.45, 0.0, 0.45) for fx in (-0.6, -0.2, 0.2, 0.6)]
    near, far = fg.scene12_distances(cam)
    dists = [near[k // 2] if k % 2 == 0 else far[k // 2] for k in range(12)]
    objects = []
    for (fx, fy), ad in zip(grid, dists, strict=True):
        xy = np.array([fx, fy]) * cam.half_field_mm
        objects.append({"type": "point", "distance_mm": ad,
                        "position_mm": cam.position(ad, xy)})
    quiet = {"photon_noise": False, "full_well_e": fg.NOISE["full_well_e"],
             "read_noise_e": 0.0}
    t0 = time.perf_counter()
    raw, _, truth = fg.simulate(cam.base, scene_from_dict(
        {"seed": 4, "rays_per_source": args.rays, "sensor": quiet, "exposure": {"peak": 0.8},
         "camera": cam.cam, "objects": objects}))
    print(f"# noise-free render: {time.perf_counter() - t0:.0f} s", flush=True)
    top = cam.used.sensor.white_level
    gain = top / fg.NOISE["full_well_e"]  # digital numbers per electron
    electrons = raw.astype(np.float64) / gain
    rng = np.random.default_rng(1)
    answers: dict[float, list[tuple[float, float]]] = {ad: [] for ad in dists}
    for t in range(args.draws):
        e = rng.poisson(electrons) + rng.normal(0.0, fg.NOISE["read_noise_e"], electrons.shape)
        img = np.clip(np.rint(e * gain), 0, top)
        results, _, wall, _ = cam.measure(img)
        for ad, src in zip(dists, truth["sources"], strict=True):
            hit = fg.nearest(results, src["centroid_px"])
            if hit is not None and hit.status == "ok":
                answers[ad].append((100.0 * (hit.distance_mm / ad - 1.0),
                                    100.0 * hit.uncertainty_mm / hit.distance_mm))
        print(f"# draw {t + 1}/{args.draws}: {wall:.0f} s", flush=True)
    print(f"\n{args.system}, focus {args.focus}, {args.method}, {args.draws} noise draws")
    print("| source (mm) | side | answered | mean error % | spread % | mean σ % | spread / σ |")
    print("|---|---|---|---|---|---|---|")
    for ad in sorted(dists):
        a = np.array(answers[ad])
        if len(a) < 2:
            print(f"| {ad:.0f} | {cam.side(ad)} | {len(a)} | — | — | — | — |")
            continue
        spread, sig = float(a[:, 0].std(ddof=1)), float(a[:, 1].mean())
        print(f"| {ad:.0f} | {cam.side(ad)} | {len(a)} | {a[:, 0].mean():+.3f} | {spread:.3f} "
              f"| {sig:.3f} | {spread / sig if sig > 0 else math.inf:.2f} |")


if __name__ == "__main__":
    main()
