"""Where the own-light centroids of a touching white go wrong at the field's rim: the disc
centres, the seam split, or the brightness model.

Run: ``python benchmarks/touching_centroids.py [--system system1] [--focus inf]
[--cache DIR]``

The white of ``focus_grid.py``'s camera (``lfcam.sim``, seed 5, noise-free) is calibrated
(``calibrate_white``); then, by quarter of the field (fully visible lenses only), radially,
in px:

* the disc centres that a disc fit (block-Jacobi Gauss–Newton, the disc-and-edge-ramp model
  of :mod:`lfcam.calibrate.microimage` written out in numpy) reaches with a brightness plane
  per lens (as the calibration's) or a quadratic one, minus the renderer's micro-image centres
  (chief-ray projections, ``focus_grid``'s truth geometry);
* own-light centroids (:func:`lfcam.calibrate.microimage.own_light_centroids`' seam split,
  written out in numpy for any brightness model), with the fitted disc centres or with the
  renderer's, minus the centroids :func:`lfcam.measure.geometry.white_centroids_px` predicts
  at the true lenslets; and the calibration's own centroids against the same prediction.

Lenses within a pitch and a half of the border are left out of the means (their neighbours
are cut).
docs/calibration.md, "Own-light centroids of touching whites at the field's rim (stop 64)".
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import focus_grid as fg  # noqa: E402

from lfcam.calibrate import calibrate_white  # noqa: E402
from lfcam.calibrate import microimage as mi  # noqa: E402
from lfcam.measure.geometry import white_centroids_px  # noqa: E402
from lfcam.sim.capture import simulate  # noqa: E402
from lfcam.sim.scene import scene_from_dict  # noqa: E402

QUARTERS = ((0.0, 0.25), (0.25, 0.5), (0.5, 0.75), (0.75, 1.01))


class Discs:
    """The white's disc model with a brightness polynomial of degree 1 or 2 per lens."""

    def __init__(self, img: np.ndarray, model: mi.DiscModel, pitch_px: float,
                 fixed: np.ndarray) -> None:
        self.img, self.model, self.fixed = img, model, fixed
        self.half = model.patch_half_px()
        self.core = mi.core_radius_px(model, pitch_px)

    def _offsets(self, c: np.ndarray):
        p = mi._Patches(self.img.shape, c, self.half)
        frac = c - p.base
        dx = p.off[None, None, :] - frac[:, 0, None, None]
        dy = p.off[None, :, None] - frac[:, 1, None, None]
        dx, dy = np.broadcast_arrays(dx.astype(np.float64), dy.astype(np.float64))
        return p, dx, dy

    def brightness(self, c: np.ndarray, degree: int) -> np.ndarray:
        """(N, 6) coefficients (1, x, y, x², xy, y²) fitted over each lens's core; a cut lens
        takes its nearest fully visible neighbour's (as ``fit_discs``)."""
        p, dx, dy = self._offsets(c)
        inc = (dx * dx + dy * dy < self.core ** 2) & p.inside
        v = np.where(p.inside, self.img.ravel()[p.flat], 0.0)
        cols = [np.ones_like(dx), dx, dy] + ([dx * dx, dx * dy, dy * dy] if degree == 2 else [])
        a = np.stack(cols, -1) * inc[..., None]
        ata = np.einsum("nijk,nijl->nkl", a, a) + 1e-9 * np.eye(len(cols))
        co = np.linalg.solve(ata, np.einsum("nijk,nij->nk", a, v)[..., None])[..., 0]
        co = np.column_stack([co, np.zeros((len(co), 6 - len(cols)))])
        free = np.flatnonzero(~self.fixed)
        return co[free[cKDTree(c[free]).query(c)[1]]]

    def models(self, c: np.ndarray, co: np.ndarray):
        """Each lens's model on its patch and its derivatives in the disc centre."""
        p, dx, dy = self._offsets(c)
        r_px, w_px = self.model.radius_px, self.model.edge_px
        d = np.sqrt(dx * dx + dy * dy)
        t = (r_px + w_px - d) * (0.5 / w_px)
        cov = np.clip(t, 0.0, 1.0) * p.inside
        band = (t > 0) & (t < 1) & p.inside
        k = [co[:, i, None, None] for i in range(6)]
        b = k[0] + k[1] * dx + k[2] * dy + k[3] * dx * dx + k[4] * dx * dy + k[5] * dy * dy
        bx = k[1] + 2 * k[3] * dx + k[4] * dy
        by = k[2] + k[4] * dx + 2 * k[5] * dy
        ramp = band * (0.5 / w_px) / np.maximum(d, 1e-9)
        return p, b * cov, -bx * cov + b * ramp * dx, -by * cov + b * ramp * dy

    def fit(self, c: np.ndarray, degree: int, iterations: int = 40,
            damping: float = 0.6) -> np.ndarray:
        """Disc centres by block-Jacobi Gauss–Newton (``fit_discs``' scheme)."""
        c = c.copy()
        co = self.brightness(c, degree)
        for it in range(iterations):
            if it % 4 == 3:
                co = self.brightness(c, degree)
            p, m, jx, jy = self.models(c, co)
            total = np.zeros(self.img.size)
            np.add.at(total, p.flat[p.inside], m[p.inside])
            r = np.where(p.inside, self.img.ravel()[p.flat] - total[p.flat], 0.0)
            axx, ayy = (jx * jx).sum((1, 2)), (jy * jy).sum((1, 2))
            axy = (jx * jy).sum((1, 2))
            gx, gy = (jx * r).sum((1, 2)), (jy * r).sum((1, 2))
            det = axx * ayy - axy * axy + 1e-12
            step = np.column_stack([(ayy * gx - axy * gy) / det, (axx * gy - axy * gx) / det])
            step = damping * np.clip(step, -0.5, 0.5)
            step[self.fixed] = 0.0
            c += step
            if np.percentile(np.abs(step[~self.fixed]).max(axis=1), 99) < 2e-4:
                break
        return c

    def own_light(self, c: np.ndarray, co: np.ndarray) -> np.ndarray:
        """Own-light centroids: the data split by the models' shares (module docstring)."""
        p, m, _, _ = self.models(c, co)
        m = np.maximum(m, 0.0)
        total = np.zeros(self.img.size)
        np.add.at(total, p.flat[p.inside], m[p.inside])
        flat = self.img.ravel()
        ratio = np.where(total > 0, flat / np.where(total > 0, total, 1.0), 0.0)
        q = np.where(p.inside, ratio[p.flat], 0.0) * m
        s0 = q.sum((1, 2))
        return np.column_stack([(q * p.x).sum((1, 2)) / s0, (q * p.y).sum((1, 2)) / s0])


