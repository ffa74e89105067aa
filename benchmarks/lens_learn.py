"""Held-out lenses: learn an unknown main lens from target captures, then measure distances.

Run: ``PYTHONPATH=. python benchmarks/lens_learn.py [--quick] [--cache DIR] [--out DIR]``

The fit never sees a prescription. Captures are rendered through multi-element lenses
(``calibration/cooke_triplet.toml``, f 50 mm F/4; the double Gauss of
``calibration/double_gauss.toml`` opened to F/2.8), each focused at 1 m and at infinity. What a
user would have is then put in a folder of its own: a white image, one capture per target plane
(4 point sources each, lateral positions spread over the field and not written anywhere),
``targets.csv`` (``capture,distance_mm``) and a black-box profile (focal length and f-number
from the prescription's paraxial data, as printed on a barrel; ``--exit-pupil`` adds the exit
pupil). The benchmark then runs exactly the user's commands::

    lfcam calibrate white.png --profile camera.toml --targets targets.csv -o calib.json
    lfcam distance hidden_k.png --profile camera.toml --calibration calib.json -o out_k

and compares ``out_k/regions.csv`` with the renderer's truth files (kept in another folder).
Hidden test sources (3 a capture, at distances between the calibration planes and at other
field positions, both sides of a 1 m focus) are never used by the fit.

Plane distances: 8 planes spaced geometrically from the nearest distance whose blur still
fits four sources on the sensor (≥ 300 mm) to 3500 mm; the headline uses 5 of them
(indices 0, 2, 4, 5, 7). Tables: per lens and focus (mean / max |error| of the hidden sources);
accuracy against the number of planes (1–8; subsets spread over the same range); accuracy with
the plane distances in ``targets.csv`` perturbed by ±1 mm and ±5 mm (random signs, and all +e:
a tape zero offset). Renders are cached (``--cache``; deterministic seeds), so a second run
only re-runs the commands. Results: ``docs/results/lens_learn.md`` and ``lens_learn.csv``.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "data" / "synthetic"))

from lenses_e2e import double_gauss_f28  # noqa: E402

from lfcam.camera import CameraProfile, load_profile  # noqa: E402
from lfcam.optics.trace import forward  # noqa: E402
from lfcam.sim.capture import simulate, write_capture  # noqa: E402
from lfcam.sim.scene import scene_from_dict  # noqa: E402

SEED = 20261123
NOISE = {"photon_noise": True, "full_well_e": 20000.0, "read_noise_e": 3.0}
RAYS = 300_000
FAR_MM = 3500.0
NEAR_MIN_MM = 300.0
N_POOL = 8
HEADLINE = (0, 2, 4, 5, 7)  # 5 of the 8 planes, spread over the range
SOURCES_PER_PLANE = 4
HIDDEN_PER_CAPTURE = 3
MAX_BLUR_FRACTION = 0.3  # of the sensor's shorter side: four sources still fit without touching


@dataclass(frozen=True)
class Config:
    """One camera: a held-out lens at one focus."""

    key: str
    label: str
    profile: CameraProfile


def configs(quick: bool) -> list[Config]:
    """Cooke triplet F/4 and double Gauss F/2.8, focus 1 m and infinity (quick: Cooke, 1 m)."""
    out = []
    lenses = [("cooke", "Cooke triplet f50 F/4", load_profile("cooke_triplet")),
              ("dg28", "double Gauss f100 F/2.8", double_gauss_f28())]
    for key, label, base in lenses[:1] if quick else lenses:
        for focus in ([1000.0] if quick else [1000.0, math.inf]):
            tag = "inf" if math.isinf(focus) else f"{focus:g}"
            out.append(Config(f"{key}-{tag}", f"{label}, focus {tag} mm",
                              base.with_focus(focus)))
    return out


# ----------------------------------------------------------------------------- the target rig


def sensor_side_mm(profile: CameraProfile) -> float:
    """The sensor's shorter side, mm (the rig is laid out in a centred square)."""
    s = profile.sensor
    return min(s.width_px, s.height_px) * s.pixel_pitch_mm


