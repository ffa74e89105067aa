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
        Jittered samples per pixel and lenslet (a perfect square: √n × √n strata of the pixel
        paired with a random permutation of √n × √n strata of the aperture).
    seed : int
    full_well_e, read_noise_e : float
        Electrons at the brightest pixel; read noise σ in electrons.
    noise : bool
        Add shot and read noise (else the expectation, scaled to 65535 at the peak).
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
    for r0 in range(0, s.height_px, rows):
        r1 = min(s.height_px, r0 + rows)
        yy, xx = np.meshgrid(np.arange(r0, r1, dtype=np.float64), cols, indexing="ij")
        xp, yp = xx.ravel(), yy.ravel()
        m = xp.size
        # the lenslet whose micro-image centre is nearest, and its 8 neighbours
        u, v = grid.lattice_coords((xp - ax) * pp / mag, (yp - ay) * pp / mag)
        i0, j0 = np.rint(u), np.rint(v)
        acc = np.zeros(m)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                cx, cy = grid.centre_mm(i0 + di, j0 + dj)
                for t in range(n):
                    jit = rng.random((4, m)) / k
                    # pixel stratum t, aperture stratum π(t) (a fresh permutation per pixel)
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
                    acc += np.where(tr.ok, cos2 * cos2, 0.0)
        out[r0:r1] = (acc / n).reshape(r1 - r0, s.width_px)
    scale = full_well_e / out.max()
    electrons = out * scale
    if noise:
        electrons = rng.poisson(electrons).astype(np.float64)
        electrons += rng.normal(0.0, read_noise_e, electrons.shape)
    dn = electrons * (65535.0 / full_well_e)
    return np.clip(np.rint(dn), 0, 65535)


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
