"""Region detection on the lenslet lattice: which lenslets a source lights, and what it is.

A point source lights a disc of lenslets with a small spot in each micro-image, so pixel-level
blobs are the wrong unit: we threshold each lenslet's energy against the noise of the dark
lenslets, connect lit lenslets that are neighbours (centres within 1.6 pitch) and describe
each cluster by the energy-weighted second moments of its lenslet centres:

* ``spot`` — near-isotropic footprint (elongation √(λ1/λ2) < ``LINE_ELONGATION``);
* ``line`` — elongated footprint;
* ``extended`` — too large a share of the array to be a point or line (textured regions):
  reported, never forced into a point or line model;
* two blurs that touch — an elongated footprint with a waist: the lit width across its long
  axis drops below ``WAIST_RATIO`` of its maxima on both sides, each side holding at least
  ``WAIST_SIDE_SHARE`` of the lenslets (a line's blur is a stadium, without a waist). The
  cluster is cut there into two regions (each cut again where it has a waist of its own), and
  the lenslets about the cut that both blurs may light (``Region.shared``: the band two discs
  of the narrower side's radius, meeting in the measured chord, share) belong to neither and
  are left out of both fits' data; each region is measured with the other as its neighbour
  (docs/distance.md, "Touching blurs cut at their waist (stop 67)"). With ``SPLIT_TOUCHING``
  off such a cluster is one region of kind ``multiple``, reported without a distance. Blurs
  that overlap without a waist stay one region here; where no point or line explains it, the
  distance run cuts it along two fitted points (:mod:`lfcam.measure.overlap`).

Far from focus a blur has a faint halo (the singlet's spherical aberration throws light outside
the rim rays) in which a few lenslets pass the threshold apart from the main disc. Such a
*fragment* — a cluster with at most ``FRAGMENT_SHARE`` of the lenslets and of the energy of a
bigger cluster, no lenslet brighter than that cluster's 90th percentile (a small source near
focus concentrates its light: it stays apart), lying within ``HALO_REACH`` times that
cluster's radius of its centroid — is merged into it: one region per source. Two clusters of
comparable size are never merged, so two sources whose blurs do not touch stay two regions.
Blurs that touch form one connected cluster: two regions when a waist shows it, otherwise
one. ``parts`` counts the clusters merged into a region.

A dim source far from focus spreads little light over hundreds of lenslets, each below the
threshold (the exposure is set by the scene's brightest source). :func:`faint_lit` finds such
blurs on the lenslet energies averaged over discs of ``FAINT_RADII_PITCH`` pitches (the
already lit lenslets left out), thresholded at ``NOISE_SIGMAS`` robust σ of the averaged map.
A faint cluster of at least ``FAINT_MIN_LENSLETS`` lenslets that touches no lit cluster of that
size becomes a region, taking in the smaller lit clusters it holds; one that touches a bigger
lit cluster (that region's halo, or a faint blur overlapping it), or lies within ``HALO_REACH``
times the radius of a bigger one's centroid (a detached arc of its halo), is left out, so the
regions of sources that pass the threshold do not change. Except: where such a cluster also
holds a smaller lit cluster of its own, its lenslets nearer to that one than to the bigger
blurs, and beyond their ``HALO_REACH``, are tried as a faint cluster on their own (a faint
source whose blur touches a brighter source's halo).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from lfcam.measure.cache import ObjectCache
from lfcam.measure.lenslets import LensletMap, LensletStats
from lfcam.robust import mad_sigma

LINE_ELONGATION = 1.6
EXTENDED_SHARE = 0.25
NOISE_SIGMAS = 8.0
MIN_LENSLETS = 3
FRAGMENT_SHARE = 0.2
WAIST_RATIO = 0.7  # (0.6 until stop 67: scene (b)'s touching lines read 0.63 there, their
#                    slices smoothed, and passed as one line on 5 of 8 draws)
WAIST_SIDE_SHARE = 0.25
WAIST_MIN_LENSLETS = 40
_NONE = np.zeros(0, dtype=np.int64)
SPLIT_TOUCHING = True  # a cluster with a waist is cut there into two regions (False: one region
#                        of kind ``multiple``, no distance)
SLIVER_SHARE = 0.25  # a side of a cut that keeps fewer lenslets than this × the band is a
#                      sliver of a blur the band took: ``multiple``, no distance (find_regions)
HALO_REACH = 1.6
FAINT_RADII_PITCH = (2.0, 4.0, 8.0, 12.0)  # scales of the faint-blur search (lenslet pitches)
FAINT_MIN_LENSLETS = 12  # a faint blur found by smoothing covers at least this many lenslets


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
    # lenslets lit by this blur and by a touching one (cut from one cluster at its waist): in
    # neither region, and left out of both fits' data
    shared: np.ndarray = dataclasses.field(default_factory=lambda: _NONE)

    @property
    def touching(self) -> bool:
        """Whether this region was cut from a cluster of touching blurs."""
        return self.shared.size > 0


def nearby_regions(regions: list[Region]) -> list[tuple[Region, ...]]:
    """For each region, the other regions whose blur may reach into its box: their boxes
    grown by their own width and height overlap it. A dim blur's edge lenslets can sit in
    its neighbour's region while its own region holds only its core (docs/distance.md,
    "Touching blurs fitted together")."""
    boxes = np.array([r.box_px for r in regions], dtype=np.float64).reshape(-1, 4)
    w = boxes[:, 2] - boxes[:, 0]
    h = boxes[:, 3] - boxes[:, 1]
    grown = np.column_stack([boxes[:, 0] - w, boxes[:, 1] - h, boxes[:, 2] + w, boxes[:, 3] + h])
    out = []
    for i, b in enumerate(boxes):
        hit = ((grown[:, 0] < b[2]) & (grown[:, 2] > b[0]) & (grown[:, 1] < b[3])
               & (grown[:, 3] > b[1]))
        hit[i] = False
        out.append(tuple(regions[j] for j in np.flatnonzero(hit)))
    return out


def _neighbour_components(points: np.ndarray, pitch_px: float) -> tuple[int, np.ndarray]:
    """Connected groups of lenslet centres ``points`` (K, 2), neighbours being closer than
    1.6 pitches: (count, label of each point)."""
    pairs = cKDTree(points).query_pairs(1.6 * pitch_px, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                       shape=(len(points), len(points)))
    return connected_components(graph, directed=False)


def lit_threshold(energy: np.ndarray) -> float:
    """Energy above which a lenslet counts as lit: median + ``NOISE_SIGMAS``·(robust σ)."""
    med = float(np.median(energy))
    mad = mad_sigma(energy)
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
        ``spot``, ``line`` or ``extended`` clusters of at least ``MIN_LENSLETS`` lenslets;
        ``multiple``: a cluster with a waist, with ``SPLIT_TOUCHING`` off, or a side of a cut
        that kept fewer lenslets than ``SLIVER_SHARE`` × the band about the cut (the rim of
        a blur whose body the band took: a line crossing another's blur read it as a
        `near-focus` blur of 8 lenslets).
    """
    energy = stats.energy
    thr = lit_threshold(energy)
    lit = np.flatnonzero(energy > thr)
    if lit.size == 0:
        return []
    centres = lmap.centres_px
    n, comp = _neighbour_components(centres[lit], pitch_px)
    groups, parts = _merge_fragments(lit, comp, n, energy, centres)
    groups, parts = _add_faint(groups, parts, faint_lit(energy, lit, centres, pitch_px),
                               centres, pitch_px)
    regions = []
    todo = [(g, p, _NONE, False) for g, p in zip(groups, parts, strict=True)]
    while todo:
        members, n_parts, shared, sliver = todo.pop(0)
        if members.size < MIN_LENSLETS:
            continue
        shape = footprint_shape(energy[members], centres[members], pitch_px)
        pos, evecs, elong = centres[members], shape[1], shape[2]
        waist = (_waist(pos, evecs[:, 1], pitch_px)
                 if elong >= LINE_ELONGATION and members.size <= EXTENDED_SHARE * len(centres)
                 else None)
        if waist is not None and SPLIT_TOUCHING:
            # two blurs that touch: each side of the waist a region of its own, fitted with
            # the other as its neighbour (its lenslets left out of the box), and the lenslets
            # both blurs may light left out of both (_overlap)
            t = (pos - pos.mean(axis=0)) @ evecs[:, 1]
            u = (pos - pos.mean(axis=0)) @ evecs[:, 0]
            half = _overlap(t, u, waist[0], waist[1], pitch_px)
            both = members[np.abs(t - waist[0]) < half]
            sides = (members[t <= waist[0] - half], members[t >= waist[0] + half])
            todo[:0] = [(side, k, np.union1d(both, shared), side.size < SLIVER_SHARE * both.size)
                        for side, k in zip(sides, (n_parts, 1), strict=True)]
            continue
        if members.size > EXTENDED_SHARE * len(centres):
            kind = "extended"
        elif waist is not None or sliver:
            kind = "multiple"
        elif elong >= LINE_ELONGATION:
            kind = "line"
        else:
            kind = "spot"
        regions.append(make_region(len(regions), kind, members, stats, lmap, pitch_px,
                                   n_parts, shared))
    return regions


