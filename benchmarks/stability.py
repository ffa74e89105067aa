"""Stability of the distance models at the extremes (no rendering: exact trace → models).

Run: ``python benchmarks/stability.py [--out docs/results] [--img docs/img] [--no-figures]``

Cases (both imaging systems unless noted; heights from :func:`lfcam.optics.trace.forward`):

* ``focus``     — distance swept through the plane where the rim rays cross on the sensor
  (blur diameter → 0, sign of y1 − y2 flips), offset 5 mm;
* ``far``       — distance → ∞ (tan φ → 0), including ``inf`` itself;
* ``rim``       — offset Δh swept to ±D/2 and beyond, at 1 m;
* ``tir``       — sources close to the lens at large offsets (the trace reports TIR/edge rays),
  and heights no source can produce;
* ``fnumber``   — main-lens f-number vs the MLA's (system 1, pupil diameter varied): micro-image
  size over pitch, and the distance error one lenslet pitch of footprint error causes;
* ``shortline`` — 10 mm → 0.1 µm lines at 1 m (eq. 20's cancellation), system 1;
* ``float32``   — heights rounded to float32 before the inversion;
* ``noise``     — Monte-Carlo height noise vs :func:`lfcam.models.auto.propagate`.

"Amplification" is the relative distance error per micrometre of independent height error
(``100·σ_d/d`` for σ_y1 = σ_y2 = 1 µm, by :func:`~lfcam.models.auto.propagate`), in % per µm.
Writes ``stability.csv`` (one row per case × system × model) and ``stability.png``.
"""

from __future__ import annotations

import argparse
import math
import pickle
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from tradeoff import write_csv_atomic  # noqa: E402

from lfcam import load_profile  # noqa: E402
from lfcam.models import POINT_MODELS, line  # noqa: E402
from lfcam.models.auto import propagate  # noqa: E402
from lfcam.models.base import STATUS_LABELS, Status  # noqa: E402
from lfcam.optics.trace import TraceStatus, forward  # noqa: E402

SYSTEMS = ("system1", "system2")
MODELS = tuple(POINT_MODELS)
SIGMA_Y_MM = 1e-3
COLUMNS = ("case", "system", "model", "cases", "statuses", "max_error_pct", "median_amp_pct_um",
           "max_amp_pct_um", "note")


def _statuses(status: np.ndarray) -> str:
    """``label:count`` of every status present."""
    vals, counts = np.unique(np.asarray(status).ravel(), return_counts=True)
    return " ".join(f"{STATUS_LABELS[v]}:{c}" for v, c in zip(vals, counts, strict=True))


def _fmt(v: float) -> str:
    return "nan" if not np.isfinite(v) else f"{v:.3g}"


def _model_rows(case, system, prof, dist, off, fw, note="") -> tuple[list[dict], dict]:
    """Invert traced heights with every model: status, error, amplification."""
    rows, curves = [], {}
    for name in MODELS:
        inv, sig = propagate(name, prof, None, fw.y1_mm, fw.y2_mm, SIGMA_Y_MM, SIGMA_Y_MM)
        ok = inv.status == Status.OK
        with np.errstate(invalid="ignore", divide="ignore"):
            err = np.abs(inv.distance_mm - dist) / dist * 100.0
            amp = 100.0 * sig / inv.distance_mm
        err = np.where(np.isfinite(dist), err, np.nan)
        fin = ok & np.isfinite(err)
        famp = ok & np.isfinite(amp)
        rows.append({
            "case": case, "system": system, "model": name, "cases": int(np.size(dist)),
            "statuses": _statuses(inv.status),
            "max_error_pct": _fmt(err[fin].max()) if fin.any() else "nan",
            "median_amp_pct_um": _fmt(np.median(amp[famp])) if famp.any() else "nan",
            "max_amp_pct_um": _fmt(amp[famp].max()) if famp.any() else "nan", "note": note,
        })
        curves[name] = (inv, err, amp)
    return rows, curves


