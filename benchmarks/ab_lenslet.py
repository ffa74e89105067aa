"""A/B of the lenslet fit: this checkout's ``lfcam.measure.fastfit`` (or its compiled kernels)
against another's, region by region in one process (each region measured by both in turn), on
the seed grid or a many-source scene.

Run: ``python benchmarks/ab_lenslet.py --baseline OTHER/lfcam/measure/fastfit.py
[--sets system1:point,system2:point,system1:line]`` (``OTHER``: e.g. a ``git worktree`` of an
earlier commit, or ``git show REV:lfcam/measure/fastfit.py > /tmp/fastfit_old.py``). Prints,
per set, each side's mean and worst CPU ms a region and mean / max ERROR %, and the ratio of
the means. The two sides share everything but ``fastfit`` (kernels, geometry, regions, noise
model), so the ratio is that module's alone, free of the machine's drift between runs.

``--kernels OTHER/lfcam/measure/kernels.py`` instead: both sides run this ``fastfit``, the
baseline with the other file's ray trace and moment deposit (the compiled kernels).
``--scene a|b``: the regions of ``benchmarks/many_sources.py``'s scene (rendered into
``--workdir`` on first use; each fitted with its neighbours' lenslets left out, as ``lfcam
distance`` fits it) instead of the seed grid; per region kind the CPU ms of both sides,
and the largest change of a distance between them (the scene's errors: ``many_sources.py``).
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
from lfcam.measure import fastfit, noise_sigma, prepare_geometry  # noqa: E402
from lfcam.measure.lenslets import lenslet_stats  # noqa: E402
from lfcam.measure.noise import capture_noise  # noqa: E402
from lfcam.measure.regions import find_regions, nearby_regions  # noqa: E402


def load_baseline(path: Path):
    """The other checkout's ``fastfit`` as a module of its own (it imports this lfcam)."""
    spec = importlib.util.spec_from_file_location("lfcam.measure.fastfit_baseline", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


KERNELS = ("trace_deposit_moments", "deposit_moments", "trace_model_rays", "trace_sample_rays",
           "cell_samples", "cell_centres", "cell_landings", "deposit_cells")


def load_kernels(path: Path):
    """A ``measure_lenslet`` that runs this ``fastfit`` with the other file's compiled trace
    and deposit (``fastfit`` looks them up in ``lfcam.measure.kernels`` at each call)."""
    import atexit
    import shutil
    import tempfile

    from lfcam.measure import kernels

    # a fresh copy: numba's on-disk cache beside an earlier copy would name another module
    copy = Path(tempfile.mkdtemp(prefix="lfcam_ab_")) / "kernels_baseline.py"
    shutil.copyfile(path, copy)
    atexit.register(shutil.rmtree, copy.parent, True)
    spec = importlib.util.spec_from_file_location("lfcam.measure.kernels_baseline", copy)
    other = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = other  # numba's on-disk cache finds the module by its name
    spec.loader.exec_module(other)
    # every kernel fastfit calls that the other file has (its signatures must be this one's)
    swap = {k: getattr(other, k) for k in KERNELS if hasattr(other, k)}
    # every signature of both sides loaded (or compiled) before any region is timed: a line's
    # first weighted evaluation compiled in its region took ~1-30 s of its time
    kernels.warm_up()
    if hasattr(other, "warm_up"):
        other.warm_up()

    def measure(*args, **kwargs):
        mine = {k: getattr(kernels, k) for k in swap}
        for k, v in swap.items():
            setattr(kernels, k, v)
        try:
            return fastfit.measure_lenslet(*args, **kwargs)
        finally:
            for k, v in mine.items():
                setattr(kernels, k, v)

    return measure


def run_scene(name: str, workdir: Path, sides: dict) -> None:
    """Both sides on every region of a many-source scene; per region kind, mean / median /
    worst CPU ms, and the largest relative change of an ``ok`` distance between the sides."""
    import many_sources as ms

    from lfcam.camera import load_profile
    from lfcam.io import load_capture

    png, cal_path, _ = ms.prepare(name, workdir)
    prof = load_profile(png.with_name(png.stem + ".profile.toml"))
    img = load_capture(png, prof).grey()
    geom = prepare_geometry(prof, load_calibration(cal_path), img.shape)
    stats = lenslet_stats(img, geom.lmap)
    capture_noise(img, geom.lmap, geom.pitch_px, stats)  # the gates' noise model (cached)
    noise = noise_sigma(img)
    regions = find_regions(stats, geom.lmap, geom.pitch_px)
    # each region with its neighbours' lenslets left out, as lfcam distance fits it (and
    # many_sources.py --per-region); without them a box holding a neighbour's light tried two
    # sources for ~0.8 s
    near = nearby_regions(regions)
    for measure in sides.values():  # load the compiled code on both sides
        measure(prof, geom, img, regions[0], noise, others=near[0])
    times = {k: [] for k in sides}
    dist = {k: [] for k in sides}
    kinds = []
    for reg, others in zip(regions, near, strict=True):
        for side, measure in sides.items():
            t0 = time.process_time()
            m = measure(prof, geom, img, reg, noise, others=others)
            times[side].append(1e3 * (time.process_time() - t0))
            _, ed, _, _, _ = _apply_model(prof, m, "exact", None)
            dist[side].append(ed if m.status == "ok" else np.nan)
        kinds.append(m.kind)
    kinds = np.array(kinds)
    for kind in sorted(set(kinds)):
        sel = kinds == kind
        for side in sides:
            t = np.array(times[side])[sel]
            print(f"scene {name} {kind:6s} {side:8s}: {t.mean():7.1f} ms a region (median "
                  f"{np.median(t):6.1f}, worst {t.max():7.1f}; {sel.sum()} regions)")
        ratio = np.sum(np.array(times["this"])[sel]) / np.sum(np.array(times["baseline"])[sel])
        print(f"scene {name} {kind:6s} this / baseline: {ratio:.3f}")
    a, b = np.array(dist["baseline"]), np.array(dist["this"])
    same = np.isnan(a) == np.isnan(b)
    print(f"scene {name}: ok in both {int((~np.isnan(a) & ~np.isnan(b)).sum())}, status "
          f"differs {int((~same).sum())}, largest distance change "
          f"{np.nanmax(np.abs(b / a - 1.0)):.2e} (relative)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    which = ap.add_mutually_exclusive_group(required=True)
    which.add_argument("--baseline", type=Path, help="the other fastfit.py")
    which.add_argument("--kernels", type=Path, help="the other kernels.py")
    ap.add_argument("--sets", default="system1:point,system2:point,system1:line",
                    help="system:source pairs of the seed grid")
    ap.add_argument("--scene", choices=("a", "b"), help="a many_sources.py scene instead")
    ap.add_argument("--workdir", type=Path, default=Path(__file__).resolve().parent / ".cache",
                    help="--scene: where the scene is rendered (as many_sources.py)")
    args = ap.parse_args()
    sides = {"baseline": (load_baseline(args.baseline).measure_lenslet if args.baseline
                          else load_kernels(args.kernels)),
             "this": fastfit.measure_lenslet}
    if args.scene:
        run_scene(args.scene, args.workdir, sides)
        return
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
