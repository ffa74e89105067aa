"""The pixel fit on a clipped capture: its infinite-draw mean, and paired noise draws.

The 12-source scene of ``benchmarks/focus_grid.py --scene12`` (one system and focus) is
rendered once without sensor noise at ``--rays`` a source (cached in ``--workdir``). Then:

* ``--mean``: the capture's infinite-draw mean, ``E[max(0, μ + n)]`` per pixel (read noise
  only, as ``lfcam.sim.sensor`` draws it before clipping), and the unclipped render itself,
  are measured with the pixel fit (``measure_lightfield``) on the regions of one noisy draw:
  (unclipped, no floor model), (clipped, no floor model), (clipped, floor model). Noise-free:
  what is left is the fit's own error. ``--pupil N`` sets the pixel model's pupil samples
  (per side; default the fit's own), ``--behind-rays K`` the factor of the end of the fit
  behind focus.
* ``--draws N``: N paired noise draws (Poisson electrons at 20 000 e full well, 3 e read
  noise, rounded), each measured clipped without and with the floor model and unclipped
  (``run_distance(method="lightfield")``); per source the mean error ± its spread.

Run (docs/distance.md, "The clipped dark floor, and the pixel fit's own rays behind focus")::

    python benchmarks/clipped_floor.py --mean
    python benchmarks/clipped_floor.py --mean --pupil 360
    python benchmarks/clipped_floor.py --draws 8

Cost: the render ~1 min (8 M rays a source); ``--mean`` ~40 s; a draw ~1.5 min.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import focus_grid as fg  # noqa: E402

import lfcam.measure.lightfield as lightfield  # noqa: E402
import lfcam.measure.pointfit as pointfit  # noqa: E402
from lfcam.measure.lenslets import lenslet_stats  # noqa: E402
from lfcam.measure.noise import NoiseModel, clipped_mean  # noqa: E402
from lfcam.measure.regions import find_regions, nearby_regions  # noqa: E402
from lfcam.sim.scene import scene_from_dict  # noqa: E402


def render(cam, rays: int, workdir: Path, name: str):
    """The noise-free 12-source capture (DN) and its truth, cached as ``name``."""
    key = workdir / f"scene12_{name}_{rays}.npz"
    grid = [(fx, fy) for fy in (-0.45, 0.0, 0.45) for fx in (-0.6, -0.2, 0.2, 0.6)]
    near, far = fg.scene12_distances(cam)
    dists = [near[k // 2] if k % 2 == 0 else far[k // 2] for k in range(12)]
    objects = [{"type": "point", "distance_mm": ad,
                "position_mm": cam.position(ad, np.array([fx, fy]) * cam.half_field_mm)}
               for (fx, fy), ad in zip(grid, dists, strict=True)]
    if key.exists():
        z = np.load(key)
        return z["raw"], json.loads(str(z["truth"]))
    quiet = {"photon_noise": False, "full_well_e": fg.NOISE["full_well_e"], "read_noise_e": 0.0}
    raw, _, truth = fg.simulate(cam.base, scene_from_dict(
        {"seed": 4, "rays_per_source": rays, "sensor": quiet, "exposure": {"peak": 0.8},
         "camera": cam.cam, "objects": objects}))
    np.savez(key, raw=raw, truth=json.dumps(truth, default=float))
    return raw, truth


def noisy(raw: np.ndarray, dn_per_e: float, top: float, seed: int, clip: bool) -> np.ndarray:
    """One draw of the sensor's noise (``lfcam.sim.sensor``), clipped at 0 or not."""
    rng = np.random.default_rng(seed)
    e = rng.poisson(raw / dn_per_e) + rng.normal(0.0, fg.NOISE["read_noise_e"], raw.shape)
    img = np.minimum(np.rint(e * dn_per_e), top)
    return np.maximum(img, 0.0) if clip else img


REAL_NOISE = lightfield.capture_noise


