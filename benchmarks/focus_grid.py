"""Both sides of focus, full field: point sources, a 12-source scene and lines (issue 16).

Renders captures with ``lfcam.sim`` for system 1 and system 2 focused at 1 m, 1.5 m or ∞
(scene ``camera`` override ``{"mla": {"focus_mm": F}}``), with photon and read noise, and
measures them through the calibrated path: ``calibrate_white`` on a rendered white image of
the same camera (once per camera, focus and sensor size; cached in ``--cache``), then
``run_distance(model="exact")``. Sources are placed by their chief ray on the sensor
(``lfcam.measure.pointfit.chief_ray_offset``) at a fraction of the half-field: half the
width of the sensor used, azimuth 30°.

Modes:

* default: one point source a capture, ``--distances`` × ``--fields``;
* ``--scene12``: 12 point sources in one capture, both sides of focus, off axis;
* ``--lines``: lines 3 mm long on the MLA (``--line-mm``), at 0°, 60° and 135°, through the
  field centre, or centred at ``--line-field`` of the half-field (azimuth 30°).

ERROR is the seed's eq. 21, |Ad − Ed| / (Ad + T/2). A region with no ``ok`` distance, or a
source with no region, counts as a miss. ``--truth-centres`` uses the renderer's lenslet
centres instead of the calibration (separates calibration from fit). Writes one row a case
to ``--csv`` and prints the table by side of focus × field bin.

``--renderer independent`` takes the captures (every mode; a line is the midpoint rule over
exact point renders) from ``benchmarks/render_independent.py`` instead of ``lfcam.sim``
(per-pixel irradiance by the Jacobian of the exact ray map: no ray binning, docs/simulate.md);
``--white analytic`` calibrates on ``benchmarks/whites_analytic.py``'s per-pixel white
instead of ``lfcam.sim``'s. ``--grid hex|rect`` sets the MLA's grid (both renderers).
The CSV's ``renderer`` and ``white`` columns tell the rows apart.

Run::

    python benchmarks/focus_grid.py --systems system1,system2 --foci 1000,1500,inf
    python benchmarks/focus_grid.py --scene12 --foci 1000
    python benchmarks/focus_grid.py --lines --systems system2 --size 1024 --foci 1000
    python benchmarks/focus_grid.py --lines --line-mm 0.75 --systems system2 --size 1024 \
        --foci 1000 --method lenslet   # short lines: 3 pitches
    python benchmarks/focus_grid.py --quick --method lenslet --renderer independent \
        --white analytic --foci 1000 --csv /tmp/fg_indep.csv
    python benchmarks/focus_grid.py --lines --systems system2 --size 1024 --foci 1000 \
        --distances 2200,3400 --method lenslet --renderer independent --white analytic \
        --grid hex   # hexagonal lines from the second renderer
    python benchmarks/focus_grid.py --table docs/results/focus_grid.csv   # table only
    python benchmarks/focus_grid.py --lines --systems system2 --size 1024 --foci 1000 \
        --distances 1500,2200,2900,3400 --method lenslet --truth-centres --noise-free \
        --rays 16000000 --fastfit LINE_FINE_RAYS=26664   # the line fit's own bias (8 × its rays)

``--fastfit NAME=VALUE,...`` sets numeric constants of ``lfcam.measure.fastfit`` for the run
(those read when a fit runs, not default arguments): experiments on the fit's budgets.
``--noise-free`` renders without photon or read noise (the render cache keeps them apart).

Measured CPU per region: 1–4 s a point (up to ~11 s near the field edge), 6–9 s a line;
wall time grows with the machine's load. ``--quick``: first and last distance on each side,
fields 0 and 0.8.
"""

from __future__ import annotations

import os

# one BLAS thread, as `lfcam distance`'s region workers have: a threaded BLAS's spinning
# threads count in the process CPU each region reports
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import csv  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))  # render_independent, whites_analytic