def rim_crossing_mm(prof, offset_mm: float = 0.0) -> float:
    """Distance at which the two rim rays meet on the sensor (y1 = y2), by bisection."""
    lo, hi = 1.5 * prof.main_lens.focal_length_mm, 1e7
    f_lo = np.subtract(*forward(prof, None, lo, offset_mm)[:2])
    for _ in range(200):
        mid = math.sqrt(lo * hi)
        f_mid = np.subtract(*forward(prof, None, mid, offset_mm)[:2])
        if np.sign(f_mid) == np.sign(f_lo):
            lo, f_lo = mid, f_mid
        else:
            hi = mid
    return math.sqrt(lo * hi)


def case_focus_far(system, prof, plots):
    """Through the rim-ray crossing and on to infinity."""
    cross = rim_crossing_mm(prof, 5.0)
    dist = np.concatenate([np.geomspace(300.0, 1e6, 600), [np.inf]])
    fw = forward(prof, None, dist, 5.0)
    near = np.abs(dist / cross - 1.0) < 0.05
    rows, curves = _model_rows("focus", system, prof, dist[near], 5.0,
                               forward(prof, None, dist[near], 5.0),
                               f"rim rays cross on the sensor at {cross:.1f} mm (±5 % window)")
    far = dist >= 1e4
    r2, _ = _model_rows("far", system, prof, dist[far], 5.0, forward(prof, None, dist[far], 5.0),
                        "1e4 mm … 1e6 mm and inf (inf: error not defined)")
    # sign flip: the seed's unsigned diameter, given the wrong side of focus
    swapped = POINT_MODELS["exact"](prof, None, fw.y2_mm, fw.y1_mm)
    k = int(np.argmin(np.abs(dist - 0.5 * cross)))
    note = (f"swapping y1/y2 at {dist[k]:.0f} mm gives {swapped.distance_mm[k]:.0f} mm "
            f"({STATUS_LABELS[swapped.status[k]]})")
    rows[0]["note"] += "; " + note
    _, curves_all = _model_rows("all", system, prof, dist, 5.0, fw)
    plots["focus"][system] = (dist, fw, curves_all, cross)
    return rows + r2


def case_rim(system, prof, plots):
    """Offsets up to and beyond the pupil radius."""
    d = prof.main_lens.pupil_diameter_mm
    off = np.linspace(-0.8 * d, 0.8 * d, 321)
    fw = forward(prof, None, 1000.0, off)
    dist = np.full(off.shape, 1000.0)
    rows, curves = _model_rows("rim", system, prof, dist, off, fw,
                               f"Δh from −0.8 D to 0.8 D at 1 m (D = {d:g} mm)")
    plots["rim"][system] = (off / d, curves)
    return rows


def case_tir(system, prof, plots):
    """Sources near the lens and far off axis; impossible heights."""
    dd, oo = np.meshgrid(np.geomspace(15.0, 400.0, 60), np.linspace(0.0, 400.0, 81))
    fw = forward(prof, None, dd, oo)
    traced = fw.status == TraceStatus.OK
    note = "trace: " + " ".join(f"{TraceStatus(v).name.lower()}:{c}" for v, c in
                                zip(*np.unique(fw.status, return_counts=True), strict=True))
    rows, _ = _model_rows("tir", system, prof, dd, oo, fw, note)
    big = np.array([50.0, 200.0, 1e3, 1e6])
    for name in MODELS:
        inv = POINT_MODELS[name](prof, None, big, -big)
        next(r for r in rows if r["model"] == name)["note"] += (
            f"; y=±(50,200,1e3,1e6) mm → {_statuses(inv.status)}")
    plots["tir"][system] = (dd, oo, fw.status, traced)
    return rows


