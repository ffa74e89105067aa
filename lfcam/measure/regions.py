"""Region detection on the lenslet lattice: which lenslets a source lights, and what it is.

A point source lights a disc of lenslets with a small spot in each micro-image, so pixel-level
blobs are the wrong unit: we threshold each lenslet's energy against the noise of the dark
lenslets, connect lit lenslets that are neighbours (centres within 1.6 pitch) and describe
each cluster by the energy-weighted second moments of its lenslet centres:

* ``spot`` — near-isotropic footprint (elongation √(λ1/λ2) < ``LINE_ELONGATION``);
* ``line`` — elongated footprint;
* ``extended`` — too large a share of the array to be a point or line (textured regions):
  reported, never forced into a point or line model;
* ``multiple`` — an elongated footprint with a waist: the lit width across its long axis
  drops below ``WAIST_RATIO`` of its maxima on both sides, each side holding at least
  ``WAIST_SIDE_SHARE`` of the lenslets. Two blurs that touch look like this (a line's blur is
  a stadium, without a waist); reported without a distance rather than measured as one
  source.

Far from focus a blur has a faint halo (the singlet's spherical aberration throws light outside
the rim rays) in which a few lenslets pass the threshold apart from the main disc. Such a
*fragment* — a cluster with at most ``FRAGMENT_SHARE`` of the lenslets and of the energy of a
bigger cluster, no lenslet brighter than that cluster's 90th percentile (a small source near
focus concentrates its light: it stays apart), lying within ``HALO_REACH`` times that
cluster's radius of its centroid — is merged into it: one region per source. Two clusters of
comparable size are never merged, so two sources whose blurs do not touch stay two regions.
Blurs that touch form one connected cluster: ``multiple`` when a waist shows it, otherwise
one region. ``parts`` counts the clusters merged into a region.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.stats import median_abs_deviation

from lfcam.measure.lenslets import LensletMap, LensletStats

LINE_ELONGATION = 1.6
EXTENDED_SHARE = 0.25
NOISE_SIGMAS = 8.0
MIN_LENSLETS = 3
FRAGMENT_SHARE = 0.2
WAIST_RATIO = 0.6
WAIST_SIDE_SHARE = 0.25
WAIST_MIN_LENSLETS = 40
HALO_REACH = 1.6


@dataclass(frozen=True)
class Region:
    """One connected cluster of lit lenslets."""

    region_id: int
    kind: str  # "spot" | "line" | "extended"
    lenslets: np.ndarray  # indices into the lenslet list
    energy: float
    centroid_px: tuple[float, float]  # energy-weighted centroid of the light on the sensor
    box_px: tuple[int, int, int, int]  # x0, y0, x1, y1 (exclusive) covering its micro-images
    elongation: float
    axis_dir: tuple[float, float]  # unit vector of the footprint's long axis (sensor x, y)
    parts: int = 1  # connected clusters merged into this region (halo fragments included)


def lit_threshold(energy: np.ndarray) -> float:
    """Energy above which a lenslet counts as lit: median + ``NOISE_SIGMAS``·(robust σ)."""
    med = float(np.median(energy))
    mad = float(median_abs_deviation(energy, scale="normal"))
    floor = 1e-6 * float(energy.max()) if energy.size else 0.0
    return max(med + NOISE_SIGMAS * mad, med + floor)


def find_regions(stats: LensletStats, lmap: LensletMap, pitch_px: float) -> list[Region]:
    """Cluster lit lenslets into regions (see module docstring).

    Parameters
    ----------
    stats : LensletStats
        Per-lenslet energies and centroids of the capture.
    lmap : LensletMap
    pitch_px : float
        Micro-image pitch (lenslets closer than 1.6 pitches are neighbours).

    Returns
    -------
    list of Region
        ``spot``, ``line`` or ``extended`` clusters of at least ``MIN_LENSLETS`` lenslets.
    """
    energy = stats.energy
    thr = lit_threshold(energy)
    lit = np.flatnonzero(energy > thr)
    if lit.size == 0:
        return []
    centres = lmap.centres_px
    pairs = cKDTree(centres[lit]).query_pairs(1.6 * pitch_px, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                       shape=(lit.size, lit.size))
    n, comp = connected_components(graph, directed=False)
    groups, parts = _merge_fragments(lit, comp, n, energy, centres)
    h, w = lmap.labels.shape
    r = lmap.radius_px
    regions = []
    for members, n_parts in zip(groups, parts, strict=True):
        if members.size < MIN_LENSLETS:
            continue
        e = energy[members]
        cen = stats.centroid_px[members]
        good = np.isfinite(cen).all(axis=1)
        wsum = e[good].sum()
        centroid = (cen[good] * e[good, None]).sum(0) / wsum
        pos = centres[members]
        mean = (pos * e[:, None]).sum(0) / e.sum()
        d = pos - mean
        cov = (d.T * e) @ d / e.sum() + np.eye(2) * (pitch_px**2 / 12.0)
        evals, evecs = np.linalg.eigh(cov)
        elong = float(np.sqrt(evals[1] / evals[0]))
        if members.size > EXTENDED_SHARE * len(centres):
            kind = "extended"
        elif elong >= LINE_ELONGATION and _has_waist(pos, evecs[:, 1], pitch_px):
            kind = "multiple"
        elif elong >= LINE_ELONGATION:
            kind = "line"
        else:
            kind = "spot"
        x0 = int(max(0, np.floor(pos[:, 0].min() - r - 1)))
        y0 = int(max(0, np.floor(pos[:, 1].min() - r - 1)))
        x1 = int(min(w, np.ceil(pos[:, 0].max() + r + 2)))
        y1 = int(min(h, np.ceil(pos[:, 1].max() + r + 2)))
        regions.append(Region(
            region_id=len(regions), kind=kind, lenslets=members, energy=float(e.sum()),
            centroid_px=(float(centroid[0]), float(centroid[1])), box_px=(x0, y0, x1, y1),
            elongation=elong, axis_dir=(float(evecs[0, 1]), float(evecs[1, 1])),
            parts=n_parts,
        ))
    return regions


def _merge_fragments(lit: np.ndarray, comp: np.ndarray, n: int, energy: np.ndarray,
                     centres: np.ndarray) -> tuple[list[np.ndarray], list[int]]:
    """Clusters of lit lenslets with halo fragments merged into their blur (module docstring).

    Returns the member lenslets of each merged cluster and how many connected
    clusters each holds.
    """
    by_comp = np.argsort(comp, kind="stable")
    members = np.split(lit[by_comp], np.cumsum(np.bincount(comp, minlength=n))[:-1])
    size = np.array([m.size for m in members])
    e = np.array([energy[m].sum() for m in members])
    cen = np.array([(centres[m] * energy[m, None]).sum(0) / max(energy[m].sum(), 1e-300)
                    for m in members]).reshape(-1, 2)
    rad = np.array([np.hypot(*(centres[m] - c).T).max() for m, c in zip(members, cen,
                                                                        strict=True)])
    peak = np.array([energy[m].max() for m in members])
    typical = np.array([np.percentile(energy[m], 90.0) for m in members])
    order = np.argsort(-size, kind="stable")
    owner = np.arange(n)
    for a in order[::-1]:  # smallest first: each fragment joins the biggest blur that takes it
        # a fragment is as faint a lenslet as the blur's; a focused source is brighter
        big = np.flatnonzero((size >= size[a] / FRAGMENT_SHARE) & (e >= e[a] / FRAGMENT_SHARE)
                            & (typical >= peak[a]))
        if big.size == 0:
            continue
        d = np.hypot(*(cen[big] - cen[a]).T)
        reach = HALO_REACH * rad[big]
        take = big[d <= reach]
        if take.size:
            owner[a] = take[np.argmax(size[take])]
    groups, parts = [], []
    for c in range(n):  # in the order of the clusters (raster order of their first lenslet)
        if owner[c] != c:
            continue
        joined = np.flatnonzero(owner == c)
        groups.append(np.sort(np.concatenate([members[k] for k in joined])))
        parts.append(int(joined.size))
    return groups, parts


def _has_waist(pos: np.ndarray, axis: np.ndarray, pitch_px: float) -> bool:
    """Whether a footprint (lenslet centres ``pos``, long axis ``axis``) narrows between two
    wide parts: the count of lenslets per slice across the axis (a pitch or 1/24 of the
    length, whichever is wider; smoothed 1-2-1) dips below ``WAIST_RATIO`` of the widest slice
    on each side, with ``WAIST_SIDE_SHARE`` of the lenslets or more on each side of the dip."""
    if len(pos) < WAIST_MIN_LENSLETS:
        return False
    t = (pos - pos.mean(axis=0)) @ np.asarray(axis, dtype=np.float64)
    step = max(pitch_px, float(np.ptp(t)) / 24.0)
    edges = np.arange(t.min(), t.max() + step, step)
    width, _ = np.histogram(t, edges)
    if width.size < 5:
        return False
    width = np.convolve(np.pad(width.astype(np.float64), 1, mode="edge"), [0.25, 0.5, 0.25],
                        mode="valid")
    total = float(width.sum())
    for i in range(1, width.size - 1):
        left, right = width[:i].max(), width[i + 1 :].max()
        share_l = width[:i].sum() / total
        share_r = width[i + 1 :].sum() / total
        if (width[i] < WAIST_RATIO * min(left, right) and share_l >= WAIST_SIDE_SHARE
                and share_r >= WAIST_SIDE_SHARE):
            return True
    return False
