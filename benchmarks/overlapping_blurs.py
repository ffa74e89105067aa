"""Two point sources whose blurs overlap, from touching to nearly coincident: the distance run
with and without the cut of overlapping blurs (issue 17; docs/distance.md, "Blurs that
overlap without a waist (stop 68)").

Run: ``python benchmarks/overlapping_blurs.py [--system system2] [--distances 1400,1500]
[--focus 1000] [--aparts 5,6,...,18] [--seeds 7,8] [--size 1024] [--method lenslet]
[--renderer sim|independent] [--brightness 1] [--field-mm 0] [--first-line-mm 0]
[--second-line-mm 0] [--second-along] [--neighbours-in] [--refits N]``
(``--method lightfield``: ~20 s a capture)

Each capture holds two point sources ``apart`` × 1/1000 of their distance off the axis on
either side (with ``--first-line-mm L``, the first a line instead: L × its distance / 1000 mm
long across the pair's line, centred where the point would be, as bright in all; with
``--second-line-mm L``, the second a line too: L × its distance / 1000 mm long, across the
pair's line or, with ``--second-along``, along it (a T), as bright per mm as a first line of
that length), rendered by
:mod:`lfcam.sim` (10⁶ rays a source) or, with ``--renderer independent``, by
``benchmarks/render_independent.py`` (per-pixel irradiance of the exact ray map: no ray
binning, no :mod:`lfcam.sim`; a line by the midpoint rule over point renders along it,
``render_line``: ~1.5 min a 1 024² capture), both with the focus grid's sensor noise
(photon noise at a full well of 20 000 e⁻, 3 e⁻ read noise, brightest pixel at half of full
scale),
on the profile's own lenslet lattice (truth geometry), the fits told the full well.
:func:`lfcam.distance.run_distance` measures each capture twice on one core,
``SPLIT_OVERLAPS`` off and on: per region the nearest source, the status, the error and its
z (error / σ), and the region's CPU time. ``--neighbours-in``: both runs without touching
regions refitted on their moments less their neighbours' light (``NEIGHBOURS_OUT`` off:
docs/distance.md, "A touching blur's light taken out (stop 71)"). A summary counts the
answers within and over 3σ and the sources left unmeasured, each way.

``--refits N``: instead, each touching region whose neighbour's fitted light is over the
gate (``NEIGHBOURS_ABOVE``) refitted without it in this process, from scratch and from its
first answer (``measure_lenslet(start=…)``) alternately, ``N`` times each: per refit the
answer's error and z, the least CPU ms of the ``N`` and the model rays traced (a count that
does not depend on the machine's load) (docs/distance.md, "A refit from the first answer
(stop 72)").
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))  # render_independent

from lfcam import distance  # noqa: E402
from lfcam.camera import load_profile  # noqa: E402
from lfcam.measure import lenslet_stats  # noqa: E402
from lfcam.measure.noise import capture_noise  # noqa: E402
from lfcam.sim.capture import apply_overrides, simulate  # noqa: E402
from lfcam.sim.geometry import truth_geometry  # noqa: E402
from lfcam.sim.scene import scene_from_dict  # noqa: E402

NOISE = {"photon_noise": True, "full_well_e": 20000.0, "read_noise_e": 3.0}  # focus_grid's
PEAK = 0.5  # brightest pixel, share of full scale


def _floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v]


def measure(image, prof, geom, white, truth, method: str, split: bool) -> list[tuple]:
    """(source index, status, error %, z, CPU ms) of each region of one run."""
    distance.SPLIT_OVERLAPS = split
    run = distance.run_distance(image, prof, None, model="exact", method=method,
                                geometry=geom, jobs=1, white_value=white)
    cs = np.array([s["centroid_px"] for s in truth["sources"]])
    out = []
    for r, t in zip(run.regions, run.timings_s["region_s"], strict=True):
        k = int(np.argmin(np.hypot(*(cs - np.array([r.x_px, r.y_px])).T)))
        d = truth["sources"][k]["distance_mm"]
        ok = r.status == "ok"
        err = 100.0 * (r.distance_mm / d - 1.0) if ok else float("nan")
        z = (r.distance_mm - d) / r.uncertainty_mm if ok else float("nan")
        out.append((k, str(r.status), err, z, 1e3 * t))
    return out


def refits(image, prof, geom, truth, repeats: int) -> list[str]:
    """Each touching region over the gate refitted from scratch and from its first answer
    (module docstring): a cell each, ``source: kind error % (z), least ms, Mrays`` both ways."""
    from lfcam.measure import fastfit
    from lfcam.measure.regions import find_regions, nearby_regions

    stats = lenslet_stats(image, geom.lmap)
    regions = find_regions(stats, geom.lmap, geom.pitch_px)
    near = nearby_regions(regions)
    noise = distance.noise_sigma(image)
    first = [fastfit.measure_lenslet(prof, geom, image, r, noise, others=n)
             if r.touching and r.kind in ("spot", "line") else None
             for r, n in zip(regions, near, strict=True)]
    answers = [m if m is not None and m.status == "ok" else None for m in first]
    cs = np.array([s["centroid_px"] for s in truth["sources"]])
    cells = []
    with fastfit.counting_rays() as rays:
        for i, reg in enumerate(regions):
            own = answers[i]
            if own is None:
                continue
            sources = distance.touching_sources(i, regions, near, answers)
            if not sources:
                continue
            light = distance.light_to_take_out(prof, geom, image, reg, near[i], own, sources)
            if light is None:
                continue
            k = int(np.argmin(np.hypot(*(cs - np.array(reg.centroid_px)).T)))
            d = truth["sources"][k]["distance_mm"]
            spent = {False: [], True: []}
            got = {}
            for _ in range(max(repeats, 1)):
                for warm in (False, True):
                    rays[0] = 0
                    c0 = time.process_time()
                    m = fastfit.measure_lenslet(prof, geom, image, reg, noise, others=near[i],
                                                light=light, start=own if warm else None)
                    spent[warm].append(time.process_time() - c0)
                    got[warm] = (m, rays[0])
            parts = []
            for warm in (False, True):
                m, n_rays = got[warm]
                ans = (f"{m.kind} {100.0 * (m.distance_mm / d - 1.0):+.3f} % "
                       f"({(m.distance_mm - d) / m.sigma_distance_mm:+.1f}σ)"
                       if m.status == "ok" else str(m.status))
                parts.append(f"{ans}, {1e3 * min(spent[warm]):.0f} ms, {n_rays / 1e6:.2f} Mrays")
            cells.append(f"{k}: " + " → ".join(parts))
    return cells


def render(base, prof, camera: dict, objects: list[dict], seed: int, renderer: str,
           top: int) -> tuple[np.ndarray, dict]:
    """One capture (digital units, black level off) and its truth: the sources' distances and
    light centroids."""
    if renderer == "independent":
        from render_independent import render_capture

        # (its schema is lfcam.sim's: points and lines alike)
        img, truth = render_capture(prof, objects, seed=seed, peak=PEAK,
                                    full_well_e=NOISE["full_well_e"],
                                    read_noise_e=NOISE["read_noise_e"],
                                    bit_depth=prof.sensor.bit_depth)
        return img * top - prof.sensor.black_level, truth
    scene = {"seed": seed, "rays_per_source": 1_000_000, "camera": camera, "sensor": NOISE,
             "exposure": {"peak": PEAK}, "objects": objects}
    raw, used, truth = simulate(base, scene_from_dict(scene))
    return raw.astype(np.float64) - used.sensor.black_level, truth


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--system", default="system2")
    ap.add_argument("--distances", default="1400,1500", help="the two sources' distances, mm")
    ap.add_argument("--focus", type=float, default=1000.0, help="focused distance, mm")
    ap.add_argument("--aparts", default="5,6,7,8,9,10,11,12,13,14,15,16,17,18",
                    help="offsets off the axis, 1/1000 of the distance, each side")
    ap.add_argument("--seeds", default="7,8", help="render seeds (rays and noise)")
    ap.add_argument("--size", type=int, default=1024, help="sensor side, px")
    ap.add_argument("--method", default="lenslet", choices=("lenslet", "lightfield", "auto"))
    ap.add_argument("--renderer", default="sim", choices=("sim", "independent"))
    ap.add_argument("--brightness", type=float, default=1.0,
                    help="the second source's intensity over the first's")
    ap.add_argument("--field-mm", type=float, default=0.0,
                    help="both sources this far off the axis across the pair's line (x), "
                         "1/1000 of their distance each, mm at 1 m")
    ap.add_argument("--first-line-mm", type=float, default=0.0,
                    help="the first source a line this long at 1 m (its length × distance / "
                         "1000 mm, across the pair's line); 0: a point")
    ap.add_argument("--second-line-mm", type=float, default=0.0,
                    help="the second source a line this long at 1 m; 0: a point")
    ap.add_argument("--second-along", action="store_true",
                    help="the second line along the pair's line (a T), not across it")
    ap.add_argument("--neighbours-in", action="store_true",
                    help="touching regions not refitted without their neighbours' light "
                         "(the code before stop 71)")
    ap.add_argument("--refits", type=int, default=0, metavar="N",
                    help="instead: touching regions' refits from scratch and from the first "
                         "answer, least CPU of N each (module docstring)")
    args = ap.parse_args()
    distance.NEIGHBOURS_OUT = not args.neighbours_in
    d1, d2 = _floats(args.distances)
    camera = {"mla": {"focus_mm": args.focus},
              "sensor": {"width_px": args.size, "height_px": args.size}}
    base = load_profile(args.system)
    prof = apply_overrides(base, camera)
    prof = prof.with_d_in(prof.d_in_mm)
    geom = truth_geometry(prof, (args.size, args.size))
    # the fits read the renders' full well (the gain a capture of two blurs cannot measure)
    measuring = replace(prof, sensor=replace(prof.sensor, full_well_e=NOISE["full_well_e"]))
    top = min(2 ** prof.sensor.bit_depth - 1, prof.sensor.white_level)
    white = float(prof.sensor.white_level - prof.sensor.black_level)
    print(f"# {args.system}, focus {args.focus:.0f} mm, {args.size}² px, sources at {d1:.0f} "
          f"and {d2:.0f} mm (the second {args.brightness:g} × as bright, both "
          f"{args.field_mm:g} mm/m off the axis"
          + (f"; the first a {args.first_line_mm:g} mm/m line" if args.first_line_mm > 0 else "")
          + (f"; the second a {args.second_line_mm:g} mm/m line "
             + ("along" if args.second_along else "across") + " the pair's line"
             if args.second_line_mm > 0 else "")
          + f"), {args.renderer} renderer, --method "
          f"{args.method}" + ("; neighbours' light left in" if args.neighbours_in else "")
          + "; each region: source, status, error, z = error/σ, CPU ms")
    if args.refits:
        print("| apart | seed | refits: source: answer, least ms, rays from scratch → from the "
              "first answer |\n|---|---|---|")
    else:
        print("| apart | seed | centroids apart px | cut off | cut on |")
        print("|---|---|---|---|---|")
    tally = {False: [0, 0, 0], True: [0, 0, 0]}  # within 3σ, over 3σ, sources unmeasured
    for apart in _floats(args.aparts):
        for seed in [int(s) for s in args.seeds.split(",")]:
            objects = [{"type": "point", "distance_mm": d, "intensity": b,
                        "position_mm": [args.field_mm * d / 1000, s * apart * d / 1000]}
                       for d, s, b in ((d1, -1.0, 1.0), (d2, 1.0, args.brightness))]
            if args.first_line_mm > 0:
                x, y = objects[0]["position_mm"]
                half = 0.5 * args.first_line_mm * d1 / 1000
                objects[0] = {"type": "line", "distance_mm": d1, "intensity": 1.0 / (2 * half),
                              "start_mm": [x - half, y], "end_mm": [x + half, y]}
            if args.second_line_mm > 0:
                x, y = objects[1]["position_mm"]
                half = 0.5 * args.second_line_mm * d2 / 1000
                per_mm = 1000.0 * args.brightness / (args.second_line_mm * d1)
                objects[1] = {"type": "line", "distance_mm": d2, "intensity": per_mm,
                              "start_mm": ([x, y - half] if args.second_along
                                           else [x - half, y]),
                              "end_mm": ([x + 0.001, y + half] if args.second_along
                                         else [x + half, y])}
            image, truth = render(base, prof, camera, objects, seed, args.renderer, top)
            stats = lenslet_stats(image, geom.lmap)
            capture_noise(image, geom.lmap, geom.pitch_px, stats,
                          sensor_gain=distance.sensor_gain(measuring, white))
            cs = [s["centroid_px"] for s in truth["sources"]]
            if args.refits:
                print(f"| {apart:g} | {seed} | "
                      + ("; ".join(refits(image, measuring, geom, truth, args.refits))
                         or "none over the gate") + " |", flush=True)
                continue
            cells = []
            for split in (False, True):
                res = measure(image, measuring, geom, white, truth, args.method, split)
                measured = set()
                for k, status, _, z, _ in res:
                    if status == "ok":
                        tally[split][0 if abs(z) <= 3 else 1] += 1
                        measured.add(k)
                tally[split][2] += 2 - len(measured)
                cells.append("; ".join(
                    f"{k}: {status}" + (f" {err:+.3f} % ({z:+.1f}σ)" if status == "ok" else "")
                    + f", {ms:.0f} ms" for k, status, err, z, ms in res))
            print(f"| {apart:g} | {seed} | {np.hypot(*np.subtract(*cs)):.0f} | {cells[0]} | "
                  f"{cells[1]} |", flush=True)
    for split in (False, True) if not args.refits else ():
        within, over, missing = tally[split]
        print(f"# cut {'on' if split else 'off'}: {within} answers within 3σ, {over} over 3σ, "
              f"{missing} sources unmeasured")


if __name__ == "__main__":
    main()
