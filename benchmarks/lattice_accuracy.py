"""How well the white calibration places the lenslet lattice, and what a lattice error costs the
pixel polish.

Run: ``python benchmarks/lattice_accuracy.py [--cases system1:1000,system1:1500,...]
[--whites sim,analytic] [--sensitivity] [--cache DIR] [--render-cache DIR]``

For each system and focus of ``focus_grid.py`` (system 1 on its 1024² sensor, system 2 on
1536²) and each white (``sim``: rendered by ``lfcam.sim``; ``analytic``: computed per pixel by
``benchmarks/whites_analytic.py``, which shares no rendering code with it), the white is
calibrated (``calibrate_white``, cached) and the geometry prepared as ``lfcam distance``
prepares it (:func:`lfcam.measure.geometry.prepare_geometry`: white centroids → lenslet
centres through the white-offset table → one affine lattice). Against the renderer's lattice
(the MLA both whites are made with) it prints:

* the lattice's error as an affine map: scale error along x and y, offset (px), and the lens
  centres' RMS and largest error (px);
* the white's measured micro-image centroids minus the centroids the white-offset table
  predicts at the true lenslets, radially, by quarter of the field (px): where the table and
  the centroid estimator agree this is ~0; a trend is one or the other's bias;
* whether the white's micro-images touch (the fitted disc radius over half the pitch).

``--sensitivity``: a bright point at 3 500 mm and 80 % of system 1's half-field (focus 1.5 m,
one noise draw) measured by ``measure_lenslet`` with its pixel polish forced on, with the
calibrated lattice, the renderer's, and the renderer's scaled by 1 + 1.5e-5 or shifted by
0.6 µm: the distance error of the pixel answer for each (docs/distance.md, "How exactly the
pixel polish needs the lenslet lattice (stop 64)").
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import focus_grid as fg  # noqa: E402

from lfcam.calibrate.model import load_calibration  # noqa: E402
from lfcam.measure import fastfit  # noqa: E402
from lfcam.measure.geometry import white_centroids_px  # noqa: E402

SIZES = {"system1": None, "system2": 1536}  # focus_grid's sensors (system 2: 1536²)
CASES = "system1:1000,system1:1500,system1:inf,system2:1000,system2:1500,system2:inf"


def _key(cam: fg.Camera, white: str) -> Path:
    """The calibration file ``focus_grid.calibrated_geometry`` caches for ``cam``."""
    focus = f"{cam.focus_mm:g}"
    name = f"calib_{cam.system}_{focus}_{cam.shape[1]}" + ("" if white == "sim" else f"_{white}")
    return Path(name + ".json")


def lattice_row(system: str, focus: float, white: str, cache: Path) -> str:
    """One table row: the calibrated lattice against the renderer's (module docstring)."""
    truth = fg.Camera(system, focus, SIZES[system], cache, True)
    cam = fg.Camera(system, focus, SIZES[system], cache, False, white=white)
    p = truth.used
    pp = p.sensor.pixel_pitch_mm
    lt = fastfit.lattice_of(truth.geom, p.mla.pitch_mm)
    got = cam.geom.lens_centres_mm
    nx, ny = lt.node(got[:, 0], got[:, 1])
    d = got - np.column_stack([nx, ny])
    a = np.column_stack([np.ones(len(nx)), nx, ny])
    coef = np.linalg.lstsq(a, d, rcond=None)[0]
    # the white's centroids against the table's prediction at the true lenslets
    lens = truth.geom.lens_centres_mm
    r = np.hypot(lens[:, 0], lens[:, 1])
    pred_px = white_centroids_px(p, float(p.d_in_mm), lens)
    cal = load_calibration(cache / _key(cam, white))
    m = np.asarray(cal.centres_px, dtype=np.float64)
    from scipy.spatial import cKDTree

    _, i = cKDTree(pred_px).query(m)
    rr = r[i]
    unit = lens[i] / np.maximum(rr, 1e-12)[:, None]
    radial = ((m - pred_px[i]) * unit).sum(axis=1)
    quarters = " ".join(
        f"{radial[(rr >= lo * rr.max()) & (rr < hi * rr.max())].mean():+.4f}"
        for lo, hi in ((0, 0.25), (0.25, 0.5), (0.5, 0.75), (0.75, 1.01)))
    touch = float(cal.diagnostics.get("disc_radius_px", np.nan)) / (0.5 * cal.pitch_px)
    err = np.hypot(d[:, 0], d[:, 1]) / pp
    return (f"| {system} | {focus:g} | {white} | {touch:.3f} | {coef[1, 0]:+.2e} "
            f"{coef[2, 1]:+.2e} | {coef[0, 0] / pp:+.4f} {coef[0, 1] / pp:+.4f} | "
            f"{np.sqrt((err ** 2).mean()):.4f} / {err.max():.4f} | {quarters} |")