def floor_switch(on: bool) -> None:
    """The pixel fit's floor model on or off (the capture's noise model otherwise as is)."""
    def patched(*a, **k):
        model = REAL_NOISE(*a, **k)
        return replace(model, clipped=model.clipped and on)

    lightfield.capture_noise = patched


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--system", default="system2")
    ap.add_argument("--focus", default="1000", help="focus distance, mm, or inf")
    ap.add_argument("--rays", type=int, default=8_000_000, help="rays per source")
    ap.add_argument("--mean", action="store_true", help="the infinite-draw mean")
    ap.add_argument("--draws", type=int, default=0, help="paired noise draws")
    ap.add_argument("--pupil", type=int, default=0, help="pixel model pupil samples a side")
    ap.add_argument("--behind-rays", type=int, default=0, help="BEHIND_FOCUS_RAYS")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/lfcam_focus_grid_cache"),
                    help="calibrations of the rendered whites (as focus_grid.py)")
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/lfcam_clipped_floor"))
    args = ap.parse_args()
    if args.pupil:
        pointfit.IMAGE_PUPIL_SAMPLES = args.pupil
    if args.behind_rays:
        pointfit.BEHIND_FOCUS_RAYS = args.behind_rays
    fg.METHOD[0] = "lightfield"
    args.cache.mkdir(parents=True, exist_ok=True)
    args.workdir.mkdir(parents=True, exist_ok=True)
    cam = fg.Camera(args.system, float(args.focus), None, args.cache, False)
    raw, truth = render(cam, args.rays, args.workdir, f"{args.system}_{args.focus}")
    top = float(cam.used.sensor.white_level)
    dn_per_e = top / fg.NOISE["full_well_e"]
    read = fg.NOISE["read_noise_e"] * dn_per_e
    sources = sorted(truth["sources"], key=lambda s: s["distance_mm"])
    if args.mean:
        mu = raw.astype(np.float64)
        mean = clipped_mean(mu, read)[0]
        draw = noisy(mu, dn_per_e, top, 100, True)
        regions = find_regions(lenslet_stats(draw, cam.geom.lmap), cam.geom.lmap,
                               cam.geom.pitch_px)
        nearby = dict(zip((r.region_id for r in regions), nearby_regions(regions), strict=True))
        print("| image, model | " + " | ".join(f"{s['distance_mm']:.0f}" for s in sources)
              + " |")
        print("|---" * (len(sources) + 1) + "|")
        for name, img, clipped in (("unclipped, no floor", mu, False),
                                   ("clipped, no floor", mean, False),
                                   ("clipped, floor", mean, True)):
            lightfield.capture_noise = lambda *a, _c=clipped, **k: NoiseModel(read, dn_per_e, _c)
            row = []
            for s in sources:
                x, y = s["centroid_px"]
                hit = [r for r in regions
                       if r.box_px[0] <= x < r.box_px[2] and r.box_px[1] <= y < r.box_px[3]]
                if not hit:
                    row.append("—")
                    continue
                m = lightfield.measure_lightfield(cam.used, cam.geom, img, hit[0], read, False,
                                                  nearby[hit[0].region_id])
                row.append(f"{100 * (m.distance_mm / s['distance_mm'] - 1):+.3f}")
            print(f"| {name} | " + " | ".join(row) + " |", flush=True)
    if args.draws:
        arms = (("clipped, no floor", True, False), ("clipped, floor", True, True),
                ("unclipped", False, True))
        errors = {a[0]: {s["distance_mm"]: [] for s in sources} for a in arms}
        for t in range(args.draws):
            for name, clip, floor in arms:
                floor_switch(floor)
                results, _, wall, _ = cam.measure(noisy(raw, dn_per_e, top, 100 + t, clip))
                for s in sources:
                    hit = fg.nearest(results, s["centroid_px"])
                    if hit is not None and hit.status == "ok":
                        errors[name][s["distance_mm"]].append(
                            100 * (hit.distance_mm / s["distance_mm"] - 1))
            print(f"# draw {t + 1}/{args.draws}", flush=True)
        print("| source (mm) | " + " | ".join(a[0] for a in arms) + " |")
        print("|---" * (len(arms) + 1) + "|")
        for s in sources:
            ad = s["distance_mm"]
            cells = []
            for name, _, _ in arms:
                e = np.array(errors[name][ad])
                cells.append(f"{e.mean():+.3f} ± {e.std(ddof=1):.3f} ({len(e)})" if len(e) > 1
                             else "—")
            print(f"| {ad:.0f} | " + " | ".join(cells) + " |")
    if not (args.mean or args.draws):
        print("nothing to do: --mean and/or --draws N")


if __name__ == "__main__":
    main()
