"""The capture's own noise model: read noise and photon gain, measured from the capture.

The poor-fit gates compare a fit's relative misfit with the misfit the region's own noise
would leave (docs/distance.md, "Noise-relative gates"). A pixel of signal ``I`` (image units,
pedestal removed) has variance ``σ_r² + g·I``:

* ``σ_r`` (:func:`dark_sigma`): the σ of the pixels that see no source. Taken from the upper
  quartile over the median: an unsigned raw with a black level of 0 clips the noise below zero,
  so that most dark pixels read exactly 0 and a median absolute deviation reads 0 too.
* ``clipped`` (:func:`clips_at_zero`): the capture's noise is cut at zero (an unsigned raw with
  a black level of 0, a processed image): a dark pixel then reads ``E[max(0, n)] = σ_r/√(2π)``
  on average, not 0, and a dim one more than its signal (:func:`clipped_mean`). The pixel fit
  models that floor (docs/distance.md, "The clipped dark floor, and the pixel fit's own rays
  behind focus").
* ``g`` (:func:`photon_gain`, image units per photo-electron): from the lenslet sums inside
  the capture's blurs. A defocused blur lights its interior lenslets smoothly (the pupil's
  image on the MLA), so a lenslet differs from the mean of its ``n`` lit neighbours by its
  noise, ``Var ≈ (1 + 1/n)·g·E`` for a sum ``E``. The median over the interior lenslets of the
  whole capture gives ``g`` without any source model, so a wrong model cannot raise its own
  noise allowance. Read noise and other per-lenslet scatter are counted in ``g``: an upper
  bound (measured 3.4× the true gain on the 12-source scene of docs/distance.md). A capture
  with too few interior lenslets (one small sharp blur) cannot measure ``g``; the camera
  profile's full well gives it then, where the caller passes it (:func:`capture_noise`'s
  ``sensor_gain``), else no photon noise is counted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import ndtr

from lfcam.measure.base import frame_sample
from lfcam.measure.cache import ObjectCache
from lfcam.measure.lenslets import LensletMap, LensletStats, lenslet_stats
from lfcam.robust import mad_sigma

NEIGHBOUR_PITCH = 1.6  # lenslets closer than this many pitches are neighbours (as regions.py)
INTERIOR_SHARE = 0.5  # an interior lenslet's neighbours all carry ≥ this × its energy ...
INTERIOR_SIGMAS = 5.0  # ... and it lies ≥ this many read-noise σ of its sum above the dark
NEIGHBOUR_SLOTS = 13  # nearest centres looked up per lenslet (itself + up to 12 neighbours)
MIN_INTERIOR = 20  # fewer interior lenslets: no gain estimate (photon noise not counted)
CHI2_MEDIAN = 0.4549364231195724  # median of χ² with one degree of freedom
CLIPPED_SHARE = 0.1  # a capture whose frame sample reads exactly 0 this often, and never
# below, clips its noise at zero (a dark pixel of an unclipped one reads 0 with probability
# ~q/(2.5 σ_r) at quantum q; of a clipped one ≥ 0.5)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


@dataclass(frozen=True)
class NoiseModel:
    """Pixel noise of one capture: variance ``read_sigma² + gain·I`` (image units)."""

    read_sigma: float
    gain: float  # image units per photo-electron (0: neither measured nor given)
    clipped: bool = False  # the noise is cut at zero (:func:`clips_at_zero`)

    @property
    def floor_sigma(self) -> float:
        """The σ of the noise a clipped capture cuts at zero (:func:`clipped_mean`); 0 when
        the capture does not clip."""
        return self.read_sigma if self.clipped else 0.0

    def moments_misfit_of(self, sums: tuple[float, float], norm: float) -> float:
        """:func:`moments_misfit` from the region's :func:`moment_noise_sums`."""
        if not norm > 0:
            return float("nan")
        return math.sqrt(max(self.read_sigma**2 * sums[0] + self.gain * sums[1], 0.0)) / norm

    def misfit(self, patch: np.ndarray, blur_px: float, norm: float) -> float:
        """Relative misfit the noise alone leaves on ``patch`` once blurred by a Gaussian of σ
        ``blur_px``, relative to the blurred patch's norm ``norm``.

        A white-noise field of per-pixel variance v, blurred by a unit-sum Gaussian of σ_b,
        keeps v/(4π σ_b²) per pixel, so the expected squared residual is
        ``Σ (σ_r² + g·max(I, 0)) / (4π σ_b²)``.
        """
        if not (norm > 0 and blur_px > 0 and patch.size):
            return float("nan")
        var = patch.size * self.read_sigma**2 + self.gain * float(np.clip(patch, 0.0, None).sum())
        return math.sqrt(var / (4.0 * math.pi * blur_px**2)) / norm