def sensitivity(cache: Path) -> None:
    """The pixel answer of one bright far point under lattices a few 1e-5 apart."""
    system, focus, dist, frac = "system1", 1500.0, 3500.0, 0.8
    cam = fg.Camera(system, focus, None, cache, False)
    truth = fg.Camera(system, focus, None, cache, True)
    pm = cam.used.mla.pitch_mm
    obj = {"type": "point", "distance_mm": dist,
           "position_mm": cam.position(dist, cam.field_xy(frac))}
    image, _, _ = cam.render([obj], seed=3, rays=1_000_000)
    import line_regions as lr

    profile, geom_c, region_c, noise = lr.prepare(cam, image)
    _, geom_t, region_t, _ = lr.prepare(truth, image)
    lt = fastfit.lattice_of(geom_t, pm)
    scaled = dataclasses.replace(lt, basis=lt.basis * (1 + 1.5e-5),
                                 inverse=lt.inverse / (1 + 1.5e-5))
    shifted = dataclasses.replace(lt, origin=lt.origin + 6e-4)
    pixel: list = []
    polish = fastfit.pixel_polish

    def recorded(*args, **kwargs):
        out = polish(*args, **kwargs)
        pixel.append(out)
        return out

    fastfit.pixel_polish, above = recorded, fastfit.PIXEL_POLISH_ABOVE
    fastfit.PIXEL_POLISH_ABOVE = 0.0
    frame = fastfit.SourceFrame(profile)
    print("\n| lattice | pixel answer error % ± σ | final answer error % ± σ |\n|---|---|---|")
    try:
        for name, geom, region, lattice in (
                ("calibrated", geom_c, region_c, fastfit.lattice_of(geom_c, pm)),
                ("renderer's", geom_t, region_t, lt),
                ("renderer's × (1 + 1.5e-5)", dataclasses.replace(geom_t), region_t, scaled),
                ("renderer's + 0.6 µm", dataclasses.replace(geom_t), region_t, shifted)):
            fastfit.keep_lattice(geom, lattice)
            pixel.clear()
            m = fastfit.measure_lenslet(profile, geom, image, region, noise)
            px = next((f for f in pixel if f is not None and f.ok), None)
            if px is None:
                ptxt = "—"
            else:
                e = 100.0 * (np.exp(fastfit._log_distance(frame.params(px.source_mm))) / dist - 1)
                ptxt = f"{e:+.3f} ± {100 * px.sigma_distance_mm / dist:.3f}"
            print(f"| {name} | {ptxt} | {100 * (m.distance_mm / dist - 1):+.3f} ± "
                  f"{100 * m.sigma_distance_mm / dist:.3f} |", flush=True)
    finally:
        fastfit.pixel_polish, fastfit.PIXEL_POLISH_ABOVE = polish, above


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default=CASES, help="system:focus pairs (focus in mm or inf)")
    ap.add_argument("--whites", default="sim,analytic")
    ap.add_argument("--sensitivity", action="store_true")
    ap.add_argument("--cache", type=Path, default=ROOT / "benchmarks" / ".cache")
    ap.add_argument("--render-cache", type=Path, default=None)
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    if args.render_cache is not None:
        fg.RENDER_CACHE[0] = args.render_cache
    print("| system | focus mm | white | disc R / (pitch/2) | lattice scale error x y | "
          "offset px | lens error RMS / max px | white centroid − table, radial px, by "
          "field quarter |\n|---|---|---|---|---|---|---|---|")
    for case in args.cases.split(","):
        system, focus = case.split(":")
        for white in args.whites.split(","):
            print(lattice_row(system, float(focus), white, args.cache), flush=True)
    if args.sensitivity:
        sensitivity(args.cache)


if __name__ == "__main__":
    main()