def case_fnumber(plots):
    """Main-lens vs MLA f-number (system 1): micro-image fill and diameter-method resolution."""
    prof0 = load_profile("system1")
    mla = prof0.mla
    f_mla = mla.focal_length_mm / mla.pitch_mm
    rows, series = [], []
    for f_num in (1.4, 2.0, f_mla, 2.8, 4.0, 5.6):
        lens = replace(prof0.main_lens,
                       pupil_diameter_mm=prof0.main_lens.focal_length_mm / f_num)
        prof = replace(prof0, main_lens=lens)
        d_in = prof.d_in_mm
        micro = lens.pupil_diameter_mm * mla.focal_length_mm / (d_in - lens.exit_pupil_z_mm)
        dist = np.array([300.0, 1000.0, 3000.0])
        fw = forward(prof, None, dist, 0.0)
        # one pitch of footprint-diameter error = ±pitch/2 on each rim height
        _, sig = propagate("exact", prof, None, fw.y1_mm, fw.y2_mm, 0.5 * mla.pitch_mm,
                           0.5 * mla.pitch_mm)
        rel = 100.0 * sig / dist
        series.append((f_num, micro / mla.pitch_mm, rel))
        rows.append({
            "case": "fnumber", "system": "system1", "model": "exact", "cases": 3,
            "statuses": _statuses(fw.status), "max_error_pct": "nan",
            "median_amp_pct_um": "nan", "max_amp_pct_um": "nan",
            "note": (f"main F/{f_num:.2f} vs MLA F/{f_mla:.2f}: micro-image/pitch "
                     f"{micro / mla.pitch_mm:.2f}; ±pitch/2 rim error → "
                     + ", ".join(f"{r:.2g} % at {d:.0f} mm" for r, d in zip(rel, dist,
                                                                             strict=True))),
        })
    plots["fnumber"] = (f_mla, series)
    return rows


def case_shortline(plots):
    """Eq. 20's cancellation for short lines (system 1, 1 m, centred on Δh = 5 mm, radial)."""
    prof = load_profile("system1")
    length = np.geomspace(1e-4, 20.0, 120)
    a = forward(prof, None, 1000.0, 5.0 - 0.5 * length)
    b = forward(prof, None, 1000.0, 5.0 + 0.5 * length)
    inv = line.invert(prof, None, a.y1_mm, a.y2_mm, b.y1_mm, b.y2_mm)
    raw = line.invert(prof, None, a.y1_mm, a.y2_mm, b.y1_mm, b.y2_mm, max_amplification=np.inf)
    rng = np.random.default_rng(1)
    draws = 200
    noisy = np.array([line.invert(prof, None, *(v + rng.normal(0, SIGMA_Y_MM, v.shape) for v in
                                                (a.y1_mm, a.y2_mm, b.y1_mm, b.y2_mm)),
                                  max_amplification=np.inf).distance_mm for _ in range(draws)])
    with np.errstate(invalid="ignore"):
        spread = 100.0 * np.nanstd(noisy, axis=0) / 1000.0
    from lfcam.models.offaxis import rim_angles

    amp = line.amplification(rim_angles(prof, None, a.y1_mm), rim_angles(prof, None, b.y1_mm))
    err = np.abs(raw.distance_mm - 1000.0) / 1000.0 * 100.0
    ok = inv.status == Status.OK
    shortest_ok = float(length[ok].min()) if ok.any() else math.nan
    plots["shortline"] = (length, amp, err, spread, inv.status)
    return [{
        "case": "shortline", "system": "system1", "model": "line", "cases": int(length.size),
        "statuses": _statuses(inv.status), "max_error_pct": _fmt(np.nanmax(err[ok])),
        "median_amp_pct_um": _fmt(np.nanmedian(spread[ok])),
        "max_amp_pct_um": _fmt(np.nanmax(spread[ok])),
        "note": (f"shortest ok line {shortest_ok:.3g} mm (amplification ≤ "
                 f"{line.DEFAULT_MAX_AMPLIFICATION:g}); 1 µm noise on a 10 mm line → "
                 f"{spread[np.argmin(np.abs(length - 10))]:.2g} %, on 0.1 mm → "
                 f"{spread[np.argmin(np.abs(length - 0.1))]:.2g} %"),
    }]


