"""Many-source scenes (issue 17): the distance run of a whole frame, stage by stage.

Run: ``python benchmarks/many_sources.py --scene a|b [--workdir DIR] [--methods lenslet]
[--jobs N] [--no-cli] [--seed N] [--lines-only]``, or ``… --per-region N [--ab
NAME=VALUE,...] [--tolerance PCT]``

* ``a``: a 1568² system-2 capture (focus 3.5 m) with 12 point sources, 600…3000 mm, spread
  over the field. Target: ``lfcam distance`` ≤ 5 s wall on the 2-core machine.
* ``b``: an Illum-size capture (``benchmarks/profiles/illum_like.toml``: system 2's main lens,
  7728×5368 px of 2.5 µm, hex MLA of 14.29 px pitch, 235 k lenslets) with 100 point sources and
  10 lines of 4 mm, 900…1500 mm (blurs of 300–1500 lenslets that do not overlap).
  Target: ≤ 15 s.

Both are rendered with :mod:`lfcam.sim` (photon and read noise, ``RAYS_PER_SOURCE`` rays a
source) into ``--workdir`` (PNG + profile sidecar + truth, cached). The calibration is the
renderer's own lenslet lattice, mapped to white-image centroids through the same radial
white-offset table that :func:`lfcam.measure.prepare_geometry` inverts ("lattice
calibration": a white image of 41 Mpx would take the backward renderer far longer than the
benchmark; the white-calibration path is measured on system 2 in ``benchmarks/lenslet_focus.py``
and ``docs/distance.md``).

Per method: the stage times of one in-process run (load, geometry, regions, fits, export),
the wall time of the ``lfcam distance`` command on the written files (``--no-cli`` skips it),
the worst single region's CPU time, and the errors against the truth (each truth source is
matched to the region nearest its light centroid; ``regions_shared`` counts regions that
several sources claim — touching blurs — and ``regions_unclaimed`` those no source claims —
fragments).

``--seed N`` renders the scene with another seed (rays and noise), ``--lines-only`` scene
``b``'s 10 lines without its points: each draw in a ``--workdir`` of its own (a workdir that
holds another draw is refused). Scene ``b``'s lines on other draws are in docs/distance.md,
"The polish's rays where photons dominate (stop 62)".

``--per-region N``: instead, every spot and line region's ``lenslet`` fit in this process
on one core (BLAS at one thread), once to warm up and then ``N`` times, least CPU, as
``line_regions.py`` times its regions (with ``--ab``, alternately as the code is and with
those fastfit constants), each with its error against the one truth source its box holds (a
region cut from touching blurs: the one nearest its light's centroid); a summary per kind:
regions over issue 17's budgets (50 ms a point region, 100 ms a line region), the slowest,
the model rays traced (``fastfit.counting_rays``: a cost the machine's load does not move,
per region and summed), the errors. ``--tolerance PCT``: each fit with the tolerance
``lfcam distance --method lenslet --tolerance PCT`` gives it. A region's time inside ``lfcam
distance`` also carries the process's first calls and, with ``--jobs``, two workers sharing
the caches.
"""

from __future__ import annotations

import os
import sys

if "--per-region" in sys.argv:  # (before numpy loads: one BLAS thread, as a region worker)
    for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from lfcam.calibrate import load_calibration  # noqa: E402
from lfcam.calibrate.model import Calibration, save_calibration  # noqa: E402
from lfcam.camera import CameraProfile, load_profile  # noqa: E402
from lfcam.distance import run_distance, write_outputs  # noqa: E402
from lfcam.io import load_capture  # noqa: E402
from lfcam.measure import prepare_geometry  # noqa: E402
from lfcam.measure.geometry import white_offset_table  # noqa: E402
from lfcam.measure.pointfit import chief_ray_offset  # noqa: E402
from lfcam.sim.capture import apply_overrides, simulate, write_capture  # noqa: E402
from lfcam.sim.render import Renderer  # noqa: E402
from lfcam.sim.scene import scene_from_dict  # noqa: E402

NOISE = {"photon_noise": True, "full_well_e": 20000, "read_noise_e": 3.0}
RAYS_PER_SOURCE = 200_000


