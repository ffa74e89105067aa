"""d_in (main-lens centre → MLA) from a capture of a dot target at a known distance.

The seed (eqs. 10–12) calibrates d_in from calibrated points on a reference plane at a known
distance: the image-space ray from lenslet centre ``y_j`` to pixel ``v`` has slope
``(y_j − v)/f_x`` (eq. 10), the object-space ray comes from the known point, and d_in is where
the two meet the main lens (eq. 12). We use the same data — a few point sources ("dots") on a
plane ``distance_mm`` before the front vertex, their light under each lenslet — in two ways:

* **exact** (:func:`fit_dot_exact`): the per-micro-image light of each dot is compared with
  the exact forward model (point source → exact thick main lens → ideal lenslets → pixels),
  with the distance held at its known value and (d_in, x, y) free. The comparison statistic
  is the energy-weighted centroid of the light in every micro-image cell of the calibration's
  pixel map, computed identically for the data and for the model (rays binned into the pixel
  they land in, so pixel integration and micro-image overlap are modelled, not ignored).
  Lenslet centres follow from the white-image centroids at each trial d_in
  (:func:`lfcam.measure.geometry.lenslet_centres_mm`), since that mapping depends on d_in.
* **paraxial** (:func:`fit_dot_paraxial`, the seed's algebra): the dot images to its paraxial
  image point (z_img, h_img); the ray from that point through lenslet centre ``y_j`` lands at
  ``v_j = y_j + f_x (y_j − h_img)/(d_in − z_img)``, so the slope of ``v − y`` against ``y``
  over the fully lit lenslets is ``f_x/(d_in − z_img)`` and
  ``d_in = z_img + f_x (y_j − h_img)/(v_j − y_j)``. Lenslet centres come from the white
  centroids through the paraxial chief ray (exit-pupil centre), which also needs d_in: the two
  are iterated to a fixed point.

The dots' lateral offsets are not needed: each dot's (x, y) is fitted (exact) or eliminated
(paraxial, the intercept h_img). The main lens's lateral magnification does not depend on
d_in, so known offsets would add almost no information, and requiring them would require the
target to be centred on the optical axis. The dots are detected automatically.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from lfcam.camera import CameraProfile
from lfcam.errors import CalibrationError
from lfcam.measure.geometry import (
    lenslet_centres_mm,
    nominal_indices,
    regularise_to_lattice,
)
from lfcam.measure.lenslets import LensletMap, build_lenslet_map, lenslet_stats
from lfcam.measure.pointfit import LocalLattice, pupil_pattern
from lfcam.optics.trace import trace_source_fast
from lfcam.robust import mad_sigma

METHOD = "reference-dots-exact"  # Calibration.d_in_method of this route
PUPIL_SAMPLES = 260  # per side of the stratified front-rim grid (~53 k rays per dot render)
MIN_CELLS = 6  # micro-images a dot must light to be measured
DOT_THRESHOLD = 0.01  # micro-images dimmer than this × the brightest one are ignored
MAP_RADIUS_PITCH = 0.54  # pixel → micro-image assignment radius (as lfcam.distance)
MAX_RMS_PX = 0.2  # a dot the model leaves a worse misfit is not a clean point at that distance
SEARCH_FRACTION = 0.2  # the exact solve looks for d_in within ±20 % of its start
SCAN_FRACTION = 0.01  # ... after a scan of d_in over ±1 % of the start
SCAN_NODES = 21
CENTRE_NODE_STEP_MM = 1.0  # spacing of the d_in nodes the lenslet-centre map is computed at


@dataclass(frozen=True)
class DotData:
    """The measured light of one dot: energy and centroid of each micro-image cell it lights."""

    region_id: int
    cells: np.ndarray  # (M,) indices into the calibration's centres
    energy: np.ndarray  # (M,)
    centroid_px: np.ndarray  # (M, 2) x, y
    light_centroid_px: tuple[float, float]  # energy centroid of the whole dot


@dataclass(frozen=True)
class DotFit:
    """d_in from one dot."""

    d_in_mm: float
    position_mm: tuple[float, float]  # fitted (exact) or paraxial-implied lateral position
    rms_px: float  # energy-weighted RMS centroid residual
    cells: int


@dataclass(frozen=True)
class DinResult:
    """d_in from a dot-target capture, both routes."""

    d_in_mm: float  # exact route (mean over dots)
    sigma_mm: float  # standard error of that mean (spread of the dots / √n)
    d_in_paraxial_mm: float  # paraxial route (seed eqs. 10–12), mean over dots
    sigma_paraxial_mm: float
    distance_mm: float
    z_image_paraxial_mm: float
    exact: tuple[DotFit, ...] = field(default=())
    paraxial: tuple[DotFit, ...] = field(default=())

    @property
    def n_dots(self) -> int:
        """Dots used."""
        return len(self.exact)


def paraxial_image_z_mm(profile: CameraProfile, distance_mm: float) -> float:
    """z of the paraxial image of a plane ``distance_mm`` before the front vertex."""
    lens = profile.main_lens
    return lens.back_principal_z_mm + float(lens.image_distance_mm(distance_mm))


def check_distance(profile: CameraProfile, distance_mm: float) -> float:
    """Validate the reference distance: finite, and well outside the front focal length."""
    d = float(distance_mm)
    f = profile.main_lens.focal_length_mm
    if not (math.isfinite(d) and d > 0):
        raise CalibrationError(f"reference distance must be a positive length, got {distance_mm}")
    if d <= 1.2 * f:
        raise CalibrationError(
            f"reference distance {d:g} mm is too close: the main lens (f = {f:.3f} mm) needs "
            f"the target beyond {1.2 * f:.0f} mm to form a real image near the MLA"
        )
    if d > 1e6:
        raise CalibrationError(f"reference distance {d:g} mm is out of range (≤ 1 km)")
    return d


class CentreMap:
    """Lenslet centres on the MLA plane (mm) from white-image centroids, at any d_in.

    The white centroid of a lenslet sits where the light through it lands on average, which
    depends on d_in (chief-ray magnification 1 + f_x/(d_in − z_exit pupil) plus aberration);
    :func:`lenslet_centres_mm` inverts that for one d_in. That inversion costs a ray-traced
    table, so it is computed at nodes ``CENTRE_NODE_STEP_MM`` apart and interpolated
    quadratically in d_in. The interpolation is within 0.04 µm (5e-4 px) of the direct
    inversion, the level of the table's own sampling noise (test). The centres are then
    regularised to the MLA lattice as the distance pipeline does.
    """

    def __init__(self, profile: CameraProfile, centres_px: np.ndarray,
                 rotation_rad: float | None = None, indices: np.ndarray | None = None) -> None:
        self.profile = profile
        self.centres_px = np.asarray(centres_px, dtype=np.float64)
        self.rotation_rad = (profile.mla.rotation_rad if rotation_rad is None
                             else float(rotation_rad))
        self.indices = None if indices is None else np.asarray(indices, dtype=np.int64)
        self._nodes: dict[int, np.ndarray] = {}

    def _node(self, k: int) -> np.ndarray:
        if k not in self._nodes:
            d = k * CENTRE_NODE_STEP_MM
            self._nodes[k] = lenslet_centres_mm(self.profile, d, self.centres_px)
        return self._nodes[k]

    def raw(self, d_in_mm: float) -> np.ndarray:
        """Unregularised centres at ``d_in_mm`` (quadratic interpolation between nodes)."""
        t = d_in_mm / CENTRE_NODE_STEP_MM
        k = int(round(t))
        u = t - k
        a, b, c = self._node(k - 1), self._node(k), self._node(k + 1)
        return b + 0.5 * u * (c - a) + 0.5 * u * u * (c - 2.0 * b + a)

    def __call__(self, d_in_mm: float) -> np.ndarray:
        """Regularised lenslet centres (mm) at ``d_in_mm``."""
        mla = self.profile.mla
        raw = self.raw(d_in_mm)
        if self.indices is None:
            self.indices = nominal_indices(raw, mla.pitch_mm, mla.grid, self.rotation_rad)
        c, _ = regularise_to_lattice(raw, self.indices, mla.pitch_mm)
        return c


def find_dots(capture: np.ndarray, centres_px: np.ndarray, pitch_px: float,
              black_level: float = 0.0) -> tuple[LensletMap, list[DotData]]:
    """Detect the dots of a dot-target capture on the micro-image lattice.

    Returns the pixel → micro-image map and one :class:`DotData` per isolated, compact dot
    that lies wholly inside the sensor.

    Raises
    ------
    CalibrationError
        If no dot is found.
    """
    img = np.asarray(capture, dtype=np.float64) - float(black_level)
    if img.ndim != 2:
        raise CalibrationError(f"reference capture must be a 2-D grey raster, got {img.shape}")
    if not np.isfinite(img).all():
        raise CalibrationError("reference capture contains non-finite values")
    lmap = build_lenslet_map(centres_px, img.shape, MAP_RADIUS_PITCH * pitch_px)
    stats = lenslet_stats(img, lmap)
    # A sensor that clips at its black level turns read noise into a positive pedestal
    # (~0.4 σ a pixel). Over a whole micro-image it drags the centroid of a dim cell towards
    # the cell's centre: behind focus, where spots are a few pixels wide, that alone gave a
    # 0.17 px misfit at the true d_in. Subtract the per-pixel level of the dimmest half.
    per_px = stats.energy / np.maximum(stats.pixels, 1)
    pedestal = float(np.median(np.sort(per_px)[: max(1, len(per_px) // 2)]))
    if pedestal != 0.0:
        img = img - pedestal
        stats = lenslet_stats(img, lmap)
    energy = stats.energy
    # A dot target lights a large share of the lenslets (F/2 aberration halos), so the
    # background and its noise come from the dimmest half, and the threshold also has a floor
    # relative to the brightest lenslet.
    dim = np.sort(energy)[: max(1, len(energy) // 2)]
    bg = float(np.median(dim))
    noise = mad_sigma(dim)
    top = float(energy.max())
    thr = bg + max(8.0 * noise, DOT_THRESHOLD * (top - bg))
    lit = np.flatnonzero(energy > thr)
    h, w = img.shape
    dots = []
    n_regions = 0
    if lit.size:
        pairs = cKDTree(lmap.centres_px[lit]).query_pairs(1.6 * pitch_px, output_type="ndarray")
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                           shape=(lit.size, lit.size))
        n_regions, comp = connected_components(graph, directed=False)
        r = lmap.radius_px
        for c in range(n_regions):
            cells = lit[comp == c]
            pos = lmap.centres_px[cells]
            if (pos[:, 0].min() - r < 0 or pos[:, 1].min() - r < 0
                    or pos[:, 0].max() + r > w - 1 or pos[:, 1].max() + r > h - 1):
                continue  # cut by the sensor edge
            e = energy[cells]
            good = np.isfinite(stats.centroid_px[cells]).all(axis=1)
            if good.sum() < MIN_CELLS:
                continue
            cells, e = cells[good], e[good]
            cen = stats.centroid_px[cells]
            light = (cen * e[:, None]).sum(axis=0) / e.sum()
            dots.append(DotData(c, cells, e, cen, (float(light[0]), float(light[1]))))
    if not dots:
        raise CalibrationError(
            f"reference capture: no dot found (need isolated point images lighting at least "
            f"{MIN_CELLS} micro-images each, wholly inside the sensor; {n_regions} lit "
            "region(s) seen)"
        )
    return lmap, dots


class DotModel:
    """Exact forward model of one dot, summarised like the data (per-cell energy, centroid)."""

    def __init__(self, profile: CameraProfile, lmap: LensletMap, dot: DotData,
                 centre_map: CentreMap, distance_mm: float,
                 pupil_samples: int = PUPIL_SAMPLES) -> None:
        self.profile = profile
        self.lmap = lmap
        self.dot = dot
        self.centre_map = centre_map
        self.z_source = profile.main_lens.front_vertex_z_mm - distance_mm
        self.pattern = pupil_pattern(pupil_samples)
        n = lmap.count
        self.slot = np.full(n + 1, -1, dtype=np.int64)  # label (−1 → last) → cell slot
        self.slot[dot.cells] = np.arange(len(dot.cells))
        # lenslets that light can cross on its way to the dot's cells: cells + neighbours
        tree = cKDTree(lmap.centres_px)
        reach = 2.5 * lmap.radius_px / MAP_RADIUS_PITCH
        near = tree.query_ball_point(lmap.centres_px[dot.cells], reach)
        self.near = np.unique(np.concatenate([np.asarray(n_, dtype=np.int64) for n_ in near]))
        self.weight = dot.energy / dot.energy.sum()

    def render(self, d_in_mm: float, x_mm: float, y_mm: float):
        """(energy share, centroid px) of each of the dot's cells for a trial (d_in, x, y)."""
        p = self.profile
        lens = p.main_lens
        fx = p.mla.focal_length_mm
        pp = p.sensor.pixel_pitch_mm
        ax, ay = p.sensor.axis_xy_px
        half = 0.5 * lens.pupil_diameter_mm
        rx, ry = self.pattern[0] * half, self.pattern[1] * half
        tr = trace_source_fast(lens, (x_mm, y_mm, self.z_source), rx, ry, d_in_mm)
        ok = tr.ok
        along = lens.rim_z_mm - self.z_source
        rho2 = (rx[ok] - x_mm) ** 2 + (ry[ok] - y_mm) ** 2 + along * along
        w = (along * along / rho2) ** 1.5  # solid angle of each rim-plane cell
        centres = self.centre_map(d_in_mm)[self.near]
        lattice = LocalLattice.fit(centres, p.mla.pitch_mm)
        if lattice is not None:  # exact Voronoi lookup on an affine lattice (fast)
            k = lattice.nearest(tr.x[ok], tr.y[ok])
        else:
            _, k = cKDTree(centres).query(np.column_stack([tr.x[ok], tr.y[ok]]))
        crossed = k >= 0
        k = np.where(crossed, k, 0)
        c = centres[k]
        px = (c[:, 0] + fx * tr.dx[ok] / tr.dz[ok]) / pp + ax
        py = (c[:, 1] + fx * tr.dy[ok] / tr.dz[ok]) / pp + ay
        ix = np.floor(px + 0.5).astype(np.int64)
        iy = np.floor(py + 0.5).astype(np.int64)
        h, wd = self.lmap.labels.shape
        inside = (ix >= 0) & (ix < wd) & (iy >= 0) & (iy < h)
        lab = np.full(ix.shape, -1, dtype=np.int64)
        lab[inside] = self.lmap.labels[iy[inside], ix[inside]]
        s = self.slot[lab]
        use = (s >= 0) & crossed
        m = len(self.dot.cells)
        e = np.bincount(s[use], w[use], minlength=m)
        with np.errstate(invalid="ignore", divide="ignore"):
            cx = np.bincount(s[use], w[use] * ix[use], minlength=m) / e
            cy = np.bincount(s[use], w[use] * iy[use], minlength=m) / e
        return e / max(e.sum(), 1e-300), np.column_stack([cx, cy])

    def residual(self, d_in_mm: float, x_mm: float, y_mm: float) -> np.ndarray:
        """Energy-weighted centroid differences (px) of every cell (2 per cell)."""
        _, cen = self.render(d_in_mm, x_mm, y_mm)
        diff = cen - self.dot.centroid_px
        # a cell the model leaves dark costs a full micro-image radius
        diff[~np.isfinite(diff).all(axis=1)] = self.lmap.radius_px
        return (diff * np.sqrt(self.weight)[:, None]).ravel()