def blur_mm(profile: CameraProfile, distance_mm: float) -> float:
    """Blur diameter on the sensor of an on-axis source (the two stop-edge rays, exact trace)."""
    r = forward(profile, None, distance_mm, 0.0)
    return float(abs(r.y1_mm - r.y2_mm))


def plane_pool(profile: CameraProfile) -> list[float]:
    """8 plane distances (mm, rounded to 10 mm), geometric from the nearest usable one."""
    near = NEAR_MIN_MM
    while blur_mm(profile, near) > MAX_BLUR_FRACTION * sensor_side_mm(profile):
        near *= 1.05
    return [float(round(d / 10.0) * 10.0) for d in np.geomspace(near, FAR_MM, N_POOL)]


def hidden_distances(pool: list[float]) -> list[float]:
    """Distances between the planes (geometric midpoints, and thirds of the widest gaps)."""
    out = [math.sqrt(a * b) for a, b in zip(pool[:-1], pool[1:], strict=True)]
    out += [pool[0] * (pool[1] / pool[0]) ** (1 / 3), pool[-2] * (pool[-1] / pool[-2]) ** (2 / 3)]
    return [float(round(d)) for d in sorted(out)]


def hidden_groups(distances: list[float]) -> list[list[float]]:
    """Hidden distances dealt into captures of 3, near, middle and far mixed."""
    n = max(1, math.ceil(len(distances) / HIDDEN_PER_CAPTURE))
    return [distances[k::n] for k in range(n)]


def object_xy_mm(profile: CameraProfile, distance_mm: float, r_frac: float,
                 azimuth_rad: float) -> list[float]:
    """Object-side position putting the blur centre at ``r_frac`` of the half shorter side
    (the stop-edge rays' mid-point, exact trace, scaled linearly from a 1 % field point)."""
    half_mm = 0.5 * sensor_side_mm(profile)
    h0 = 0.01 * distance_mm
    r = forward(profile, None, distance_mm, h0)
    r_obj = r_frac * half_mm * h0 / abs(0.5 * float(r.y1_mm + r.y2_mm))
    return [r_obj * math.cos(azimuth_rad), r_obj * math.sin(azimuth_rad)]


def plane_scene(profile: CameraProfile, distance_mm: float, seed: int,
                noise: dict | None = None) -> dict:
    """4 sources on one plane at seeded field positions (radius 0.55–0.65, four quadrants)."""
    rng = np.random.default_rng(seed)
    az0 = rng.uniform(0.0, 2.0 * math.pi)
    objs = []
    for k in range(SOURCES_PER_PLANE):
        az = az0 + k * 2.0 * math.pi / SOURCES_PER_PLANE + rng.uniform(-0.1, 0.1)
        objs.append({"type": "point", "distance_mm": distance_mm,
                     "position_mm": object_xy_mm(profile, distance_mm,
                                                 rng.uniform(0.55, 0.65), az)})
    return {"seed": seed, "rays_per_source": RAYS, "sensor": noise or NOISE, "objects": objs}


def hidden_scene(profile: CameraProfile, distances: list[float], seed: int,
                 noise: dict | None = None) -> dict:
    """Sources at several distances in one capture, 120° apart, radius 0.15–0.6."""
    rng = np.random.default_rng(seed)
    az0 = rng.uniform(0.0, 2.0 * math.pi)
    objs = []
    for k, d in enumerate(distances):
        az = az0 + k * 2.0 * math.pi / len(distances)
        objs.append({"type": "point", "distance_mm": d,
                     "position_mm": object_xy_mm(profile, d, rng.uniform(0.15, 0.6), az)})
    return {"seed": seed, "rays_per_source": RAYS, "sensor": noise or NOISE, "objects": objs}


def render(profile: CameraProfile, body: dict, cache: Path, name: str) -> tuple[Path, dict]:
    """Render once into ``cache`` (PNG + truth); returns (raster path, truth)."""
    img = cache / f"{name}.png"
    tru = cache / f"{name}.truth.json"
    if not (img.is_file() and tru.is_file()):
        raw, used, truth = simulate(profile, scene_from_dict(body))
        write_capture(img, raw, used, truth)
    return img, json.loads(tru.read_text(encoding="utf-8"))