import lfcam.measure.fastfit as FF  # noqa: E402
import lfcam.measure.lightfield as LF  # noqa: E402
from lfcam.calibrate import calibrate_white, load_calibration, save_calibration  # noqa: E402
from lfcam.camera import CameraProfile, load_profile  # noqa: E402
from lfcam.distance import run_distance  # noqa: E402
from lfcam.measure import Geometry, find_regions, lenslet_stats, prepare_geometry  # noqa: E402
from lfcam.measure.pointfit import chief_ray_offset  # noqa: E402
from lfcam.sim.capture import apply_overrides, simulate  # noqa: E402
from lfcam.sim.geometry import truth_geometry  # noqa: E402
from lfcam.sim.scene import scene_from_dict  # noqa: E402

NOISE = {"photon_noise": True, "full_well_e": 20000, "read_noise_e": 3.0}
DEFAULT_NOISE = dict(NOISE)
AZIMUTH_DEG = 30.0
LINE_HALF_MM = 1.5  # half length of a line's image on the MLA
LINE_ANGLES_DEG = (0, 60, 135)
DEFAULT_DISTANCES = {  # 3–4 distances on each side of the focus
    1000.0: "300,500,700,1500,2200,2900,3500",
    1500.0: "300,700,1100,2000,2900,3500",
    math.inf: "300,700,1500,2500,3500",
}
LINE_DISTANCES = "380,560,720,1500,2200,2900,3400"
BINS = (("0", 0.0, 0.0), ("<=40%", 0.0, 0.4), ("<=80%", 0.4, 0.8))
COLUMNS = ("mode", "system", "focus_mm", "size_px", "centres", "ad_mm", "field", "r_sensor_mm",
           "angle_deg", "side", "kind", "status", "ed_mm", "signed_pct", "error_pct",
           "lenslets", "path", "render_s", "fit_s", "fit_cpu_s", "renderer", "white",
           "sigma_mm", "region_cpu_s")
RENDERERS = ("sim", "independent")
WHITES = ("sim", "analytic")


def parse_focus(text: str) -> float:
    """``inf`` or a distance in mm."""
    return math.inf if text.strip().lower() in ("inf", "infinity") else float(text)


def overrides(focus_mm: float, size: int | None, rotation_rad: float = 0.0,
              grid: str | None = None) -> dict:
    """Scene ``camera`` overrides: focus, MLA rotation and grid (None: the system's own),
    optionally a centred square crop."""
    cam: dict = {"mla": {"focus_mm": "inf" if math.isinf(focus_mm) else focus_mm}}
    if rotation_rad:
        cam["mla"]["rotation_rad"] = rotation_rad
    if grid:
        cam["mla"]["grid"] = grid
    if size:
        cam["sensor"] = {"width_px": size, "height_px": size}
    return cam


def magnification(profile: CameraProfile) -> float:
    """Sensor-over-MLA scale of the chief rays (exit pupil centre through the lenslets)."""
    z_ep = profile.main_lens.exit_pupil_z_mm
    return 1.0 + profile.mla.focal_length_mm / (profile.d_in_mm - z_ep)


def calibrated_geometry(base: CameraProfile, cam: dict, used: CameraProfile,
                        shape: tuple[int, int], cache: Path, key: str,
                        white_source: str = "sim") -> Geometry:
    """Geometry from ``calibrate_white`` on a rendered white image (cached per camera).

    ``white_source``: ``"sim"`` renders the white with ``lfcam.sim`` (noise-free);
    ``"analytic"`` computes it per pixel with ``benchmarks/whites_analytic.py`` (noise-free),
    a path that shares no rendering code with ``lfcam.sim``. The two are cached apart.
    """
    path = cache / (f"calib_{key}.json" if white_source == "sim"
                    else f"calib_{key}_{white_source}.json")
    if path.exists():
        cal = load_calibration(path)
    elif white_source == "analytic":
        from whites_analytic import analytic_white

        white = analytic_white(used, noise=False)
        cal = calibrate_white(white.astype(np.float32))
        save_calibration(cal, path)
    else:
        white, _, _ = simulate(base, scene_from_dict(
            {"seed": 5, "objects": [{"type": "white"}], "camera": cam}))
        cal = calibrate_white(white.astype(np.float32))
        save_calibration(cal, path)
    return prepare_geometry(used, cal.with_d_in(used.d_in_mm, "profile"), shape)