def _start_position(profile: CameraProfile, d_in_mm: float, distance_mm: float,
                    dot: DotData) -> np.ndarray:
    """Lateral start: the paraxial object point whose image sits under the dot's light."""
    lens = profile.main_lens
    pp = profile.sensor.pixel_pitch_mm
    ax, ay = profile.sensor.axis_xy_px
    cen = np.array([(dot.light_centroid_px[0] - ax) * pp, (dot.light_centroid_px[1] - ay) * pp])
    # light centroid on the sensor ≈ chief ray through the exit pupil, extended to the sensor
    z_img = paraxial_image_z_mm(profile, distance_mm)
    z_ex = lens.exit_pupil_z_mm
    h_img = cen * (z_img - z_ex) / (d_in_mm + profile.mla.focal_length_mm - z_ex)
    s_img = z_img - lens.back_principal_z_mm
    s_obj = distance_mm + lens.principal_depth_mm
    return -h_img * s_obj / s_img


def fit_dot_exact(profile: CameraProfile, lmap: LensletMap, dot: DotData,
                  centre_map: CentreMap, distance_mm: float, d_in_start_mm: float,
                  pupil_samples: int = PUPIL_SAMPLES) -> DotFit:
    """Exact route for one dot: least squares over (d_in, x, y) at the known distance.

    Raises
    ------
    CalibrationError
        If the solve does not converge to a d_in within ±``SEARCH_FRACTION`` of the start.
    """
    model = DotModel(profile, lmap, dot, centre_map, distance_mm, pupil_samples)
    lo, hi = (1 - SEARCH_FRACTION) * d_in_start_mm, (1 + SEARCH_FRACTION) * d_in_start_mm
    # physically sized finite-difference steps (~0.3 px of spot motion): the binned model is
    # piecewise constant on the scale of single rays crossing pixel borders
    step_d = 0.02 * abs(d_in_start_mm - paraxial_image_z_mm(profile, distance_mm)) + 0.01
    step_xy = 2e-4 * distance_mm

    def fun(q):
        return model.residual(q[0], q[1], q[2])

    def jac(q):
        base = fun(q)
        cols = []
        for i, h in enumerate((step_d, step_xy, step_xy)):
            dq = np.zeros(3)
            dq[i] = h
            cols.append((fun(q + dq) - fun(q - dq)) / (2 * h) if i == 0
                        else (fun(q + dq) - base) / h)
        return np.column_stack(cols)

    def solve(q0):
        try:
            return least_squares(fun, q0, jac=jac, method="trf",
                                 x_scale=[step_d, step_xy, step_xy],
                                 bounds=([lo, -np.inf, -np.inf], [hi, np.inf, np.inf]),
                                 max_nfev=30, xtol=1e-6, ftol=1e-10)
        except ValueError as exc:
            raise CalibrationError(f"reference dot {dot.region_id}: exact solve failed "
                                   f"({exc})") from None

    res = solve(np.array([d_in_start_mm, *_start_position(profile, d_in_start_mm,
                                                          distance_mm, dot)]))
    if float(np.sqrt((res.fun**2).sum())) > 0.5 * MAX_RMS_PX:
        # Behind the focused plane the image point sits a few mm before the MLA, so a 0.4 mm
        # error of d_in rescales the spot pattern by ~10 %: the local solve stalls in a side
        # basin. A scan of d_in (lateral start re-derived at each node) picks the basin.
        span = SCAN_FRACTION * d_in_start_mm
        best = None
        for d_try in d_in_start_mm + np.linspace(-span, span, SCAN_NODES):
            q = np.array([d_try, *_start_position(profile, d_try, distance_mm, dot)])
            cost = float((fun(q) ** 2).sum())
            if best is None or cost < best[0]:
                best = (cost, q)
        again = solve(best[1])
        if (again.fun**2).sum() < (res.fun**2).sum():
            res = again
    d = float(res.x[0])
    if not np.isfinite(res.x).all() or d <= lo * 1.0001 or d >= hi * 0.9999:
        raise CalibrationError(
            f"reference dot {dot.region_id}: no d_in within ±{100 * SEARCH_FRACTION:.0f} % of "
            f"{d_in_start_mm:.3f} mm explains the dot at {distance_mm:g} mm (check the "
            "distance, the profile and the calibration)"
        )
    rms = float(np.sqrt((res.fun**2).sum()))
    return DotFit(d, (float(res.x[1]), float(res.x[2])), rms, len(dot.cells))