def footprint_moments(e: np.ndarray, pos: np.ndarray, pitch_px: float
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A footprint's energy-weighted centre, the eigenvalues of its second moments (the
    variances across and along it, ascending; each lenslet a pitch-wide square) and their
    eigenvectors (columns, the long axis last), from its lenslets' energies ``e`` and
    centres ``pos`` (``pitch_px`` 0: points at the centres)."""
    mean = (pos * e[:, None]).sum(0) / e.sum()
    d = pos - mean
    cov = (d.T * e) @ d / e.sum() + np.eye(2) * (pitch_px**2 / 12.0)
    evals, evecs = np.linalg.eigh(cov)
    return mean, evals, evecs


def footprint_shape(e: np.ndarray, pos: np.ndarray, pitch_px: float
                    ) -> tuple[np.ndarray, np.ndarray, float]:
    """A footprint's energy-weighted centre (px), the eigenvectors of its second moments
    (columns, the long axis last) and its elongation √(λ₁/λ₂) (:func:`footprint_moments`)."""
    mean, evals, evecs = footprint_moments(e, pos, pitch_px)
    return mean, evecs, float(np.sqrt(evals[1] / evals[0]))


def make_region(region_id: int, kind: str, members: np.ndarray, stats: LensletStats,
                lmap: LensletMap, pitch_px: float, parts: int = 1,
                shared: np.ndarray = _NONE, centroid_px: np.ndarray | None = None) -> Region:
    """The :class:`Region` of the lenslets ``members`` (indices into ``lmap``'s list): its
    energy, light centroid (or ``centroid_px``, where the caller knows the light better than
    the members do), box, elongation and axis from ``stats``."""
    e = stats.energy[members]
    cen = stats.centroid_px[members]
    good = np.isfinite(cen).all(axis=1)
    centroid = ((cen[good] * e[good, None]).sum(0) / e[good].sum() if centroid_px is None
                else np.asarray(centroid_px, dtype=np.float64))
    pos = lmap.centres_px[members]
    _, evecs, elong = footprint_shape(e, pos, pitch_px)
    h, w = lmap.labels.shape
    r = lmap.radius_px
    x0 = int(max(0, np.floor(pos[:, 0].min() - r - 1)))
    y0 = int(max(0, np.floor(pos[:, 1].min() - r - 1)))
    x1 = int(min(w, np.ceil(pos[:, 0].max() + r + 2)))
    y1 = int(min(h, np.ceil(pos[:, 1].max() + r + 2)))
    return Region(
        region_id=region_id, kind=kind, lenslets=members, energy=float(e.sum()),
        centroid_px=(float(centroid[0]), float(centroid[1])), box_px=(x0, y0, x1, y1),
        elongation=elong, axis_dir=(float(evecs[0, 1]), float(evecs[1, 1])),
        parts=parts, shared=shared,
    )


def faint_lit(energy: np.ndarray, lit: np.ndarray, centres_px: np.ndarray,
              pitch_px: float) -> np.ndarray:
    """Lenslets inside faint blurs: the energy over its median, lit lenslets set to 0, averaged
    over discs of each of ``FAINT_RADII_PITCH`` pitches, above ``NOISE_SIGMAS`` robust σ of the
    averaged map (module docstring). A connected patch found at a coarser scale is added only
    where no finer scale found one (the coarse average dilates a blur by its radius).

    Parameters
    ----------
    energy : (N,) array
        Per-lenslet energies.
    lit : (K,) int array
        Lenslets above :func:`lit_threshold` (left out of the averages).
    centres_px : (N, 2) array
    pitch_px : float

    Returns
    -------
    (N,) bool array
        Lenslets of faint blurs that are not in ``lit``.
    """
    n = energy.size
    sig = np.asarray(energy, dtype=np.float64) - float(np.median(energy))
    sig[lit] = 0.0
    found = np.zeros(n, dtype=bool)
    for mean in _disc_means(sig, centres_px, pitch_px, FAINT_RADII_PITCH):
        # fine to coarse: a blur keeps the finest scale that sees it
        spread = mad_sigma(mean)
        if not spread > 0:
            continue
        above = np.flatnonzero(mean > float(np.median(mean)) + NOISE_SIGMAS * spread)
        above = above[~np.isin(above, lit)]
        if above.size == 0:
            continue
        _, comp = _neighbour_components(centres_px[above], pitch_px)
        seen = np.bincount(comp, weights=found[above].astype(np.float64))
        found[above[seen[comp] == 0]] = True
    return found


DISC_CELLS_PER_PITCH = 8  # fallback raster of the disc averages: centres rounded to pitch / 8,
DISC_CELLS_PER_RADIUS = 32  # ... or to radius / 32 where that is coarser (large discs),
DISC_MIN_CELLS_PER_PITCH = 4  # ... but never coarser than pitch / 4
_LATTICE_CACHE = ObjectCache(4)
LATTICE_MAX_RESIDUAL = 0.25  # lattice coordinates are used when every centre lies this close
# (pitches) to the lattice fitted to them, each on its own index


def lattice_coordinates(centres_px: np.ndarray, pitch_px: float
                        ) -> tuple[np.ndarray, np.ndarray] | None:
    """Integer lattice indices of micro-image centres and the lattice's basis, found from the
    centres alone.

    The lattice's kind, pitch and rotation are the white calibration's rough estimate
    (:func:`lfcam.calibrate.grid.rough_lattice`, from nearest-neighbour vectors) on the
    central lenslets; indices are rounded from that basis about the most central lenslet, and
    the lattice ``c = o + B·(i, j)`` is refitted to all centres by least squares, three
    times.

    Parameters
    ----------
    centres_px : (N, 2) array
    pitch_px : float
        Micro-image pitch.

    Returns
    -------
    (indices (N, 2) int array, basis (2, 2) array: columns the two lattice vectors, px), or
    None when the centres are not such a lattice: no regular grid, a pitch more than 15 % from
    ``pitch_px``, two centres on one index, or one lying more than
    ``LATTICE_MAX_RESIDUAL`` pitches from the fitted lattice (irregular centres, a gap of a
    missing row, a lattice too distorted for one affine fit).
    """
    c = np.asarray(centres_px, dtype=np.float64)
    n = len(c)
    if n < 8 or not pitch_px > 0:
        return None
    # the lattice's kind, pitch and rotation from the central lenslets (the calibration's own
    # estimate, lfcam.calibrate.grid.rough_lattice, on the 8000 nearest the centroid: a tree
    # of every centre cost 0.2 s at Illum size), in lfcam's one lattice convention
    from lfcam.calibrate.grid import rough_lattice
    from lfcam.errors import CalibrationError
    from lfcam.optics.mla import lattice_basis, rotation_matrix

    near = np.argsort(((c - c.mean(axis=0)) ** 2).sum(axis=1))[:8000]
    try:
        grid, pitch, rotation, _ = rough_lattice(c[near])
    except CalibrationError:  # no regular grid
        return None
    if abs(pitch - pitch_px) > 0.15 * pitch_px:
        return None
    basis = pitch * rotation_matrix(rotation) @ lattice_basis(grid)
    origin = c[near[0]]
    for _ in range(3):
        try:
            ij = np.rint(np.linalg.solve(basis, (c - origin).T).T)
        except np.linalg.LinAlgError:
            return None
        design = np.column_stack([np.ones(n), ij])
        coef = np.linalg.lstsq(design, c, rcond=None)[0]
        origin, basis = coef[0], coef[1:].T
    ij = np.rint(np.linalg.solve(basis, (c - origin).T).T).astype(np.int64)
    resid = np.hypot(*(c - origin - ij @ basis.T).T)
    if float(resid.max()) > LATTICE_MAX_RESIDUAL * pitch_px:
        return None
    span = ij.max(axis=0) - ij.min(axis=0) + 1
    key = (ij[:, 0] - ij[:, 0].min()) * span[1] + (ij[:, 1] - ij[:, 1].min())
    if np.unique(key).size != n:
        return None
    return ij, basis


def _disc_means(values: np.ndarray, centres_px: np.ndarray, pitch_px: float,
                radii_pitch: tuple[float, ...]) -> list[np.ndarray]:
    """Mean of ``values`` over the lenslets whose centres lie within each radius (pitches) of
    each lenslet's centre, one array per radius.

    On a lattice (:func:`lattice_coordinates`) the values and the lenslet counts are placed
    on the grid of lattice indices and filtered (OpenCV, Fourier domain for large kernels)
    with the index offsets whose lattice vector is within the radius: one cell a lenslet, and
    a pair is in or out by the fitted lattice's distance (exact up to the centres' deviation
    from it). Illum size: the four discs take 0.04 s, against 1.9 s on the fallback raster.

    Fallback (irregular centres): the lenslets are placed on a raster of ``pitch /
    DISC_CELLS_PER_PITCH`` cells, which changes a pair's distance by at most √2 cells (0.18
    pitch); discs of more than 4 pitches use cells of ``radius / DISC_CELLS_PER_RADIUS`` (at
    most ``pitch / DISC_MIN_CELLS_PER_PITCH``). A sparse all-pairs matrix of the 12-pitch disc
    held 1.2·10⁸ entries on an Illum-size sensor (17-22 s, ~2 GB).
    """
    import cv2

    values = np.asarray(values, dtype=np.float64)
    # per centres array (one geometry, every capture measured on it: a batch fits its lattice
    # once, not once a capture; 0.15 s at Illum size)
    pitch, lattice = _LATTICE_CACHE.get(
        centres_px, lambda: (pitch_px, lattice_coordinates(centres_px, pitch_px)))
    if pitch != pitch_px:
        lattice = lattice_coordinates(centres_px, pitch_px)
    if lattice is not None:
        ij, basis = lattice
        ij = ij - ij.min(axis=0)
        shape = (int(ij[:, 1].max()) + 1, int(ij[:, 0].max()) + 1)  # rows: j, columns: i
        flat = ij[:, 1] * shape[1] + ij[:, 0]
        size = shape[0] * shape[1]
        grid_v = np.bincount(flat, weights=values, minlength=size).reshape(shape)
        grid_n = np.bincount(flat, minlength=size).astype(np.float64).reshape(shape)
        # the smallest lattice vector length bounds the index reach of a disc
        short = float(np.linalg.svd(basis, compute_uv=False).min())
        out = []
        for radius in radii_pitch:
            r_px = radius * pitch_px
            k = int(np.ceil(r_px / short)) + 1
            dj, di = np.mgrid[-k:k + 1, -k:k + 1]
            off = np.column_stack([di.ravel(), dj.ravel()]) @ basis.T
            kernel = (np.hypot(off[:, 0], off[:, 1]) <= r_px + 1e-9).astype(np.float64)
            kernel = kernel.reshape(di.shape)
            sums = cv2.filter2D(grid_v, cv2.CV_64F, kernel, borderType=cv2.BORDER_CONSTANT)
            counts = cv2.filter2D(grid_n, cv2.CV_64F, kernel, borderType=cv2.BORDER_CONSTANT)
            out.append(sums.ravel()[flat] / np.maximum(np.rint(counts.ravel()[flat]), 1.0))
        return out
    c = np.asarray(centres_px, dtype=np.float64)
    c = c - c.min(axis=0)
    out = []
    grids: dict[int, tuple] = {}
    for radius in radii_pitch:
        per_pitch = min(DISC_CELLS_PER_PITCH, max(DISC_MIN_CELLS_PER_PITCH,
                                                  round(DISC_CELLS_PER_RADIUS / radius)))
        if per_pitch not in grids:
            cell = pitch_px / per_pitch
            ij = np.rint(c / cell).astype(np.int64)
            shape = (int(ij[:, 1].max()) + 1, int(ij[:, 0].max()) + 1)
            flat = ij[:, 1] * shape[1] + ij[:, 0]
            size = shape[0] * shape[1]
            grid_v = np.bincount(flat, weights=values, minlength=size).reshape(shape)
            grid_n = np.bincount(flat, minlength=size).astype(np.float64).reshape(shape)
            grids[per_pitch] = (flat, grid_v, grid_n)
        flat, grid_v, grid_n = grids[per_pitch]
        r = radius * per_pitch
        k = int(np.floor(r))
        yy, xx = np.mgrid[-k:k + 1, -k:k + 1]
        kernel = (np.hypot(xx, yy) <= r + 1e-9).astype(np.float64)
        sums = cv2.filter2D(grid_v, cv2.CV_64F, kernel, borderType=cv2.BORDER_CONSTANT)
        counts = cv2.filter2D(grid_n, cv2.CV_64F, kernel, borderType=cv2.BORDER_CONSTANT)
        out.append(sums.ravel()[flat] / np.maximum(np.rint(counts.ravel()[flat]), 1.0))
    return out


def _add_faint(groups: list[np.ndarray], parts: list[int], faint: np.ndarray,
               centres: np.ndarray, pitch_px: float) -> tuple[list[np.ndarray], list[int]]:
    """The lit clusters with the faint blurs added (module docstring)."""
    idx = np.flatnonzero(faint)
    if idx.size < FAINT_MIN_LENSLETS:
        return groups, parts
    n, comp = _neighbour_components(centres[idx], pitch_px)
    owner = np.full(centres.shape[0], -1)
    for g, members in enumerate(groups):
        owner[members] = g
    lit_tree = cKDTree(centres[owner >= 0]) if (owner >= 0).any() else None
    lit_ids = np.flatnonzero(owner >= 0)
    # the blurs that passed the threshold: centroid and reach of their halo
    big = [g for g, m in enumerate(groups) if m.size >= FAINT_MIN_LENSLETS]
    big_cen = np.array([centres[groups[g]].mean(axis=0) for g in big]).reshape(-1, 2)
    big_reach = np.array([HALO_REACH * np.hypot(*(centres[groups[g]] - c).T).max()
                          for g, c in zip(big, big_cen, strict=True)])
    big_size = np.array([groups[g].size for g in big])
    taken: set[int] = set()
    new_groups, new_parts = [], []

    def touching(members: np.ndarray) -> set[int]:
        touched: set[int] = set()
        if lit_tree is not None:
            for near in lit_tree.query_ball_point(centres[members], 1.6 * pitch_px):
                touched.update(int(owner[lit_ids[j]]) for j in near)
        return touched

    patches = [(idx[comp == c], True) for c in range(n)]
    while patches:
        members, whole = patches.pop()
        if members.size < FAINT_MIN_LENSLETS:
            continue
        touched = touching(members)
        bright = [big.index(g) for g in touched if groups[g].size >= FAINT_MIN_LENSLETS]
        peaks = [g for g in touched if groups[g].size < FAINT_MIN_LENSLETS]
        if bright:
            # the halo of a blur that passed the threshold, or blurs that overlap. A faint blur
            # with lit lenslets of its own that merely touches such a halo is kept apart: the
            # lenslets nearer to its lit cluster than to the bright blurs, and beyond their
            # halo reach (system 2, F 1 m: a 3500 mm source 22 pitches from a 2700 mm one
            # shared one faint patch with its halo and had no region)
            if not (whole and peaks):
                continue
            pc = centres[members]
            for g in peaks:
                gc = centres[groups[g]].mean(axis=0)
                own = np.hypot(*(pc - gc).T)
                keep = np.ones(members.size, dtype=bool)
                for k in bright:
                    to_bright = np.hypot(*(pc - big_cen[k]).T)
                    keep &= (to_bright > big_reach[k]) & (own < to_bright)
                part = members[keep]
                if part.size >= FAINT_MIN_LENSLETS:
                    _, lab = _neighbour_components(centres[part], pitch_px)
                    # the piece round the lit cluster only
                    near = lab[np.argmin(np.hypot(*(centres[part] - gc).T))]
                    patches.append((part[lab == near], False))
            continue
        centre = centres[members].mean(axis=0)
        if big and np.any((np.hypot(*(big_cen - centre).T) < big_reach)
                          & (big_size > members.size)):
            continue  # a detached arc of a bigger blur's halo (as _merge_fragments' reach)
        taken.update(touched)
        new_groups.append(np.sort(np.concatenate([members, *(groups[g] for g in touched)])))
        new_parts.append(1 + sum(parts[g] for g in touched))
    keep = [g for g in range(len(groups)) if g not in taken]
    return ([groups[g] for g in keep] + new_groups, [parts[g] for g in keep] + new_parts)


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


def _overlap(t: np.ndarray, u: np.ndarray, waist: float, ratio: float, pitch_px: float
             ) -> float:
    """Half the width, along the axis (``t``; ``u`` across it), of the band about a waist at
    ``waist`` where two touching discs both lie: discs of the narrower side's radius (half its
    extent across the axis) whose chord at the waist is ``ratio`` × their diameter reach
    ``R (1 − √(1 − ratio²))`` past it; half a pitch more for the lenslets' own size."""
    side = t < waist
    radii = [0.5 * float(np.ptp(u[m])) for m in (side, ~side) if m.sum() > 1]
    r = min(radii) if radii else 0.0
    return r * (1.0 - math.sqrt(max(1.0 - ratio * ratio, 0.0))) + 0.5 * pitch_px


