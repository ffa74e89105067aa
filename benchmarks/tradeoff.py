"""Speed/accuracy trade-off of the distance pipeline on the rendered captures.

Run: ``python benchmarks/tradeoff.py [--quick] [--out docs/results] [--img docs/img]``

For every imaging system × measurement method × distance model, on the same rendered inputs
(``data/synthetic/point_system{1,2}_{Ad}mm_dh{0,5,10}.png`` and, for system 1, the 10 mm lines
``line_system1_{Ad}mm.png``): the seed's eq. 21 error |Ad − Ed|/(Ad + T/2) (mean and max), the
time per region and the time per frame. Each capture is measured once per method; every model is
then applied to that same measurement, so the models differ only by their own cost and error.

Methods: ``lightfield`` (exact forward-model fit of the pixels; slow), ``lightfield-fast``
(triangulation of the lenslet spots alone), ``lenslet`` (exact forward model fitted to
per-lenslet moments, issue 17), ``diameter`` (the seed's footprint diameter).
Times are single-core CPU seconds (``time.process_time``) of each method in the same run;
``max_time_per_region_ms`` is the worst single region. Per-capture work (lenslet statistics,
regions, the capture's noise model) counts in the frame's time, not the region's, as in
``lfcam distance``'s stages.
Budget: the slow method runs on :data:`SLOW_POINTS` and :data:`SLOW_LINES_MM` only; the fast ones
on the whole seed grid. ``--quick`` keeps one capture per system and source (schema test).

Writes (atomically) ``tradeoff.csv`` (one row per system × source × method × model),
``tradeoff_captures.csv`` (one row per capture × method × model) and ``seed_comparison.csv``
(the seed's Tables 2/3 next to our runs of the same grid) into ``--out``; and, unless
``--no-figures``, ``error_vs_distance.png`` and ``pareto.png`` into ``--img``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import csv  # noqa: E402
import io  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from models import SEED_AD, SEED_DH, seed_errors  # noqa: E402

from lfcam.atomic import atomic_write, atomic_write_text  # noqa: E402
from lfcam.calibrate import load_calibration  # noqa: E402
from lfcam.camera import load_profile  # noqa: E402
from lfcam.distance import _apply_model  # noqa: E402
from lfcam.io import load_capture  # noqa: E402
from lfcam.measure import (  # noqa: E402
    measure_diameter,
    measure_lenslet,
    measure_lightfield,
    noise_sigma,
    prepare_geometry,
)
from lfcam.measure.lenslets import lenslet_stats  # noqa: E402
from lfcam.measure.noise import capture_noise  # noqa: E402
from lfcam.measure.regions import find_regions  # noqa: E402

DATA = ROOT / "data" / "synthetic"
SYSTEMS = ("system1", "system2")
METHODS = ("lightfield", "lightfield-fast", "lenslet", "diameter")
MODELS = ("exact", "offaxis", "onaxis", "thin", "auto")
# the slow method: 6 point captures per system (every Δh twice) and 3 lines
SLOW_POINTS = ((3500, 0), (2500, 5), (1800, 10), (1100, 0), (600, 5), (300, 10))
SLOW_LINES_MM = (3500, 1500, 600)
QUICK_POINTS = {"system1": (450, 10), "system2": (1500, 5)}  # cheap for the slow fit
QUICK_LINE_MM = 3500
CSV_COLUMNS = ("system", "source", "method", "model", "captures", "ok", "mean_error_pct",
               "max_error_pct", "time_per_region_ms", "time_per_frame_ms",
               "max_time_per_region_ms")


@dataclass(frozen=True)
class Row:
    """One capture × method × model outcome."""

    system: str
    source: str  # "point" or "line"
    distance_mm: float
    offset_mm: float
    method: str
    model: str
    estimate_mm: float
    status: str
    error_pct: float
    region_s: float  # measurement + model, summed over the frame's regions
    frame_s: float  # region detection + region_s
    regions: int
    max_region_s: float = math.nan  # the frame's slowest region (measurement + model)


def captures(system: str, quick: bool, slow: bool) -> list[tuple[str, int, int]]:
    """(source, Ad, Δh) of the captures one method runs on."""
    lines = system == "system1"  # the seed's Table 3 (lines) is system 1 only
    if quick:
        return [("point", *QUICK_POINTS[system])] + ([("line", QUICK_LINE_MM, 0)] if lines else [])
    if slow:
        out = [("point", d, h) for d, h in SLOW_POINTS]
        return out + ([("line", d, 0) for d in SLOW_LINES_MM] if lines else [])
    out = [("point", int(d), int(h)) for d in SEED_AD for h in SEED_DH]
    return out + ([("line", int(d), 0) for d in SEED_AD] if lines else [])


def load(system: str, source: str, dist: int, dh: int):
    """Grey image, profile and truth of one rendered capture."""
    name = (f"point_{system}_{dist}mm_dh{dh}" if source == "point"
            else f"line_{system}_{dist}mm")
    prof = load_profile(DATA / f"{name}.profile.toml")
    cap = load_capture(DATA / f"{name}.png", prof)
    img = cap.grey()
    truth = json.loads((DATA / f"{name}.truth.json").read_text(encoding="utf-8"))
    return img, prof, truth["sources"][0]


def run_capture(img, prof, geom, method: str) -> dict[str, tuple[float, str, float, float, int]]:
    """Measure every region once, apply every model; per model: (first region's distance,
    status, summed region seconds, frame seconds, region count)."""
    t0 = time.process_time()
    stats = lenslet_stats(img, geom.lmap)
    regions = find_regions(stats, geom.lmap, geom.pitch_px)
    noise = noise_sigma(img)
    if method != "diameter" and regions:  # the capture's noise model, once, as run_distance
        capture_noise(img, geom.lmap, geom.pitch_px, stats)
    detect_s = time.process_time() - t0
    measured = []
    for reg in regions:
        t1 = time.process_time()
        if method == "diameter":
            meas = measure_diameter(prof, geom, img, stats, reg, noise)
        elif method == "lenslet":
            meas = measure_lenslet(prof, geom, img, reg, noise)
        else:
            meas = measure_lightfield(prof, geom, img, reg, noise, method == "lightfield-fast")
        measured.append((meas, time.process_time() - t1))
    out = {}
    for model in MODELS:
        region_s = 0.0
        worst = 0.0
        first = (math.nan, "no-region")
        for k, (meas, meas_s) in enumerate(measured):
            t1 = time.process_time()
            with np.errstate(invalid="ignore"):  # auto.ErrorTable.predict casts NaN
                _, d, _, _, status = _apply_model(prof, meas, model, None)
            one = meas_s + time.process_time() - t1
            region_s += one
            worst = max(worst, one)
            if k == 0:
                first = (d, status)
        out[model] = (first[0], first[1], region_s, detect_s + region_s, len(regions), worst)
    return out


def collect(quick: bool, log=print) -> list[Row]:
    """Run the grid (module docstring) and return one :class:`Row` per capture × method × model."""
    rows: list[Row] = []
    for system in SYSTEMS:
        cal = load_calibration(DATA / f"calib_{system}.json")
        geom = None
        for method in METHODS:
            t_start = time.perf_counter()
            todo = captures(system, quick, method == "lightfield")
            for source, dist, dh in todo:
                img, prof, truth = load(system, source, dist, dh)
                if geom is None:
                    geom = prepare_geometry(prof, cal, img.shape)
                t_half = 0.5 * prof.main_lens.thickness_mm
                ad = float(truth["distance_mm"])
                off = float(truth.get("offset_mm", dh))
                for model, (d, status, rs, fs, n, worst) in run_capture(img, prof, geom,
                                                                       method).items():
                    ok = status == "ok" and math.isfinite(d)
                    err = abs(ad - d) / (ad + t_half) * 100.0 if ok else math.nan
                    rows.append(Row(system, source, ad, off, method, model, d, status, err,
                                    rs, fs, n, worst))
            log(f"  {system} {method:15} {len(todo):3d} captures "
                f"{time.perf_counter() - t_start:6.1f} s")
    return rows


def summarise(rows: list[Row]) -> list[dict]:
    """Aggregate rows into the ``tradeoff.csv`` table (key: system, source, method, model)."""
    keys = []
    for r in rows:
        k = (r.system, r.source, r.method, r.model)
        if k not in keys:
            keys.append(k)
    table = []
    for k in keys:
        sel = [r for r in rows if (r.system, r.source, r.method, r.model) == k]
        errs = np.array([r.error_pct for r in sel])
        ok = np.isfinite(errs)
        nreg = sum(r.regions for r in sel)
        table.append({
            "system": k[0], "source": k[1], "method": k[2], "model": k[3],
            "captures": len(sel), "ok": int(ok.sum()),
            "mean_error_pct": f"{errs[ok].mean():.4g}" if ok.any() else "nan",
            "max_error_pct": f"{errs[ok].max():.4g}" if ok.any() else "nan",
            "time_per_region_ms": f"{1e3 * sum(r.region_s for r in sel) / max(nreg, 1):.4g}",
            "time_per_frame_ms": f"{1e3 * np.mean([r.frame_s for r in sel]):.4g}",
            "max_time_per_region_ms": f"{1e3 * max(r.max_region_s for r in sel):.4g}",
        })
    return table


def write_csv_atomic(path: Path, columns, records) -> None:
    """Write dict records as CSV through a temporary file in the same folder."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(columns), lineterminator="\n")
    w.writeheader()
    w.writerows(records)
    atomic_write_text(path, buf.getvalue())