def case_float32(system, prof, plots):
    """Heights rounded to float32: error vs the float64 answer, vs eps·amplification."""
    dist = np.geomspace(300.0, 1e5, 200)
    fw = forward(prof, None, dist, 5.0)
    rows = []
    out = {}
    for name in MODELS:
        ref = POINT_MODELS[name](prof, None, fw.y1_mm, fw.y2_mm)
        f32 = POINT_MODELS[name](prof, None, fw.y1_mm.astype(np.float32),
                                 fw.y2_mm.astype(np.float32))
        _, sig = propagate(name, prof, None, fw.y1_mm, fw.y2_mm, SIGMA_Y_MM, SIGMA_Y_MM)
        with np.errstate(invalid="ignore"):
            rel = np.abs(f32.distance_mm - ref.distance_mm) / ref.distance_mm * 100.0
            # predicted: amplification (%/µm) × float32 half-ulp of |y| (µm)
            big = np.maximum(np.abs(fw.y1_mm), np.abs(fw.y2_mm)).astype(np.float32)
            ulp_um = 0.5 * np.spacing(big).astype(np.float64) * 1e3
            pred = 100.0 * sig / ref.distance_mm * ulp_um
        ok = (ref.status == Status.OK) & (f32.status == Status.OK)
        rows.append({
            "case": "float32", "system": system, "model": name, "cases": int(dist.size),
            "statuses": _statuses(f32.status),
            "max_error_pct": _fmt(np.nanmax(rel[ok])) if ok.any() else "nan",
            "median_amp_pct_um": "nan", "max_amp_pct_um": "nan",
            "note": (f"float32 vs float64 answer, 300 mm…1e5 mm; predicted ≤ "
                     f"{_fmt(np.nanmax(pred[ok]) * math.sqrt(2)) if ok.any() else 'nan'} % "
                     "(half-ulp × amplification × √2)"),
        })
        out[name] = (dist, rel, pred)
    plots["float32"][system] = out
    return rows


def case_noise(system, prof, plots):
    """Monte-Carlo height noise vs first-order propagation."""
    rng = np.random.default_rng(2)
    dist = np.array([300.0, 1000.0, 3500.0])
    fw = forward(prof, None, dist, 5.0)
    rows = []
    for name in ("exact", "offaxis"):
        for sigma_um in (0.1, 1.0, 10.0):
            s = sigma_um * 1e-3
            _, pred = propagate(name, prof, None, fw.y1_mm, fw.y2_mm, s, s)
            n = 2000
            y1 = fw.y1_mm[None, :] + rng.normal(0, s, (n, dist.size))
            y2 = fw.y2_mm[None, :] + rng.normal(0, s, (n, dist.size))
            inv = POINT_MODELS[name](prof, None, y1, y2)
            with np.errstate(invalid="ignore"):
                mc = np.nanstd(inv.distance_mm, axis=0)
                bias = np.nanmean(inv.distance_mm, axis=0) - POINT_MODELS[name](
                    prof, None, fw.y1_mm, fw.y2_mm).distance_mm
            ratio = mc / pred
            rows.append({
                "case": "noise", "system": system, "model": name, "cases": n * dist.size,
                "statuses": _statuses(inv.status), "max_error_pct": "nan",
                "median_amp_pct_um": _fmt(np.median(100 * pred / dist / sigma_um)),
                "max_amp_pct_um": _fmt(np.max(100 * pred / dist / sigma_um)),
                "note": (f"σ_y = {sigma_um:g} µm at 300/1000/3500 mm: Monte-Carlo σ_d / "
                         f"propagated σ_d = {', '.join(f'{r:.2f}' for r in ratio)}; bias "
                         f"{', '.join(f'{b:.2g}' for b in bias)} mm"),
            })
            plots["noise"].setdefault(system, []).append((name, sigma_um, dist, mc, pred))
    return rows