def interior_cells(dot: DotData, centres_px: np.ndarray) -> np.ndarray:
    """Mask of the dot's micro-images whose lattice neighbours are all lit too (fully lit).

    Energy cannot tell: at F/2 the spherical-aberration caustic makes the rim lenslets of a
    blur the brightest ones.
    """
    c = np.asarray(centres_px, dtype=np.float64)[dot.cells]
    tree = cKDTree(c)
    d, _ = tree.query(c, k=2)
    pitch = float(np.median(d[:, 1]))
    all_tree = cKDTree(np.asarray(centres_px, dtype=np.float64))
    n_lit = np.array([len(x) for x in tree.query_ball_point(c, 1.2 * pitch)])
    n_all = np.array([len(x) for x in all_tree.query_ball_point(c, 1.2 * pitch)])
    return n_lit == n_all


def fit_dot_paraxial(profile: CameraProfile, dot: DotData, centres_px: np.ndarray,
                     distance_mm: float, d_in_start_mm: float,
                     iterations: int = 30) -> DotFit:
    """Paraxial route for one dot (seed eqs. 10–12, module docstring).

    Raises
    ------
    CalibrationError
        If too few fully lit micro-images remain or the slope field has no defocus.
    """
    lens = profile.main_lens
    fx = profile.mla.focal_length_mm
    pp = profile.sensor.pixel_pitch_mm
    ax, ay = profile.sensor.axis_xy_px
    z_img = paraxial_image_z_mm(profile, distance_mm)
    full = interior_cells(dot, centres_px)
    if full.sum() < 4:
        raise CalibrationError(f"reference dot {dot.region_id}: too few fully lit micro-images")
    w = dot.energy[full]
    white = np.asarray(centres_px, dtype=np.float64)[dot.cells[full]]
    white_mm = np.column_stack([(white[:, 0] - ax) * pp, (white[:, 1] - ay) * pp])
    v = np.column_stack([(dot.centroid_px[full, 0] - ax) * pp,
                         (dot.centroid_px[full, 1] - ay) * pp])
    d = float(d_in_start_mm)
    slope = np.nan
    h_img = np.zeros(2)
    for _ in range(iterations):
        y = white_mm / (1.0 + fx / (d - lens.exit_pupil_z_mm))  # paraxial chief ray
        # v − y = s·y + b (both axes share s = f_x/(d_in − z_img); b = −s·h_img per axis)
        a = np.zeros((2 * len(y), 3))
        a[0::2, 0], a[1::2, 0] = y[:, 0], y[:, 1]
        a[0::2, 1], a[1::2, 2] = 1.0, 1.0
        rhs = (v - y).ravel()
        sw = np.repeat(np.sqrt(w), 2)
        sol, *_ = np.linalg.lstsq(a * sw[:, None], rhs * sw, rcond=None)
        slope = float(sol[0])
        if not (np.isfinite(slope) and abs(slope) > 1e-9):
            raise CalibrationError(
                f"reference dot {dot.region_id}: the dot is in focus on the MLA (no slope "
                "field); use a distance further from focus")
        h_img = -sol[1:] / slope
        d_new = z_img + fx / slope
        if not (math.isfinite(d_new) and d_new > lens.exit_pupil_z_mm + fx):
            raise CalibrationError(
                f"reference dot {dot.region_id}: paraxial d_in {d_new:.3f} mm is unphysical")
        if abs(d_new - d) < 1e-10 * d:
            d = d_new
            break
        d = d_new
    y = white_mm / (1.0 + fx / (d - lens.exit_pupil_z_mm))
    pred = y + slope * (y - h_img)
    rms = float(np.sqrt((w[:, None] * (pred - v) ** 2).sum() / w.sum())) / pp
    s_img = z_img - lens.back_principal_z_mm
    s_obj = distance_mm + lens.principal_depth_mm
    pos = -h_img * s_obj / s_img
    return DotFit(float(d), (float(pos[0]), float(pos[1])), rms, int(full.sum()))


