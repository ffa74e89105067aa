"""Learning a black-box main lens (issue 15), quick end-to-end run on held-out lenses.

Run: ``PYTHONPATH=. python benchmarks/lensfit_quick.py [--configs cooke-1m,dg-inf] [--rays N]``

For each held-out lens (``calibration/cooke_triplet.toml``, ``calibration/double_gauss.toml``;
the fit never sees their prescriptions) and focus:

* the white image is rendered and calibrated from the renderer's micro-image centroids
  (``data/synthetic/make_calibration.py``);
* the profile given to the fit is a black box: the focal length and f-number as a barrel
  states them (rounded: 50 mm F/4, 100 mm F/4) and the exit pupil → MLA distance rounded to
  0.1 mm, plus the MLA and sensor;
* 5 target planes (300 … 3500 mm) with 4 point sources each, one capture a plane;
* hidden sources at other distances and field positions, measured with the learned lens and,
  as the baseline of the measurement itself, with the true prescription (same method,
  ``lenslet``, same captures).

Prints the fitted parameters and per-config tables; ``--csv`` writes the hidden rows.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "data" / "synthetic"))

from make_calibration import reference_calibration  # noqa: E402

from lfcam.calibrate.lensfit import Target, fit_lens, learned_profile  # noqa: E402
from lfcam.camera import load_profile, profile_from_dict  # noqa: E402
from lfcam.distance import run_distance  # noqa: E402
from lfcam.measure import prepare_geometry  # noqa: E402
from lfcam.sim.capture import simulate  # noqa: E402
from lfcam.sim.scene import scene_from_dict  # noqa: E402

NOISE = {"photon_noise": True, "full_well_e": 20000.0, "read_noise_e": 3.0}
CONFIGS = {
    # name: (profile, focus_mm, barrel focal length, barrel f-number, planes, hidden distances)
    "cooke-1m": ("cooke_triplet", 1000.0, 50.0, 4.0, (300, 550, 1600, 2500, 3500),
                 (400, 650, 1400, 2000, 3000)),
    "cooke-inf": ("cooke_triplet", math.inf, 50.0, 4.0, (300, 500, 900, 1800, 3500),
                  (400, 700, 1300, 2500, 3000)),
    "dg-1m": ("double_gauss", 1000.0, 100.0, 4.0, (300, 550, 1600, 2500, 3500),
              (400, 650, 1400, 2000, 3000)),
    "dg-inf": ("double_gauss", math.inf, 100.0, 4.0, (300, 500, 900, 1800, 3500),
               (400, 700, 1300, 2500, 3000)),
}


def black_box(true, focal_mm: float, f_number: float):
    """The profile a user writes: barrel focal length and f-number, exit pupil → MLA."""
    xp = round(true.d_in_mm - true.main_lens.exit_pupil_z_mm, 1)
    s = true.sensor
    return profile_from_dict({
        "name": f"{true.name}-black-box",
        "main_lens": {"focal_length_mm": focal_mm, "f_number": f_number, "exit_pupil_mm": xp},
        "mla": {"focal_length_mm": true.mla.focal_length_mm, "pitch_mm": true.mla.pitch_mm,
                "grid": true.mla.grid},
        "sensor": {"pixel_pitch_mm": s.pixel_pitch_mm, "width_px": s.width_px,
                   "height_px": s.height_px},
    })


def render(true, distance_mm: float, image_xy_mm: list, seed: int, rays: int) -> np.ndarray:
    """Point sources whose chief rays land near ``image_xy_mm`` on the MLA."""
    lens = true.main_lens
    v = true.d_in_mm - lens.back_principal_z_mm
    u = distance_mm + lens.front_principal_z_mm
    m = v / u
    objs = [{"type": "point", "distance_mm": distance_mm,
             "position_mm": [-x / m, -y / m]} for x, y in image_xy_mm]
    scene = {"seed": seed, "rays_per_source": rays, "sensor": NOISE, "objects": objs}
    raw, _, _ = simulate(true, scene_from_dict(scene))
    return raw.astype(np.float64)


def target_positions(true, distance_mm: float, half_mm: float, phase: float,
                     radius_frac: float = 0.55) -> list:
    """4 sources on a ring when their blurs stay apart and on the sensor, else 2, else 1."""
    from lfcam.optics.trace import forward

    fw = forward(true, None, distance_mm, 0.0)
    blur = abs(float(fw.y1_mm - fw.y2_mm)) * 1.15 + 0.15
    r = min(radius_frac * half_mm, 0.95 * half_mm - 0.5 * blur)
    if r > 0 and 2 * r * math.sin(math.pi / 4) > blur:
        return ring(r, 4, phase)
    if r > 0 and 2 * r > blur:
        return ring(r, 2, phase)
    return [(0.05 * half_mm, 0.0)]


def ring(radius_mm: float, n: int, phase: float) -> list:
    return [(radius_mm * math.cos(phase + 2 * math.pi * k / n),
             radius_mm * math.sin(phase + 2 * math.pi * k / n)) for k in range(n)]


def run_config(name: str, rays: int) -> list[dict]:
    prof_name, focus, f_label, n_label, planes, hidden = CONFIGS[name]
    true = load_profile(prof_name)
    true = replace(true, mla=replace(true.mla, distance_mm=None, focus_mm=focus))
    true = true.with_d_in(true.d_in_mm)
    half = 0.5 * true.sensor.width_px * true.sensor.pixel_pitch_mm
    t0 = time.perf_counter()
    cal = reference_calibration(true)
    box = black_box(true, f_label, n_label)
    targets = [Target(render(true, d, target_positions(true, d, half, 0.3 + i), 100 + i, rays),
                      float(d), f"{d}mm") for i, d in enumerate(planes)]
    t1 = time.perf_counter()
    c0 = time.process_time()
    fit = fit_lens(box, cal, targets)
    cpu = time.process_time() - c0
    t2 = time.perf_counter()
    par = true.main_lens
    print(f"\n## {name}: {par.as_prescription.name or prof_name}, focus {focus:g} mm; "
          f"black box f {f_label} F/{n_label}, exit pupil {box.main_lens.black_box.exit_pupil_mm}"
          f" mm; render+calibrate {t1 - t0:.0f} s, fit {t2 - t1:.0f} s wall, {cpu:.0f} s CPU")
    print(f"true: f {par.focal_length_mm:.3f} mm, H {par.front_principal_z_mm:.3f}, "
          f"d_in − H′ {true.d_in_mm - par.back_principal_z_mm:.3f} mm, exit pupil diameter "
          f"{par.exit_pupil_diameter_mm:.3f} mm")
    for n, v, s in zip(fit.names, fit.values, fit.sigma, strict=True):
        print(f"  {n:16s} {v:10.4f} ± {s:.4f}   {fit.why[n]}")
    print(f"  d_in − principal {fit.param('d_in_mm') - fit.param('principal_mm'):.4f} mm; "
          f"exit pupil diameter {fit.exit_pupil_diameter_mm:.4f} mm; "
          f"{fit.why['spherical_lsa_mm']}; zone: {fit.why['spherical_zone_lsa_mm']}")
    res = np.array([r.error_pct for r in fit.residuals])
    print(f"targets: {fit.n_sources} sources, |error| mean {np.abs(res).mean():.3f} %, "
          f"max {np.abs(res).max():.3f} %")
    learned = learned_profile(box, fit.to_dict())
    nocal = replace(cal, d_in_mm=None)
    g_learned = prepare_geometry(learned, nocal, (true.sensor.height_px, true.sensor.width_px))
    g_true = prepare_geometry(true, replace(cal, d_in_mm=true.d_in_mm),
                              (true.sensor.height_px, true.sensor.width_px))
    rows = []
    print("| distance mm | image radius mm | learned error % | true-lens error % |")
    print("|---|---|---|---|")
    for i, d in enumerate(hidden):
        pos = target_positions(true, d, half, 1.1 + 0.7 * i, radius_frac=0.4 + 0.1 * (i % 3))
        img = render(true, d, pos, 500 + i, rays)
        out = {}
        for label, p, g in (("learned", learned, g_learned), ("true", true, g_true)):
            run = run_distance(img, p, None, model="exact", method="lenslet", geometry=g)
            out[label] = {round(r.x_px): r for r in run.regions}
        for key, r in sorted(out["learned"].items()):
            rt_ = out["true"].get(key)
            pp = true.sensor.pixel_pitch_mm
            rad = math.hypot(r.x_px - 0.5 * (true.sensor.width_px - 1),
                             r.y_px - 0.5 * (true.sensor.height_px - 1)) * pp
            el = 100 * (r.distance_mm / d - 1) if r.status == "ok" else math.nan
            et = 100 * (rt_.distance_mm / d - 1) if rt_ is not None and rt_.status == "ok" \
                else math.nan
            rows.append({"config": name, "distance_mm": d, "radius_mm": rad,
                         "learned_error_pct": el, "true_error_pct": et,
                         "learned_status": str(r.status)})
            print(f"| {d} | {rad:.2f} | {el:+.3f} ({r.kind}, {r.status}) | {et:+.3f} |")
    el = np.array([r["learned_error_pct"] for r in rows])
    et = np.array([r["true_error_pct"] for r in rows])
    print(f"hidden: learned |error| mean {np.nanmean(np.abs(el)):.3f} %, max "
          f"{np.nanmax(np.abs(el)):.3f} % ({np.isfinite(el).sum()}/{len(el)} measured); "
          f"true lens mean {np.nanmean(np.abs(et)):.3f} %, max {np.nanmax(np.abs(et)):.3f} %")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", default="cooke-1m,dg-inf")
    ap.add_argument("--rays", type=int, default=200_000)
    ap.add_argument("--csv", help="write the hidden-source rows here")
    args = ap.parse_args()
    rows = []
    for name in args.configs.split(","):
        rows += run_config(name.strip(), args.rays)
    if args.csv:
        from lfcam.atomic import atomic_write_text

        keys = list(rows[0])
        text = ",".join(keys) + "\n" + "".join(
            ",".join(str(r[k]) for k in keys) + "\n" for r in rows)
        atomic_write_text(Path(args.csv), text)


if __name__ == "__main__":
    main()