def scene_a() -> tuple[CameraProfile, dict]:
    """12 point sources on a 1568² system-2 sensor."""
    base = load_profile("system2")
    camera = {"sensor": {"width_px": 1568, "height_px": 1568}}
    prof = apply_overrides(base, camera)
    dists = (600.0, 800.0, 1000.0, 1200.0, 1500.0, 1800.0, 2000.0, 2200.0, 2500.0, 2800.0,
             3000.0, 1100.0)
    # a 4 × 3 grid of sensor positions (mm), clear of each other's blurs
    spots = [(x, y) for y in (-7.5, 0.0, 7.5) for x in (-8.5, -2.8, 2.8, 8.5)]
    objects = []
    for d, (sx, sy) in zip(dists, spots, strict=True):
        xy = _source_xy(prof, d, sx, sy)
        objects.append({"type": "point", "distance_mm": d, "position_mm": xy})
    return base, {"seed": 11, "rays_per_source": RAYS_PER_SOURCE, "sensor": NOISE,
                  "exposure": {"peak": 0.8}, "camera": camera, "objects": objects}


def scene_b() -> tuple[CameraProfile, dict]:
    """100 point sources and 10 lines on the Illum-size sensor."""
    base = load_profile(ROOT / "benchmarks" / "profiles" / "illum_like.toml")
    rng = np.random.default_rng(17)
    w = base.sensor.width_px * base.sensor.pixel_pitch_mm
    h = base.sensor.height_px * base.sensor.pixel_pitch_mm
    cols, rows = 11, 10  # 110 cells: 100 points, 10 lines
    objects = []
    for k in range(cols * rows):
        i, j = k % cols, k // cols
        sx = (i + 0.5) / cols * w - 0.5 * w
        sy = (j + 0.5) / rows * h - 0.5 * h
        d = float(rng.uniform(900.0, 1500.0))
        xy = _source_xy(base, d, sx, sy)
        if k % 11 == 5:  # every 11th cell: a 4 mm line
            ang = float(rng.uniform(0.0, math.pi))
            dx, dy = 2.0 * math.cos(ang), 2.0 * math.sin(ang)
            objects.append({"type": "line", "distance_mm": d,
                            "start_mm": [xy[0] - dx, xy[1] - dy],
                            "end_mm": [xy[0] + dx, xy[1] + dy]})
        else:
            objects.append({"type": "point", "distance_mm": d, "position_mm": xy})
    return base, {"seed": 12, "rays_per_source": RAYS_PER_SOURCE, "sensor": NOISE,
                  "exposure": {"peak": 0.8}, "objects": objects}


def _source_xy(prof: CameraProfile, distance: float, sx: float, sy: float) -> list[float]:
    """Source position whose chief ray lands at sensor point (sx, sy) mm."""
    mag = 1 + prof.mla.focal_length_mm / (prof.d_in_mm - prof.main_lens.exit_pupil_z_mm)
    xy = chief_ray_offset(prof, prof.d_in_mm, distance, np.array([sx, sy]) / mag)
    return [float(xy[0]), float(xy[1])]


def lattice_calibration(prof: CameraProfile, shape: tuple[int, int]) -> Calibration:
    """The renderer's lenslet lattice as a calibration (module docstring)."""
    rend = Renderer(prof)
    c = np.stack([rend.lcx, rend.lcy], 1)
    pp = prof.sensor.pixel_pitch_mm
    ax, ay = prof.sensor.axis_xy_px
    r = np.hypot(c[:, 0], c[:, 1])
    radii, r_w = white_offset_table(prof, float(prof.d_in_mm), float(r.max() * 1.05 + 1e-6))
    rw = np.interp(r, radii, r_w)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(r > 0, rw / r, r_w[1] / radii[1])
    px = c * scale[:, None] / pp + np.array([ax, ay])
    h, w = shape
    keep = (px[:, 0] > 1) & (px[:, 0] < w - 2) & (px[:, 1] > 1) & (px[:, 1] < h - 2)
    mag = float(r_w[1] / radii[1])
    return Calibration.from_lattice(
        prof.mla.grid, prof.mla.pitch_mm * mag / pp, prof.mla.rotation_rad,
        (ax + prof.mla.offset_mm[0] * mag / pp, ay + prof.mla.offset_mm[1] * mag / pp),
        px[keep], image_size_px=(w, h), d_in_mm=prof.d_in_mm, source="lattice calibration")


