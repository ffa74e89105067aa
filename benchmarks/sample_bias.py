"""The ray-sampled line model's own error at a line's answer: bias and spread by sample size.

Run: ``python benchmarks/sample_bias.py [--system system1] [--distance 3400] [--field 0.8]``

Renders one line (``benchmarks/focus_grid.py``'s camera and placement: a 1 m focus, the line
centred at ``--field`` of the half-field), fits it with ``--method lenslet`` and keeps the
answer ``q`` (where its last line stage ended) and the fit's last line model. Then, at that
``q``, for ray-sampled line models of 1, 4 and 8 × the fine model's rays a point, each with
``--turns`` turns of its pupil sample, with a ray's share across a cell border by one box of
the ray spacing (``box``, until stop 53) and by the two boxes' combination (``two``,
:func:`lfcam.measure.sampling.ray_share`), prints:

* the shift of each sample's minimum against a reference of 32 × the fine rays, by one
  Gauss–Newton step on the reference's Jacobian (``ref-J mean``, ``std`` over the turns): the
  sample's bias and spread, seen by an independent Jacobian;
* the part of the mean shift the lenslets' light (moment 0) alone carries (``m0 part``);
* the minima the samples reach by Levenberg–Marquardt with their own Jacobians (``own
  minima``, the fine model only).

docs/distance.md, "The refit's rays and the fine sample's bias (stop 53)", "Ray shares
without the box's variance (stop 53)".
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # (as focus_grid.py)

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import focus_grid as fg  # noqa: E402

import lfcam.distance as distance  # noqa: E402
from lfcam.measure import fastfit as ff  # noqa: E402
from lfcam.measure import kernels  # noqa: E402
from lfcam.measure.lenslets import lenslet_stats  # noqa: E402
from lfcam.measure.regions import find_regions  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--system", default="system1")
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--grid", default=None, help="rect or hex (default: the profile's)")
    ap.add_argument("--distance", type=float, default=3400.0, help="mm")
    ap.add_argument("--field", type=float, default=0.8, help="share of the half-field")
    ap.add_argument("--turns", type=int, default=6)
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "lfcam_fg")
    args = ap.parse_args()
    kernels.warm_up()
    cam = fg.Camera(args.system, 1000.0, args.size, args.cache, False, grid=args.grid)
    img, _, _ = cam.render([cam.line(args.distance, 0.0, args.field, 1_000_000,
                                     fg.LINE_HALF_MM)], seed=3, rays=1_000_000)
    geom, prof = cam.geom, cam.used
    regions = find_regions(lenslet_stats(img, geom.lmap), geom.lmap, geom.pitch_px)
    region = max(regions, key=lambda r: len(r.lenslets))

    made, ends = [], []
    line_model, gauss_newton = ff.line_model, ff.gauss_newton_fixed

    def keep_model(model, frame, count, steps):
        made.append((model, frame, count, steps))
        return line_model(model, frame, count, steps)

    def keep_end(*a, **k):
        out = gauss_newton(*a, **k)
        ends.append(out[0])
        return out

    levenberg = ff.levenberg_marquardt

    def keep_lm_end(*a, **k):
        out = levenberg(*a, **k)
        if len(out[0]) == 5:  # (a line's)
            ends.append(out[0])
        return out

    turned = []  # the settled test's turned sample (phase 1): the fine model's rays a point
    init = ff.LensletModel.__init__

    def keep_turned(self, *a, **k):
        init(self, *a, **k)
        if k.get("phase") == 1.0:
            turned.append(self.rx.size)

    ff.line_model, ff.gauss_newton_fixed = keep_model, keep_end
    ff.levenberg_marquardt = keep_lm_end
    ff.LensletModel.__init__ = keep_turned
    try:
        got = ff.measure_lenslet(prof, geom, img, region, distance.noise_sigma(img))
    finally:
        ff.line_model, ff.gauss_newton_fixed = line_model, gauss_newton
        ff.levenberg_marquardt = levenberg
        ff.LensletModel.__init__ = init
    ray_models = [m for m in made if not m[0].cells]
    if got.kind != "line" or not ray_models:
        raise SystemExit(f"not a ray-sampled line fit ({got.kind})")
    if any(m[0].cells and not m[0].folded for m in made):
        raise SystemExit("the line was fitted on the lenslet cells: its rays only raced")
    last, frame, count, steps = ray_models[-1]
    q = ends[-1]
    if not turned:
        raise SystemExit("the line's fit ended before its settled test")
    n_fine = turned[-1]
    print(f"# {args.system} line at {args.distance:g} mm, {100 * args.field:g} % of the "
          f"half-field: {got.kind}, {100 * (got.distance_mm / args.distance - 1):+.3f} %; fine "
          f"model {n_fine} rays a point, {count} points")

    def sample(n_rays: int, phase: float, richardson: bool = True):
        ff.RAY_SHARE_RICHARDSON = richardson
        model = ff.LensletModel(prof, geom, last.mom, n_rays, phase=phase, turn_every=count)
        fun, jac = line_model(model, frame, count, steps)
        pts = ff._line_points(frame, q, count)
        m = model.simulate_groups(pts, np.zeros(count, dtype=np.int64), 1, 1)[0]
        return model, fun, jac, m / m[:, 0].sum()

    ref_model, ref_fun, ref_jac, ref_m = sample(32 * n_fine, 0.3)
    r_ref = ref_fun(q)
    j_ref = ref_jac(q, r_ref)

    def shift(model, m):  # one Gauss–Newton step on the reference's Jacobian: the minimum
        return float(np.linalg.lstsq(j_ref, -(model.residual_of(m) - ref_model.residual_of(
            ref_m)), rcond=None)[0][0])

    print(f"{'rays a point':>13} {'share':>6} {'ref-J mean':>11} {'std':>9} {'m0 part':>9} "
          f"{'own minima':>11} {'std':>9}")
    for mult in (1, 4, 8):
        for richardson in (False, True):
            shifts, moments, own = [], [], []
            for k in range(args.turns):
                model, fun, jac, m = sample(mult * n_fine, 0.37 * k + 0.01, richardson)
                shifts.append(shift(model, m))
                moments.append(m)
                if mult == 1:
                    qq = levenberg(fun, q, steps, 8, 1e-4, jac_of=jac)[0]
                    own.append(float(qq[0] - q[0]))
            d0 = np.zeros_like(ref_m)
            d0[:, 0] = np.mean(moments, axis=0)[:, 0] - ref_m[:, 0]
            m0_part = shift(ref_model, ref_m + d0)
            own_s = (f"{np.mean(own):+11.2e} {np.std(own):9.2e}" if own
                     else f"{'':>11} {'':>9}")
            print(f"{mult * n_fine:13d} {'two' if richardson else 'box':>6} "
                  f"{np.mean(shifts):+11.2e} "
                  f"{np.std(shifts):9.2e} {m0_part:+9.2e} {own_s}")


if __name__ == "__main__":
    main()
