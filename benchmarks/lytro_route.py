"""The Lytro route end to end: Illum-like LFR files in, distances out, no hand-written profile.

Run: ``PYTHONPATH=. python benchmarks/lytro_route.py [--quick] [--cache DIR] [--out DIR]``

An Illum-like camera is rendered: hex MLA of 20 µm pitch at 37 µm from the sensor (its
separation = the lenslets' focal length), 1.4 µm pixels, RGGB Bayer, 10-bit raws with black
level 64, photon noise (8000 e- full well) and 10 e- read noise (≈ 1.2 DN). The sensor is a
2000×1400 px crop of the Illum's 7728×5368
(140×98 lenslets instead of 386×268: the full frame makes the white render and every distance
run ~15× slower and adds nothing the crop lacks but field angle). The main lens is a
multi-element lens lfcam never sees as a prescription: the double Gauss of
``calibration/double_gauss.toml`` scaled to f 30 mm and opened to F/2.8, focused at 1 m.

Every capture is written as an Illum LFR through ``lfcam.io.write_lfp`` with Illum-style
metadata (``lfcam.sim.lytro``: ``devices.lens`` focal length, f-number, exit pupil offset,
zoom and focus steps; ``devices.mla``; ``devices.sensor``); nothing else goes into the user's
folder. Then the Lytro owner's commands run::

    lfcam info white.LFR
    lfcam calibrate white.LFR --targets targets.csv -o calib.json
    lfcam distance scene_k.LFR --calibration calib.json -o out_k

and ``regions.csv`` is compared with the renderer's truth (kept elsewhere). The target rig is
the one of ``benchmarks/lens_learn.py`` (5 planes between the nearest usable distance and
3500 mm, 4 point sources each; hidden sources between the planes, 3 a scene capture).
Results: ``docs/results/lytro_route.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "data" / "synthetic"))

from lens_learn import (  # noqa: E402
    HEADLINE,
    hidden_distances,
    hidden_groups,
    hidden_scene,
    lfcam,
    match_regions,
    plane_pool,
    plane_scene,
)
from lenses_e2e import double_gauss_f28  # noqa: E402

from lfcam.camera import CameraProfile, MainLens, profile_from_dict  # noqa: E402
from lfcam.optics.lens import Prescription  # noqa: E402
from lfcam.sim.capture import profile_to_dict, simulate, write_capture  # noqa: E402
from lfcam.sim.lytro import write_lytro_capture  # noqa: E402
from lfcam.sim.scene import scene_from_dict  # noqa: E402

SEED = 20261124
SCALE = 0.3  # double Gauss f 100 → f 30 mm
ZOOM_STEP, FOCUS_STEP = 412, 886  # arbitrary motor steps: they only name the lens state
# small pixels: ~8000 e- full well, 10 e- read noise (≈ 1.2 DN at 10 bit): the dark background
# is not one flat raw value, as it is on a real 10-bit sensor
NOISE = {"photon_noise": True, "full_well_e": 8000.0, "read_noise_e": 10.0}


def illum_like(width_px: int, height_px: int) -> CameraProfile:
    """The rendering camera (the prescription stays in this script)."""
    dg = double_gauss_f28()
    rx = dg.main_lens.as_prescription
    surfaces = tuple(
        dataclasses.replace(s, radius_mm=s.radius_mm * SCALE, thickness_mm=s.thickness_mm * SCALE,
                            semi_diameter_mm=s.semi_diameter_mm * SCALE)
        for s in rx.surfaces)
    d = profile_to_dict(dg)
    d["name"] = "illum-like"
    d["main_lens"] = MainLens(prescription=Prescription(surfaces, name="f30 F/2.8")).to_dict()
    d["mla"] = {"focal_length_mm": 0.037, "pitch_mm": 0.020, "grid": "hex", "focus_mm": 1000.0,
                "rotation_rad": -0.0008, "offset_mm": [0.0014, 0.0063]}
    d["sensor"] = {"pixel_pitch_mm": 0.0014, "width_px": width_px, "height_px": height_px,
                   "bit_depth": 10, "bayer": "RGGB", "black_level": 64, "white_level": 1023}
    return profile_from_dict(d)


def render_lfr(profile: CameraProfile, body: dict, cache: Path, user: Path,
               name: str) -> tuple[Path, dict]:
    """Render once into the cache (LFR, truth, profile); only the LFR goes to the user folder."""
    lfr, tru = cache / f"{name}.LFR", cache / f"{name}.truth.json"
    if not (lfr.is_file() and tru.is_file()):
        raw, used, truth = simulate(profile, scene_from_dict(body))
        write_capture(lfr, raw, used, truth)  # truth and the rendering profile stay in cache
        write_lytro_capture(lfr, raw, used, zoom_step=ZOOM_STEP, focus_step=FOCUS_STEP)
    dst = user / lfr.name
    if not dst.is_file():
        shutil.copyfile(lfr, dst)
    return dst, json.loads(tru.read_text(encoding="utf-8"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="1000×700 px crop, a third of the "
                    "hidden sources")
    ap.add_argument("--cache", default=str(Path(os.environ.get("TMPDIR", "/tmp"))
                                           / "lfcam_lytro_route"))
    ap.add_argument("--out", default=str(ROOT / "docs" / "results"))
    ap.add_argument("--method", default=None,
                    help="pass --method to lfcam distance (default: lfcam's own choice)")
    ap.add_argument("--reuse-calibration", action="store_true",
                    help="keep an existing calib.json from an earlier run (skip the lens fit)")
    args = ap.parse_args()
    w, h = (1000, 700) if args.quick else (2000, 1400)
    prof = illum_like(w, h)
    cache = Path(args.cache) / f"{w}x{h}"
    user = cache / "user"
    user.mkdir(parents=True, exist_ok=True)
    t0 = time.process_time()
    pool = plane_pool(prof)
    planes = [pool[i] for i in HEADLINE]
    hid = hidden_distances(pool)
    if args.quick:
        hid = hid[::3]
    print(f"Illum-like {w}x{h} px, lens EFL {prof.main_lens.focal_length_mm:.3f} mm "
          f"F/{prof.main_lens.f_number:.2f}, focus 1000 mm\nplanes {planes}\nhidden {hid}",
          flush=True)
    white, _ = render_lfr(prof, {"seed": SEED, "objects": [{"type": "white"}],
                                 "sensor": NOISE}, cache, user, "white")
    files = [render_lfr(prof, plane_scene(prof, d, SEED + 10 + k, NOISE), cache, user,
                        f"plane_{int(d)}")[0] for k, d in enumerate(planes)]
    scenes = [render_lfr(prof, hidden_scene(prof, ds, SEED + 100 + k, NOISE), cache, user,
                         f"scene_{k}") for k, ds in enumerate(hidden_groups(hid))]
    render_cpu = time.process_time() - t0
    (user / "targets.csv").write_text(
        "capture,distance_mm\n" + "".join(f"{p.name},{d:.1f}\n"
                                          for p, d in zip(files, planes, strict=True)),
        encoding="utf-8")
    code, msg, _ = lfcam("info", str(white))
    print(f"lfcam info white.LFR: exit {code} {msg}", flush=True)
    calib = user / "calib.json"
    if args.reuse_calibration and calib.is_file():
        code, msg, cal_cpu = 0, "reused", 0.0
    else:
        calib.unlink(missing_ok=True)
        code, msg, cal_cpu = lfcam("calibrate", str(white), "--targets",
                                   str(user / "targets.csv"), "-o", str(calib), "--quiet")
    print(f"lfcam calibrate white.LFR --targets targets.csv: exit {code} {msg} "
          f"(CPU {cal_cpu:.0f} s)", flush=True)
    rows, missed, failure = [], 0, "" if code == 0 else f"calibrate exit {code}: {msg}"
    pitch_px = prof.mla.pitch_mm / prof.sensor.pixel_pitch_mm
    if code == 0:
        for k, (lfr, truth) in enumerate(scenes):
            out = user / f"out_{k}"
            shutil.rmtree(out, ignore_errors=True)
            extra = ["--method", args.method] if args.method else []
            code, msg, cpu = lfcam("distance", str(lfr), "--calibration", str(calib), "-o",
                                   str(out), "--quiet", *extra)
            if code != 0:
                failure = f"distance exit {code}: {msg}"
                missed += len(truth["sources"])
                continue
            for m, src in zip(match_regions(out / "regions.csv", truth, pitch_px,
                                            prof.sensor.pixel_pitch_mm), truth["sources"],
                              strict=True):
                err = 100.0 * abs(m["estimate_mm"] - m["distance_mm"]) / m["distance_mm"]
                rows.append((m["distance_mm"], src["offset_mm"], m["estimate_mm"], err))
                missed += int(math.isnan(err))
                print(f"  {m['distance_mm']:7.0f} mm  offset {src['offset_mm']:6.2f} mm  "
                      f"estimate {m['estimate_mm']:9.2f} mm  error {err:6.2f} %", flush=True)
    errs = np.array([r[3] for r in rows if not math.isnan(r[3])])
    mean = float(errs.mean()) if errs.size else math.nan
    mx = float(errs.max()) if errs.size else math.nan
    print(f"\nmean {mean:.3f} %  max {mx:.3f} %  ({errs.size} sources, {missed} missed) "
          f"{failure}")
    md = ["# The Lytro route on rendered Illum-like LFR files (issue 15)", "",
          f"Produced by `PYTHONPATH=. python benchmarks/lytro_route.py"
          f"{' --quick' if args.quick else ''}` (render CPU {render_cpu:.0f} s). "
          f"Sensor crop {w}×{h} px of 1.4 µm (Illum: 7728×5368), hex MLA 20 µm at 37 µm, "
          "RGGB, 10 bit; lens: a double Gauss scaled to "
          f"f {prof.main_lens.focal_length_mm:.2f} mm F/{prof.main_lens.f_number:.2f}, "
          "focus 1 m, never given to lfcam. Commands: `lfcam calibrate white.LFR --targets "
          "targets.csv -o calib.json`, `lfcam distance scene_k.LFR --calibration calib.json "
          "-o out_k` (no `--profile`).", "",
          f"Calibration planes (mm): {', '.join(f'{d:g}' for d in planes)}; "
          f"4 sources each. {failure}", "",
          "| distance mm | offset mm | estimate mm | error % |", "|---|---|---|---|"]
    md += [f"| {d:g} | {o:.2f} | {e:.2f} | {x:.2f} |" for d, o, e, x in rows]
    md += ["", f"**Mean {mean:.2f} %, max {mx:.2f} %** over {errs.size} hidden sources"
           f"{f', {missed} missed' if missed else ''}."]
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "lytro_route.md").write_text("\n".join(md) + "\n", encoding="utf-8")
    print(f"wrote {out_dir / 'lytro_route.md'}")


if __name__ == "__main__":
    main()