def by_quarter(values: np.ndarray, radius: np.ndarray, keep: np.ndarray) -> str:
    """Mean of ``values`` over ``keep`` in each quarter of the field's radius."""
    top = radius[keep].max()
    return " | ".join(f"{values[keep & (radius >= lo * top) & (radius < hi * top)].mean():+.4f}"
                      for lo, hi in QUARTERS)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--system", default="system1")
    ap.add_argument("--focus", default="inf")
    ap.add_argument("--cache", type=Path, default=ROOT / "benchmarks" / ".cache")
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    truth = fg.Camera(args.system, float(args.focus), fg_size(args.system), args.cache, True)
    white, _, _ = simulate(truth.base, scene_from_dict(
        {"seed": 5, "objects": [{"type": "white"}], "camera": truth.cam}))
    white = white.astype(np.float32)
    img = white.astype(np.float64)
    h, w = img.shape
    cal = calibrate_white(white)
    model = mi.DiscModel(cal.diagnostics["disc_radius_px"], cal.diagnostics["disc_edge_px"], 0.0)
    # every lens whose disc reaches the sensor; the measured ones start at their centroids
    lc = cal.lens_centres((h, w), margin_px=model.support_px)
    start = np.column_stack([lc.x.ravel(), lc.y.ravel()])
    measured = np.asarray(cal.centres_px, dtype=np.float64)
    start[cKDTree(start).query(measured)[1]] = measured
    s = model.support_px
    fixed = ~((start[:, 0] >= s) & (start[:, 0] <= w - 1 - s) & (start[:, 1] >= s)
              & (start[:, 1] <= h - 1 - s))
    discs = Discs(img, model, cal.pitch_px, fixed)
    # the renderer's micro-image centres, and the table's centroids at the true lenslets
    p = truth.used
    chief = np.asarray(truth.geom.lmap.centres_px)
    chief = chief[cKDTree(chief).query(start)[1]]
    pred_px = white_centroids_px(p, float(p.d_in_mm), truth.geom.lens_centres_mm)
    table = pred_px[cKDTree(pred_px).query(start)[1]]
    mid = np.array([0.5 * (w - 1), 0.5 * (h - 1)])
    radius = np.hypot(*(chief - mid).T)
    unit = (chief - mid) / np.maximum(radius, 1e-9)[:, None]
    # lenses a pitch and a half inside the border: their neighbours are all measured
    inner = 1.5 * cal.pitch_px
    keep = ~fixed & (start[:, 0] > inner) & (start[:, 0] < w - 1 - inner) & (
        start[:, 1] > inner) & (start[:, 1] < h - 1 - inner)

    def radial(xy: np.ndarray, ref: np.ndarray) -> np.ndarray:
        return ((xy - ref) * unit).sum(axis=1)

    print(f"# {args.system}, focus {args.focus}: disc R {model.radius_px:.3f} px (half pitch "
          f"{0.5 * cal.pitch_px:.3f}), edge {model.edge_px:.3f} px; {int(keep.sum())} lenses")
    print("| quantity (radial, px) | " + " | ".join(f"{lo:.0%}–{min(hi, 1):.0%}"
                                                   for lo, hi in QUARTERS) + " |")
    print("|---|---|---|---|---|")
    own_cal = np.full_like(start, np.nan)
    own_cal[cKDTree(start).query(measured)[1]] = measured
    print("| calibration's centroid − table | "
          f"{by_quarter(radial(own_cal, table), radius, keep)} |")
    for degree in (1, 2):
        fitted = discs.fit(start, degree)
        co = discs.brightness(fitted, degree)
        name = "plane" if degree == 1 else "quadratic"
        print(f"| disc centre ({name}) − renderer's | "
              f"{by_quarter(radial(fitted, chief), radius, keep)} |")
        print(f"| own light ({name}, fitted discs) − table | "
              f"{by_quarter(radial(discs.own_light(fitted, co), table), radius, keep)} |")
        co_t = discs.brightness(chief, degree)
        print(f"| own light ({name}, renderer's discs) − table | "
              f"{by_quarter(radial(discs.own_light(chief, co_t), table), radius, keep)} |",
              flush=True)


def fg_size(system: str) -> int | None:
    """``focus_grid``'s sensor for ``system`` (system 2: 1536²)."""
    return 1536 if system == "system2" else None


if __name__ == "__main__":
    main()