def prepare(name: str, workdir: Path, seed: int | None = None,
            lines_only: bool = False) -> tuple[Path, Path, dict]:
    """Render (or reuse) the scene and its calibration; (capture, calibration, truth).
    ``seed``: the render's seed (rays and noise; default the scene's own); ``lines_only``:
    scene (b)'s lines without its points. A workdir that holds another draw is refused."""
    workdir.mkdir(parents=True, exist_ok=True)
    png = workdir / f"scene_{name}.png"
    cal_path = workdir / f"scene_{name}.calib.json"
    truth_path = workdir / f"scene_{name}.truth.json"
    base, scene = scene_a() if name == "a" else scene_b()
    if seed is not None:
        scene["seed"] = seed
    if lines_only:
        scene["objects"] = [o for o in scene["objects"] if o["type"] == "line"]
    if png.exists() and cal_path.exists() and truth_path.exists():
        held = json.loads(truth_path.read_text(encoding="utf-8"))
        if (held.get("seed"), len(held["sources"])) != (scene["seed"], len(scene["objects"])):
            raise SystemExit(f"{workdir} holds scene {name} with seed {held.get('seed')} and "
                             f"{len(held['sources'])} sources, not seed {scene['seed']} and "
                             f"{len(scene['objects'])}: give another --workdir")
    else:
        t = time.perf_counter()
        raw, used, truth = simulate(base, scene_from_dict(scene))
        print(f"# rendered scene {name}: {raw.shape[1]}×{raw.shape[0]} px, "
              f"{len(scene['objects'])} sources, {time.perf_counter() - t:.0f} s", flush=True)
        write_capture(png, raw, used, truth)
        save_calibration(lattice_calibration(used, raw.shape), cal_path)
    return png, cal_path, json.loads(truth_path.read_text(encoding="utf-8"))


def region_census(regions, truth: dict) -> dict:
    """One region per source? Each truth source claims the region nearest its light centroid:
    regions claimed by several sources (touching blurs reported as one) and regions claimed by
    none (fragments or spurious detections)."""
    claims = [int(np.argmin([math.hypot(r.x_px - s["centroid_px"][0],
                                        r.y_px - s["centroid_px"][1]) for r in regions]))
              for s in truth["sources"]]
    counts = np.bincount(claims, minlength=len(regions))
    return {"regions_shared": int((counts > 1).sum()),
            "sources_sharing": int(counts[counts > 1].sum()),
            "regions_unclaimed": int((counts == 0).sum())}


def match(regions, truth: dict, t_half: float) -> list[float]:
    """Eq. 21 error (%) of the region nearest each truth source's light centroid."""
    errs = []
    for src in truth["sources"]:
        cx, cy = src["centroid_px"]
        k = int(np.argmin([math.hypot(r.x_px - cx, r.y_px - cy) for r in regions]))
        r = regions[k]
        ad = float(src["distance_mm"])
        errs.append(abs(r.distance_mm - ad) / (ad + t_half) * 100.0 if r.status == "ok"
                    else math.nan)
    return errs


def region_budgets(regions, region_s) -> dict:
    """Per kind the answer reports (spot, line): the regions over issue 17's budget (50 ms a
    point region, 100 ms a line region, each region's own CPU) and the slowest one's ms."""
    out = {}
    for kind, budget_ms in (("spot", 50.0), ("line", 100.0)):
        ms = [1e3 * t for r, t in zip(regions, region_s, strict=False) if r.kind == kind]
        out[f"{kind}_regions"] = len(ms)
        out[f"{kind}_over_{budget_ms:.0f}ms"] = sum(v > budget_ms for v in ms)
        out[f"{kind}_worst_ms"] = max(ms, default=0.0)
    return out


