"""The lenslet model's evaluation, numpy chain against the compiled kernels (issue 17).

Run: ``python benchmarks/speed_kernels.py [--repeats N]``

For each main lens (the seed singlet of system 2, the Cooke triplet, the double Gauss) and
ray count, on a 300×300 px box round the sensor centre (system 2's MLA, focus 1 m) with a
point source 1600 mm away, 3 mm off axis: the wall time of

* the lens trace alone: :func:`lfcam.optics.trace.trace_sources_fast` (numpy) against
  :func:`lfcam.measure.kernels.trace_model_rays` (compiled, SIMD-friendly loops);
* one model evaluation, :meth:`lfcam.measure.fastfit.LensletModel.simulate`, with
  ``kernel="numpy"`` (numpy trace and deposit) and ``kernel="compiled"``;

in ns a ray, the ratio numpy / compiled, and the largest difference of the moments relative
to their largest value (the two must agree to rounding). One core (BLAS threads pinned).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from functools import partial  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lfcam.camera import load_profile  # noqa: E402
from lfcam.measure.fastfit import LensletModel, SourceFrame, _packed_lens, data_moments  # noqa: E402
from lfcam.measure.kernels import trace_model_rays, warm_up  # noqa: E402
from lfcam.optics.trace import pupil_map, trace_sources_fast  # noqa: E402
from lfcam.sim.capture import apply_overrides  # noqa: E402
from lfcam.sim.geometry import truth_geometry  # noqa: E402

LENSES = ("system2", "cooke_triplet", "double_gauss")
RAYS = (1000, 3000, 20000, 80000)


def _best(fn, repeats: int) -> float:
    """Best wall time of ``repeats`` calls (s)."""
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=15)
    args = ap.parse_args()
    warm_up()
    print(f"{'lens':14s} {'rays':>6s} | {'trace numpy':>11s} {'compiled':>9s} {'ratio':>6s} | "
          f"{'eval numpy':>10s} {'compiled':>9s} {'ratio':>6s} | {'max rel diff':>12s}")
    print("  (ns a ray)")
    for name in LENSES:
        base = load_profile(ROOT / "calibration" / f"{name}.toml")
        prof = apply_overrides(base, {"mla": {"focus_mm": 1000.0},
                                      "sensor": {"width_px": 400, "height_px": 400}})
        prof = prof.with_d_in(prof.d_in_mm)
        shape = (prof.sensor.height_px, prof.sensor.width_px)
        geom = truth_geometry(prof, shape)
        mom = data_moments(geom, np.zeros(shape), (50, 50, 350, 350))
        src = np.array([3.0, -2.0, SourceFrame(prof).z_front - 1600.0])
        lens = prof.main_lens
        table, coef, mapped = _packed_lens(lens)[:3]
        maps = np.array([pupil_map(lens, tuple(src)) if mapped else (0.0, 0.0, 1.0, 1.0)])
        for n in RAYS:
            fast = LensletModel(prof, geom, mom, n, kernel="compiled")
            ref = LensletModel(prof, geom, mom, n, kernel="numpy")
            kargs = (src[None], maps, fast.turns(1), fast.rx, fast.ry, table, coef,
                     float(lens.front_vertex_z_mm), float(lens.rim_z_mm), float(geom.d_in_mm),
                     float(prof.mla.focal_length_mm))
            t_np = _best(partial(trace_sources_fast, lens, src[None], ref.rx, ref.ry,
                                 geom.d_in_mm), args.repeats)
            t_c = _best(partial(trace_model_rays, *kargs), args.repeats)
            e_np = _best(partial(ref.simulate, src), args.repeats)
            e_c = _best(partial(fast.simulate, src), args.repeats)
            a, b = fast.simulate(src), ref.simulate(src)
            diff = float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))
            print(f"{name:14s} {n:6d} | {t_np / n * 1e9:11.1f} {t_c / n * 1e9:9.1f} "
                  f"{t_np / t_c:6.1f} | {e_np / n * 1e9:10.1f} {e_c / n * 1e9:9.1f} "
                  f"{e_np / e_c:6.1f} | {diff:12.1e}")


if __name__ == "__main__":
    main()
