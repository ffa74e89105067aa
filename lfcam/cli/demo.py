"""``lfcam demo``: the whole pipeline on a built-in scene — no arguments, no downloads.

1. render a white image and a scene of point sources and a 10 mm line through the exact
   system-1 optics (``lfcam.sim``), writing them as a capture with its profile and truth;
2. calibrate the microlens grid from the white image;
3. detect regions, measure them with the exact light-field fit, and turn them into distances
   with the exact model and with the seed's closed forms;
4. write ``regions.csv``, ``distance.tiff`` and ``distance.png`` into ``./lfcam-demo/`` and
   print true against estimated distances.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from lfcam.camera import load_profile

# (kind, distance_mm, lateral position as a fraction of the distance); spread over the field
SCENE = [
    ("point", 450.0, (-0.10, -0.10)),
    ("point", 900.0, (0.09, -0.09)),
    ("point", 1500.0, (-0.09, 0.09)),
    ("point", 2500.0, (0.09, 0.09)),
    ("point", 3400.0, (0.0, 0.0)),
    ("line", 1100.0, (0.10, 0.0)),
]
LINE_LENGTH_MM = 10.0
SEED = 7


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``demo`` sub-command."""
    p = sub.add_parser("demo", help="render, calibrate and measure a built-in scene")
    p.add_argument("-o", "--output", default="lfcam-demo", help="output folder (lfcam-demo)")
    p.set_defaults(func=run)


def scene_objects() -> list[dict]:
    """The demo scene in the renderer's schema (docs/simulate.md)."""
    objs = []
    for kind, dist, (fx, fy) in SCENE:
        x, y = fx * dist, fy * dist
        if kind == "point":
            objs.append({"type": "point", "distance_mm": dist, "position_mm": [x, y]})
        else:
            # radial (along the meridian), so the seed's line model (eq. 20) applies
            half = 0.5 * LINE_LENGTH_MM
            objs.append({"type": "line", "distance_mm": dist, "start_mm": [x - half, y],
                         "end_mm": [x + half, y]})
    return objs


def white_calibration(profile, out: Path) -> tuple[Path, float]:
    """Render the profile's white image, calibrate it, save ``calibration.json``.

    Returns the path and the RMS distance (px) of the calibrated centres from the renderer's
    ray-traced micro-image centroids (the independent truth of the white image).
    """
    from scipy.spatial import cKDTree

    from lfcam.calibrate import calibrate_white, save_calibration
    from lfcam.sim.capture import simulate
    from lfcam.sim.scene import scene_from_dict

    white, prof, truth = simulate(profile, scene_from_dict({"seed": SEED,
                                                            "objects": [{"type": "white"}]}))
    cal = calibrate_white(white.astype(np.float32) - np.float32(prof.sensor.black_level))
    cal = replace(cal, d_in_mm=float(prof.d_in_mm), d_in_method="profile")
    path = save_calibration(cal, out / "calibration.json")
    truth_c = np.asarray(truth["lenses"]["centroid_px"], dtype=np.float64)
    d, _ = cKDTree(truth_c).query(cal.centres_px)
    return path, float(np.sqrt(np.mean(d**2)))


def _say(text: str) -> None:
    print(text, flush=True)


def run(args: argparse.Namespace) -> int:
    """Render, calibrate, measure; print the table; write the outputs."""
    from lfcam.atomic import check_output_dir
    from lfcam.calibrate import load_calibration
    from lfcam.distance import run_distance, write_outputs
    from lfcam.io.grey import GREY_WHITE, to_grey
    from lfcam.models import line as line_model
    from lfcam.models import offaxis
    from lfcam.sim.capture import simulate, write_capture
    from lfcam.sim.scene import scene_from_dict

    out = Path(args.output)
    check_output_dir(out)
    out.mkdir(parents=True, exist_ok=True)
    profile = load_profile("system1")
    t0 = time.perf_counter()
    _say(f"lfcam demo — camera {profile.name} (seed paper's imaging system 1, F/2), "
         f"d_in = {profile.d_in_mm:.3f} mm")
    _say("1/4 rendering and calibrating the white image…")
    calib_path, rms_px = white_calibration(profile, out)
    _say(f"      {calib_path.name}: micro-image centres within {rms_px:.4f} px RMS of the "
         "ray-traced centroids")
    _say("2/4 rendering the scene: 5 point sources and a 10 mm line…")
    raw, prof, truth = simulate(profile, scene_from_dict({"seed": SEED,
                                                          "objects": scene_objects()}))
    write_capture(out / "capture.png", raw, prof, truth)
    _say("3/4 detecting and measuring regions (exact light-field fit)…")
    image = to_grey(raw, "none", prof.sensor.black_level, prof.sensor.white_level)
    calibration = load_calibration(calib_path)

    def progress(stage: str, done: int, total: int) -> None:
        print(f"      {stage} {done}/{total}", file=sys.stderr, flush=True)

    result = run_distance(image, prof, calibration, model="exact", progress=progress,
                          white_value=GREY_WHITE)
    write_outputs(out, result, "lfcam demo scene  model exact, method lightfield")
    _say(f"4/4 wrote {out}/regions.csv, distance.tiff, distance.png "
         f"({time.perf_counter() - t0:.0f} s)\n")
    head = (f"{'#':>2} {'kind':5} {'true mm':>8} {'lfcam mm':>10} {'± mm':>7} {'error %':>8}   "
            f"{'seed model mm':>13} {'error %':>8}")
    _say(head)
    _say("-" * len(head))
    sources = truth["sources"]
    errs, seed_errs = [], []
    for r in result.regions:
        src = min((s for s in sources if s.get("centroid_px")),
                  key=lambda s: np.hypot(s["centroid_px"][0] - r.x_px,
                                         s["centroid_px"][1] - r.y_px))
        true = src["distance_mm"]
        err = (r.distance_mm / true - 1) * 100 if r.status == "ok" else float("nan")
        # the seed's closed form fed the same measurement (fitted rim-ray heights)
        if src["kind"] == "line":
            a, b = src["endpoints"]
            inv = line_model.invert(prof, None, a["y1_mm"], a["y2_mm"], b["y1_mm"], b["y2_mm"])
        else:
            inv = offaxis.invert(prof, None, src["y1_mm"], src["y2_mm"])
        seed = float(inv.distance_mm)
        seed_err = (seed / true - 1) * 100
        errs.append(abs(err))
        seed_errs.append(abs(seed_err))
        _say(f"{r.region_id:>2} {r.kind:5} {true:8.0f} {r.distance_mm:10.2f} "
             f"{r.uncertainty_mm:7.2f} {err:+8.3f}   {seed:13.2f} {seed_err:+8.3f}")
    _say(f"\nmean |error|: lfcam {np.nanmean(errs):.3f} %   seed closed form "
         f"{np.nanmean(seed_errs):.3f} % (fed exact rim heights)")
    return 0