def _mean_sigma(values: list[float]) -> tuple[float, float]:
    arr = np.asarray(values, dtype=np.float64)
    sigma = float(arr.std(ddof=1) / np.sqrt(len(arr))) if len(arr) > 1 else float("nan")
    return float(arr.mean()), sigma


def measure_d_in(
    capture: np.ndarray,
    centres_px: np.ndarray,
    profile: CameraProfile,
    distance_mm: float,
    pitch_px: float | None = None,
    d_in_start_mm: float | None = None,
    rotation_rad: float | None = None,
    black_level: float | None = None,
    pupil_samples: int = PUPIL_SAMPLES,
    max_dots: int = 25,
    indices: np.ndarray | None = None,
) -> DinResult:
    """d_in from a dot-target capture and the white-image micro-image centroids.

    Parameters
    ----------
    capture : (H, W) array
        Raw grey capture of point sources on a plane ``distance_mm`` before the front vertex.
    centres_px : (N, 2) array
        Micro-image centroids (x, y) of the white image (any calibration that returns white
        intensity centroids, e.g. :func:`lfcam.calibrate.calibrate_white`).
    profile : CameraProfile
        Main lens, MLA (pitch, f_x, grid) and sensor; its d_in is only the start of the solve
        unless ``d_in_start_mm`` is given.
    distance_mm : float
        Dot plane → front vertex.
    pitch_px : float, optional
        Micro-image pitch (default: from the profile's d_in and pixel pitch).
    rotation_rad : float, optional
        MLA rotation (default: the profile's).
    black_level : float, optional
        Subtracted from the capture (default: the profile's).
    indices : (N, 2) int array, optional
        Lattice indices of the centres (the calibration's); default: rounded on the nominal
        lattice.

    Raises
    ------
    CalibrationError
        Bad distance, no dots, size mismatch, or no d_in explains the dots.
    """
    distance_mm = check_distance(profile, distance_mm)
    centres = np.asarray(centres_px, dtype=np.float64)
    if centres.ndim != 2 or centres.shape[1] != 2 or len(centres) < 16:
        raise CalibrationError("reference: need at least 16 micro-image centres (N×2)")
    if not np.isfinite(centres).all():
        raise CalibrationError("reference: micro-image centres contain non-finite values")
    img = np.asarray(capture)
    h, w = img.shape[:2]
    if (centres[:, 0].max() > w + 1) or (centres[:, 1].max() > h + 1) or centres.min() < -1:
        raise CalibrationError(
            f"reference capture is {w}×{h} px but the calibration centres reach "
            f"({centres[:, 0].max():.0f}, {centres[:, 1].max():.0f}) px: not the same sensor")
    d0 = float(profile.d_in_mm if d_in_start_mm is None else d_in_start_mm)
    if pitch_px is None:
        z_ex = profile.main_lens.exit_pupil_z_mm
        pitch_px = (profile.mla.pitch_mm * (1 + profile.mla.focal_length_mm / (d0 - z_ex))
                    / profile.sensor.pixel_pitch_mm)
    black = profile.sensor.black_level if black_level is None else black_level
    lmap, dots = find_dots(img, centres, float(pitch_px), black)
    dots = sorted(dots, key=lambda t: -t.energy.sum())[:max_dots]
    centre_map = CentreMap(profile, centres, rotation_rad, indices)
    fits = [fit_dot_exact(profile, lmap, dot, centre_map, distance_mm, d0, pupil_samples)
            for dot in dots]
    # clean dots fit to ~0.01 px; merged blurs, stuck fits and a wrong distance leave more
    keep = [k for k, f in enumerate(fits) if f.rms_px <= MAX_RMS_PX]
    if not keep:
        raise CalibrationError(
            f"reference capture: no dot matches a point source at {distance_mm:g} mm (best "
            f"misfit {min(f.rms_px for f in fits):.2f} px, limit {MAX_RMS_PX} px): check the "
            "distance and that the dots are isolated points")
    exact = tuple(fits[k] for k in keep)
    dots = [dots[k] for k in keep]
    parax = []
    for dot in dots:
        try:
            parax.append(fit_dot_paraxial(profile, dot, centres, distance_mm, d0))
        except CalibrationError:  # the paraxial route is a diagnostic: record the failure
            nan = float("nan")
            parax.append(DotFit(nan, (nan, nan), nan, 0))
    parax = tuple(parax)
    d_ex, s_ex = _mean_sigma([f.d_in_mm for f in exact])
    d_par, s_par = _mean_sigma([f.d_in_mm for f in parax if math.isfinite(f.d_in_mm)] or
                               [float("nan")])
    return DinResult(d_ex, s_ex, d_par, s_par, distance_mm,
                     paraxial_image_z_mm(profile, distance_mm), exact, parax)
