"""Speed of the general tracer (lfcam.optics.raytrace) against the former singlet tracers.

Run: ``PYTHONPATH=. python benchmarks/raytrace.py [n_rays]`` (default 10⁶ rays, best of 3).
Prints rays/s for, in the same run:

* the seed singlet (``calibration/system1.toml``): the former hand-unrolled two-sphere tracers
  (``legacy_singlet_trace.py``: ``trace_source_fast`` / ``trace_backward_fast`` /
  ``trace_rays``), the stages' wrappers that replaced them (``lfcam.optics.trace``, now over
  the general tracer), and :func:`~lfcam.optics.raytrace.trace` /
  :func:`~lfcam.optics.raytrace.trace_backward` on the same rays;
* the new tracer on the Cooke triplet and the double Gauss of ``tests/data/lenses``;
* ray aiming (:func:`~lfcam.optics.raytrace.rays_from_angle`, Newton on the real trace).
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

from lfcam.camera import load_profile
from lfcam.optics import raytrace as rt
from lfcam.optics import trace as stage
from lfcam.optics.lens import Prescription

sys.path.insert(0, str(Path(__file__).resolve().parent))
from legacy_singlet_trace import (  # noqa: E402
    trace_backward_fast,
    trace_rays,
    trace_source_fast,
)

from lfcam.optics.zmx import load_zmx

LENS_DIR = Path(__file__).resolve().parents[1] / "tests" / "data" / "lenses"


def best(fn, repeat: int = 3) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def disk(n: int, radius: float, rng) -> tuple[np.ndarray, np.ndarray]:
    r = radius * np.sqrt(rng.random(n))
    a = rng.random(n) * 2.0 * math.pi
    return r * np.cos(a), r * np.sin(a)


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000
    rng = np.random.default_rng(0)
    profile = load_profile("system1")
    lens = profile.main_lens
    shift = 0.5 * lens.thickness_mm  # legacy frame (lens centre) → prescription frame
    singlet = Prescription.from_singlet(
        lens.radius_mm, lens.thickness_mm, lens.refractive_index, lens.pupil_diameter_mm
    )
    z_sensor = profile.sensor_z_mm
    rows: list[tuple[str, str, float]] = []

    # forward, singlet: one source 1 m away, aim points uniform over the rim plane
    qx, qy = disk(n, 0.5 * lens.pupil_diameter_mm, rng)
    src = (2.0, 3.0, lens.front_vertex_z_mm - 1000.0)
    t = best(lambda: trace_source_fast(lens, src, qx.copy(), qy.copy(), z_sensor))
    rows.append(("singlet", "legacy trace_source_fast (forward)", n / t))
    t = best(lambda: stage.trace_source_fast(lens, src, qx, qy, z_sensor))
    rows.append(("singlet", "stage trace_source_fast (general)", n / t))
    origins = np.tile(src, (n, 1))
    dirs = np.column_stack([qx - src[0], qy - src[1], np.full(n, lens.rim_z_mm - src[2])])
    t = best(lambda: trace_rays(lens, origins, dirs, z_sensor))
    rows.append(("singlet", "legacy trace_rays (forward, (N, 3))", n / t))
    o_new = origins + [0.0, 0.0, shift]
    t = best(lambda: rt.trace(singlet, o_new, dirs, z_sensor + shift))
    rows.append(("singlet", "new trace (forward)", n / t))

    # backward, singlet: sensor points and slopes
    x, y = disk(n, 20.0, rng)
    sx, sy = rng.uniform(-0.2, 0.2, n), rng.uniform(-0.2, 0.2, n)
    t = best(lambda: trace_backward_fast(lens, x, y, z_sensor, sx, sy))
    rows.append(("singlet", "legacy trace_backward_fast", n / t))
    t = best(lambda: stage.trace_backward_fast(lens, x, y, z_sensor, sx, sy))
    rows.append(("singlet", "stage trace_backward_fast (general)", n / t))
    o_b = np.column_stack([x, y, np.full(n, z_sensor + shift)])
    d_b = -np.column_stack([sx, sy, np.ones(n)])
    t = best(lambda: rt.trace_backward(singlet, o_b, d_b, None))
    rows.append(("singlet", "new trace_backward", n / t))

    for name in ("cooke_triplet", "double_gauss"):
        pres = load_zmx(LENS_DIR / f"{name}.zmx").prescription
        par = pres.paraxial
        px, py = disk(n, 0.5 * par.entrance_pupil_diameter_mm, rng)
        d = np.array([0.0, math.sin(math.radians(5.0)), math.cos(math.radians(5.0))])
        o = np.column_stack([px, py, np.full(n, par.entrance_pupil_z_mm)])
        o = o + d * ((-10.0 - par.entrance_pupil_z_mm) / d[2])
        dd = np.broadcast_to(d, (n, 3))
        t = best(lambda pres=pres, o=o, dd=dd, z=par.back_focal_z_mm: rt.trace(pres, o, dd, z))
        label = f"{name} ({len(pres.surfaces)} surfaces)"
        rows.append((label, "new trace (forward)", n / t))
        fwd = rt.trace(pres, o, dd, par.back_focal_z_mm)
        ok = fwd.status == 0
        ob, db = fwd.points[ok], -fwd.directions[ok]
        t = best(lambda pres=pres, ob=ob, db=db: rt.trace_backward(pres, ob, db, -10.0))
        rows.append((label, "new trace_backward (image → object)", len(ob) / t))
        m = 10_000
        t = best(lambda pres=pres, m=m: rt.rays_from_angle(pres, 10.0, m), repeat=1)
        rows.append((label, "ray aiming (rays_from_angle, 10 deg)", m / t))

    ref = rows[0][2]
    print(f"{n} rays, best of 3; ratio = legacy fast forward / this")
    print(f"{'lens':34s} {'tracer':40s} {'Mrays/s':>8s} {'ratio':>6s}")
    for lens_name, tracer, rate in rows:
        print(f"{lens_name:34s} {tracer:40s} {rate / 1e6:8.2f} {ref / rate:6.2f}")


if __name__ == "__main__":
    main()
