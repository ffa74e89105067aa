"""Full-size whites from both rendering paths, calibrated side by side (issue 16).

For each camera (shipped profile, MLA rotated by ``--rotation``, optionally a hex MLA) this
renders two noisy whites of the full sensor:

* ``lfcam.sim`` — the renderer (``lfcam simulate``'s white): photon noise at a 20 000 e⁻ full
  well, 5 e⁻ read noise. Truth: ``lenses.centroid_px`` (ray-traced centroid of each
  lenslet's own light); fully visible = the renderer's ``complete``.
* ``analytic`` — ``benchmarks/whites_analytic.py``: each pixel's irradiance integrated
  directly (exact backward thick-lens trace, no ``lfcam.sim`` code), same noise. Truth:
  centroid of each lenslet's own noise-free light; fully visible = < 1e-4 of its light on the
  outermost pixel rows/columns.

and calibrates each with ``lfcam.calibrate.calibrate_white``. Columns: found (matched one-to-
one within pitch/4) / fully visible, with the percentage; centres returned beyond the fully
visible set; invented (farther than pitch/4 from every lit lenslet); rejected counts per
reason; centre RMS / max error against the truth centroids (matched, fully visible); the
noise-limited expectation of that RMS (√mean σ², σ from the analytic white's expectation:
pixel shot + read noise split between lenslets by their light, propagated through the
centroid, ``analytic_white_truth``); the calibration's lattice residual and the same lattice
model's residual on the truth centroids; the fitted model, radial term (largest radial shift
over the sensor, px) and CPU time of the calibration.

Run:  python benchmarks/whites_fullsize.py [--cameras system1:rect system2:rect system2:hex]
      [--samples 16]   (renders cached in $TMPDIR; ~25 min CPU the first time)
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from calibrate_touching import match_one_to_one  # noqa: E402
from whites_analytic import analytic_white_truth  # noqa: E402

from lfcam.calibrate import calibrate_white  # noqa: E402
from lfcam.camera import load_profile  # noqa: E402
from lfcam.sim.capture import apply_overrides, simulate  # noqa: E402
from lfcam.sim.scene import scene_from_dict  # noqa: E402

FULL_WELL_E, READ_NOISE_E = 20000.0, 5.0


def camera(system: str, grid: str, rotation: float) -> dict:
    """Camera overrides of one case."""
    return {"mla": {"grid": grid, "rotation_rad": rotation}}


def render_both(system: str, grid: str, rotation: float, samples: int):
    """Both whites and their truth (cached)."""
    tag = f"{system}_{grid}_{rotation:+.4f}_{samples}"
    cache = Path(tempfile.gettempdir()) / f"lfcam_whites_fullsize_{tag}_v1.npz"
    if cache.exists():
        z = np.load(cache)
        return {k: z[k] for k in z.files}
    cam = camera(system, grid, rotation)
    prof = apply_overrides(load_profile(system), cam)
    t = time.process_time()
    white_a, ta = analytic_white_truth(prof, samples, seed=3, full_well_e=FULL_WELL_E,
                                       read_noise_e=READ_NOISE_E)
    t_a = time.process_time() - t
    t = time.process_time()
    white_s, _, ts = simulate(load_profile(system), scene_from_dict(
        {"seed": 5, "objects": [{"type": "white"}], "camera": cam,
         "sensor": {"photon_noise": True, "full_well_e": FULL_WELL_E,
                    "read_noise_e": READ_NOISE_E}}))
    t_s = time.process_time() - t
    ls = ts["lenses"]
    out = {"white_a": white_a.astype(np.float32), "white_s": white_s.astype(np.float32),
           "a_centroid": ta["centroid_px"], "a_complete": ta["complete"],
           "a_sigma": ta["sigma_px"], "a_flux": ta["flux"],
           "s_centroid": np.asarray(ls["centroid_px"], float),
           "s_complete": np.asarray(ls["complete"], bool),
           "t_a": t_a, "t_s": t_s}
    np.savez(cache, **out)
    print(f"{tag}: analytic {t_a:.0f} s CPU, lfcam.sim {t_s:.0f} s CPU", flush=True)
    return out


def score(cal, truth_c: np.ndarray, complete: np.ndarray, pitch: float) -> dict:
    """Match ``cal``'s centres to the truth centroids (one-to-one within pitch/4)."""
    lit = truth_c[np.isfinite(truth_c).all(axis=1)]
    vis = truth_c[complete & np.isfinite(truth_c).all(axis=1)]
    c = np.asarray(cal.centres_px)
    lim = 0.25 * pitch
    matched, ic, err = match_one_to_one(c, vis, lim)
    d_lit, j_lit = cKDTree(lit).query(c)
    # the lattice model of the calibration, applied to the truth centroids of its lenses
    idx = np.asarray(cal.indices)[d_lit < lim]
    tr = lit[j_lit[d_lit < lim]]
    res_t = tr - cal.predict(idx)
    return {"found": int(matched.sum()), "visible": len(vis),
            "beyond": int(np.sum(~matched & (d_lit < lim))),
            "invented": int(np.sum(d_lit >= lim)),
            "rms": float(np.sqrt(np.mean(err ** 2))), "max": float(err.max()),
            "truth_lattice_rms": float(np.sqrt(np.mean(np.sum(res_t ** 2, axis=1)))),
            "matched_idx": ic[matched]}