def black_box_toml(profile: CameraProfile, exit_pupil: bool) -> str:
    """The profile a rig builder writes: barrel focal length and f-number, MLA, sensor."""
    lens, mla, s = profile.main_lens, profile.mla, profile.sensor
    lines = [f'name = "{profile.name}-blackbox"', "", "[main_lens]",
             f"focal_length_mm = {lens.focal_length_mm:.2f}", f"f_number = {lens.f_number:.2f}"]
    if exit_pupil:
        lines.append(f"exit_pupil_mm = {profile.mla_z_mm - lens.exit_pupil_z_mm:.2f}")
    lines += ["", "[mla]", f"focal_length_mm = {mla.focal_length_mm!r}",
              f"pitch_mm = {mla.pitch_mm!r}", f'grid = "{mla.grid}"', "", "[sensor]",
              f"pixel_pitch_mm = {s.pixel_pitch_mm!r}", f"width_px = {s.width_px}",
              f"height_px = {s.height_px}", f"bit_depth = {s.bit_depth}",
              f'bayer = "{s.bayer}"', f"black_level = {s.black_level}",
              f"white_level = {s.white_level}", ""]
    return "\n".join(lines)


# ----------------------------------------------------------------------------- the user's commands


LFCAM_ROOT = os.environ.get("LFCAM_ROOT", str(ROOT))  # the checkout whose lfcam the commands run


def lfcam(*args: str) -> tuple[int, str, float]:
    """Run ``python -m lfcam ARGS``; (exit code, last stderr line, CPU seconds of the child).

    The commands run this checkout's lfcam, or ``$LFCAM_ROOT``'s (another branch, same renders).
    """
    env = dict(os.environ, PYTHONPATH=LFCAM_ROOT)
    t0 = os.times()
    p = subprocess.run([sys.executable, "-m", "lfcam", *args], capture_output=True, text=True,
                       env=env, cwd=LFCAM_ROOT)  # python -m puts the cwd first on sys.path
    t1 = os.times()
    cpu = (t1.children_user - t0.children_user) + (t1.children_system - t0.children_system)
    msg = (p.stderr.strip().splitlines() or [""])[-1]
    return p.returncode, msg, cpu


def match_regions(regions_csv: Path, truth: dict, pitch_px: float,
                  pixel_pitch_mm: float) -> list[dict]:
    """Per truth source: the nearest ``ok`` region whose blur centroid lies within 3 lenslet
    pitches + a quarter of the true blur diameter of the source's; else a miss (NaN)."""
    rows = []
    with open(regions_csv, newline="", encoding="utf-8") as f:
        for r in csv.DictReader(f):
            if r["status"] == "ok" and r["distance_mm"]:
                rows.append((float(r["x_px"]), float(r["y_px"]), float(r["distance_mm"])))
    out = []
    for src in truth["sources"]:
        cx, cy = src["centroid_px"]
        reach_px = 3.0 * pitch_px + 0.25 * (src.get("diameter_mm") or 0.0) / pixel_pitch_mm
        best = min(rows, key=lambda q: math.hypot(q[0] - cx, q[1] - cy), default=None)
        found = best is not None and math.hypot(best[0] - cx, best[1] - cy) <= reach_px
        out.append({"distance_mm": src["distance_mm"],
                    "estimate_mm": best[2] if found else math.nan})
    return out


@dataclass
class Trial:
    """One calibration (a set of planes, possibly perturbed) and its hidden-source errors."""

    config: str
    table: str
    variant: str
    planes_mm: tuple[float, ...]
    errors_pct: list[float]
    missed: int
    failure: str
    calib_cpu_s: float
    sources: list = field(default_factory=list)  # (true mm, estimate mm or NaN) per hidden source

    def summary(self) -> tuple[float, float]:
        e = np.array(self.errors_pct)
        return ((float(np.mean(e)), float(np.max(e))) if e.size else (math.nan, math.nan))