class Camera:
    """One system at one focus and sensor size: profile, geometry, placement helpers."""

    def __init__(self, system: str, focus_mm: float, size: int | None, cache: Path,
                 truth_centres: bool, rotation_rad: float = 0.0, renderer: str = "sim",
                 white: str = "sim", grid: str | None = None):
        self.system, self.focus_mm, self.size = system, focus_mm, size
        self.renderer, self.white = renderer, white
        self.base = load_profile(ROOT / "calibration" / f"{system}.toml")
        self.cam = overrides(focus_mm, size, rotation_rad, grid)
        used = apply_overrides(self.base, self.cam)
        self.used = used.with_d_in(used.d_in_mm)
        self.shape = (self.used.sensor.height_px, self.used.sensor.width_px)
        self.half_field_mm = 0.5 * self.shape[1] * self.used.sensor.pixel_pitch_mm
        self.half_t = 0.5 * self.used.main_lens.thickness_mm
        self.centres = "truth" if truth_centres else "calibrated"
        key = (f"{system}_{focus_mm:g}_{self.shape[1]}"
               + (f"_r{rotation_rad:g}" if rotation_rad else "") + (f"_{grid}" if grid else ""))
        t0 = time.perf_counter()
        self.geom = (truth_geometry(self.used, self.shape) if truth_centres else
                     calibrated_geometry(self.base, self.cam, self.used, self.shape, cache, key,
                                         white))
        print(f"# {system}, focus {focus_mm:g} mm, {self.shape[1]}² sensor, half-field "
              f"{self.half_field_mm:.2f} mm, d_in {self.used.d_in_mm:.3f} mm, {self.centres} "
              f"centres ({'' if truth_centres else white + ' white, '}"
              f"{time.perf_counter() - t0:.0f} s), {renderer} renderer", flush=True)

    def position(self, distance_mm: float, sensor_xy_mm) -> list[float]:
        """Lateral source position whose chief ray lands at ``sensor_xy_mm`` on the sensor."""
        target = np.asarray(sensor_xy_mm, dtype=np.float64) / magnification(self.used)
        xy = chief_ray_offset(self.used, self.used.d_in_mm, distance_mm, target)
        return [float(xy[0]), float(xy[1])]

    def line(self, distance_mm: float, angle_deg: float, field: float, rays: int,
             half_mm: float = LINE_HALF_MM) -> dict:
        """Scene object of a line whose image on the MLA is ``2 × half_mm`` long, turned
        ``angle_deg``, centred at ``field`` of the half-field (each end placed by its chief
        ray)."""
        u = np.array([math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))])
        centre = self.field_xy(field)
        mag = magnification(self.used)
        return {"type": "line", "distance_mm": distance_mm,
                "start_mm": self.position(distance_mm, centre - half_mm * mag * u),
                "end_mm": self.position(distance_mm, centre + half_mm * mag * u), "rays": rays}

    def field_xy(self, fraction: float, azimuth_deg: float = AZIMUTH_DEG) -> np.ndarray:
        """Sensor position (mm from the axis) at ``fraction`` of the half-field."""
        az = math.radians(azimuth_deg)
        return fraction * self.half_field_mm * np.array([math.cos(az), math.sin(az)])

    def side(self, distance_mm: float) -> str:
        """``front`` (nearer than the focused plane) or ``behind``."""
        return "front" if distance_mm < self.focus_mm else "behind"

    def error_pct(self, ad: float, ed: float) -> tuple[float, float]:
        """(signed % of Ad, the seed's eq. 21 ERROR %)."""
        return 100.0 * (ed / ad - 1.0), 100.0 * abs(ad - ed) / (ad + self.half_t)

    def render(self, objects: list[dict], seed: int, rays: int):
        """Noisy capture (float64), truth mapping, render seconds.

        With the ``independent`` renderer the capture comes from
        ``benchmarks/render_independent.py`` with the same peak and noise, in the same digital
        units (``lfcam.sim``'s white level); ``rays`` is not used. With ``--render-cache``
        each capture and its sources' centroids are kept there, keyed by everything that
        makes them (a rerun of the fits on the same captures renders nothing).
        """
        key = None
        if RENDER_CACHE[0] is not None:
            import hashlib
            import json

            made = [self.renderer, self.system, self.cam, objects, seed, rays]
            if NOISE != DEFAULT_NOISE:  # (the default is not in the key: older caches hold)
                made.append(NOISE)
            key = RENDER_CACHE[0] / (hashlib.sha256(json.dumps(
                made, sort_keys=True).encode()).hexdigest()[:24] + ".npz")
            if key.exists():
                with np.load(key) as z:
                    cen = z["centroids"]
                    truth = {"sources": [{"centroid_px": [float(c[0]), float(c[1])]}
                                         for c in cen]}
                    return z["image"], truth, float(z["render_s"])
        img, truth, took = self._render(objects, seed, rays)
        if key is not None:
            cen = np.array([s["centroid_px"] for s in truth["sources"]], dtype=np.float64)
            tmp = key.with_suffix(f".{os.getpid()}.tmp.npz")  # (runs side by side)
            np.savez_compressed(tmp, image=img, centroids=cen, render_s=took)
            os.replace(tmp, key)
        return img, truth, took

    def _render(self, objects: list[dict], seed: int, rays: int):
        """:meth:`render` without the cache."""
        t0 = time.perf_counter()
        if self.renderer == "independent":
            from render_independent import render_capture

            img, truth = render_capture(self.used, objects, seed=seed, peak=0.8,
                                        full_well_e=NOISE["full_well_e"],
                                        read_noise_e=NOISE["read_noise_e"],
                                        bit_depth=self.used.sensor.bit_depth)
            top = min(2 ** self.used.sensor.bit_depth - 1, self.used.sensor.white_level)
            return img * top, truth, time.perf_counter() - t0
        raw, _, truth = simulate(self.base, scene_from_dict(
            {"seed": seed, "rays_per_source": rays, "sensor": NOISE, "exposure": {"peak": 0.8},
             "camera": self.cam, "objects": objects}))
        return raw.astype(np.float64), truth, time.perf_counter() - t0

    def measuring_profile(self) -> CameraProfile:
        """The profile the fits read: the rendered one, with the renders' full well where
        they have photon noise (the sensor gain a capture of one small blur cannot measure:
        docs/distance.md, "A sensor gain for captures that cannot measure one (stop 49)"),
        unless ``--no-sensor-gain``."""
        if not (NOISE["photon_noise"] and SENSOR_GAIN[0]):
            return self.used
        return replace(self.used, sensor=replace(self.used.sensor,
                                                 full_well_e=float(NOISE["full_well_e"])))

    def measure(self, img: np.ndarray):
        """(run results, their regions' lenslet counts and measurement CPU s (dicts by region
        id), the run's wall s, CPU s)."""
        t0, c0 = time.perf_counter(), time.process_time()
        res = run_distance(img, self.measuring_profile(), None, model="exact",
                           method=METHOD[0], tolerance_pct=TOLERANCE[0], geometry=self.geom,
                           jobs=1, white_value=float(self.used.sensor.white_level
                                                     - self.used.sensor.black_level))
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        regions = find_regions(lenslet_stats(img, self.geom.lmap), self.geom.lmap,
                               self.geom.pitch_px)
        per_region = {r.region_id: (len(r.lenslets), math.nan) for r in regions}
        # run_distance's own CPU for each region's measurement (timings_s["region_s"], in the
        # order of its results): the per-region time, without the capture's shared stages
        for r, t in zip(res.regions, res.timings_s.get("region_s", ()), strict=False):
            if r.region_id in per_region:
                per_region[r.region_id] = (per_region[r.region_id][0], t)
        return res.regions, per_region, wall, cpu

    def row(self, mode, ad, field, r_mm, angle, result, per_region, render_s, fit_s, cpu_s):
        """One CSV row; ``result`` is the matched RegionResult or None."""
        kind = status = path = ""
        ed = signed = err = sigma = math.nan
        n, region_cpu = 0, math.nan
        if result is not None:
            kind, status = result.kind, result.status
            n, region_cpu = per_region.get(result.region_id, (0, math.nan))
            path = ("line" if kind == "line" else
                    "tri" if n >= LF.TRIANGULATION_ENOUGH else "pix")
            if status == "ok":
                ed = result.distance_mm
                sigma = result.uncertainty_mm
                signed, err = self.error_pct(ad, ed)
        return {"mode": mode, "system": self.system, "focus_mm": self.focus_mm,
                "size_px": self.shape[1], "centres": self.centres, "ad_mm": ad,
                "field": field, "r_sensor_mm": round(r_mm, 3), "angle_deg": angle,
                "side": self.side(ad), "kind": kind or "none", "status": status or "no-region",
                "ed_mm": round(ed, 3), "signed_pct": round(signed, 4), "error_pct": round(err, 4),
                "lenslets": n, "path": path, "render_s": round(render_s, 2),
                "fit_s": round(fit_s, 2), "fit_cpu_s": round(cpu_s, 2),
                "renderer": self.renderer,
                "white": "truth" if self.centres == "truth" else self.white,
                "sigma_mm": round(sigma, 3), "region_cpu_s": round(region_cpu, 4)}


