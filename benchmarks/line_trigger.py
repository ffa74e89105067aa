"""Which regions the point/line decision sends to the line fit, and what that costs.

Run: ``python benchmarks/line_trigger.py [--scene a|b] [--workdir DIR]``

Runs ``lfcam distance``'s library path (``lenslet``, ``jobs=1``) on a scene of
``benchmarks/many_sources.py`` (rendered there, cached in ``--workdir``) and prints, per region:
the truth's kind and distance (nearest truth source), the point fit's relative misfit, the
misfit the region's noise alone would leave (``lfcam.measure.noise.moments_misfit``), their
ratio, the line fit's misfit when it ran, the CPU of both fits, and the outcome. The totals
show how many regions ran the line fit and its CPU (docs/distance.md, "Blurs of a few
lenslets", the line trigger).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import many_sources  # noqa: E402

from lfcam.calibrate import load_calibration  # noqa: E402
from lfcam.camera import load_profile  # noqa: E402
from lfcam.distance import run_distance  # noqa: E402
from lfcam.io import load_capture  # noqa: E402
from lfcam.measure import fastfit, prepare_geometry  # noqa: E402


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", choices=("a", "b"), default="b")
    ap.add_argument("--workdir", type=Path, default=ROOT / "benchmarks" / ".cache")
    args = ap.parse_args(argv)
    png, cal_path, truth = many_sources.prepare(args.scene, args.workdir)
    records: list[dict] = []
    stages, line_fit, trigger = (fastfit.point_fit_stages, fastfit.fit_lenslet_line,
                                 fastfit.line_trigger)

    def timed_stages(profile, geom, image, region, *args, **kwargs):
        # the point fit's stages (measure_lenslet drives the generator; the region's record
        # was opened by its trigger): CPU and last misfit
        rec = records[-1]
        rec["c"] = region.centroid_px
        gen = stages(profile, geom, image, region, *args, **kwargs)
        while True:
            t = time.process_time()
            try:
                fit = next(gen)
            except StopIteration:
                return
            finally:
                rec["pt_s"] += time.process_time() - t
            rec["pm"] = fit.misfit
            yield fit

    def seen_trigger(nm, floor, *args):
        # measure_lenslet computes its trigger first: one record a region from here
        records.append({"nm": nm, "pm": float("nan"), "pt_s": 0.0, "c": (math.nan, math.nan)})
        return trigger(nm, floor, *args)

    def timed_line(*args, **kwargs):
        t = time.process_time()
        line = line_fit(*args, **kwargs)
        records[-1].update(lm=line.misfit, line_s=time.process_time() - t)
        return line

    fastfit.point_fit_stages, fastfit.fit_lenslet_line = timed_stages, timed_line
    fastfit.line_trigger = seen_trigger
    try:
        prof = load_profile(png.with_name(png.stem + ".profile.toml"))
        cal = load_calibration(cal_path)
        img = load_capture(png, prof).grey()
        geom = prepare_geometry(prof, cal, img.shape)
        run = run_distance(img, prof, cal, model="exact", method="lenslet", geometry=geom,
                           jobs=1)
    finally:
        fastfit.point_fit_stages, fastfit.fit_lenslet_line = stages, line_fit
        fastfit.line_trigger = trigger
    sources = truth["sources"]
    nan = float("nan")
    print("| truth | mm | point misfit | noise misfit | ratio | line misfit | point s | line s "
          "| kind | status | error % |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in run.regions:
        s = min(sources, key=lambda s: math.hypot(r.x_px - s["centroid_px"][0],
                                                  r.y_px - s["centroid_px"][1]))
        d = min(records, key=lambda v: math.hypot(v["c"][0] - r.x_px, v["c"][1] - r.y_px),
                default={"pm": nan, "pt_s": nan})
        err = 100 * (r.distance_mm / s["distance_mm"] - 1) if r.status == "ok" else nan
        nm = d.get("nm", nan)
        print(f"| {s.get('kind', '?')} | {s['distance_mm']:.0f} | {d['pm']:.4f} | {nm:.4f} | "
              f"{d['pm'] / nm:.2f} | {d.get('lm', nan):.4f} | {d['pt_s']:.2f} | "
              f"{d.get('line_s', 0.0):.2f} | {r.kind} | {r.status} | {err:+.3f} |")
    lines = [v for v in records if "lm" in v]
    print(f"\n{len(run.regions)} regions; line fit run on {len(lines)}; CPU: point fits "
          f"{sum(v['pt_s'] for v in records):.1f} s, line fits "
          f"{sum(v['line_s'] for v in lines):.1f} s")
    ok = np.array([abs(r.distance_mm / min(sources, key=lambda s: math.hypot(
        r.x_px - s["centroid_px"][0], r.y_px - s["centroid_px"][1]))["distance_mm"] - 1) * 100
        for r in run.regions if r.status == "ok"])
    print(f"ok regions {ok.size}: mean |error| {ok.mean():.3f} %, max {ok.max():.3f} %")


if __name__ == "__main__":
    main()