def run(name: str, workdir: Path, method: str, jobs: int | None, cli: bool,
        draw: dict | None = None) -> dict:
    """One method on one scene: stage times, CLI wall time, worst region, errors (``draw``:
    :func:`prepare`'s ``seed`` and ``lines_only``)."""
    png, cal_path, truth = prepare(name, workdir, **(draw or {}))
    out = workdir / f"out_{name}_{method}"
    t0 = time.perf_counter()
    prof = load_profile(png.with_name(png.stem + ".profile.toml"))
    cal = load_calibration(cal_path)
    img = load_capture(png, prof).grey()
    t1 = time.perf_counter()
    geom = prepare_geometry(prof, cal, img.shape)
    t2 = time.perf_counter()
    res = run_distance(img, prof, cal, model="exact", method=method, geometry=geom, jobs=jobs)
    t3 = time.perf_counter()
    write_outputs(out, res)
    t4 = time.perf_counter()
    errs = np.array(match(res.regions, truth, 0.5 * prof.main_lens.thickness_mm))
    rec = {
        "scene": name, "method": method, "jobs": res.timings_s["jobs"],
        "regions": len(res.regions), "sources": len(truth["sources"]),
        **region_census(res.regions, truth),
        "load_s": t1 - t0, "geometry_s": t2 - t1, "regions_s": res.timings_s["regions"],
        "fits_s": res.timings_s["measure"], "export_s": t4 - t3, "total_s": t4 - t0,
        "region_cpu_sum_s": float(sum(res.timings_s["region_s"])),
        "worst_region_ms": 1e3 * max(res.timings_s["region_s"], default=0.0),
        **region_budgets(res.regions, res.timings_s["region_s"]),
        "missing": int(np.isnan(errs).sum()),
        "within_0.3pct": int((errs <= 0.3).sum()), "within_1pct": int((errs <= 1.0).sum()),
        "mean_error_pct": float(np.nanmean(errs)), "max_error_pct": float(np.nanmax(errs)),
    }
    if cli:
        cmd = [sys.executable, "-m", "lfcam", "distance", str(png), "--calibration",
               str(cal_path), "--method", method, "--model", "exact", "--json", "--timings",
               "-q",
               "-o", str(workdir / f"cli_{name}_{method}")]
        if jobs:
            cmd += ["--jobs", str(jobs)]
        for f in ("regions.csv", "distance.tiff", "distance.png"):
            (workdir / f"cli_{name}_{method}" / f).unlink(missing_ok=True)
        t = time.perf_counter()
        done = subprocess.run(cmd, capture_output=True, text=True,
                              env={**os.environ, "PYTHONPATH": str(ROOT)})
        rec["cli_wall_s"] = time.perf_counter() - t
        if done.returncode != 0:
            raise SystemExit(done.stderr)
        rec["cli_timings_s"] = {k: v for k, v in json.loads(done.stdout)["timings_s"].items()
                                if k != "region_s"}
        rec["cli_timings_line"] = done.stderr.strip().splitlines()[-1]
    return rec


def scene_regions(name: str, workdir: Path, draw: dict | None = None) -> tuple:
    """The scene (:func:`prepare`; ``draw``: its keyword arguments) loaded as ``lfcam
    distance`` reads it, and its regions: (profile, geometry, grey image, regions, pixel
    noise, truth)."""
    import line_regions as lr

    png, cal_path, truth = prepare(name, workdir, **(draw or {}))
    prof = load_profile(png.with_name(png.stem + ".profile.toml"))
    img = load_capture(png, prof).grey()
    geom = prepare_geometry(prof, load_calibration(cal_path), img.shape)
    regions, noise = lr.capture_regions(prof, geom, img, float(
        prof.sensor.white_level - prof.sensor.black_level))
    return prof, geom, img, regions, noise, truth