def moments_misfit(noise: NoiseModel, image: np.ndarray, lmap: LensletMap, pitch_px: float,
                   box: tuple[int, int, int, int], pedestal: float, norm: float) -> float:
    """Relative misfit the noise alone leaves on the four lenslet moments of a region
    (:func:`lfcam.measure.fastfit.data_moments`: per lenslet Σv, Σv·dx, Σv·dy, Σv·(dx² + dy²),
    offsets from the lenslet's centre in pitches).

    Each moment is a weighted pixel sum, so its variance is ``Σ var·f²`` with ``var = σ_r² +
    g·max(v, 0)``; the misfit is the square root of their total over ``norm`` (the data
    moments' norm). The lenslet fit reads the same number from the sums that
    :func:`~lfcam.measure.fastfit.data_moments` gathers in its own pass
    (:meth:`NoiseModel.moments_misfit_of`); this standalone pass over the box is the reference
    it is tested against.

    Parameters
    ----------
    noise : NoiseModel
    image : (H, W) array
    lmap : LensletMap
    pitch_px : float
    box : tuple of int
        (x0, y0, x1, y1) of the moments.
    pedestal : float
        Dark level removed from the data before the moments.
    norm : float

    Returns
    -------
    float
    """
    x0, y0, x1, y1 = box
    lab = lmap.labels[y0:y1, x0:x1]
    keep = lab >= 0
    if not (norm > 0 and keep.any()):
        return float("nan")
    yy, xx = np.nonzero(keep)
    cen = lmap.centres_px[lab[keep]]
    dx = (xx + x0 - cen[:, 0]) / pitch_px
    dy = (yy + y0 - cen[:, 1]) / pitch_px
    v = np.asarray(image[y0:y1, x0:x1], dtype=np.float64)[keep] - pedestal
    return noise.moments_misfit_of(moment_noise_sums(dx, dy, v), norm)


def moment_noise_sums(dx: np.ndarray, dy: np.ndarray, v: np.ndarray) -> tuple[float, float]:
    """``(Σ f², Σ max(v, 0)·f²)`` over a region's pixels, ``f² = 1 + dx² + dy² + r⁴`` the
    squared weights of the four lenslet moments (offsets ``dx, dy`` from the lenslet centre in
    pitches, ``v`` the pixel values): what :meth:`NoiseModel.moments_misfit_of` needs, so the
    moments and their noise are read in one pass over the pixels."""
    r2 = dx * dx + dy * dy
    f2 = 1.0 + r2 + r2 * r2
    return float(f2.sum()), float((np.clip(v, 0.0, None) * f2).sum())  # (no BLAS threads)


def dark_sigma(image: np.ndarray) -> float:
    """σ of the pixels of ``image`` that see no source, in its units, safe against noise
    clipped at zero: (upper quartile − median) / 0.6745 of :func:`frame_sample`. Most pixels
    see no source, and clipping below zero moves neither the median (0) nor the upper
    quartile."""
    med, upper = np.percentile(np.asarray(frame_sample(image), dtype=np.float64), [50.0, 75.0])
    return float(upper - med) / 0.6745


def clips_at_zero(image: np.ndarray) -> bool:
    """Whether ``image`` clips its noise at zero: its :func:`frame_sample` has no value below
    0 and reads exactly 0 at least ``CLIPPED_SHARE`` of the time (an unsigned raw with a black
    level of 0; a raw with a black level above 0 keeps the values below it negative,
    :mod:`lfcam.io`)."""
    s = np.asarray(frame_sample(image))
    return bool(s.size and s.min() >= 0 and np.count_nonzero(s == 0) >= CLIPPED_SHARE * s.size)


