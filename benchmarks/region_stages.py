"""Where a lenslet region's model rays go: each evaluation tagged by the stage that made it.

Run: ``python benchmarks/region_stages.py --scene a|b --regions ID,ID,... [--workdir DIR]
[--ab NAME=VALUE,...] [--tolerance PCT]``

Renders (or reuses) ``many_sources.py``'s scene, finds its regions as ``lfcam distance``
does, and fits each named region's ``lenslet`` measurement once to warm up and once counted:
every :class:`lfcam.measure.fastfit.LensletModel` evaluation is tagged with the fit it
belongs to (``point``, ``line``) and the model's role there, read from the calling fit's own
names (``scan``, ``coarse``, ``fine``, ``turned``, ``polish``, ``summary_model``;
``scan_model``, ``coarse``, ``fine``, the settled test's ``turned`` and the refit's
``refined``), and with the helper that called it (``_match_summary``, ``first_look``,
``_settled``, a Jacobian ``jac``, the solver's ``gauss_newton_fixed`` or
``levenberg_marquardt`` …). Prints one table a region: the model rays (points ×
pupil samples, as :func:`lfcam.measure.fastfit.counting_rays` counts them) and the wall time
of those evaluations, by stage, largest first; the rest of the region's CPU is the fit's own
arithmetic. The roles come from the fits' local names, not their line numbers, so the table
survives edits of the fit (docs/distance.md, "A large line's coarse stage on super-cells
(stop 76)"). ``--ab`` sets fastfit constants for the counted fit (as ``many_sources.py``);
``--tolerance PCT`` fits as ``lfcam distance --method lenslet --tolerance PCT`` does.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402
from functools import partial  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import many_sources as ms  # noqa: E402

from lfcam.measure import fastfit as ff  # noqa: E402
from lfcam.measure.regions import nearby_regions  # noqa: E402
from lfcam.models import auto  # noqa: E402

FITS = {"point_fit_stages": "point", "fit_lenslet_line": "line"}
HELPERS = ("_starts", "_match_summary", "_recentre", "_recentre_coarse", "first_look",
           "_settled", "_profile_sigma", "scanned_starts", "oriented",
           "settled_early", "_refit_start", "jac", "pixel_polish", "gauss_newton_fixed",
           "levenberg_marquardt")


def _role(model, names: dict) -> str:
    """The local name (or list) under which the calling fit holds ``model``."""
    for name, value in names.items():
        if value is model:
            return name
        if isinstance(value, list) and any(v is model for v in value):
            return f"{name}[]"
    return "(unnamed)"


def stage_of(model) -> str:
    """``fit: role (helper)`` for an evaluation of ``model`` made from the current stack."""
    frame = sys._getframe(2)
    helper = ""
    while frame is not None:
        name = frame.f_code.co_name
        if name in FITS:
            return f"{FITS[name]}: {_role(model, frame.f_locals)}" + (f" ({helper})"
                                                                      if helper else "")
        if not helper and name in HELPERS:
            helper = name
        frame = frame.f_back
    return f"other ({helper})" if helper else "other"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", choices=("a", "b"), default="b")
    ap.add_argument("--regions", required=True, help="region ids, comma-separated")
    ap.add_argument("--workdir", type=Path, default=ROOT / "benchmarks" / ".cache")
    ap.add_argument("--ab", default="", metavar="NAME=VALUE,...",
                    help="fastfit constants set for the fits")
    ap.add_argument("--tolerance", type=float, default=None, metavar="PCT",
                    help="each fit with this tolerance (as lfcam distance --method lenslet "
                         "--tolerance PCT)")
    args = ap.parse_args()
    accept = (None if args.tolerance is None
              else partial(auto.lenslet_answer_meets, tolerance_pct=args.tolerance))
    wanted = [int(v) for v in args.regions.split(",") if v.strip()]
    settings = {}
    for item in filter(None, args.ab.split(",")):
        name, value = item.split("=", 1)
        current = getattr(ff, name)
        settings[name] = (bool(int(value)) if isinstance(current, bool)
                          else type(current)(float(value)))
    for name, value in settings.items():
        setattr(ff, name, value)

    prof, geom, img, regions, noise, _ = ms.scene_regions(args.scene, args.workdir)
    near = dict(zip([r.region_id for r in regions], nearby_regions(regions), strict=True))
    by_id = {r.region_id: r for r in regions}
    missing = [k for k in wanted if k not in by_id]
    if missing:
        raise SystemExit(f"no region {missing} in scene {args.scene} "
                         f"({len(regions)} regions, ids 0-{len(regions) - 1})")

    rays: dict[str, int] = defaultdict(int)
    spent: dict[str, float] = defaultdict(float)
    simulate = ff.LensletModel._simulate

    def counted(self, sources, group=None, groups=1, second=None):
        tag = stage_of(self)
        t = time.perf_counter()
        out = simulate(self, sources, group, groups, second)
        spent[tag] += time.perf_counter() - t
        rays[tag] += (len(sources) if sources.ndim > 1 else 1) * self.rx.size
        return out

    for rid in wanted:
        reg = by_id[rid]
        ff.measure_lenslet(prof, geom, img, reg, noise, others=near[rid], accept=accept)  # warm up
        rays.clear()
        spent.clear()
        ff.LensletModel._simulate = counted
        try:
            cpu = time.process_time()
            m = ff.measure_lenslet(prof, geom, img, reg, noise, others=near[rid],
                                      accept=accept)
            cpu = time.process_time() - cpu
        finally:
            ff.LensletModel._simulate = simulate
        total = sum(rays.values())
        print(f"\n# region {rid} ({len(reg.lenslets)} lenslets): {m.kind}, {m.status}, "
              f"{m.distance_mm:.2f} mm; {1e3 * cpu:.1f} ms CPU (counted), model rays "
              f"{total / 1e6:.2f} M in {1e3 * sum(spent.values()):.1f} ms")
        print("| stage | model rays | share | ms |\n|---|---|---|---|")
        for tag in sorted(rays, key=lambda k: -rays[k]):
            print(f"| {tag} | {rays[tag] / 1e6:.3f} M | {100.0 * rays[tag] / total:.0f} % "
                  f"| {1e3 * spent[tag]:.1f} |")


if __name__ == "__main__":
    main()