def figure(plots, path: Path) -> None:
    """Six panels: diameter and amplification through focus; rim; short lines; float32; F#."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from tradeoff import _save

    fig, axes = plt.subplots(2, 3, figsize=(16, 9))
    ax = axes[0, 0]
    for system, (dist, fw, _, cross) in plots["focus"].items():
        ax.plot(dist, fw.y1_mm - fw.y2_mm, label=f"{system}: y1 − y2")
        ax.axvline(cross, ls=":", color="grey")
    ax.set_xscale("log")
    ax.set_xlabel("distance (mm)")
    ax.set_ylabel("signed blur y1 − y2 (mm)")
    ax.set_title("blur through the rim-ray crossing (dotted)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    ax = axes[0, 1]
    for system, (dist, _, curves, _) in plots["focus"].items():
        for name, (inv, _, amp) in curves.items():
            ax.plot(dist, np.where(inv.status == Status.OK, amp, np.nan), label=f"{system} {name}",
                    ls="-" if system == "system1" else "--")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("distance (mm)")
    ax.set_ylabel("distance error (%) per µm of height error")
    ax.set_title("error amplification, offset 5 mm")
    ax.legend(fontsize=6, ncol=2)
    ax.grid(alpha=0.3, which="both")
    ax = axes[0, 2]
    for system, (frac, curves) in plots["rim"].items():
        for name in ("offaxis", "onaxis", "exact"):
            inv, err, _ = curves[name]
            ax.plot(frac, np.where(inv.status == Status.OK, err, np.nan),
                    label=f"{system} {name}", ls="-" if system == "system1" else "--")
    ax.axvline(-0.5, color="grey", ls=":")
    ax.axvline(0.5, color="grey", ls=":")
    ax.set_xlabel("Δh / D")
    ax.set_ylabel("model error (%) at 1 m")
    ax.set_title("offset to the rim (±D/2 dotted) and beyond")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    ax = axes[1, 0]
    length, amp, err, spread, status = plots["shortline"]
    ax.plot(length, amp, label="eq. 20 amplification")
    ax.plot(length, spread, label="σ_d (%) for 1 µm height noise")
    ax.plot(length, err, label="noise-free error (%)")
    bad = status != Status.OK
    if bad.any():
        ax.axvspan(length[bad].min(), length[bad].max(), color="red", alpha=0.1,
                   label="ill-conditioned")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("line length (mm), 1 m, system 1")
    ax.set_title("short lines: eq. 20 cancellation")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3, which="both")
    ax = axes[1, 1]
    for system, out in plots["float32"].items():
        for name in ("exact", "offaxis", "thin"):
            dist, rel, pred = out[name]
            ax.plot(dist, rel, label=f"{system} {name}", ls="-" if system == "system1" else "--")
        ax.plot(dist, out["exact"][2], color="k", lw=0.8, ls=":" if system == "system1" else "-.",
                label=f"{system} predicted (exact)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("distance (mm)")
    ax.set_ylabel("|float32 − float64| (%)")
    ax.set_title("float32 heights")
    ax.legend(fontsize=6, ncol=2)
    ax.grid(alpha=0.3, which="both")
    ax = axes[1, 2]
    f_mla, series = plots["fnumber"]
    fn = [s[0] for s in series]
    ax.plot(fn, [s[1] for s in series], "o-", label="micro-image / pitch")
    for k, d in enumerate((300, 1000, 3000)):
        ax.plot(fn, [s[2][k] for s in series], "s--", label=f"σ_d (%) at {d} mm, ±pitch/2")
    ax.axvline(f_mla, color="grey", ls=":", label="MLA f-number")
    ax.set_yscale("log")
    ax.set_xlabel("main-lens f-number (system 1)")
    ax.set_title("f-number mismatch")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def run() -> tuple[list[dict], dict]:
    """All cases; returns the rows and the plot data."""
    plots = {"focus": {}, "rim": {}, "tir": {}, "float32": {}, "noise": {}}
    rows = []
    for system in SYSTEMS:
        prof = load_profile(system)
        rows += case_focus_far(system, prof, plots)
        rows += case_rim(system, prof, plots)
        rows += case_tir(system, prof, plots)
        rows += case_float32(system, prof, plots)
        rows += case_noise(system, prof, plots)
    rows += case_fnumber(plots)
    rows += case_shortline(plots)
    return rows, plots


def main(argv: list[str] | None = None) -> list[dict]:
    """Print the table, write the CSV and the figure."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--img", type=Path, default=ROOT / "docs" / "img")
    ap.add_argument("--no-figures", action="store_true")
    ap.add_argument("--curves", type=Path, help="also write the plotted curves (pickle)")
    args = ap.parse_args(argv)
    rows, plots = run()
    if args.curves:
        args.curves.write_bytes(pickle.dumps(plots))
    order = {c: i for i, c in enumerate(
        ("focus", "far", "rim", "tir", "fnumber", "shortline", "float32", "noise"))}
    rows.sort(key=lambda r: (order[r["case"]], r["system"]))
    for r in rows:
        print(f"{r['case']:9} {r['system']:7} {r['model']:7} n={r['cases']:<6} "
              f"[{r['statuses']}] err≤{r['max_error_pct']}% amp {r['median_amp_pct_um']}"
              f"/{r['max_amp_pct_um']} %/µm  {r['note']}")
    write_csv_atomic(args.out / "stability.csv", COLUMNS, rows)
    if not args.no_figures:
        figure(plots, args.img / "stability.png")
    return rows


if __name__ == "__main__":
    main()