def clipped_mean(mu: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """The mean reading ``E[max(0, μ + n)]`` of a pixel of signal ``μ`` under Gaussian noise
    ``n`` of σ ``sigma`` cut at zero, and its slope in ``μ``:

    ``E = μ·Φ(μ/σ) + σ·φ(μ/σ)``, ``dE/dμ = Φ(μ/σ)``

    (0.399 σ at μ = 0; within 0.01 σ of μ from μ = 2 σ). Read noise only: the photon noise
    of the dim pixels where the cut matters is below it on the captures measured, and the
    capture's gain estimate is an upper bound (:func:`photon_gain`). Quantisation is not
    modelled (rounding to steps of q ≤ σ moves the mean by < 0.02 σ; of q ≤ σ/2, < 0.005 σ).
    """
    mu = np.asarray(mu, dtype=np.float64)
    if not sigma > 0:
        return mu, np.ones_like(mu)
    t = mu / sigma
    cdf = ndtr(t)
    return mu * cdf + sigma * _INV_SQRT_2PI * np.exp(-0.5 * t * t), cdf


def photon_gain(stats: LensletStats, lmap: LensletMap, pitch_px: float) -> float:
    """Image units per photo-electron (an upper bound), from the lenslet sums inside blurs.

    Parameters
    ----------
    stats : LensletStats
    lmap : LensletMap
    pitch_px : float
        Micro-image pitch.

    Returns
    -------
    float
        The median over interior lenslets (module docstring) of ``d² / ((1 + 1/n)·Ē)``,
        divided by the median of χ²₁, where ``d`` is the lenslet's sum minus its neighbours'
        mean and ``Ē`` that mean over the median sum. The read noise of the lenslet's pixels
        and any other per-lenslet scatter (a renderer's ray sampling) are counted as photon
        noise, so this bounds the gain from above: the gates stay on the safe side. 0 when
        fewer than ``MIN_INTERIOR`` lenslets are interior (sharp spots only).
    """
    e = np.asarray(stats.energy, dtype=np.float64)
    if e.size < MIN_INTERIOR:
        return 0.0
    sig = e - float(np.median(e))
    spread = mad_sigma(e)
    cand = np.flatnonzero(sig > INTERIOR_SIGMAS * spread)
    if cand.size < MIN_INTERIOR:
        return 0.0
    tree = cKDTree(lmap.centres_px)
    # neighbours within NEIGHBOUR_PITCH, nearest first: a lattice has at most 8 (rect: 4 at 1
    # pitch, 4 at 1.41); NEIGHBOUR_SLOTS − 1 leaves room for irregular centres
    slots = NEIGHBOUR_SLOTS
    while True:
        dist, idx = tree.query(lmap.centres_px[cand], k=min(slots, len(sig)),
                               distance_upper_bound=NEIGHBOUR_PITCH * pitch_px)
        if slots >= len(sig) or not np.isfinite(dist[:, -1]).any():
            break
        slots *= 2  # some lenslet has more neighbours than slots (irregular centres)
    near = np.isfinite(dist) & (idx != cand[:, None])
    count = near.sum(axis=1)
    sn = np.where(near, sig[np.minimum(idx, len(sig) - 1)], np.nan)
    sk = sig[cand]
    with np.errstate(invalid="ignore"):
        interior = ((count >= 4) & ~(np.nanmin(sn, axis=1, initial=np.inf, where=near)
                                     < INTERIOR_SHARE * sk)
                    & ~(np.nanmax(sn, axis=1, initial=-np.inf, where=near) * INTERIOR_SHARE > sk))
    if int(interior.sum()) < MIN_INTERIOR:
        return 0.0
    n = count[interior]
    mean = np.nansum(sn[interior], axis=1) / n
    vals = (sk[interior] - mean) ** 2 / ((1.0 + 1.0 / n) * mean)
    return float(np.median(vals)) / CHI2_MEDIAN


_CACHE = ObjectCache(1)


def capture_noise(image: np.ndarray, lmap: LensletMap, pitch_px: float,
                  stats: LensletStats | None = None,
                  known: NoiseModel | None = None, sensor_gain: float = 0.0) -> NoiseModel:
    """The noise model of one capture (read σ and photon gain), computed once per image.

    Parameters
    ----------
    image : (H, W) array
    lmap : LensletMap
    pitch_px : float
    stats : LensletStats, optional
        The capture's lenslet statistics on ``lmap``, when the caller has them (saves a pass
        over the image: 1.6 s at Illum size).
    known : NoiseModel, optional
        The model already computed for this capture (by the parent of a region worker): it
        is remembered for ``image`` and returned.
    sensor_gain : float
        Image units per photo-electron from the camera profile (its ``sensor.full_well_e``),
        or 0: the gain where the capture cannot measure its own (:func:`photon_gain` 0: too
        few interior lenslets, one small sharp blur). The measured gain is an upper bound and
        is kept where there is one. As the model is computed once per image, only the first
        call's counts (:func:`lfcam.distance.run_distance` makes it).

    Returns
    -------
    NoiseModel
    """
    def model() -> NoiseModel:
        if known is not None:
            return known
        st = lenslet_stats(image, lmap) if stats is None else stats
        gain = photon_gain(st, lmap, pitch_px)
        return NoiseModel(dark_sigma(image), gain if gain > 0 else max(sensor_gain, 0.0),
                          clips_at_zero(image))

    # per image, then per lenslet map (one capture measured on two geometries: two models)
    return _CACHE.get(image, ObjectCache).get(lmap, model)
