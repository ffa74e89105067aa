"""The compiled kernels' warm-up covers what the measurement passes them.

``lfcam.measure.kernels.warm_up`` loads (or, the first time on a machine, compiles) every kernel
with the argument types the lenslet models pass, in the fork server before the region workers
start. A call with other types (an array that is a strided view, say) is a new signature: numba
compiles it inside the region that makes it, and on a fresh install that region reports seconds
(the first hexagonal line of a fresh tree took 5.7 s instead of 0.19 s: the hexagonal coarse
rule's points were a view of every second ring point, and ``cell_centres`` took 5.5 s to compile
for it; docs/distance.md, "A kernel signature the warm-up missed (stop 52)").

The check runs in a fresh interpreter, where the kernels' signatures are exactly what it has
called: after the warm-up, the models of both lattices (rays, the cells at n = 2, 4 and 6 with
their whole-cell rules and the rim, a point and a line's points in groups and weighted, the
data's moments of a float64 and a float32 frame) may add none.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent("""
    import json
    import numpy as np
    from lfcam.camera import load_profile
    from lfcam.measure import fastfit as ff, kernels as k
    from lfcam.measure.pointfit import chief_ray_offset
    from lfcam.sim.capture import apply_overrides
    from lfcam.sim.geometry import truth_geometry

    k.warm_up()
    k.warm_up_frame()
    kernels = {n: d for n, d in vars(k).items() if hasattr(d, "signatures")}
    before = {n: set(map(str, d.signatures)) for n, d in kernels.items()}
    size = 1024
    for grid in ("rect", "hex"):
        prof = apply_overrides(load_profile("system2"), {
            "mla": {"focus_mm": 1000.0, "grid": grid},
            "sensor": {"width_px": size, "height_px": size}})
        geom = truth_geometry(prof, (size, size))
        c = size // 2
        image = np.random.default_rng(1).random((size, size))
        mom = ff.data_moments(geom, image, (c - 260, c - 260, c + 260, c + 260))
        ff.data_moments(geom, image.astype(np.float32), (c - 260, c - 260, c + 260, c + 260),
                        exclude=mom.ids[:5])
        for distance in (380.0, 3400.0):  # in front of a 1 m focus (rays), behind (cells)
            a = chief_ray_offset(prof, prof.d_in_mm, distance, np.array([-1.5, 0.0]))
            b = chief_ray_offset(prof, prof.d_in_mm, distance, np.array([1.5, 0.0]))
            t = (np.arange(12) + 0.5) / 12
            z = prof.main_lens.front_vertex_z_mm - distance
            pts = np.column_stack([a + t[:, None] * (b - a), np.full(12, z)])
            for cells in (0, 2, 4, 6):
                model = ff.LensletModel(prof, geom, mom, 2000, cells=cells, turn_every=12)
                model.residual_of(model.simulate(pts))
                model.simulate_sets([pts, pts + [0.01, 0.0, 0.0]])
                model.simulate_weighted(pts, np.zeros(12, dtype=np.int64), 1, t, 1)
                ff.LensletModel(prof, geom, mom, 2000, cells=cells).simulate(pts[:1])
    added = {n: sorted(set(map(str, d.signatures)) - before[n]) for n, d in kernels.items()}
    print(json.dumps({n: s for n, s in added.items() if s}))
""")


def test_models_call_no_kernel_signature_the_warm_up_does_not_load():
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True,
                         timeout=900)
    assert out.returncode == 0, out.stderr[-2000:]
    added = json.loads(out.stdout.strip().splitlines()[-1])
    assert added == {}
