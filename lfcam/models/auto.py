"""Uncertainty propagation and ``--model auto``: per region, only as much model as needed.

* :func:`propagate` pushes the measurement uncertainty of (y1, y2) through any point model by
  central differences (vectorised; one extra pair of model calls per input).
* :class:`ErrorTable` holds each closed-form model's own error (against the exact trace) over
  distance and offset for one camera; it is computed once per (camera, d_in), in milliseconds.
* :func:`choose` picks for each region the cheapest model whose predicted total error,
  ``hypot(model error, propagated measurement error)``, meets the tolerance; ``exact`` (no model
  error) is the fallback and the default when no tolerance is given.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from lfcam.camera import CameraProfile
from lfcam.models import POINT_MODELS
from lfcam.models.base import Inversion, Status
from lfcam.optics.trace import forward

# cheapest first (benchmarks/models.py: thin ≫ onaxis > offaxis > exact in regions/s)
COST_ORDER = ("thin", "onaxis", "offaxis", "exact")
# |offset| grid of the error table, in entrance-pupil diameters: the seed's small offsets and
# on to the field of a wide capture (a source 600 mm away at 60 % of system 2's field sits
# ~70 mm off axis, 1.75 diameters; the closed forms miss it by 10-35 %)
TABLE_OFFSET_FRACTIONS = np.array([0.0, 0.05, 0.1, 0.2, 0.3, 0.45, 0.6, 0.8, 1.0, 1.25, 1.5,
                                   1.75, 2.0, 2.5, 3.0])
TABLE_DISTANCES = 192  # (the cell's worst node is read: a finer grid claims less; 2 ms a table)


def propagate(
    model: str, profile: CameraProfile, d_in_mm: float | None, y1_mm, y2_mm, sigma1_mm, sigma2_mm
) -> tuple[Inversion, np.ndarray]:
    """Invert with ``model`` and propagate independent height errors to a distance error.

    Returns
    -------
    inversion : Inversion
    sigma_distance_mm : ndarray
        1-σ distance uncertainty (NaN where the status is not ok or a derivative is undefined).
    """
    fn = POINT_MODELS[model]
    y1 = np.asarray(y1_mm, dtype=np.float64)
    y2 = np.asarray(y2_mm, dtype=np.float64)
    s1 = np.broadcast_to(np.asarray(sigma1_mm, dtype=np.float64), y1.shape)
    s2 = np.broadcast_to(np.asarray(sigma2_mm, dtype=np.float64), y2.shape)
    inv = fn(profile, d_in_mm, y1, y2)
    h1 = np.maximum(0.25 * s1, 1e-7)
    h2 = np.maximum(0.25 * s2, 1e-7)
    d1 = (fn(profile, d_in_mm, y1 + h1, y2).distance_mm
          - fn(profile, d_in_mm, y1 - h1, y2).distance_mm) / (2 * h1)
    d2 = (fn(profile, d_in_mm, y1, y2 + h2).distance_mm
          - fn(profile, d_in_mm, y1, y2 - h2).distance_mm) / (2 * h2)
    sigma = np.hypot(d1 * s1, d2 * s2)
    sigma = np.where(inv.status == Status.OK, sigma, np.nan)
    return inv, sigma


@dataclass(frozen=True)
class ErrorTable:
    """Relative distance error of each model against the exact trace, over (distance, |offset|)."""

    log_distance: np.ndarray  # (Nd,) log of distance_mm
    offsets_mm: np.ndarray  # (No,) |offset| grid
    relative_error: dict  # model → (No, Nd) array, inf where the model gives no answer

    def predict(self, model: str, distance_mm, offset_mm) -> np.ndarray:
        """Model error (relative) at the given places: the largest of the four table nodes
        around each (log distance, |offset|). ``inf`` where a corner has no answer, and
        outside the table's offsets or nearer than its first distance: a model's error is
        never claimed where it was not measured (the old clamp to the table's edge let the
        on-axis form claim ≤ 1 % at 70 mm off axis, where it missed by 17 %). Beyond the
        last distance (100 m) the last column holds."""
        if model == "exact":
            return np.zeros(np.shape(distance_mm))
        table = self.relative_error[model]
        dist = np.asarray(distance_mm, dtype=np.float64)
        offs = np.abs(np.asarray(offset_mm, dtype=np.float64))
        unknown = ~(np.isfinite(dist) & (dist > 0) & np.isfinite(offs))
        with np.errstate(divide="ignore", invalid="ignore"):
            unknown |= (offs > self.offsets_mm[-1] * (1 + 1e-12)) | (
                np.log(np.where(dist > 0, dist, 1.0)) < self.log_distance[0] - 1e-12)
        dist = np.where(unknown, np.exp(self.log_distance[0]), dist)
        offs = np.where(unknown, 0.0, offs)
        ld = np.clip(np.log(dist), self.log_distance[0], self.log_distance[-1])
        off = np.clip(offs, self.offsets_mm[0], self.offsets_mm[-1])
        fi = np.interp(ld, self.log_distance, np.arange(self.log_distance.size))
        fj = np.interp(off, self.offsets_mm, np.arange(self.offsets_mm.size))
        i0 = np.clip(np.floor(fi).astype(int), 0, self.log_distance.size - 2)
        j0 = np.clip(np.floor(fj).astype(int), 0, self.offsets_mm.size - 2)
        # the worst corner of the cell (inf if any has no answer): between the nodes the
        # bilinear blend understated the error by up to 7 % of a tolerance across the field
        corners = np.stack([table[j0, i0], table[j0, i0 + 1], table[j0 + 1, i0],
                            table[j0 + 1, i0 + 1]])
        known = np.isfinite(corners).all(axis=0) & ~unknown
        return np.where(known, corners.max(0), np.inf)


@lru_cache(maxsize=16)
def error_table(profile: CameraProfile, d_in_mm: float | None = None) -> ErrorTable:
    """Build the :class:`ErrorTable` of ``profile`` (cached per camera and d_in)."""
    lens = profile.main_lens
    dist = np.geomspace(1.2 * lens.focal_length_mm, 1e5, TABLE_DISTANCES)
    offs = TABLE_OFFSET_FRACTIONS * lens.pupil_diameter_mm
    dd, oo = np.meshgrid(dist, offs)
    fw = forward(profile, d_in_mm, dd, oo)
    errors = {}
    for name in COST_ORDER[:-1]:
        inv = POINT_MODELS[name](profile, d_in_mm, fw.y1_mm, fw.y2_mm)
        rel = np.abs(inv.distance_mm - dd) / dd
        errors[name] = np.where(inv.status == Status.OK, rel, np.inf)
    return ErrorTable(np.log(dist), offs, errors)


def choose(
    profile: CameraProfile,
    d_in_mm: float | None,
    y1_mm,
    y2_mm,
    sigma1_mm,
    sigma2_mm,
    tolerance_pct: float | None = None,
) -> tuple[np.ndarray, Inversion, np.ndarray]:
    """Per region, the cheapest model whose predicted error meets ``tolerance_pct``.

    Parameters
    ----------
    tolerance_pct : float or None
        Allowed relative distance error in percent; ``None`` = the best available (``exact``).

    Returns
    -------
    models : ndarray of str
    inversion : Inversion
        Each region's answer from its chosen model.
    sigma_distance_mm : ndarray
        Propagated 1-σ measurement uncertainty plus the chosen model's predicted error (added
        in quadrature).
    """
    y1 = np.atleast_1d(np.asarray(y1_mm, dtype=np.float64))
    y2 = np.atleast_1d(np.asarray(y2_mm, dtype=np.float64))
    s1 = np.broadcast_to(np.asarray(sigma1_mm, dtype=np.float64), y1.shape)
    s2 = np.broadcast_to(np.asarray(sigma2_mm, dtype=np.float64), y2.shape)
    ref, ref_sigma = propagate("exact", profile, d_in_mm, y1, y2, s1, s2)
    chosen = np.full(y1.shape, "exact", dtype=object)
    if tolerance_pct is not None:
        table = error_table(profile, d_in_mm)
        tol = tolerance_pct / 100.0
        meas = ref_sigma / ref.distance_mm
        undecided = ref.status == Status.OK
        for name in COST_ORDER[:-1]:
            predicted = np.hypot(table.predict(name, ref.distance_mm, ref.offset_mm), meas)
            take = undecided & (predicted <= tol)
            chosen[take] = name
            undecided &= ~take
    distance = ref.distance_mm.copy()
    offset = ref.offset_mm.copy()
    status = ref.status.copy()
    sigma = ref_sigma.copy()
    for name in COST_ORDER[:-1]:
        idx = np.flatnonzero(chosen == name)
        if idx.size == 0:
            continue
        inv, sig = propagate(name, profile, d_in_mm, y1[idx], y2[idx], s1[idx], s2[idx])
        model_err = error_table(profile, d_in_mm).predict(name, inv.distance_mm, inv.offset_mm)
        distance[idx], offset[idx], status[idx] = inv.distance_mm, inv.offset_mm, inv.status
        sigma[idx] = np.hypot(sig, model_err * inv.distance_mm)
    return chosen.astype(str), Inversion(distance, offset, status), sigma


# ----------------------------------------------------------------------------- method choice
# Measurement methods, cheapest first, with the largest ERROR (eq. 21, %) measured for each
# source kind over every benchmark with the calibrated path and model ``exact``: the seed grid
# (``benchmarks/tradeoff.py``, docs/results/tradeoff.csv) and both sides of focus over the full
# field (``benchmarks/focus_grid.py``, docs/results/focus_grid.csv and focus_grid_lenslet.csv,
# point captures and the 12-source scenes). What ``method="auto"`` reads to pick the cheapest
# method that meets a tolerance; never below a measured worst case (tests/test_speed.py checks
# it against those CSVs). Lines: the seed grid's 16 system-1 lines and focus_grid's lines
# behind and in front of a 1 m focus (3 mm long on the MLA for both systems; for system 2 also
# 0.75 and 0.5 mm, 3 and 2 pitches, and 3 mm lines 60 % of the half-field off axis). Spot,
# ``lenslet``: 0.35 % over the 108 single sources of both systems' full field and both sides of
# focus; 7.94 % is the faintest source of a 12-source scene (~2 % of the brightest source's
# light, stated σ 3.8 %; photon-limited, docs/distance.md). Line, ``lenslet``: 0.810 %, a 3 mm
# line of system 1 at 80 % of the half-field behind a 1 m focus on the independent renderer
# (docs/distance.md, "A line's points, each with its own turn of the pupil sample"; 0.818 %
# before, on lfcam.sim's, and 1.32 % before "A line's settled test"). ``lightfield``:
# spot 1.27 % (system 2, 3500 mm behind a 1 m focus in a 12-source scene, the pixel fit of
# ``--method auto``: photon-limited, spread 0.6 % over noise draws, docs/distance.md "The
# pixel fit's minimum"; the 108 single sources now reach 0.68 %), line 0.717 % (a 3 mm line
# of system 1 at 80 % of the half-field behind a 1 m focus, stop 35's rerun with the pixel fit
# of stop 34 starting from stop 35's lenslet line; 0.626 % at stop 33, 1.15 % before the
# lenslet line's settled test, which the pixel fit starts from; through the centre and
# system 2 at 60 %: 0.25 %, a line 3 pitches long behind focus).
METHOD_COST_ORDER = ("diameter", "lenslet", "lightfield")
METHOD_MAX_ERROR_PCT = {
    "spot": {"diameter": 46.98, "lenslet": 7.939, "lightfield": 1.267},
    "line": {"diameter": 38.18, "lenslet": 0.810, "lightfield": 0.717},
}


# A spot's lenslet answer stands for ``--method auto --tolerance T`` when this many of its
# stated σ fit within T (else the region is measured again with the pixel fit). 3 until stop
# 62: over 192 measured spots (one noise draw of each capture) no answer so accepted missed
# its tolerance for T from 0.1 to 2 % (docs/distance.md, "Auto: the lenslet fit first"), but
# over 20 draws of the six 12-source captures 2-5 kept answers in ~1 000 missed T at every T
# from 0.3 to 5 %, all short (the lenslet σ of dim far sources understates their scatter
# 1.2-2 ×; the worst −5.49 % at σ 0.78 %). With 5, chosen on those draws, none missed on 10
# other draws (720 regions, T 0.3-10 %; 3 σ: 13 misses), at 11-17 % fewer lenslet answers
# (docs/distance.md, "The lenslet fit on dim far sources (stop 62)"). Lines are not covered
# (their bias behind focus exceeds their σ) and keep the table: the lenslet method is theirs
# at any tolerance. The same rule spares a point the polish and a line the refit with more
# rays where the σ, with the step still to go in it, meets the tolerance
# (lfcam.measure.fastfit's ``accept``).
LENSLET_ACCEPT_SIGMAS = 5.0


def lenslet_answer_meets(distance_mm: float, sigma_mm: float, tolerance_pct: float) -> bool:
    """Whether a spot measured by the lenslet fit, at ``distance_mm`` ± ``sigma_mm``, is
    answer enough for ``tolerance_pct`` (:data:`LENSLET_ACCEPT_SIGMAS`)."""
    return bool(distance_mm > 0 and np.isfinite(sigma_mm)
                and LENSLET_ACCEPT_SIGMAS * sigma_mm <= 0.01 * tolerance_pct * distance_mm)


def choose_method(tolerance_pct: float | None, kind: str = "spot") -> str:
    """The cheapest measurement method whose measured worst error for ``kind`` (``spot`` or
    ``line``) meets ``tolerance_pct``.

    Without a tolerance (or when none meets it): the method with the smallest measured worst
    error.
    """
    table = METHOD_MAX_ERROR_PCT["line" if kind == "line" else "spot"]
    best = min(METHOD_COST_ORDER, key=table.__getitem__)
    if tolerance_pct is None:
        return best
    for name in METHOD_COST_ORDER:
        if table[name] <= tolerance_pct:
            return name
    return best