def per_region(name: str, workdir: Path, repeats: int, settings: list[dict],
               draw: dict | None = None, tolerance_pct: float | None = None) -> None:
    """Every spot and line region's ``lenslet`` fit in this process (module docstring): a row
    each (region, the kind the fit answers, lenslets, error against the truth source its box
    holds, or for a region cut from touching blurs the nearest, least ms per setting) and a
    summary per kind; ``tolerance_pct``: each fit with the tolerance ``lfcam distance
    --method lenslet --tolerance`` gives it."""
    from functools import partial

    import line_regions as lr

    from lfcam.measure.regions import nearby_regions
    from lfcam.models import auto

    prof, geom, img, regions, noise, truth = scene_regions(name, workdir, draw)
    rows = {}  # kind (setting A's answer) -> [(least ms, error %, model rays: per setting)]
    print("| region | lenslets | " + " | ".join(
        f"{k} kind, status, error % | {k} least ms | {k} model rays"
        for k in "AB"[:len(settings)]) + " |")
    for reg, near in zip(regions, nearby_regions(regions), strict=True):
        if reg.kind not in ("spot", "line"):
            continue
        spent, answers, rays = lr.alternate(
            prof, geom, img, reg, noise, settings, repeats, near,
            None if tolerance_pct is None
            else partial(auto.lenslet_answer_meets, tolerance_pct=tolerance_pct))
        x0, y0, x1, y1 = reg.box_px
        held = [src for src in truth["sources"]
                if x0 <= src["centroid_px"][0] < x1 and y0 <= src["centroid_px"][1] < y1]
        if reg.touching and held:
            # a region cut from touching blurs: its box may hold both sources' centroids; the
            # nearer its own light's is its source
            held = [min(held, key=lambda src: math.hypot(
                src["centroid_px"][0] - reg.centroid_px[0],
                src["centroid_px"][1] - reg.centroid_px[1]))]
        errs = [100.0 * (m.distance_mm / held[0]["distance_mm"] - 1.0)
                if len(held) == 1 and m.status == "ok" else math.nan for m in answers]
        least = [1e3 * min(t) for t in spent]
        rows.setdefault(answers[0].kind, []).append((least, errs, rays))
        print(f"| {reg.region_id} | {len(reg.lenslets)} | " + " | ".join(
            f"{m.kind}, {m.status}, {e:+.4f} | {t:.1f} | {n / 1e6:.2f} M"
            for m, e, t, n in zip(answers, errs, least, rays, strict=True)) + " |",
            flush=True)
    for kind, budget in (("spot", 50.0), ("line", 100.0)):
        got = rows.get(kind, [])
        if not got:
            print(f"# {kind}: no regions")
            continue
        for k, name_k in enumerate("AB"[:len(settings)]):
            t = np.array([r[0][k] for r in got])
            e = np.abs([r[1][k] for r in got])
            n = np.array([r[2][k] for r in got], dtype=np.float64)
            print(f"# {name_k} {kind}: {len(got)} regions, {int((t > budget).sum())} over "
                  f"{budget:.0f} ms, slowest {t.max(initial=0.0):.0f} ms, sum {t.sum():.0f} ms; "
                  f"model rays sum {n.sum() / 1e6:.1f} M, most {n.max(initial=0.0) / 1e6:.2f} M; "
                  f"{int(np.isfinite(e).sum())} with an error, mean {np.nanmean(e):.4f} %, "
                  f"max {np.nanmax(e, initial=0.0):.3f} %")


def main(argv=None) -> list[dict]:
    """Run and print (module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", choices=("a", "b"), default="a")
    ap.add_argument("--workdir", type=Path, default=ROOT / "benchmarks" / ".cache")
    ap.add_argument("--methods", default="lenslet")
    ap.add_argument("--jobs", type=int, default=None, help="default: all cores")
    ap.add_argument("--no-cli", action="store_true")
    ap.add_argument("--per-region", type=int, default=0, metavar="N",
                    help="each region's lenslet fit in this process, least CPU of N")
    ap.add_argument("--ab", default="", metavar="NAME=VALUE,...",
                    help="with --per-region: also fit each region with these fastfit constants")
    ap.add_argument("--seed", type=int, default=None,
                    help="render seed (rays and noise; default the scene's own), in a workdir "
                         "of its own")
    ap.add_argument("--tolerance", type=float, default=None, metavar="PCT",
                    help="with --per-region: each fit with this tolerance (as lfcam distance "
                         "--method lenslet --tolerance PCT)")
    ap.add_argument("--lines-only", action="store_true",
                    help="scene b's 10 lines without its points, in a workdir of its own")
    args = ap.parse_args(argv)
    draw = {"seed": args.seed, "lines_only": args.lines_only}
    if args.per_region:
        import focus_grid as fg

        from lfcam.measure import kernels

        try:
            other = fg.fastfit_overrides(args.ab)
        except ValueError as exc:
            ap.error(f"--ab: {exc}")
        kernels.warm_up()
        per_region(args.scene, args.workdir, args.per_region, [{}, other] if other else [{}],
                   draw, args.tolerance)
        return []
    recs = []
    for method in args.methods.split(","):
        rec = run(args.scene, args.workdir, method, args.jobs, not args.no_cli, draw)
        recs.append(rec)
        print(json.dumps(rec, indent=1), flush=True)
    return recs


if __name__ == "__main__":
    main()