def radial_shift_px(cal, shape) -> float:
    """Largest displacement of the radial term over the sensor (0 without one)."""
    if cal.lattice_radial is None:
        return 0.0
    cx, cy, k1, k2 = cal.lattice_radial
    h, w = shape
    rho = max(np.hypot(x - cx, y - cy) for x in (0, w) for y in (0, h)) / 1000.0
    return float(abs(k1 * rho ** 2 + k2 * rho ** 4) * rho * 1000.0)


def main() -> None:
    """Print the side-by-side table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", nargs="+", default=["system1:rect", "system2:rect",
                                                      "system2:hex"])
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--rotation", type=float, default=0.012)
    args = ap.parse_args()
    rows = []
    for cam in args.cameras:
        system, grid = cam.split(":")
        d = render_both(system, grid, args.rotation, args.samples)
        for path, key in (("lfcam.sim", "s"), ("analytic", "a")):
            white = d[f"white_{key}"]
            t = time.process_time()
            cal = calibrate_white(white)
            cpu = time.process_time() - t
            sc = score(cal, d[f"{key}_centroid"], d[f"{key}_complete"], cal.pitch_px)
            # noise-limited expectation: σ of the analytic white's lenslets (same camera)
            vis_a = d["a_complete"]
            sig = d["a_sigma"][vis_a]
            if key == "a":
                sig = sig[sc["matched_idx"]]
            expect = float(np.sqrt(np.mean(sig ** 2)))
            rej = dict(cal.rejected) if cal.rejected else {}
            diag = cal.diagnostics
            rows.append((cam, path, sc, expect, rej, cal, cpu, diag, white.shape))
            print(f"{cam} {path}: found {sc['found']}/{sc['visible']} rms {sc['rms']:.4f} "
                  f"(noise {expect:.4f}) lattice {cal.residual_rms_px:.4f} rej {rej} "
                  f"model {cal.model} radial {radial_shift_px(cal, white.shape):.3f} px "
                  f"{cpu:.1f} s CPU", flush=True)
    print()
    print("| camera | white | found / fully visible | beyond | invented | rejected | centre RMS "
          "(max) px | noise-limited px | lattice residual px (truth on same model) | model | "
          "radial shift px | solver | CPU s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for cam, path, sc, expect, rej, cal, cpu, diag, shape in rows:
        print(f"| {cam} | {path} | {sc['found']} / {sc['visible']} "
              f"({100 * sc['found'] / sc['visible']:.2f} %) | {sc['beyond']} | "
              f"{sc['invented']} | {', '.join(f'{k} {v}' for k, v in rej.items()) or '0'} | "
              f"{sc['rms']:.4f} ({sc['max']:.3f}) | {expect:.4f} | {cal.residual_rms_px:.4f} "
              f"({sc['truth_lattice_rms']:.4f}) | {cal.model} | "
              f"{radial_shift_px(cal, shape):.3f}"
              f" | {diag.get('model_solver', diag.get('centroid_method'))} | {cpu:.1f} |")


if __name__ == "__main__":
    main()