def read_seed_tables(path: Path = ROOT / "docs" / "results" / "seed_tables.csv") -> list[dict]:
    """The seed's published Tables 2 and 3 (Ed and ERROR), as committed (or any CSV)."""
    with path.open(encoding="utf-8", newline="") as fh:
        return list(csv.DictReader(fh))


def seed_comparison(rows: list[Row]) -> list[dict]:
    """The seed's Table 2/3 rows next to ours: the seed's closed form (``offaxis``) on the exact
    trace's rim heights and through our pipeline, and our exact pipeline, same grid."""
    model_err = {}
    for system in SYSTEMS:
        prof = load_profile(system)
        model_err[(system, "point")] = seed_errors(prof, "offaxis")  # (3 Δh, 16 Ad)
        model_err[(system, "line")] = seed_errors(prof, "line")
    pipe = {(r.system, r.source, r.distance_mm, r.offset_mm, r.method, r.model): r.error_pct
            for r in rows}
    seed = read_seed_tables()
    out = []
    for s in seed:
        if s["method"] != "proposed":
            continue
        system, source = s["system"], s["source"]
        ad, dh = float(s["ad_mm"]), float(s["dh_mm"] or 0.0)
        i = SEED_DH.index(dh)
        j = int(np.flatnonzero(SEED_AD == ad)[0])
        hahne = next(t for t in seed if t["method"] == "hahne14" and t["table"] == s["table"]
                     and t["system"] == system and float(t["ad_mm"]) == ad)
        pkey = (system, source, ad, dh if source == "point" else 0.0)

        def fmt(v):
            return "" if v is None or not math.isfinite(v) else f"{v:.3g}"

        out.append({
            "table": s["table"], "system": system, "source": source, "dh_mm": s["dh_mm"],
            "ad_mm": s["ad_mm"], "seed_hahne14_error_pct": hahne["error_pct"],
            "seed_proposed_error_pct": s["error_pct"],
            "ours_offaxis_exact_heights_pct": fmt(model_err[(system, source)][i, j]),
            "ours_offaxis_diameter_pct": fmt(pipe.get(pkey + ("diameter", "offaxis"))),
            "ours_exact_lightfield_fast_pct": fmt(pipe.get(pkey + ("lightfield-fast", "exact"))),
            "ours_exact_lightfield_pct": fmt(pipe.get(pkey + ("lightfield", "exact"))),
            "ours_exact_lenslet_pct": fmt(pipe.get(pkey + ("lenslet", "exact"))),
        })
    return out


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the non-dominated (time, error) points, fastest first."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def figures(rows: list[Row], table: list[dict], img_dir: Path) -> None:
    """``error_vs_distance.png`` (the seed's Fig. 8 layout) and ``pareto.png``. Needs
    matplotlib, which lfcam itself does not (``pip install matplotlib``); without it the
    tables are written and the run ends with a one-line message (or pass ``--no-figures``)."""
    try:
        import matplotlib
    except ImportError:
        raise SystemExit("tradeoff.py: the figures need matplotlib (pip install matplotlib); "
                         "--no-figures skips them (a measuring run writes its tables first)"
                         ) from None

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seed = read_seed_tables()
    panels = [("system1", "point", "(a) point source, system 1"),
              ("system2", "point", "(b) point source, system 2"),
              ("system1", "line", "(c) 10 mm line, system 1")]
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.6), sharey=False)
    ours = [("lightfield", "exact", "ours: lightfield + exact", "C0", "o-"),
            ("lightfield-fast", "exact", "ours: lightfield-fast + exact", "C2", "s-"),
            ("lenslet", "exact", "ours: lenslet + exact", "C5", "D-"),
            ("diameter", "offaxis", "seed model on our diameter measurement", "C1", "^-"),
            ("diameter", "exact", "ours: diameter + exact", "C4", "v-")]
    for ax, (system, source, title) in zip(axes, panels, strict=True):
        for method, model, label, colour, style in ours:
            sel = [r for r in rows if r.system == system and r.source == source
                   and r.method == method and r.model == model]
            if not sel:
                continue
            ads = sorted({r.distance_mm for r in sel})
            errs = [[r.error_pct for r in sel if r.distance_mm == a] for a in ads]
            mean = [np.nanmean(e) if np.isfinite(e).any() else math.nan for e in errs]
            ax.plot(ads, mean, style, color=colour, label=label, ms=4)
        prof = load_profile(system)
        pure = np.nanmean(seed_errors(prof, "offaxis" if source == "point" else "line"), axis=0)
        ax.plot(SEED_AD, pure, "-", color="C3", lw=1,
                label="seed model on exact rim heights (no measurement error)")
        for method, label, style in (("hahne14", "seed Table: [14] (Hahne)", "k--"),
                                     ("proposed", "seed Table: proposed", "r:")):
            recs = [s for s in seed if s["system"] == system and s["source"] == source
                    and s["method"] == method]
            for dh in sorted({s["dh_mm"] for s in recs}):
                pts = sorted((float(s["ad_mm"]), float(s["error_pct"])) for s in recs
                             if s["dh_mm"] == dh)
                tag = "" if method == "hahne14" or source == "line" else f" Δh={float(dh):g}"
                ax.plot(*zip(*pts, strict=True), style, marker="x", ms=4, label=label + tag,
                        alpha=0.8 if dh in ("5", "5.0", "") else 0.5)
        ax.set_title(title)
        ax.set_xlabel("Ad (mm)")
        ax.set_ylabel("ERROR (%) — eq. 21, mean over Δh")
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=8,
               title="(c): the seed's line table has one 'proposed' column (no Δh)",
               title_fontsize=8)
    fig.tight_layout(rect=(0, 0.16, 1, 1))
    _save(fig, img_dir / "error_vs_distance.png")
    plt.close(fig)

    fig, axes = plt.subplots(1, 3, figsize=(17, 5.8))
    markers = {"lightfield": "o", "lightfield-fast": "s", "lenslet": "D", "diameter": "^"}
    colours = dict(zip(MODELS, ("C0", "C1", "C2", "C3", "C4"), strict=True))
    panels = [(system, "point") for system in SYSTEMS] + [("system1", "line")]
    for ax, (system, source) in zip(axes, panels, strict=True):
        pts, labels = [], []
        for t in table:
            if (t["system"] != system or t["source"] != source
                    or t["mean_error_pct"] == "nan"):
                continue
            x, y = float(t["time_per_region_ms"]), float(t["mean_error_pct"])
            pts.append((x, y))
            labels.append(f"{t['method']}+{t['model']}")
            ax.scatter(x, y, marker=markers[t["method"]], color=colours[t["model"]], s=40,
                       label=f"{t['method']} + {t['model']}")
        front = pareto_front(pts)
        ax.plot([pts[i][0] for i in front], [pts[i][1] for i in front], "k-", lw=1,
                label="Pareto front")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("time per region (ms, measurement + model, 1 core)")
        ax.set_ylabel("mean ERROR (%)")
        ax.set_title(f"{system}: {'point sources' if source == 'point' else '10 mm lines'}")
        ax.grid(alpha=0.3, which="both")
    # one legend below the panels (inside them it hid the full fit's points)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=7, fontsize=7)
    fig.tight_layout(rect=(0, 0.17, 1, 1))
    _save(fig, img_dir / "pareto.png")
    plt.close(fig)