def run_trial(cfg: Config, user: Path, white: Path, profile_toml: Path, plane_files: list[Path],
              csv_distances: list[float], hidden: list[tuple[Path, dict]], tag: str,
              table: str, variant: str, true_planes: list[float]) -> Trial:
    """Write targets.csv, calibrate, measure every hidden capture, compare with truth."""
    # one folder per trial and per lfcam checkout, so two checkouts can run side by side
    folder = user / (tag if LFCAM_ROOT == str(ROOT) else f"{tag}@{Path(LFCAM_ROOT).name}")
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["capture,distance_mm"] + [f"../{p.name},{d:.1f}"
                                       for p, d in zip(plane_files, csv_distances, strict=True)]
    (folder / "targets.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    calib = folder / "calib.json"
    calib.unlink(missing_ok=True)
    code, msg, cpu = lfcam("calibrate", str(white), "--profile", str(profile_toml),
                           "--targets", str(folder / "targets.csv"), "-o", str(calib), "--quiet")
    trial = Trial(cfg.key, table, variant, tuple(true_planes), [], 0, "", cpu)
    if code != 0:
        trial.failure = f"calibrate exit {code}: {msg}"
        return trial
    pitch_px = cfg.profile.mla.pitch_mm / cfg.profile.sensor.pixel_pitch_mm
    for k, (img, truth) in enumerate(hidden):
        out = folder / f"out_{k}"
        shutil.rmtree(out, ignore_errors=True)
        code, msg, _ = lfcam("distance", str(img), "--profile", str(profile_toml),
                             "--calibration", str(calib), "-o", str(out), "--quiet")
        if code != 0:
            trial.failure = f"distance exit {code}: {msg}"
            trial.missed += len(truth["sources"])
            continue
        for m in match_regions(out / "regions.csv", truth, pitch_px,
                               cfg.profile.sensor.pixel_pitch_mm):
            trial.sources.append((m["distance_mm"], m["estimate_mm"]))
            if math.isnan(m["estimate_mm"]):
                trial.missed += 1
            else:
                trial.errors_pct.append(
                    100.0 * abs(m["estimate_mm"] - m["distance_mm"]) / m["distance_mm"])
    return trial


def prepare(cfg: Config, cache: Path, exit_pupil: bool, quick: bool):
    """Render (cached) and lay out the user's folder; returns what the trials need."""
    rc = cache / cfg.key
    rc.mkdir(parents=True, exist_ok=True)
    user = rc / ("user_ep" if exit_pupil else "user")
    user.mkdir(exist_ok=True)
    prof = cfg.profile
    pool = plane_pool(prof)
    hid = hidden_distances(pool)
    if quick:
        hid = hid[::3]
    base = SEED + sum(map(ord, cfg.key))
    white, _ = render(prof, {"seed": base, "objects": [{"type": "white"}], "sensor": NOISE},
                      rc, "white")
    planes = [render(prof, plane_scene(prof, d, base + 10 + k), rc, f"plane_{int(d)}")[0]
              for k, d in enumerate(pool)]
    hidden = [render(prof, hidden_scene(prof, ds, base + 100 + k), rc, f"hidden_{k}")
              for k, ds in enumerate(hidden_groups(hid))]
    # the user's folder holds rasters only: no profile sidecar, no truth
    for src in [white, *planes, *(h[0] for h in hidden)]:
        dst = user / src.name
        if not dst.is_file():
            shutil.copyfile(src, dst)
    profile_toml = user / "camera.toml"
    profile_toml.write_text(black_box_toml(prof, exit_pupil), encoding="utf-8")
    return (user, user / white.name, profile_toml, pool, [user / p.name for p in planes],
            [(user / h[0].name, h[1]) for h in hidden])


def describe_rig(cfg: Config, user: Path, hidden: list[tuple[Path, dict]]) -> None:
    """Print every source's blur centroid and diameter (truth), to check nothing overlaps."""
    pp = cfg.profile.sensor.pixel_pitch_mm
    for name in sorted(p.stem for p in user.glob("*.png")):
        tru = user.parent / f"{name}.truth.json"
        if not tru.is_file():
            continue
        srcs = [s for s in json.loads(tru.read_text(encoding="utf-8"))["sources"]
                if "distance_mm" in s]
        if not srcs:
            continue
        print(f"  {name:>12}: " + "  ".join(
            f"{s['distance_mm']:g}@({s['centroid_px'][0]:.0f},{s['centroid_px'][1]:.0f})"
            f"⌀{(s['diameter_mm'] or 0) / pp:.0f}px" for s in srcs))


def spread(n: int) -> tuple[int, ...]:
    """Indices of n planes of the 8, spread over the range (n = 1: the middle one)."""
    if n == 1:
        return (N_POOL // 2,)
    return tuple(sorted({int(round(x)) for x in np.linspace(0, N_POOL - 1, n)}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true",
                    help="Cooke triplet at 1 m only, a third of the hidden sources, planes 2/5/8")
    ap.add_argument("--cache", default=str(Path(os.environ.get("TMPDIR", "/tmp"))
                                           / "lfcam_lens_learn"),
                    help="render cache and user folders (default $TMPDIR/lfcam_lens_learn)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "results"),
                    help="folder for lens_learn.md and lens_learn.csv")
    ap.add_argument("--exit-pupil", action="store_true",
                    help="give the black box the exit pupil too (default: f and N only)")
    ap.add_argument("--tables", default="cooke-1000",
                    help="configurations (comma list, or 'all') that also get the plane-count "
                    "and perturbation tables")
    ap.add_argument("--configs", default="", help="only these configurations (comma list)")
    ap.add_argument("--planes", default="",
                    help="plane counts for the plane table (comma list; default 1-8, quick 2,5,8)")
    ap.add_argument("--perturb", default="1,5",
                    help="plane-distance errors (mm, comma list) for the perturbation table")
    ap.add_argument("--no-headline", action="store_true",
                    help="skip the headline trial (tables only)")
    ap.add_argument("--render-only", action="store_true",
                    help="render and lay out the folders, print the rig, run no command")
    args = ap.parse_args()
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    chosen = configs(args.quick)
    if args.configs:
        chosen = [c for c in chosen if c.key in args.configs.split(",")]
    trials: list[Trial] = []
    t_start = time.process_time()
    for cfg in chosen:
        print(f"\n# {cfg.label}: EFL {cfg.profile.main_lens.focal_length_mm:.3f} mm, "
              f"F/{cfg.profile.main_lens.f_number:.2f}", flush=True)
        user, white, prof_toml, pool, plane_files, hidden = prepare(cfg, cache, args.exit_pupil,
                                                                    args.quick)
        hid = [s["distance_mm"] for _, t in hidden for s in t["sources"]]
        print(f"planes {pool}\nhidden {hid}", flush=True)
        if args.render_only:
            describe_rig(cfg, user, hidden)
            continue

        def trial(idx, table, variant, perturb=None, cfg=cfg, user=user, white=white,
                  prof_toml=prof_toml, pool=pool, plane_files=plane_files, hidden=hidden):
            true = [pool[i] for i in idx]
            given = (list(true) if perturb is None
                     else [d + e for d, e in zip(true, perturb, strict=True)])
            t = run_trial(cfg, user, white, prof_toml, [plane_files[i] for i in idx], given,
                          hidden, f"{table}_{variant}".replace(" ", "").replace("±", "pm"),
                          table, variant, true)
            mean, mx = t.summary()
            print(f"{table:>12} {variant:>14}: mean {mean:6.3f} %  max {mx:6.3f} %  "
                  f"({len(t.errors_pct)} sources, missed {t.missed}, calibrate CPU "
                  f"{t.calib_cpu_s:.0f} s) {t.failure}", flush=True)
            trials.append(t)

        if not args.no_headline:
            trial(HEADLINE, "headline", "5 planes")
        if not (args.tables == "all" or cfg.key in args.tables.split(",")):
            continue
        counts = ([int(n) for n in args.planes.split(",")] if args.planes
                  else [2, 5, 8] if args.quick else range(1, N_POOL + 1))
        for n in counts:
            if n != 5:
                trial(spread(n), "planes", f"{n} planes")
        rng = np.random.default_rng(SEED)
        for e in (float(x) for x in args.perturb.split(",") if x):
            signs = rng.choice([-1.0, 1.0], size=len(HEADLINE))
            trial(HEADLINE, "perturbed", f"±{e:g} mm random", list(signs * e))
            trial(HEADLINE, "perturbed", f"+{e:g} mm all", [e] * len(HEADLINE))
    if not args.render_only:
        write_results(trials, chosen, Path(args.out), args, time.process_time() - t_start)


def write_results(trials: list[Trial], chosen: list[Config], out: Path, args,
                  cpu_s: float) -> None:
    """``lens_learn.csv`` (one row a trial) and ``lens_learn.md`` (the three tables)."""
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "lens_learn.csv", "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["config", "table", "variant", "planes_mm", "n_sources", "missed",
                    "mean_error_pct", "max_error_pct", "calibrate_cpu_s", "failure"])
        for t in trials:
            mean, mx = t.summary()
            w.writerow([t.config, t.table, t.variant, " ".join(f"{d:g}" for d in t.planes_mm),
                        len(t.errors_pct), t.missed, f"{mean:.4f}", f"{mx:.4f}",
                        f"{t.calib_cpu_s:.1f}", t.failure])
    with open(out / "lens_learn_sources.csv", "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["config", "table", "variant", "distance_mm", "estimate_mm", "error_pct"])
        for t in trials:
            for d, e in t.sources:
                w.writerow([t.config, t.table, t.variant, f"{d:g}", f"{e:.2f}",
                            f"{100.0 * (e - d) / d:+.3f}"])
    labels = {c.key: c.label for c in chosen}

    def row(t: Trial, first: str) -> str:
        mean, mx = t.summary()
        verdict = t.failure or (f"{len(t.errors_pct)} sources"
                                + (f", {t.missed} missed" if t.missed else ""))
        return f"| {first} | {mean:.2f} | {mx:.2f} | {verdict} |"

    md = ["# Learning held-out main lenses from target captures (issue 15)", "",
          f"Produced by `PYTHONPATH=. python benchmarks/lens_learn.py"
          f"{' --quick' if args.quick else ''}{' --exit-pupil' if args.exit_pupil else ''}`"
          f" (benchmark CPU {cpu_s:.0f} s, child processes not included). Error = "
          "|estimate − truth| / truth of hidden point sources (never used by the fit), from "
          "`lfcam distance`'s regions.csv against the renderer's truth files. The black-box "
          "profile gives focal length and f-number"
          f"{' and the exit pupil' if args.exit_pupil else ' only'}.", "",
          "## Per lens and focus (5 planes, 4 sources each)", "",
          "| configuration | mean % | max % | |", "|---|---|---|---|"]
    md += [row(t, labels[t.config]) for t in trials if t.table == "headline"]
    for table, title in (("planes", "Accuracy against the number of calibration planes"),
                         ("perturbed", "Accuracy with the plane distances mis-measured")):
        rows = [t for t in trials if t.table in (table, "headline")
                and any(u.table == table and u.config == t.config for u in trials)]
        if not rows:
            continue
        md += ["", f"## {title}", "", "| configuration | variant | planes (mm) | mean % | max % "
               "| |", "|---|---|---|---|---|---|"]
        for t in sorted(rows, key=lambda t: (t.config, t.table != "headline", t.variant)):
            mean, mx = t.summary()
            verdict = t.failure or f"{len(t.errors_pct)} sources" + (
                f", {t.missed} missed" if t.missed else "")
            variant = "5 planes (exact)" if t.table == "headline" else t.variant
            md.append(f"| {t.config} | {variant} | {' '.join(f'{d:g}' for d in t.planes_mm)} | "
                      f"{mean:.2f} | {mx:.2f} | {verdict} |")
    (out / "lens_learn.md").write_text("\n".join(md) + "\n", encoding="utf-8")
    print(f"\nwrote {out / 'lens_learn.md'} and {out / 'lens_learn.csv'}")


if __name__ == "__main__":
    main()
