"""A/B of the lenslet fit: this checkout's ``lfcam.measure.fastfit`` against another's, region
by region in one process (each region measured by both in turn), on the seed grid.

Run: ``python benchmarks/ab_lenslet.py --baseline OTHER/lfcam/measure/fastfit.py
[--sets system1:point,system2:point,system1:line]`` (``OTHER``: e.g. a ``git worktree`` of an
earlier commit). Prints, per set, each side's mean and worst CPU ms a region and mean / max
ERROR %, and the ratio of the means. The two sides share everything but ``fastfit`` (kernels,
geometry, regions, noise model), so the ratio is that module's alone, free of the machine's
drift between runs.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import importlib.util  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import tradeoff as tr  # noqa: E402

from lfcam.calibrate import load_calibration  # noqa: E402
from lfcam.distance import _apply_model  # noqa: E402
from lfcam.measure import fastfit, prepare_geometry  # noqa: E402
from lfcam.measure.lenslets import lenslet_stats  # noqa: E402
from lfcam.measure.noise import capture_noise  # noqa: E402
from lfcam.measure.regions import find_regions  # noqa: E402


def load_baseline(path: Path):
    """The other checkout's ``fastfit`` as a module of its own (it imports this lfcam)."""
    spec = importlib.util.spec_from_file_location("lfcam.measure.fastfit_baseline", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", type=Path, required=True, help="the other fastfit.py")
    ap.add_argument("--sets", default="system1:point,system2:point,system1:line",
                    help="system:source pairs of the seed grid")
    args = ap.parse_args()
    sides = {"baseline": load_baseline(args.baseline).measure_lenslet,
             "this": fastfit.measure_lenslet}
    for pair in args.sets.split(","):
        system, source = pair.split(":")
        cal = load_calibration(tr.DATA / f"calib_{system}.json")
        geom = None
        times = {k: [] for k in sides}
        errors = {k: [] for k in sides}
        for d in tr.SEED_AD:
            for dh in ((0,) if source == "line" else tr.SEED_DH):
                img, prof, _ = tr.load(system, source, int(d), int(dh))
                if geom is None:  # first capture: load the compiled code on both sides
                    geom = prepare_geometry(prof, cal, img.shape)
                    reg0 = find_regions(lenslet_stats(img, geom.lmap), geom.lmap,
                                        geom.pitch_px)[0]
                    for measure in sides.values():
                        measure(prof, geom, img, reg0, 0.0)
                stats = lenslet_stats(img, geom.lmap)
                capture_noise(img, geom.lmap, geom.pitch_px, stats)
                for reg in find_regions(stats, geom.lmap, geom.pitch_px):
                    for name, measure in sides.items():
                        t0 = time.process_time()
                        m = measure(prof, geom, img, reg, 0.0)
                        times[name].append(1e3 * (time.process_time() - t0))
                        _, ed, _, _, _ = _apply_model(prof, m, "exact", None)
                        half_t = prof.main_lens.thickness_mm / 2
                        errors[name].append(100 * abs(ed - d) / (d + half_t))
        for name in sides:
            t, e = np.array(times[name]), np.array(errors[name])
            print(f"{system} {source:5s} {name:8s}: {t.mean():7.1f} ms a region "
                  f"(worst {t.max():6.1f}); ERROR {e.mean():.4f} / {e.max():.4f} % "
                  f"({len(t)} regions)", flush=True)
        print(f"{system} {source:5s} this / baseline: "
              f"{np.mean(times['this']) / np.mean(times['baseline']):.3f}", flush=True)


if __name__ == "__main__":
    main()