def _waist(pos: np.ndarray, axis: np.ndarray, pitch_px: float) -> tuple[float, float] | None:
    """Where a footprint (lenslet centres ``pos``, long axis ``axis``) narrows between two
    wide parts, or None: the count of lenslets per slice across the axis (a pitch or 1/24 of
    the length, whichever is wider; smoothed 1-2-1) dips below ``WAIST_RATIO`` of the widest
    slice on each side, with ``WAIST_SIDE_SHARE`` of the lenslets or more on each side of the
    dip. Returns where about the narrowest such slice a slice as wide holds the fewest
    lenslets (along ``axis``, from the centres' mean), and that count over the most such a
    slice holds on the narrower side."""
    if len(pos) < WAIST_MIN_LENSLETS:
        return None
    t = (pos - pos.mean(axis=0)) @ np.asarray(axis, dtype=np.float64)
    step = max(pitch_px, float(np.ptp(t)) / 24.0)
    edges = np.arange(t.min(), t.max() + step, step)
    width, _ = np.histogram(t, edges)
    if width.size < 5:
        return None
    width = np.convolve(np.pad(width.astype(np.float64), 1, mode="edge"), [0.25, 0.5, 0.25],
                        mode="valid")
    total = float(width.sum())
    best, where = math.inf, None
    for i in range(1, width.size - 1):
        side = min(width[:i].max(), width[i + 1 :].max())
        share_l = width[:i].sum() / total
        share_r = width[i + 1 :].sum() / total
        if (width[i] < WAIST_RATIO * side and share_l >= WAIST_SIDE_SHARE
                and share_r >= WAIST_SIDE_SHARE and width[i] / side < best):
            best, where = width[i] / side, i
    if where is None:
        return None
    # the cut: where a slice as wide, slid over the lenslets within a slice of it, holds the
    # fewest of them (the slices' edges fall anywhere on the lattice's rows)
    # (and the chord there over the narrower side's widest, as slices that wide read them)
    ts = np.sort(t)
    held = (np.searchsorted(ts, ts + 0.5 * step, side="left")
            - np.searchsorted(ts, ts - 0.5 * step, side="right"))
    mid = 0.5 * (edges[where] + edges[where + 1])
    near = np.abs(ts - mid) <= step
    if not near.any():
        return mid, best
    at = float(ts[near][held[near] == held[near].min()].mean())
    side = min(held[ts < at].max(initial=0), held[ts > at].max(initial=0))
    return at, float(held[near].min() / side) if side > 0 else best