def nearest(results, xy_px) -> object | None:
    """The region result whose centre is nearest ``xy_px`` (None if there is none)."""
    if not results:
        return None
    d = [math.hypot(r.x_px - xy_px[0], r.y_px - xy_px[1]) for r in results]
    return results[int(np.argmin(d))]


def run_points(cam: Camera, distances, fields, rays: int, emit) -> None:
    """One point source a capture."""
    for ad in distances:
        for frac in fields:
            xy = cam.field_xy(frac)
            obj = {"type": "point", "distance_mm": ad, "position_mm": cam.position(ad, xy)}
            img, truth, t_r = cam.render([obj], seed=3, rays=rays)
            results, per_region, wall, cpu = cam.measure(img)
            hit = nearest(results, truth["sources"][0]["centroid_px"])
            emit(cam.row("point", ad, frac, float(np.hypot(*xy)), AZIMUTH_DEG, hit, per_region,
                         t_r, wall / max(1, len(results)), cpu / max(1, len(results))))


def scene12_objects(cam: Camera) -> tuple[list[dict], list[tuple]]:
    """The 12-source scene's objects, and each one's (Ad mm, field fraction, azimuth °,
    sensor radius mm): a 4 × 3 grid, corners at 75 % of the half-field, near and far
    sources alternating."""
    grid = [(fx, fy) for fy in (-0.45, 0.0, 0.45) for fx in (-0.6, -0.2, 0.2, 0.6)]
    near, far = scene12_distances(cam)
    dists = [near[k // 2] if k % 2 == 0 else far[k // 2] for k in range(12)]
    objects, placed = [], []
    for (fx, fy), ad in zip(grid, dists, strict=True):
        xy = np.array([fx, fy]) * cam.half_field_mm
        objects.append({"type": "point", "distance_mm": ad, "position_mm": cam.position(ad, xy)})
        placed.append((ad, float(np.hypot(fx, fy)), math.degrees(math.atan2(fy, fx)),
                       float(np.hypot(*xy))))
    return objects, placed


def run_scene12(cam: Camera, rays: int, emit) -> None:
    """12 point sources in one capture."""
    objects, placed = scene12_objects(cam)
    img, truth, t_r = cam.render(objects, seed=4, rays=rays)
    results, per_region, wall, cpu = cam.measure(img)
    n = max(1, len(results))
    print(f"# 12 sources: {len(results)} regions, {wall:.0f} s", flush=True)
    for (ad, frac, az, r_mm), src in zip(placed, truth["sources"], strict=True):
        hit = nearest(results, src["centroid_px"])
        x, y = src["centroid_px"]
        if hit is not None and not (hit.bbox_px[0] <= x < hit.bbox_px[2]
                                    and hit.bbox_px[1] <= y < hit.bbox_px[3]):
            hit = None  # the nearest region does not cover this source: not found
        emit(cam.row("scene12", ad, round(frac, 3), r_mm, round(az, 1), hit, per_region, t_r / 12,
                     wall / n, cpu / n))


def scene12_distances(cam: Camera) -> tuple[list[float], list[float]]:
    """Six sources nearer than the focus and six farther (all nearer for ∞ focus)."""
    if math.isinf(cam.focus_mm):
        return [600.0, 900.0, 1200.0, 1500.0, 1800.0, 2100.0], [2400.0, 2700.0, 3000.0,
                                                                 3200.0, 3400.0, 3500.0]
    if cam.focus_mm <= 1000.0:
        return [550.0, 600.0, 650.0, 700.0, 750.0, 800.0], [1500.0, 1900.0, 2300.0, 2700.0,
                                                            3100.0, 3500.0]
    return [700.0, 800.0, 900.0, 1000.0, 1100.0, 1200.0], [2000.0, 2300.0, 2600.0, 2900.0,
                                                          3200.0, 3500.0]


def run_lines(cam: Camera, distances, rays: int, emit,
              half_mm: float = LINE_HALF_MM, field: float = 0.0) -> None:
    """Lines 2 × ``half_mm`` long on the MLA (CSV mode ``line``; another length:
    ``line-<length>mm``), centred on the field centre or at ``field`` of the half-field (the
    CSV's ``field`` and ``r_sensor_mm``)."""
    mode = "line" if half_mm == LINE_HALF_MM else f"line-{2 * half_mm:g}mm"
    centre = cam.field_xy(field)
    for ad in distances:
        for ang in LINE_ANGLES_DEG:
            img, truth, t_r = cam.render([cam.line(ad, ang, field, rays, half_mm)], seed=3,
                                         rays=rays)
            results, per_region, wall, cpu = cam.measure(img)
            hit = nearest(results, truth["sources"][0]["centroid_px"])
            emit(cam.row(mode, ad, field, float(np.hypot(*centre)), ang, hit, per_region, t_r,
                         wall / max(1, len(results)), cpu / max(1, len(results))))


def field_bin(frac: float) -> str:
    """``0``, ``<=40%`` or ``<=80%`` (fractions of the half-field)."""
    for name, lo, hi in BINS:
        if (frac == 0.0 and hi == 0.0) or lo < frac <= hi + 1e-9:
            return name
    return ">80%"


def cell(rows) -> str:
    """``mean / max (answered/total)`` of ERROR % over ``rows``."""
    e = np.array([float(r["error_pct"]) for r in rows])
    ok = np.isfinite(e)
    if not ok.any():
        return f"— (0/{len(rows)})"
    return f"{e[ok].mean():.3f} / {e[ok].max():.3f} ({ok.sum()}/{len(rows)})"


def _source_tag(row: dict) -> str:
    """``centres`` of a row, with its renderer and white when they are not lfcam.sim's."""
    tag = row["centres"]
    ren, white = row.get("renderer") or "sim", row.get("white") or "sim"
    if ren != "sim":
        tag += f", {ren} captures"
    if white not in ("sim", "truth"):
        tag += f", {white} white"
    return tag


def print_table(rows: list[dict]) -> None:
    """Markdown tables: per camera and overall, side of focus × field bin."""
    if not rows:
        return
    # rows from different renderers or whites never share a line (older CSVs: lfcam.sim)
    rows = [dict(r, centres=_source_tag(r)) for r in rows]
    for mode in sorted({r["mode"] for r in rows}):
        sel = [r for r in rows if r["mode"] == mode]
        print(f"\n### {mode}: ERROR % mean / max (answered/cases)\n")
        print("| system | focus mm | centres | side | field 0 | ≤ 40 % | ≤ 80 % | s/region wall "
              "(CPU) |")
        print("|---|---|---|---|---|---|---|---|")

        def line(label, grp, key):
            cells = []
            for name, _, _ in BINS:
                b = [r for r in grp if field_bin(float(r["field"])) == name]
                cells.append(cell(b) if b else "")
            wall = np.array([float(r["fit_s"]) for r in grp])
            cpu = np.array([float(r["fit_cpu_s"]) for r in grp])
            print(f"| {label} | {key[1]} | {key[2]} | {key[3]} | {' | '.join(cells)} | "
                  f"{wall.mean():.1f} ({cpu.mean():.1f}) |")

        keys = sorted({(r["system"], float(r["focus_mm"]), r["centres"], r["side"]) for r in sel},
                      key=lambda k: (k[2], k[0], k[1], k[3] != "front"))
        for key in keys:
            line(key[0], [r for r in sel if (r["system"], float(r["focus_mm"]), r["centres"],
                                             r["side"]) == key], (key[0], f"{key[1]:g}", *key[2:]))
        for centres in sorted({r["centres"] for r in sel}):
            for side in ("front", "behind"):
                grp = [r for r in sel if r["side"] == side and r["centres"] == centres]
                if grp:
                    line("**all**", grp, ("", "", centres, side))
        kinds = {k: sum(r["kind"] == k for r in sel) for k in sorted({r["kind"] for r in sel})}
        bad = [f"{r['system']} F{float(r['focus_mm']):g} Ad {float(r['ad_mm']):g} "
               f"field {r['field']}: {r['status']}" for r in sel if r["status"] != "ok"]
        print(f"\n{mode}: all {cell(sel)}; kinds {kinds}; not ok: {bad or 'none'}")
        # does the stated uncertainty cover the error? (CSVs with the sigma_mm column)
        z = [abs(float(r["ed_mm"]) - float(r["ad_mm"])) / float(r["sigma_mm"]) for r in sel
             if r["status"] == "ok" and r.get("sigma_mm") not in (None, "", "nan")
             and float(r["sigma_mm"]) > 0]
        if z:
            z = np.array(z)
            print(f"{mode}: |Ed − Ad| within 1σ {int((z <= 1).sum())}, within 2σ "
                  f"{int((z <= 2).sum())}, within 3σ {int((z <= 3).sum())} of {z.size}; "
                  f"largest {z.max():.1f}σ")


def read_rows(paths) -> list[dict]:
    """Rows of one or more CSVs written by this benchmark."""
    rows = []
    for p in paths:
        with open(p, newline="") as fh:
            rows.extend(csv.DictReader(fh))
    return rows


METHOD = ["lightfield"]  # set from --method
RENDER_CACHE: list = [None]  # set from --render-cache
SENSOR_GAIN = [True]  # the fits read the renders' full well (--no-sensor-gain: they do not)
TOLERANCE: list = [None]  # set from --tolerance (--method auto)


def fastfit_overrides(text: str) -> dict[str, int | float | bool]:
    """``NAME=VALUE,...`` as values for numeric constants of :mod:`lfcam.measure.fastfit`,
    each of its constant's type (a bool: 0 or 1). ``ValueError`` names one that is not."""
    out: dict[str, int | float | bool] = {}
    for item in filter(None, text.split(",")):
        name, _, value = item.partition("=")
        old = getattr(FF, name, None)
        if not isinstance(old, (int, float)) or not value:  # (bool: 0 or 1)
            raise ValueError(f"{name!r} is not a numeric constant of lfcam.measure.fastfit")
        out[name] = type(old)(float(value))
    return out


def main() -> None:
    """Render, measure, write the CSV, print the tables."""
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--systems", default="system1,system2")
    ap.add_argument("--foci", default="1000,1500,inf", help="focus distances, mm, or inf")
    ap.add_argument("--distances", help="comma-separated Ad, mm (default: per focus)")
    ap.add_argument("--fields", default="0,0.4,0.8", help="fractions of the half-field")
    ap.add_argument("--size", type=int, default=0,
                    help="square sensor crop, px (0: the profile's sensor)")
    ap.add_argument("--rotation", type=float, default=0.0, help="MLA rotation, rad")
    ap.add_argument("--grid", choices=("rect", "hex"), default=None,
                    help="the MLA's grid (default: the system's own)")
    ap.add_argument("--rays", type=int, default=1_000_000, help="rays per source")
    ap.add_argument("--quick", action="store_true", help="2 distances a side, fields 0 and 0.8")
    ap.add_argument("--method", default="lightfield", choices=("lightfield", "lenslet", "auto"),
                    help="measurement method (docs/distance.md)")
    ap.add_argument("--tolerance", type=float, default=None,
                    help="--method auto: allowed distance error, percent")
    ap.add_argument("--scene12", action="store_true", help="12 point sources in one capture")
    ap.add_argument("--lines", action="store_true", help="lines at 0°, 60°, 135°")
    ap.add_argument("--line-mm", type=float, default=2 * LINE_HALF_MM,
                    help="--lines: the line's image length on the MLA, mm (system 2's pitch is "
                         "0.25 mm: 0.75 is 3 pitches)")
    ap.add_argument("--line-field", type=float, default=0.0,
                    help="--lines: the lines' centre, a fraction of the half-field (0: axis)")
    ap.add_argument("--renderer", default="sim", choices=RENDERERS,
                    help="captures from lfcam.sim or from benchmarks/render_independent.py")
    ap.add_argument("--white", default="sim", choices=WHITES,
                    help="calibration white from lfcam.sim or benchmarks/whites_analytic.py")
    ap.add_argument("--truth-centres", action="store_true",
                    help="renderer's lenslet centres instead of the white calibration")
    ap.add_argument("--cache", type=Path,
                    default=Path(tempfile.gettempdir()) / "lfcam_focus_grid",
                    help="folder for the white-image calibrations")
    ap.add_argument("--render-cache", type=Path,
                    help="folder keeping the rendered captures (reruns of the fits reuse them)")
    ap.add_argument("--csv", type=Path, default=ROOT / "docs" / "results" / "focus_grid.csv")
    ap.add_argument("--append", action="store_true", help="append to --csv")
    ap.add_argument("--table", nargs="+", type=Path, metavar="CSV",
                    help="only print the tables of these CSVs")
    ap.add_argument("--no-sensor-gain", action="store_true",
                    help="do not give the fits the renders' full well (a capture of one small "
                         "blur then counts no photon noise, as before stop 49)")
    ap.add_argument("--noise-free", action="store_true",
                    help="no photon or read noise in the captures (--renderer sim)")
    ap.add_argument("--fastfit", default="", metavar="NAME=VALUE,...",
                    help="experiments: override constants of lfcam.measure.fastfit (e.g. "
                         "LINE_FINE_RAYS=26664, LINE_TURNS=0); printed in the log")
    args = ap.parse_args()
    if args.no_sensor_gain:
        SENSOR_GAIN[0] = False
    if args.noise_free:
        NOISE.update({"photon_noise": False, "read_noise_e": 0.0})
    try:
        overrides = fastfit_overrides(args.fastfit)
    except ValueError as exc:
        ap.error(f"--fastfit: {exc}")
    for name, value in overrides.items():
        print(f"# fastfit {name}: {getattr(FF, name)} -> {value}", flush=True)
        setattr(FF, name, value)
    METHOD[0] = args.method
    if args.render_cache:
        args.render_cache.mkdir(parents=True, exist_ok=True)
        RENDER_CACHE[0] = args.render_cache
    TOLERANCE[0] = args.tolerance
    if args.table:
        print_table(read_rows(args.table))
        return
    args.cache.mkdir(parents=True, exist_ok=True)
    # the compiled kernels loaded (or compiled, in a new checkout) before any fit is timed:
    # else the first line's row holds that (9.2 s for one independent-renderer line at stop 38)
    from lfcam.measure.kernels import warm_up
    warm_up()
    fields = [float(v) for v in args.fields.split(",")]
    if args.quick:
        fields = [0.0, 0.8]
    new = not (args.append and args.csv.exists())
    args.csv.parent.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    with open(args.csv, "w" if new else "a", newline="") as fh:
        out = csv.DictWriter(fh, fieldnames=COLUMNS)
        if new:
            out.writeheader()

        def emit(row: dict) -> None:
            rows.append(row)
            out.writerow(row)
            fh.flush()
            print(" ".join(f"{row[c]}" for c in COLUMNS[1:]), flush=True)

        print("# " + " ".join(COLUMNS[1:]))
        for system in args.systems.split(","):
            for focus in [parse_focus(v) for v in args.foci.split(",")]:
                cam = Camera(system, focus, args.size or None, args.cache, args.truth_centres,
                             args.rotation, args.renderer, args.white, args.grid)
                if args.lines:
                    dists = args.distances or LINE_DISTANCES
                    run_lines(cam, [float(v) for v in dists.split(",")], args.rays, emit,
                              0.5 * args.line_mm, args.line_field)
                    continue
                if args.scene12:
                    run_scene12(cam, args.rays, emit)
                    continue
                dists = [float(v) for v in (args.distances or DEFAULT_DISTANCES.get(
                    focus, DEFAULT_DISTANCES[1000.0])).split(",")]
                if args.quick:
                    front = [d for d in dists if d < focus]
                    behind = [d for d in dists if d >= focus]
                    dists = front[:1] + front[-1:] + behind[:1] + behind[-1:]
                    dists = sorted(set(dists))
                run_points(cam, dists, fields, args.rays, emit)
    print_table(rows)
    print(f"\nwrote {os.path.relpath(args.csv)}")


if __name__ == "__main__":
    main()
