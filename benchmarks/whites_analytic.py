"""White images from a second, independent rendering path, and what calibration makes of them.

``analytic_white`` computes each pixel's irradiance directly, without :mod:`lfcam.sim`: a
white (uniform-radiance) scene sends every direction through every point of a lenslet's
aperture; an ideal lenslet focused at infinity sends the parallel bundle of slope
``σ = (s − c)/f_x`` to the sensor point ``s``. So pixel ``s`` under lenslet ``c`` receives

    E(s) ∝ ∫_pixel ∫_aperture  pass(p, σ(s')) · cos⁴θ(p, s')  dp ds'

where ``pass`` is the exact backward thick-lens trace (:func:`lfcam.optics.trace.
trace_backward_fast`) of the ray at MLA point ``p`` with slope ``σ`` (it must clear the
stop and the lens edge) and θ is the image-side angle from ``p`` to ``s'``. The integral is
a stratified sum (jittered 4-D strata over pixel × aperture) over the 3×3 lenslets nearest
each pixel, so overlapping micro-images (system 2) add up. Shot noise: Poisson at
``full_well_e`` for the brightest pixel, plus Gaussian read noise, 16-bit clipped.

Run:  python benchmarks/whites_analytic.py [--system system2] [--size 1024] [--samples 16]
It calibrates (``lfcam.calibrate.calibrate_white``) the analytic white and ``lfcam.sim``'s
white of the same camera and prints residual and converged/rejected counts side by side.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lfcam.camera import CameraProfile, load_profile  # noqa: E402
from lfcam.optics.mla import MlaGrid  # noqa: E402
from lfcam.optics.trace import trace_backward_fast  # noqa: E402


def analytic_white(profile: CameraProfile, samples: int = 16, seed: int = 0,
                   full_well_e: float = 20000.0, read_noise_e: float = 3.0,
                   noise: bool = True) -> np.ndarray:
    """Per-pixel analytic white of ``profile`` (module docstring); uint16-scaled float array.

    Parameters
    ----------
    profile : CameraProfile
    samples : int
        Jittered samples per pixel and lenslet (a perfect square: √n × √n strata of the pixel,
        each paired with a random stratum of the aperture).
    seed : int
    full_well_e, read_noise_e : float
        Electrons at the brightest pixel; read noise σ in electrons.
    noise : bool
        Add shot and read noise (else the expectation, scaled to 65535 at the peak).
    """
    return analytic_white_truth(profile, samples, seed, full_well_e, read_noise_e, noise)[0]


def analytic_white_truth(profile: CameraProfile, samples: int = 16, seed: int = 0,
                         full_well_e: float = 20000.0, read_noise_e: float = 3.0,
                         noise: bool = True) -> tuple[np.ndarray, dict]:
    """:func:`analytic_white` plus the truth of every lenslet that lights the sensor.

    Returns
    -------
    white : (H, W) float
    truth : dict
        ``indices`` (N, 2) lattice indices (i, j) of the MLA grid; ``centroid_px`` (N, 2)
        intensity centroid of each lenslet's own (noise-free) light; ``flux`` (N,);
        ``complete`` (N,) the lenslet puts < 1e-4 of its light on the outermost pixel rows
        and columns (its micro-image is fully on the sensor); ``sigma_px`` (N,) the noise-
        limited error of an own-light centroid, √(σx² + σy²): pixel noise (shot at
        ``full_well_e`` for the brightest pixel plus read noise, in the same units) split
        between the lenslets sharing the pixel in proportion to their light,
        σx² = Σ (x − cx)² · share² · var / flux².
    """
    rng = np.random.default_rng(seed)
    s = profile.sensor
    lens = profile.main_lens
    grid = MlaGrid.from_mla(profile.mla)
    fx = profile.mla.focal_length_mm
    d_in = profile.d_in_mm
    pp = s.pixel_pitch_mm
    ax, ay = s.axis_xy_px
    k = int(round(np.sqrt(samples)))
    n = k * k
    basis = grid.basis_mm * grid.fill_factor
    mag = 1.0 + fx / (d_in - lens.exit_pupil_z_mm)
    out = np.zeros((s.height_px, s.width_px))
    rows = max(1, 2_000_000 // (s.width_px * n * 9))
    cols = np.arange(s.width_px, dtype=np.float64)
    st = (np.arange(k) + 0.5) / k - 0.5  # stratum centres in [−½, ½)
    su, sv = [a.ravel() for a in np.meshgrid(st, st)]
    # lattice index range of every lenslet that can light the sensor (corners ± 3)
    cu, cv = grid.lattice_coords((np.array([0, s.width_px, 0, s.width_px]) - ax) * pp / mag,
                                 (np.array([0, 0, s.height_px, s.height_px]) - ay) * pp / mag)
    ilo, jlo = int(np.floor(cu.min())) - 3, int(np.floor(cv.min())) - 3
    ni, nj = int(np.ceil(cu.max())) + 4 - ilo, int(np.ceil(cv.max())) + 4 - jlo
    # per lenslet: Σ e·(1, x, y); border light; for the noise: Σ share²·E·(1, x, y, x², y²)
    # (shot part) and Σ share²·(…) (read part), combined at the end when the scale is known
    mom = np.zeros((3, ni * nj))
    border = np.zeros(ni * nj)
    var_shot = np.zeros((5, ni * nj))
    var_read = np.zeros((5, ni * nj))
    for r0 in range(0, s.height_px, rows):
        r1 = min(s.height_px, r0 + rows)
        yy, xx = np.meshgrid(np.arange(r0, r1, dtype=np.float64), cols, indexing="ij")
        xp, yp = xx.ravel(), yy.ravel()
        m = xp.size
        edge_pix = (xp == 0) | (xp == s.width_px - 1) | (yp == 0) | (yp == s.height_px - 1)
        # the lenslet whose micro-image centre is nearest, and its 8 neighbours
        u, v = grid.lattice_coords((xp - ax) * pp / mag, (yp - ay) * pp / mag)
        i0, j0 = np.rint(u), np.rint(v)
        acc = np.zeros(m)
        per = np.zeros((9, m))
        ids = np.zeros((9, m), np.int64)
        for q9, (di, dj) in enumerate((a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)):
            cx, cy = grid.centre_mm(i0 + di, j0 + dj)
            ids[q9] = (i0 + di - ilo).astype(np.int64) * nj + (j0 + dj - jlo).astype(np.int64)
            for t in range(n):
                jit = rng.random((4, m)) / k
                # pixel stratum t, a random aperture stratum (drawn per pixel)
                q = rng.integers(0, n, m)
                sxm = (xp + su[t] + jit[0] - 0.5 / k - ax) * pp
                sym = (yp + sv[t] + jit[1] - 0.5 / k - ay) * pp
                a = su[q] + jit[2] - 0.5 / k
                b = sv[q] + jit[3] - 0.5 / k
                px = cx + basis[0, 0] * a + basis[0, 1] * b
                py = cy + basis[1, 0] * a + basis[1, 1] * b
                slx, sly = (sxm - cx) / fx, (sym - cy) / fx
                tr = trace_backward_fast(lens, px, py, d_in, slx, sly)
                ex, ey = sxm - px, sym - py
                cos2 = fx * fx / (fx * fx + ex * ex + ey * ey)
                per[q9] += np.where(tr.ok, cos2 * cos2, 0.0)
        per /= n
        acc = per.sum(axis=0)
        share = per / np.where(acc > 0, acc, 1.0)
        feats = np.stack([np.ones(m), xp, yp, xp * xp, yp * yp])
        for q9 in range(9):
            e = per[q9]
            lit = e > 0
            if not lit.any():
                continue
            li = ids[q9][lit]
            for c_, f_ in enumerate((e, e * xp, e * yp)):
                mom[c_] += np.bincount(li, f_[lit], ni * nj)
            border += np.bincount(li, (e * edge_pix)[lit], ni * nj)
            s2 = share[q9][lit] ** 2
            for c_ in range(5):
                var_shot[c_] += np.bincount(li, (s2 * acc[lit] * feats[c_][lit]), ni * nj)
                var_read[c_] += np.bincount(li, (s2 * feats[c_][lit]), ni * nj)
        out[r0:r1] = acc.reshape(r1 - r0, s.width_px)
    scale = full_well_e / out.max()  # electrons per unit of ``out``
    electrons = out * scale
    # noise-limited centroid error per lenslet (variance in units of ``out``²)
    var = var_shot / scale + var_read * (read_noise_e / scale) ** 2
    lit = mom[0] > 0
    f0 = np.where(lit, mom[0], 1.0)
    cxs, cys = mom[1] / f0, mom[2] / f0
    sx2 = var[3] - 2 * cxs * var[1] + cxs * cxs * var[0]
    sy2 = var[4] - 2 * cys * var[2] + cys * cys * var[0]
    sigma = np.sqrt(np.maximum(sx2 + sy2, 0.0)) / f0
    ii, jj = np.divmod(np.arange(ni * nj), nj)
    truth = {"indices": np.column_stack([ii + ilo, jj + jlo])[lit],
             "centroid_px": np.column_stack([cxs, cys])[lit], "flux": mom[0][lit],
             "complete": (border < 1e-4 * mom[0])[lit], "sigma_px": sigma[lit]}
    if noise:
        electrons = rng.poisson(electrons).astype(np.float64)
        electrons += rng.normal(0.0, read_noise_e, electrons.shape)
    dn = electrons * (65535.0 / full_well_e)
    return np.clip(np.rint(dn), 0, 65535), truth


def _summary(cal, visible: int) -> str:
    rej = sum(cal.rejected.values()) if cal.rejected else 0
    radial = "none" if cal.lattice_radial is None else f"k1={cal.lattice_radial[2]:+.3f}"
    return (f"{len(cal.centres_px):6d} centres ({100 * len(cal.centres_px) / visible:5.1f} % of "
            f"{visible} visible) | rejected {rej:5d} {dict(cal.rejected)} | residual "
            f"{cal.residual_rms_px:.4f} px | model {cal.model} | radial {radial}")


def main() -> None:
    """Render both whites, calibrate both, print the comparison."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--system", default="system2")
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--rotation", type=float, default=0.012)
    args = ap.parse_args()
    from lfcam.calibrate import calibrate_white
    from lfcam.sim.capture import apply_overrides, simulate
    from lfcam.sim.scene import scene_from_dict

    base = load_profile(args.system)
    cam = {"mla": {"rotation_rad": args.rotation},
           "sensor": {"width_px": args.size, "height_px": args.size}}
    prof = apply_overrides(base, cam)
    t0 = time.time()
    white_a = analytic_white(prof, args.samples)
    t1 = time.time()
    white_s, used, truth = simulate(base, scene_from_dict(
        {"seed": 5, "objects": [{"type": "white"}], "camera": cam,
         "sensor": {"photon_noise": True, "full_well_e": 20000, "read_noise_e": 3.0}}))
    t2 = time.time()
    visible = int(np.sum(truth["lenses"]["complete"]))
    # same expectation? (noise-free comparison of the two paths, normalised)
    print(f"analytic white {t1 - t0:.0f} s, lfcam.sim white {t2 - t1:.0f} s; "
          f"{visible} fully visible lenslets")
    sa = white_a.astype(np.float64) / white_a.mean()
    ss = white_s.astype(np.float64) / white_s.mean()
    print(f"pixelwise |analytic − sim| / mean: RMS {np.sqrt(((sa - ss) ** 2).mean()):.4f}")
    for name, w in (("analytic", white_a), ("lfcam.sim", white_s)):
        t = time.time()
        cal = calibrate_white(w.astype(np.float32))
        print(f"{name:9s}: {_summary(cal, visible)} ({time.time() - t:.0f} s)")
    np.save(Path("/tmp") / f"white_analytic_{args.system}_{args.size}.npy", white_a)


if __name__ == "__main__":
    main()