def _save(fig, path: Path) -> None:
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110))


def print_table(table: list[dict]) -> None:
    """The summary table on stdout."""
    head = (f"{'system':8} {'source':6} {'method':15} {'model':8} {'ok/n':>7} {'mean%':>8} "
            f"{'max%':>8} {'ms/region':>10} {'ms/frame':>9} {'worst ms':>9}")
    print(head)
    print("-" * len(head))
    for t in table:
        print(f"{t['system']:8} {t['source']:6} {t['method']:15} {t['model']:8} "
              f"{t['ok']:>3}/{t['captures']:<3} {t['mean_error_pct']:>8} {t['max_error_pct']:>8} "
              f"{t['time_per_region_ms']:>10} {t['time_per_frame_ms']:>9} "
              f"{t['max_time_per_region_ms']:>9}")


def main(argv: list[str] | None = None) -> list[dict]:
    """Run, print, write; returns the summary table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="a few captures per cell (tests)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--img", type=Path, default=ROOT / "docs" / "img")
    ap.add_argument("--no-figures", action="store_true")
    ap.add_argument("--replot", action="store_true",
                    help="redraw the figures from the CSVs in --out (no measurement)")
    args = ap.parse_args(argv)
    if args.replot:
        rows = [Row(**{k: (v if k in ("system", "source", "method", "model", "status")
                           else int(v) if k == "regions" else float(v)) for k, v in r.items()})
                for r in read_seed_tables(args.out / "tradeoff_captures.csv")]
        table = read_seed_tables(args.out / "tradeoff.csv")
        figures(rows, table, args.img)
        return table
    slow = ", ".join(f"{d}/{h}" for d, h in SLOW_POINTS)
    print("# trade-off: seed eq. 21 error vs time, rendered captures in data/synthetic, 1 core")
    if args.quick:
        print("# --quick: 1 point capture per system (+1 line, system1) per method")
    else:
        print(f"# lightfield (slow) on Ad/Δh = {slow} mm and lines at "
              f"{', '.join(map(str, SLOW_LINES_MM))} mm only;\n# lightfield-fast and diameter "
              "on all 16 Ad × 3 Δh (+16 lines, system 1)")
        print("# lenslet on all 16 Ad × 3 Δh (+16 lines, system 1)")
    t0 = time.perf_counter()
    rows = collect(args.quick)
    table = summarise(rows)
    print_table(table)
    print(f"# total {time.perf_counter() - t0:.0f} s")
    write_csv_atomic(args.out / "tradeoff.csv", CSV_COLUMNS, table)
    write_csv_atomic(args.out / "tradeoff_captures.csv", Row.__dataclass_fields__.keys(),
                     [r.__dict__ for r in rows])
    comparison = seed_comparison(rows)
    write_csv_atomic(args.out / "seed_comparison.csv", comparison[0].keys(), comparison)
    if not args.no_figures:
        figures(rows, table, args.img)
    return table


if __name__ == "__main__":
    main()
