"""Renderer speed: rays per second (forward, backward) and 1536² white-image time.

Run: ``python benchmarks/sim.py``. Baseline in the same run: the general (N, 3) reference
tracer ``lfcam.optics.trace.trace_rays``.
"""

from __future__ import annotations

import math
import time

import numpy as np

from lfcam.camera import load_profile
from lfcam.optics.trace import trace_backward_fast, trace_rays, trace_source_fast
from lfcam.sim.render import Renderer
from lfcam.sim.scene import scene_from_dict


def best(fn, repeat=3):
    t = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    return min(t)


def main() -> None:
    p = load_profile("system2")
    lens = p.main_lens
    n = 1_000_000
    rng = np.random.default_rng(0)
    r = 0.5 * lens.pupil_diameter_mm * np.sqrt(rng.random(n))
    a = rng.random(n) * 2 * math.pi
    qx, qy = r * np.cos(a), r * np.sin(a)
    src = (2.0, 3.0, lens.front_vertex_z_mm - 1000.0)
    origins = np.tile(src, (n, 1))
    dirs = np.stack([qx - src[0], qy - src[1], np.full(n, lens.rim_z_mm - src[2])], 1)
    t_ref = best(lambda: trace_rays(lens, origins, dirs, p.d_in_mm))
    t_fwd = best(lambda: trace_source_fast(lens, src, qx, qy, p.d_in_mm))
    f = trace_source_fast(lens, src, qx, qy, p.d_in_mm)
    sx, sy = f.dx / f.dz, f.dy / f.dz
    t_bwd = best(lambda: trace_backward_fast(lens, f.x, f.y, p.d_in_mm, sx, sy))
    rend = Renderer(p)
    scene = scene_from_dict({"rays_per_source": n,
                             "objects": [{"type": "point", "distance_mm": 600.0}]})
    t_pt = best(lambda: rend.render(scene), 2)
    white = scene_from_dict({"objects": [{"type": "white"}]})
    t0 = time.perf_counter()
    res = rend.render(white)
    t_white = time.perf_counter() - t0
    st = res.stats
    rays = st["corner_rays"] + st["boundary_rays"] + st["interior_rays"]
    rows = [
        ("trace_rays (N,3) reference, 1M rays", t_ref, n / t_ref, 1.0),
        ("trace_source_fast, 1M rays", t_fwd, n / t_fwd, t_ref / t_fwd),
        ("trace_backward_fast, 1M rays", t_bwd, n / t_bwd, t_ref / t_bwd),
        ("point source render (lens + MLA + binning), 1M rays", t_pt, n / t_pt, t_ref / t_pt),
        (f"white image 1536x1536 system2 ({rays / 1e6:.1f} M rays)", t_white, rays / t_white,
         float("nan")),
    ]
    print(f"{'case':58s} {'time s':>8s} {'Mrays/s':>9s} {'vs ref':>7s}")
    for name, t, rate, ratio in rows:
        print(f"{name:58s} {t:8.3f} {rate / 1e6:9.2f} {ratio:7.2f}")
    print(f"white image: {st['full_pixels']} fully lit (lens, pixel) pairs decided from "
          f"{st['corner_rays']} corner rays, {st['boundary_pixels']} boundary pairs sampled")
    print("targets: >= 5 M rays/s (one core), 1536^2 white image < 10 s")


if __name__ == "__main__":
    main()
