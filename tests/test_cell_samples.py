"""Samples fixed on the lenslet cells: ``LensletModel(cells=n)`` and ``kernels.cell_samples``.

A ray-sampled model's Jacobian by differences is mostly its own sample's noise on a large blur
(docs/distance.md, "Large line blurs: why they stay slow"). The cell-sampled model maps the
centres of an n × n sub-grid of every lenslet cell back to the pupil through each point's
polynomial pupil → MLA map, so its samples stay put on the MLA as the source moves
(docs/distance.md, "Samples fixed on the lenslet cells").
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lfcam.camera import load_profile
from lfcam.measure import fastfit as ff
from lfcam.measure.kernels import MAP_DEGREE, cell_samples
from lfcam.measure.pointfit import LocalLattice, chief_ray_offset
from lfcam.optics.trace import trace_sources_fast
from lfcam.sim.capture import apply_overrides
from lfcam.sim.geometry import truth_geometry

SIZE = 1024
CAMERA = {"mla": {"focus_mm": 1000.0}, "sensor": {"width_px": SIZE, "height_px": SIZE}}


def _term(k: int, i: int) -> int:
    """Index of the term u^i v^(k−i) in the map's polynomial (kernels._map2's order)."""
    return k * (k + 1) // 2 + i


def _radial_map(scale, kappa, centre):
    """Coefficients of X = centre + scale·(1 + κ·r²)·(u, v): a linear map bent by a cubic
    radial term, as spherical aberration bends a lens's."""
    terms = (MAP_DEGREE + 1) * (MAP_DEGREE + 2) // 2
    cx, cy = np.zeros(terms), np.zeros(terms)
    cx[0], cy[0] = centre
    cx[_term(1, 1)] = cy[_term(1, 0)] = scale
    cx[_term(3, 3)] = cx[_term(3, 1)] = scale * kappa  # u³ + u·v²
    cy[_term(3, 2)] = cy[_term(3, 0)] = scale * kappa  # u²·v + v³
    return cx, cy


@pytest.mark.parametrize("grid", ["rect", "hex"])
@pytest.mark.parametrize("n", [2, 4])
@pytest.mark.parametrize("kappa", [0.2, 0.6])
def test_samples_invert_a_known_map_and_tile_the_pupil(grid, n, kappa):
    # the sub-grid of a lattice of unit pitch seen through a map known in closed form (8
    # pitches a pupil radius, 20 % or 60 % more at the rim: Newton from the map's linear part
    # takes more passes): every sample inside the pupil must map to its sub-grid point, weigh
    # the sub-cell's area over the map's Jacobian determinant (analytic: s²(1 + κr²)(1 +
    # 3κr²)), every cell wholly inside the footprint holds n² of them, and their pupil areas
    # add up to the disc's, π
    scale, centre = 8.0, (0.3, -0.2)
    cx, cy = _radial_map(scale, kappa, centre)
    basis = (np.eye(2) if grid == "rect"
             else np.array([[1.0, 0.5], [0.0, math.sqrt(3.0) / 2.0]]))
    origin = np.array([0.1, 0.05])
    reach = scale * (1.0 + kappa) + 2.0
    boxes = np.array([[centre[0] - reach, centre[0] + reach, centre[1] - reach,
                       centre[1] + reach]])
    offset = 0.5 * ((n + 1) % 2)  # the sub-cell centres: (index + ½)/n − ½ modulo 1
    la, lb, rect = ff._cell_shape(_lattice(origin, basis))
    u, v, w, rows, du, tx, _ = cell_samples(cx[None], cy[None], boxes,
                                            np.array([[centre[0], centre[1], reach]]), origin,
                                            basis, np.linalg.inv(basis), n,
                                            np.zeros((1, 5), dtype=np.int64),
                                            np.zeros(1, dtype=bool), 1.0, rect, la, lb)
    assert tx.size == 0  # (no whole cells: no sample moved to a neighbour's node)
    r = np.hypot(u, v)
    inside = r < 1.0 - 1e-9  # (samples beyond the rim are placed on it, with their share)
    x = centre[0] + scale * (1.0 + kappa * r * r) * u
    y = centre[1] + scale * (1.0 + kappa * r * r) * v
    lat = np.linalg.inv(basis) @ np.vstack([x - origin[0], y - origin[1]])
    fine = lat * n - offset
    assert np.abs(fine - np.round(fine))[:, inside].max() < 1e-6
    sub_area = abs(np.linalg.det(basis)) / n**2
    det = scale**2 * (1.0 + kappa * r**2) * (1.0 + 3.0 * kappa * r**2)
    full = inside & (r < 1.0 - du[0])
    # (the determinant at the root: one pass after Newton has converged; measured 1e-15)
    assert np.allclose(w[full], sub_area / det[full], rtol=1e-9)
    cell = np.floor(lat + 0.5).astype(int) if grid == "rect" else None
    if cell is not None:  # rectangular cells: count each whole cell's samples
        deep = r < 0.8
        keys = cell[0] * 1000 + cell[1]
        deep_cells = np.unique(keys[deep])
        counts = np.array([(keys == k).sum() for k in deep_cells])
        assert np.all(counts[counts > 0] <= n * n)
        assert np.median(counts) == n * n
    assert w.sum() == pytest.approx(math.pi, rel=2e-3)
    assert np.all(rows == 0)


def _lattice(origin, basis):
    """A lattice of nodes ``origin + basis @ (i, j)`` (its lookup table unused here)."""
    return LocalLattice(np.asarray(origin, float), np.asarray(basis, float),
                        np.linalg.inv(basis), np.zeros((1, 1), dtype=np.int64), 0, 0,
                        np.zeros((1, 2)))


def _radial_preimage(x, y, scale, kappa, centre):
    """The exact preimage of MLA points under :func:`_radial_map`: the pupil radius solves
    s·r·(1 + κr²) = ρ (a cubic with one real root, increasing), the direction is X's."""
    dx, dy = np.asarray(x) - centre[0], np.asarray(y) - centre[1]
    rho = np.hypot(dx, dy)
    r = np.array([np.real(np.roots([scale * kappa, 0.0, scale, -p])[
        np.argmin(np.abs(np.imag(np.roots([scale * kappa, 0.0, scale, -p]))))]) for p in rho])
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.where(rho > 0, r / rho, 1.0 / scale)
    return dx * f, dy * f


def test_whole_cells_are_every_cell_the_rule_admits_on_a_strongly_bent_map():
    # a map 2× wider at the rim than its linear part (κ = 1: the rim's cells have linear
    # preimages at pupil radii 1.5-2): the cells cell_centres integrates whole must be exactly
    # those its rule admits, worked out here from the map's closed-form inverse and Jacobian:
    # the node's pupil point r, the half-diagonals' preimages p₁, p₂ by the Jacobian's inverse,
    # r + margin·max(p₁, p₂) < 1 and max(p₁, p₂) ≤ CELL_WHOLE_MAX_PATCH, every Gauss point
    # inside the pupil. A bound on the linear preimage (2.25, the radius 1.5) once left out
    # every cell past pupil radius ~0.88 on system 2 behind focus
    from lfcam.measure.kernels import (
        CELL_GAUSS_2,
        CELL_WHOLE_MARGIN,
        CELL_WHOLE_MAX_PATCH,
        cell_centres,
    )

    scale, kappa, centre = 14.0, 1.0, (0.3, -0.2)
    cx, cy = _radial_map(scale, kappa, centre)
    basis = np.eye(2)
    origin = np.array([0.1, 0.05])
    reach = scale * (1.0 + kappa) + 2.0
    boxes = np.array([[centre[0] - reach, centre[0] + reach, centre[1] - reach,
                       centre[1] + reach]])
    rule = ff.cell_rule(_lattice(origin, basis))
    rows, ci, cj = cell_centres(cx[None], cy[None], boxes,
                                np.array([[centre[0], centre[1], reach]]), origin, basis,
                                np.linalg.inv(basis), CELL_WHOLE_MARGIN, rule.corners,
                                rule.points, rule.weights, np.zeros((0, 2)))[:3]
    got = set(zip(ci.astype(int).tolist(), cj.astype(int).tolist(), strict=True))
    assert np.all(rows == 0)
    span = int(reach) + 2
    ii, jj = (g.ravel() for g in np.meshgrid(np.arange(-span, span + 1),
                                              np.arange(-span, span + 1), indexing="ij"))
    x, y = origin[0] + ii, origin[1] + jj
    u, v = _radial_preimage(x, y, scale, kappa, centre)
    r2 = u * u + v * v
    want = set()
    for k in np.flatnonzero(r2 < 1.0):
        jac = scale * ((1.0 + kappa * r2[k]) * np.eye(2)
                       + 2.0 * kappa * np.outer([u[k], v[k]], [u[k], v[k]]))
        inv = np.linalg.inv(jac)
        p = max(np.hypot(*(inv @ [0.5, 0.5])), np.hypot(*(inv @ [0.5, -0.5])))
        if math.sqrt(r2[k]) + CELL_WHOLE_MARGIN * p >= 1.0 or p > CELL_WHOLE_MAX_PATCH:
            continue
        g = CELL_GAUSS_2
        gu, gv = _radial_preimage(x[k] + g * np.array([-1, -1, 1, 1]),
                                  y[k] + g * np.array([-1, 1, -1, 1]), scale, kappa, centre)
        if np.all(gu * gu + gv * gv < 1.0):
            want.add((int(ii[k]), int(jj[k])))
    r_want = max(math.sqrt(r2[(ii == a) & (jj == b)][0]) for a, b in want)
    assert r_want > 0.93  # (the rule reaches the rim's band: measured 0.95)
    assert got == want


def _system2():
    prof = apply_overrides(load_profile("system2"), CAMERA)
    geom = truth_geometry(prof, (SIZE, SIZE))
    return prof, geom


def _line_points(prof, distance_mm, count=12, image_len_mm=3.0):
    """``count`` points along a line whose image on the MLA is ``image_len_mm`` long."""
    a = chief_ray_offset(prof, prof.d_in_mm, distance_mm, np.array([-0.5 * image_len_mm, 0.0]))
    b = chief_ray_offset(prof, prof.d_in_mm, distance_mm, np.array([0.5 * image_len_mm, 0.0]))
    t = (np.arange(count) + 0.5) / count
    xy = a[None, :] + t[:, None] * (b - a)[None, :]
    z = prof.main_lens.front_vertex_z_mm - distance_mm
    return np.column_stack([xy, np.full(count, z)])


def _moments_box(prof, geom, half_px=260):
    """The lenslets of a box about the sensor's centre (the model needs the region's lenslet
    map, not its pixels)."""
    image = np.zeros((SIZE, SIZE))
    c = SIZE // 2
    return ff.data_moments(geom, image, (c - half_px, c - half_px, c + half_px, c + half_px))


def _normalised(m):
    return m / m[:, 0].sum()


def test_cells_model_is_closer_to_a_dense_ray_model_at_the_same_samples():
    # system 2's 3 mm line at 3400 mm, behind a 1 m focus (a blur of ~600 lenslets), its 12
    # points: the cell-sampled moments against a 400 000-ray reference, and the ray-sampled
    # ones with as many rays a point as the cells' samples
    prof, geom = _system2()
    mom = _moments_box(prof, geom)
    pts = _line_points(prof, 3400.0)
    ref = _normalised(ff.LensletModel(prof, geom, mom, 400_000, turn_every=12).simulate(pts))
    cells = ff.LensletModel(prof, geom, mom, 1000, cells=4, turn_every=12)
    got = _normalised(cells.simulate(pts))
    assert not cells.folded
    samples = int(cells._cell_samples(pts)[0].size / len(pts))
    rays = _normalised(ff.LensletModel(prof, geom, mom, samples, turn_every=12).simulate(pts))
    err_cells = np.linalg.norm(got - ref) / np.linalg.norm(ref)
    err_rays = np.linalg.norm(rays - ref) / np.linalg.norm(ref)
    # (measured 0.0013 against 0.0055 at 7 981 samples a point)
    assert err_cells < 0.0025
    assert err_cells < 0.4 * err_rays


def test_cells_cut_to_a_small_box_keep_its_moments():
    # the same line in a box that holds only the middle of its blur: the cells whose light
    # cannot reach the box are not sampled (docs/distance.md, "Speed at stop 42"), whether
    # the map is one to one is read at n = 2 over the whole footprint, and the box's moments
    # are still those of a 400 000-ray model
    prof, geom = _system2()
    pts = _line_points(prof, 3400.0)
    small = _moments_box(prof, geom, half_px=70)
    cells = ff.LensletModel(prof, geom, small, 1000, cells=4, turn_every=12)
    whole = ff.LensletModel(prof, geom, _moments_box(prof, geom), 1000, cells=4, turn_every=12)
    kept = cells._cell_samples(pts)[0].size
    assert kept < 0.45 * whole._cell_samples(pts)[0].size  # (measured 0.35)
    got = _normalised(cells.simulate(pts))
    assert not cells.folded
    ref = _normalised(ff.LensletModel(prof, geom, small, 400_000, turn_every=12).simulate(pts))
    # (measured 0.0013, as on the whole box)
    assert np.linalg.norm(got - ref) / np.linalg.norm(ref) < 0.0025


def test_cells_jacobian_is_not_sample_noise():
    # the moments' derivative in log distance (a 1 % difference) of one point at 3400 mm:
    # two cell quadratures (n = 4 and 6) agree far better than two ray samples of as many
    # rays (the Vogel spiral at two phases), against a 200 000-ray reference
    prof, geom = _system2()
    mom = _moments_box(prof, geom)
    src = _line_points(prof, 3400.0, count=1)[0]
    moved = src.copy()
    z_front = prof.main_lens.front_vertex_z_mm
    moved[2] = z_front - (z_front - src[2]) * math.exp(0.01)

    def derivative(model):
        return (_normalised(model.simulate(moved)) - _normalised(model.simulate(src))) / 0.01

    ref = derivative(ff.LensletModel(prof, geom, mom, 200_000))
    c4 = derivative(ff.LensletModel(prof, geom, mom, 1000, cells=4))
    c6 = derivative(ff.LensletModel(prof, geom, mom, 1000, cells=6))
    samples = int(ff.LensletModel(prof, geom, mom, 1000, cells=4)._cell_samples(
        src[None])[0].size)
    r0 = derivative(ff.LensletModel(prof, geom, mom, samples))
    r1 = derivative(ff.LensletModel(prof, geom, mom, samples, phase=1.0))
    size = np.linalg.norm(ref)
    cells_apart = np.linalg.norm(c4 - c6) / size
    rays_apart = np.linalg.norm(r0 - r1) / size
    assert cells_apart < 0.5
    assert cells_apart < 0.3 * rays_apart
    assert np.linalg.norm(c6 - ref) / size < 0.5


def _fold_of_exact_trace(prof, src, grid=41):
    """Whether the exact trace's pupil → MLA map folds: the sign of its Jacobian determinant
    by differences over a grid of the pupil (the numpy reference trace)."""
    lens = prof.main_lens
    half = 0.5 * lens.pupil_diameter_mm
    g = np.linspace(-0.95, 0.95, grid)
    u, v = np.meshgrid(g, g, indexing="ij")
    tr = trace_sources_fast(lens, src[None], (u * half).ravel()[None], (v * half).ravel()[None],
                            prof.d_in_mm)
    x = np.where(tr.ok, tr.x, np.nan).reshape(grid, grid)
    y = np.where(tr.ok, tr.y, np.nan).reshape(grid, grid)
    det = (np.diff(x, axis=0)[:, :-1] * np.diff(y, axis=1)[:-1, :]
           - np.diff(x, axis=1)[:-1, :] * np.diff(y, axis=0)[:, :-1])
    inside = (np.hypot(u, v) < 0.95)[:-1, :-1]
    det = det[inside & np.isfinite(det)]
    return bool((det > 0).any() and (det < 0).any())


@pytest.mark.parametrize("fold_first", [True, False])
@pytest.mark.parametrize("distance_mm, folds", [(380.0, True), (3400.0, False)])
def test_cells_apply_only_where_the_map_is_one_to_one(distance_mm, folds, fold_first,
                                                      monkeypatch):
    # In front of a 1 m focus (380 mm) the MLA cuts the spherical caustic: the exact trace's
    # map from the pupil to the MLA folds, each sub-grid point has several pupil points, and
    # the cell model falls back to rays (its samples' pupil areas add up to 0.25-0.95 π
    # there); behind focus the map is one to one. The polynomial map's Jacobian sign
    # (CELLS_FOLD_FIRST) tells the fold before the whole cells are inverted (no call of
    # cell_centres), as the samples' area does after them
    from lfcam.measure import kernels

    monkeypatch.setattr(ff, "CELLS_FOLD_FIRST", fold_first)
    calls = []
    inner = kernels.cell_centres
    monkeypatch.setattr(kernels, "cell_centres", lambda *a: calls.append(1) or inner(*a))
    prof, geom = _system2()
    mom = _moments_box(prof, geom)
    src = _line_points(prof, distance_mm, count=1)[0]
    assert _fold_of_exact_trace(prof, src) == folds
    model = ff.LensletModel(prof, geom, mom, 4000, cells=4)
    assert model.invertible(src[None]) == (not folds)
    assert bool(calls) == (not (folds and fold_first))
    model.simulate(src)
    assert model.folded == folds


def _polynomial_miss(prof, src, rays=3000):
    """How far (pitches, at most) a polynomial of the kernel's degree, fitted by least squares
    to ``rays`` exactly traced rays of the source (the numpy reference trace), lies off them."""
    from lfcam.measure.sampling import vogel_disc

    half = 0.5 * prof.main_lens.pupil_diameter_mm
    u, v = vogel_disc(rays)
    tr = trace_sources_fast(prof.main_lens, src[None], (u * half)[None], (v * half)[None],
                            prof.d_in_mm)
    ok = tr.ok[0]
    terms = ff._map_basis(u[ok], v[ok])
    miss = 0.0
    for coord in (tr.x[0, ok], tr.y[0, ok]):
        coef = np.linalg.lstsq(terms, coord, rcond=None)[0]
        miss = max(miss, float(np.abs(coord - terms @ coef).max()))
    return miss / prof.mla.pitch_mm


def test_cells_do_not_apply_where_the_polynomial_misses_the_map():
    # system 1 at 80 % of its half-field (coma, a far source): the pupil → MLA map bends more
    # than a quintic follows (0.05 pitch off at most; system 2 on axis 0.003), and samples
    # placed by it would sit off their sub-cells (the grid's lines there: 0.37 / 1.10 % on the
    # cells against 0.31 / 0.68 % ray-sampled); on axis the cells apply
    prof = apply_overrides(load_profile("system1"), CAMERA)
    geom = truth_geometry(prof, (SIZE, SIZE))
    mom = _moments_box(prof, geom)
    half_field = 0.5 * SIZE * prof.sensor.pixel_pitch_mm
    z = prof.main_lens.front_vertex_z_mm - 3400.0
    xy = chief_ray_offset(prof, prof.d_in_mm, 3400.0, np.array([0.8 * half_field, 0.0]))
    off_axis = np.array([xy[0], xy[1], z])
    centre = np.array([0.0, 0.0, z])
    assert _polynomial_miss(prof, off_axis) > 0.02
    assert _polynomial_miss(prof, centre) < 0.005
    assert not ff.LensletModel(prof, geom, mom, 4000, cells=4).invertible(off_axis[None])
    assert ff.LensletModel(prof, geom, mom, 4000, cells=4).invertible(centre[None])


def test_large_line_blur_behind_focus_is_fitted_on_the_cells(monkeypatch):
    # system 2's 3 mm line at 2900 mm behind a 1 m focus (a blur of ~800 lenslets, photon
    # noise, the renderer's centres): its fit runs on the cells (coarse n = 2, fine n = 4, the
    # settled test n = 6), needs no refit, and lands within 0.2 % and 3σ of the truth
    # (measured +0.08 %, σ 0.15 %)
    from lfcam.distance import run_distance
    from lfcam.sim.capture import simulate
    from lfcam.sim.scene import scene_from_dict

    base = load_profile("system2")
    prof = apply_overrides(base, CAMERA)
    a = chief_ray_offset(prof, prof.d_in_mm, 2900.0, np.array([-1.5, 0.0]))
    b = chief_ray_offset(prof, prof.d_in_mm, 2900.0, np.array([1.5, 0.0]))
    scene = {"seed": 3, "camera": CAMERA,
             "sensor": {"photon_noise": True, "full_well_e": 20000, "read_noise_e": 3.0},
             "objects": [{"type": "line", "distance_mm": 2900.0, "start_mm": a.tolist(),
                          "end_mm": b.tolist(), "rays": 1_000_000}]}
    raw, used, _ = simulate(base, scene_from_dict(scene))
    built = []
    init = ff.LensletModel.__init__

    def spy(self, *args, **kwargs):
        init(self, *args, **kwargs)
        built.append(self)

    monkeypatch.setattr(ff.LensletModel, "__init__", spy)
    run = run_distance(raw.astype(np.float64), used, None, model="exact", method="lenslet",
                       geometry=truth_geometry(used, (SIZE, SIZE)), jobs=1)
    best = max(run.regions, key=lambda r: r.diameter_mm if r.status == "ok" else -1)
    assert best.kind == "line" and best.status == "ok"
    cells = sorted({m.cells for m in built if m.cells})
    # (a rectangular lattice: the fine model's n where the cells lit whole are integrated)
    assert cells == sorted([ff.LINE_CELLS_COARSE, ff.LINE_CELLS_FINE_WHOLE, ff.LINE_CELLS_SETTLE])
    assert not any(m.folded for m in built if m.cells and m.evaluations)
    err = best.distance_mm - 2900.0
    assert abs(err) < 0.002 * 2900.0
    assert abs(err) < 3.0 * best.uncertainty_mm


def test_gauss_newton_does_not_evaluate_a_step_under_its_floor():
    # a linear residual r(q) = A q − b with its exact Jacobian: one step reaches the minimum,
    # where the next step is round-off. Without a floor that step is evaluated and, the misfit
    # not falling, halved twice (three evaluations for nothing); with one, none
    rng = np.random.default_rng(1)
    a = rng.normal(size=(40, 3))
    b = rng.normal(size=40)
    calls = []

    def fun(q):
        calls.append(q.copy())
        return a @ q - b

    q0 = np.zeros(3)
    q_min = np.linalg.lstsq(a, b, rcond=None)[0]
    for floor, evaluations in ((0.0, 4), (1e-6, 1)):
        calls.clear()
        q, r, f = ff.gauss_newton_fixed(fun, q0, fun(q0), a, 4, skip_below=floor)
        assert len(calls) - 1 == evaluations
        np.testing.assert_allclose(q, q_min, atol=1e-9)
        assert f == pytest.approx(float((a @ q_min - b) @ (a @ q_min - b)), rel=1e-9)


def _hex_line(distance_mm: float, angle_deg: float) -> tuple:
    """System 2 with a hexagonal MLA: the benchmark's 3 mm line at ``distance_mm`` and
    ``angle_deg`` (``benchmarks/lines_on_cells.py``), its capture, profile, geometry, region
    and the region's moments: (img, used, geom, reg, mom)."""
    import sys
    from pathlib import Path

    from lfcam.measure.lenslets import lenslet_stats
    from lfcam.measure.regions import find_regions

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from lines_on_cells import line_capture  # the benchmark's capture of that line

    img, used, geom = line_capture("hex", distance_mm, angle_deg)
    regions = find_regions(lenslet_stats(img, geom.lmap), geom.lmap, geom.pitch_px)
    reg = max(regions, key=lambda r: len(r.lenslets))
    return img, used, geom, reg, ff.data_moments(geom, img, ff._region_box(geom, reg, img.shape))


@pytest.fixture(scope="module")
def hex_line_3400():
    """:func:`_hex_line` at 3400 mm and 135°: its region's moments, its line fit, and the
    fit's answer as the line model's parameters ``q``: (profile, geom, mom, line, frame, q)."""
    img, used, geom, reg, mom = _hex_line(3400.0, 135.0)
    line = ff.fit_lenslet_line(used, geom, img, reg, mom=mom)
    frame = ff.SourceFrame(used)
    a, b = line.ends_mm
    along = frame.z_rim - a[2]
    q = np.r_[math.log(frame.z_front - a[2]), a[:2] / along, b[:2] / along]
    return used, geom, mom, line, frame, q


def test_line_on_a_hexagonal_lattice_lands_on_the_fine_models_minimum(hex_line_3400):
    # system 2 with a hexagonal MLA, a 3 mm line at 3400 mm and 135°: the fit's answer must be
    # the minimum of the n = 6 model it reports, found here independently by
    # Levenberg–Marquardt on that model alone from the fit's answer. With the coarse n = 2
    # Jacobian for the fine steps (a hexagonal cell's borders cut n = 2's sub-cells: its
    # distance column 10 % off) the answer lay 0.26 % from it (σ 0.21 %); measured 0.002 %,
    # 0.027 % with the rim's cells cut (stop 46: the n = 4 and 6 models nearly the same, the
    # settled step is the fine steps' last 3e-4)
    used, geom, mom, line, frame, q = hex_line_3400
    assert line.ok
    fine = ff.LensletModel(used, geom, mom, 1000, cells=ff.LINE_CELLS_SETTLE)
    steps = np.r_[ff.COARSE_STEPS[0], np.full(4, ff.COARSE_STEPS[1])]
    # the fit's own point count (its footprint's length, LINE_SPACING_PITCH apart)
    spread = np.linalg.eigvalsh(ff._footprint(geom, mom, mom.data[:, 0])[1])
    length_mm = math.sqrt(12.0 * float(spread[1] - spread[0]))
    n_pts = int(np.clip(math.ceil(length_mm / (ff.LINE_SPACING_PITCH * used.mla.pitch_mm)),
                        ff.LINE_POINTS, ff.LINE_POINTS_MAX))
    fun, jac = ff.line_model(fine, frame, n_pts, steps)
    q_min = ff.levenberg_marquardt(fun, q, steps, 6, 1e-4, jac_of=jac, settle_log=1e-6)[0]
    assert not fine.folded
    assert abs(q_min[0] - q[0]) < 5e-4
    assert abs(line.source_mm[2] - (frame.z_front - 3400.0)) < 3.0 * line.sigma_distance_mm


def test_line_jacobian_along_the_line_from_its_ends(hex_line_3400, monkeypatch):
    # On the cells a line's lateral columns along it come from its two end points (the
    # points' weighted derivative sums telescope: fastfit.line_model). Against the Jacobian
    # of every point shifted along x and y (the reference, its own differences), on the
    # hexagonal 3400 mm line at its fitted answer: the distance column the same; the
    # lateral columns within 20 % (measured 12-13 % here, 7-16 % on nine lines); from a start
    # 0.5 % off, the fine stage's steps and the settled step with each Jacobian (taken
    # there) land within 0.02 % of each other (measured 0.0097 %; ≤ 0.006 % on eight of the
    # nine lines from the n = 6 minimum, 0.019 % on one; this line's σ is 0.23 %)
    used, geom, mom, line, frame, q = hex_line_3400
    assert line.ok
    steps = np.r_[ff.COARSE_STEPS[0], np.full(4, ff.COARSE_STEPS[1])]
    fine = ff.LensletModel(used, geom, mom, 1000, cells=ff.LINE_CELLS_FINE)
    fun, jac = ff.line_model(fine, frame, ff.LINE_POINTS, steps)
    settle = ff.line_model(ff.LensletModel(used, geom, mom, 1000, cells=ff.LINE_CELLS_SETTLE),
                           frame, 2 * ff.LINE_POINTS, steps)[0]
    # from a start 0.5 % farther and off to one side, as the fit's fine stage: Gauss–Newton
    # with the Jacobian taken there, then the settled step with it
    q0 = q + np.r_[0.005, 2e-5, -1e-5, 2e-5, -1e-5]
    r0 = fun(q0)
    got = jac(q0, r0)
    monkeypatch.setattr(ff, "LINE_JACOBIAN_ENDS", False)
    ref = jac(q0, r0)
    assert not fine.folded
    np.testing.assert_allclose(got[:, 0], ref[:, 0], rtol=1e-12, atol=1e-15)
    for k in range(1, 5):
        assert np.linalg.norm(got[:, k] - ref[:, k]) < 0.2 * np.linalg.norm(ref[:, k])

    def settled(j):
        qk = q0.copy()
        for _ in range(ff.FINE_ITERATIONS):
            qk = qk - np.linalg.lstsq(j, fun(qk), rcond=None)[0]
        return qk - np.linalg.lstsq(j, settle(qk), rcond=None)[0]

    q_got, q_ref = settled(got), settled(ref)
    assert abs(q_ref[0] - q0[0]) > 3e-3  # (both come back most of the 0.5 %)
    assert abs(q_got[0] - q_ref[0]) < 2e-4


def test_line_jacobian_of_a_folded_cells_model_is_the_per_point_one(hex_line_3400, monkeypatch):
    # a cells model whose map folded samples rays from then on (LensletModel.folded): its
    # line Jacobian is the per-point one, as every ray-sampled line's (the ends' own pupil
    # samples moved ray-sampled answers by up to 1.4σ: docs/distance.md, "A line's Jacobian
    # along it from its ends (stop 56)"), bit for bit
    used, geom, mom, _, frame, q = hex_line_3400
    steps = np.r_[ff.COARSE_STEPS[0], np.full(4, ff.COARSE_STEPS[1])]
    model = ff.LensletModel(used, geom, mom, 1000, cells=ff.LINE_CELLS_FINE)
    model.folded = True
    fun, jac = ff.line_model(model, frame, ff.LINE_POINTS, steps)
    r = fun(q)
    got = jac(q, r)
    monkeypatch.setattr(ff, "LINE_JACOBIAN_ENDS", False)
    np.testing.assert_array_equal(got, jac(q, r))


def _matches_logged(monkeypatch):
    """Spy on ``fastfit._match_summary``: (the model's n, whether ``jac0`` was given, the
    model evaluations it made, its normalised misfit at the end) a call."""
    log = []
    match = ff._match_summary

    def spy(*args, **kwargs):
        model = args[4]
        before = model.evaluations
        out = match(*args, **kwargs)
        log.append((model.cells, kwargs.get("jac0") is not None,
                    model.evaluations - before, out[2]))
        return out

    monkeypatch.setattr(ff, "_match_summary", spy)
    return log


def _large_point_2900(monkeypatch, same_log: float | None = None):
    """System 2's point at 2900 mm behind a 1 m focus, 23 mm off axis, the data a
    2 000 000-ray model's moments at the source: its two fits (first look, answer), the
    models made, the summary matches logged, the frame and the source."""
    import dataclasses

    prof, geom = _system2()
    mom = _moments_box(prof, geom, half_px=330)
    frame = ff.SourceFrame(prof)
    z = prof.main_lens.front_vertex_z_mm - 2900.0
    src = np.array([23.0, 0.0, z])
    dense = ff.LensletModel(prof, geom, mom, 2_000_000).simulate(src[None])
    mom = dataclasses.replace(mom, data=dense, norm=float(np.sqrt((dense * dense).sum())))
    made = []

    class Recorded(ff.LensletModel):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made.append(self)

    with monkeypatch.context() as mp:
        mp.setattr(ff, "LensletModel", Recorded)
        if same_log is not None:
            mp.setattr(ff, "SUMMARY_SAME_LOG", same_log)
        matches = _matches_logged(mp)
        # (with ``mom`` given the fit reads neither the image nor the region)
        stages = ff.point_fit_stages(prof, geom, np.zeros((SIZE, SIZE)), None, mom=mom)
        first = next(stages)
        used_first = {m.cells for m in made if m.evaluations and not m.folded}
        fit = next(stages)
    return first, fit, used_first, matches, frame, src


def test_a_lines_blur_is_summary_matched_on_the_scan_rays_alone(hex_line_3400, monkeypatch):
    # A line's blur fitted as a point: a point's summary cannot match it (the scan's match
    # ends at 0.04-0.27 on the grid's lines behind focus, most over 0.06, and at 0.004-0.065
    # on its points; this line's at 0.051 and 0.052), and its
    # Broyden steps on the coarse cells (8-14 evaluations a start) changed nothing the line
    # fit needs. With SUMMARY_SCAN_FIRST the point's coarse stage spends fewer evaluations on
    # the cells matching it, and the line fit's answer is the one the cells' match gave
    # (measured: the same to the last digit; σ 7 mm) and within 3σ of the truth
    used, geom, mom, _, frame, _ = hex_line_3400
    img = np.zeros((1, 1))  # (with ``mom`` given the fits read neither image nor region)

    def fitted(scan_first):
        monkeypatch.setattr(ff, "SUMMARY_SCAN_FIRST", scan_first)
        log = _matches_logged(monkeypatch)
        point = next(ff.point_fit_stages(used, geom, img, None, mom=mom, early=True))
        line = ff.fit_lenslet_line(used, geom, img, None, point=point, mom=mom)
        monkeypatch.undo()
        assert point.ok and point.coarse and line.ok
        return log, line

    log, line = fitted(True)
    log_cells, line_cells = fitted(False)
    on_cells = sum(n for cells, _, n, _ in log if cells)
    assert log and log[0][0] == 0  # (the scan's rays first)
    # a match goes on on the cells only after a scan's match under SUMMARY_MATCHED
    for (c0, _, _, err), (c1, jac0, _, _) in zip(log, log[1:], strict=False):
        if c1:
            assert c0 == 0 and err < ff.SUMMARY_MATCHED and jac0
    assert on_cells < 0.5 * sum(n for _, _, n, _ in log_cells)  # (measured 0 against 16)
    assert abs(line.source_mm[2] - line_cells.source_mm[2]) < 0.1 * line.sigma_distance_mm
    assert abs(line.source_mm[2] - (frame.z_front - 3400.0)) < 3.0 * line.sigma_distance_mm


def test_a_point_at_the_far_bound_gives_the_line_no_start(hex_line_3400, monkeypatch):
    # A point fit run out to the far bound (system 2's lines at 380 mm, 60-80 % of the
    # field) says nothing of where the line is: with LINE_FAR_POINT_START the line fit's
    # starts are the scan's best node alone, without it the far bound and its turned copies
    # raced too (a Jacobian and failed steps each). Either way this line is found where
    # the fit from its own point finds it (within a tenth of its σ) and within 3σ of the
    # truth (3400 mm)
    import dataclasses

    used, geom, mom, line, frame, _ = hex_line_3400
    img = np.zeros((1, 1))  # (with ``mom`` given the fits read neither image nor region)
    point = next(ff.point_fit_stages(used, geom, img, None, mom=mom))
    far = math.exp(ff.LOG_DISTANCE_RANGE[1])
    at_bound = dataclasses.replace(point, source_mm=np.array([3.0, -2.0, frame.z_front - far]))

    def raced(flag):
        monkeypatch.setattr(ff, "LINE_FAR_POINT_START", flag)
        # (every start races: on this line the far ones start over 10× the best's misfit²,
        # which alone keeps them out; on the 380 mm lines they start within 5×)
        monkeypatch.setattr(ff, "LINE_RACE_START_RATIO", 1e9)
        monkeypatch.setattr(ff, "LINE_RACE_HOPELESS", 1e9)
        starts = []
        inner = ff.levenberg_marquardt

        def logged(fun, q0, *args, **kwargs):
            starts.append(float(q0[0]))
            return inner(fun, q0, *args, **kwargs)

        monkeypatch.setattr(ff, "levenberg_marquardt", logged)
        fit = ff.fit_lenslet_line(used, geom, img, None, point=at_bound, mom=mom)
        monkeypatch.undo()
        return starts, fit

    new_starts, new = raced(True)
    old_starts, old = raced(False)
    bound = ff.LOG_DISTANCE_RANGE[1] - 1e-6
    assert any(q >= bound for q in old_starts) and not any(q >= bound for q in new_starts)
    for fit in (new, old):
        assert fit.ok
        assert abs(fit.source_mm[2] - line.source_mm[2]) < 0.1 * line.sigma_distance_mm
        assert abs(fit.source_mm[2] - (frame.z_front - 3400.0)) < 3.0 * fit.sigma_distance_mm


def test_a_start_far_behind_the_best_is_not_raced(monkeypatch):
    # System 2 with a hexagonal MLA, the benchmark's 3 mm line at 1500 mm and 60°: the
    # distance scan's start begins at 8.0 × the point fit's misfit² and, raced, ends at 8 ×
    # the winner's end (0.053 against 0.0066). Over LINE_RACE_START_RATIO (5 since stop 61,
    # 10 before) it is not raced, and the answer and its σ are those of the full race
    # (the same measured on the 231 grid lines; every winner logged started within 2.81 ×)
    img, used, geom, reg, mom = _hex_line(1500.0, 60.0)
    point = next(ff.point_fit_stages(used, geom, img, reg, mom=mom))

    def raced(ratio):
        monkeypatch.setattr(ff, "LINE_RACE_START_RATIO", ratio)
        heats = []  # (misfit² where a heat starts, where it ends)
        inner = ff.levenberg_marquardt

        def logged(fun, q0, *args, **kwargs):
            out = inner(fun, q0, *args, **kwargs)
            if "stop_above" in kwargs:  # (only the race's heats give up)
                heats.append((ff.sq(kwargs["r0"]), out[2]))
            return out

        monkeypatch.setattr(ff, "levenberg_marquardt", logged)
        fit = ff.fit_lenslet_line(used, geom, img, reg, point=point, mom=mom)
        monkeypatch.undo()
        return heats, fit

    assert ff.LINE_RACE_START_RATIO == 5.0
    every, full = raced(10.0)
    assert len(every) == 2
    (f0, end0), (f1, end1) = every
    assert 5.0 < f1 / f0 < 10.0 and end1 > 5.0 * end0  # a start that began and ended far behind
    tight, fit = raced(5.0)
    assert tight == every[:1]
    assert fit.ok and full.ok
    assert fit.source_mm[2] == full.source_mm[2]
    assert fit.sigma_distance_mm == full.sigma_distance_mm
    frame = ff.SourceFrame(used)
    assert abs(frame.z_front - fit.source_mm[2] - 1500.0) < 3.0 * fit.sigma_distance_mm


def _deposit_pair(spot_centre, e, labels, centres_px, dense=240, s_px=1e-4, pieces=None):
    """deposit_cells of one whole cell (weight 1) and deposit_moments of ``dense``² samples
    spread evenly over the same parallelogram, each an ``s_px`` box (pixel pitch 1 mm,
    lattice pitch 10 mm, the cell at the lattice origin, so that a landing's pixel
    coordinates are its offsets); ``pieces``: deposit_cells' (none: a rectangular cell's)."""
    from lfcam.measure.kernels import CELL_SPLIT, deposit_cells, deposit_moments

    pieces = np.zeros((0, 3, 2)) if pieces is None else pieces

    eye10 = 10.0 * np.eye(2)
    inv = np.linalg.inv(eye10)
    zero = np.zeros(1, dtype=np.int64)
    out = deposit_cells(np.zeros((len(centres_px), 4)), zero, np.zeros(1), np.zeros(1),
                        np.array([spot_centre[0]]), np.array([spot_centre[1]]), np.ones(1),
                        np.array([e], dtype=float), zero, np.zeros(2), eye10, 1.0, 0.0, 0.0,
                        0, 0, labels, centres_px, 10.0, pieces,
                        CELL_SPLIT if pieces.shape[0] else 1)
    t = (np.arange(dense) + 0.5) / dense - 0.5
    a, b = (g.ravel() for g in np.meshgrid(t, t))
    sx = spot_centre[0] + a * e[0] + b * e[2]
    sy = spot_centre[1] + a * e[1] + b * e[3]
    n = sx.size
    ref = deposit_moments(np.zeros(n), np.zeros(n), sx, sy, np.full(n, 1.0 / n),
                          np.zeros(n, dtype=np.int64), np.ones(1), zero, 1, np.zeros(2), eye10,
                          inv, True, 10.0, 10.0, 1.0, 0.0, 0.0, 0, 0, s_px, labels, centres_px,
                          10.0, np.empty(0), False)
    return out, ref


def test_whole_cell_deposit_is_the_limit_of_dense_samples():
    # a sheared parallelogram 1.3 × 0.9 px across a pixel corner, one lenslet's pixels: the
    # trapezoid marginals against 57 600 samples of the same parallelogram, each binned to
    # its pixel (the samples' own rule converges as 1/dense)
    labels = np.zeros((12, 12), dtype=np.int64)
    centres = np.array([[5.2, 5.7]])
    out, ref = _deposit_pair((5.45, 4.62), (1.1, 0.35, -0.3, 0.8), labels, centres)
    assert np.allclose(out, ref, rtol=0, atol=2e-5)
    # an upright square across two lenslets' pixels: each pixel its column's × its row's
    # share (exact for an upright rectangle), against samples whose boxes tile it exactly
    labels[:, 6:] = 1
    centres = np.array([[3.0, 5.0], [9.0, 5.0]])
    out, ref = _deposit_pair((5.8, 4.3), (1.2, 0.0, 0.0, 1.2), labels, centres, s_px=1.2 / 240)
    assert abs(out[0, 0] - 0.25) < 1e-12  # (5.5 − 5.2) / 1.2 in the left lenslet's pixels
    assert np.allclose(out, ref, rtol=0, atol=1e-9)


def test_whole_cells_are_closer_to_a_dense_cell_sample(monkeypatch):
    # system 2's point at 3400 mm behind a 1 m focus (~490 lenslets): the cells it lights whole
    # integrated by the 2 × 2 Gauss rule against every cell sampled 24 × 24, on those cells'
    # lenslets (whose light comes from their own cell alone); the sampled model at the same n
    # leaves several times the difference there (docs/distance.md, "Cells integrated whole")
    prof, geom = _system2()
    mom = _moments_box(prof, geom)
    pts = _line_points(prof, 3400.0, count=1)
    monkeypatch.setattr(ff, "CELLS_WHOLE", True)
    model = ff.LensletModel(prof, geom, mom, 1000, cells=4)
    u, v, w, rows, du, maps, args, whole, _ = model._cell_samples(pts)
    lat = model.lattice
    nodes = lat.origin + np.column_stack([whole[1], whole[2]]) @ lat.basis.T
    lens = geom.lens_centres_mm[mom.ids]
    fed = np.argmin(((lens[:, None, :] - nodes[None]) ** 2).sum(-1), axis=0)
    monkeypatch.setattr(ff, "CELLS_WHOLE", False)
    ref = ff.LensletModel(prof, geom, mom, 1000, cells=24).simulate(pts)
    lit = ref[:, 0] > 0.05 * ref[:, 0].max()
    # two thirds of the lit cells whole (measured 0.67), and the pupil's area in all (samples
    # and Gauss points) π
    assert len(fed) > 0.6 * np.count_nonzero(lit)
    assert abs((w.sum() + whole[5].sum()) / math.pi - 1.0) < 1e-4
    want = ref[fed] / ref[fed, 0].sum()
    sampled = {n: ff.LensletModel(prof, geom, mom, 1000, cells=n).simulate(pts)[fed]
               for n in (4, 6)}
    monkeypatch.setattr(ff, "CELLS_WHOLE", True)
    for n in (4, 6):
        model = ff.LensletModel(prof, geom, mom, 1000, cells=n)
        got = model.simulate(pts)[fed]
        assert not model.folded
        e_whole = np.linalg.norm(got / got[:, 0].sum() - want) / np.linalg.norm(want)
        e_sampled = (np.linalg.norm(sampled[n] / sampled[n][:, 0].sum() - want)
                     / np.linalg.norm(want))
        # (measured 1.5e-4 at either n, against 6.8e-4 and 3.9e-4 sampled, each sample its
        # own box)
        assert e_whole < 3e-4
        assert e_whole < 0.5 * e_sampled


def test_each_samples_box_brings_a_blurs_compressed_centre_to_a_dense_sample(monkeypatch):
    # system 2's point at 3400 mm behind a 1 m focus: at the blur's centre the map compresses
    # the pupil (cells there stand for pupil patches over 0.1 of its radius, sampled n × n).
    # Each sample spread as a box of its own pupil area's size on the sensor brings n = 3's
    # moments of the central lenslets within 8e-4 of every cell sampled 24 × 24 (measured
    # 5.1e-4; one box size for all, the mean, left 2.5e-3: docs/distance.md, "The whole cells
    # reach the rim; each sample its own box (stop 44)")
    prof, geom = _system2()
    mom = _moments_box(prof, geom)
    pts = _line_points(prof, 3400.0, count=1)
    monkeypatch.setattr(ff, "CELLS_WHOLE", False)
    ref = ff.LensletModel(prof, geom, mom, 1000, cells=24).simulate(pts)
    got = ff.LensletModel(prof, geom, mom, 1000, cells=3).simulate(pts)
    e = ref[:, 0]
    centres = mom.centres_px
    c = (e[:, None] * centres).sum(0) / e.sum()
    rad = np.hypot(*(centres - c).T)
    spread = math.sqrt(2.0 * (e * rad**2).sum() / e.sum())  # the blur's radius
    central = rad < 0.2 * spread
    assert np.count_nonzero(central) >= 8
    err = np.linalg.norm((got - ref)[central]) / np.linalg.norm(ref)
    assert err < 8e-4


def test_large_point_blur_is_fitted_on_the_cells_then_answered_by_the_rays(monkeypatch):
    # system 2's point at 2900 mm behind a 1 m focus (~840 lenslets), 23 mm off axis: the data
    # are a 2 000 000-ray model's moments at the source, so the answer's distance must be that
    # model's. The coarse and fine stages and the first look (all a line region needs) run on
    # the cells; the answer comes from the ray models started there, since the cells' quintic
    # area element leaves points 0.04-0.07 % short (docs/distance.md, "Large point blurs on
    # the cells (stop 44)")
    first, fit, used_first, matches, frame, src = _large_point_2900(monkeypatch)
    assert first.ok and fit.ok
    # a point's summary is matched on the scan's rays (measured 0.017-0.018), then on the
    # coarse cells from there with that match's Jacobian (SUMMARY_SCAN_FIRST); the second
    # start's scan match lands in the first's basin (SUMMARY_SAME_LOG) and is not matched on
    # the cells again (docs/distance.md, "One cells match a basin (stop 58)")
    assert [(cells, jac0) for cells, jac0, _, _ in matches] == [
        (0, False), (ff.LINE_CELLS_COARSE, True), (0, False)]
    assert all(err < ff.SUMMARY_MATCHED for _, _, _, err in matches[::2])
    # the first look on the cells: the coarse, fine and polishing models' n
    assert {ff.LINE_CELLS_COARSE, ff.LINE_CELLS_FINE_WHOLE, ff.LINE_CELLS_SETTLE} <= used_first
    d_first = frame.z_front - first.source_mm[2]
    d = frame.z_front - fit.source_mm[2]
    # the cells' fine fit within 0.1 % (measured +0.034 %), the answer within the ray fit's
    # settled test (SETTLED_LOG: measured +0.037 %, settled on 20 000 rays)
    assert abs(d_first / 2900.0 - 1.0) < 1e-3
    assert abs(d / 2900.0 - 1.0) < ff.SETTLED_LOG
    assert np.hypot(*(fit.source_mm[:2] - src[:2])) < 0.1  # (mm; measured 0.001)
    # every start matched on the cells (the rule off): both starts' cells matches, the second
    # a quarter of the first's evaluations or more (measured 4 against 11), and the same
    # answer to 0.01 % (measured: to the last digit, the first start winning either way)
    _, fit_all, _, matches_all, _, _ = _large_point_2900(monkeypatch, same_log=0.0)
    assert [(cells, jac0) for cells, jac0, _, _ in matches_all] == [
        (0, False), (ff.LINE_CELLS_COARSE, True)] * 2
    assert matches_all[3][2] >= 0.25 * matches_all[1][2]
    d_all = frame.z_front - fit_all.source_mm[2]
    assert abs(d / d_all - 1.0) < 1e-4


def test_cell_landings_are_the_bincount_sums_bit_for_bit():
    # kernels.cell_landings against the numpy bincounts it replaced (shuffled rays, one cell
    # missing a ray): the same sums in the same order, so equal to the last bit
    from lfcam.measure.kernels import CELL_GAUSS_2, cell_landings

    rng = np.random.default_rng(5)
    n = 300
    ray = rng.permutation(4 * n)
    ray = np.sort(ray[ray != 37])  # (the trace keeps its rays in order; cell 9 lost one)
    wt, sx, sy = rng.random(ray.size), rng.normal(size=ray.size), rng.normal(size=ray.size)
    w4 = rng.random(4 * n)
    rect = ff.cell_rule(_lattice(np.zeros(2), np.eye(2)))
    every, weight, lx, ly, sides = cell_landings(ray, wt, sx, sy, w4, n, rect.sides)
    cell, q = np.divmod(ray, 4)
    wq = wt * w4[ray]
    assert not every and np.all(np.bincount(cell, minlength=n)[np.arange(n) != 9] == 4)
    want = np.bincount(cell, wq, minlength=n)
    s1 = np.array([-1.0, -1.0, 1.0, 1.0])[q] / (4.0 * CELL_GAUSS_2)
    s2 = np.array([-1.0, 1.0, -1.0, 1.0])[q] / (4.0 * CELL_GAUSS_2)
    assert np.array_equal(weight, want)
    assert np.array_equal(lx, np.bincount(cell, wq * sx, minlength=n) / want)
    assert np.array_equal(ly, np.bincount(cell, wq * sy, minlength=n) / want)
    assert np.array_equal(sides, np.column_stack([np.bincount(cell, s1 * sx, minlength=n),
                                                  np.bincount(cell, s1 * sy, minlength=n),
                                                  np.bincount(cell, s2 * sx, minlength=n),
                                                  np.bincount(cell, s2 * sy, minlength=n)]))
    assert cell_landings(np.arange(8), wt[:8], sx[:8], sy[:8], w4[:8], 2, rect.sides)[0]


def _hexagon_moment(radius, px, py):
    """∫ x^px y^py over the regular hexagon of circumradius ``radius`` with corners at
    30° + k·60° (the lattice of pitch √3·radius whose neighbours lie at k·60°), exactly: the
    hexagon is a rectangle |x| ≤ h, |y| ≤ radius/2 and two triangles above and below, h =
    radius·√3/2 (polynomials integrated in closed form by numpy's)."""
    from numpy.polynomial import polynomial as P

    h = radius * math.sqrt(3.0) / 2.0
    total = 0.0
    # |y| ≤ radius − |x|/√3 for |x| ≤ h: ∫ x^px [y^(py+1)/(py+1)] between the two bounds
    for sign in (1.0, -1.0):  # x ≥ 0 and x ≤ 0 halves
        top = np.array([radius, -sign / math.sqrt(3.0)])  # y_max(x) as a polynomial in x
        ypow = P.polypow(top, py + 1)
        inner = (ypow - P.polypow(-top, py + 1)) / (py + 1)
        f = P.polymul(inner, np.r_[np.zeros(px), 1.0])
        anti = P.polyint(f)
        lo, hi = (0.0, h) if sign > 0 else (-h, 0.0)
        total += P.polyval(hi, anti) - P.polyval(lo, anti)
    return total


def test_hexagonal_cells_rule_integrates_cubics_exactly():
    # a regular hexagonal lattice (pitch 0.25 mm, neighbours at 0°, 60°, …, and a lattice
    # found with them at 0° and 120°): the whole cells' ring of six integrates every
    # monomial up to degree 3 over the nearest-node hexagon to rounding, against its closed
    # form; the quartic x⁴ it does not (the rule's degree). A lattice whose neighbours'
    # distances differ by 5 % gets no rule (its cells are sampled); a rectangular one the
    # 2 × 2 Gauss rule
    pitch = 0.25
    radius = pitch / math.sqrt(3.0)
    area = 1.5 * math.sqrt(3.0) * radius**2
    for b2 in ((0.5, math.sqrt(3.0) / 2.0), (-0.5, math.sqrt(3.0) / 2.0)):
        rule = ff.cell_rule(_lattice((0.3, 0.1), pitch * np.array([[1.0, b2[0]], [0.0, b2[1]]])))
        assert rule is not None and not rule.rect and len(rule.points) == 6
        assert rule.weights.sum() == pytest.approx(1.0, abs=1e-15)
        x, y = rule.points.T
        for px in range(4):
            for py in range(4 - px):
                want = _hexagon_moment(radius, px, py) / area
                got = float((rule.weights * x**px * y**py).sum())
                assert got == pytest.approx(want, abs=1e-15 + 1e-12 * radius ** (px + py)), (
                    px, py)
        quartic = float((rule.weights * x**4).sum())
        assert abs(quartic / (_hexagon_moment(radius, 4, 0) / area) - 1.0) > 0.1
        # the corners: the hexagon's, at radius R, 60° apart
        assert np.allclose(np.hypot(*rule.corners.T), radius)
    stretched = pitch * np.array([[1.0, 0.5], [0.0, 1.05 * math.sqrt(3.0) / 2.0]])
    assert ff.cell_rule(_lattice((0.0, 0.0), stretched)) is None
    rect = ff.cell_rule(_lattice((0.0, 0.0), pitch * np.eye(2)))
    assert rect.rect and len(rect.points) == 4


def test_samples_left_to_whole_cells_are_the_rest_of_the_sub_grid():
    # cell_samples with cells marked whole (rectangular and hexagonal lattices, a bent map)
    # against its own output without them, filtered here by the rule: on a rectangular
    # lattice exactly the samples whose nearest node is not whole, in order and to the bit;
    # on a hexagonal one a sample with a whole nearest node keeps only its share in a
    # neighbour that is not (placed on that node), one beside a whole neighbour only its own
    # share, and one between two whole cells none
    from lfcam.measure.kernels import cell_samples

    scale, kappa, centre = 8.0, 0.3, (0.3, -0.2)
    cx, cy = _radial_map(scale, kappa, centre)
    reach = scale * (1.0 + kappa) + 2.0
    boxes = np.array([[centre[0] - reach, centre[0] + reach, centre[1] - reach,
                       centre[1] + reach]])
    disc = np.array([[centre[0], centre[1], reach]])
    origin = np.array([0.1, 0.05])
    n = 4
    share_spacing = ff.CELL_SHARE / n
    for basis in (np.eye(2), np.array([[1.0, 0.5], [0.0, math.sqrt(3.0) / 2.0]])):
        inv = np.linalg.inv(basis)
        lat = _lattice(origin, basis)
        i0, j0, ni, nj = -24, -24, 49, 49
        grid = np.array([[i0, j0, ni, nj, 0]])
        ii, jj = np.meshgrid(np.arange(ni) + i0, np.arange(nj) + j0, indexing="ij")
        whole = ((ii - 0.7) ** 2 + (jj + 0.4) ** 2 < 30.0) & ((ii + jj) % 7 != 3)  # (holes)
        none = (np.zeros((1, 5), dtype=np.int64), np.zeros(1, dtype=bool))
        shape = ff._cell_shape(lat)
        spacing_shape = (share_spacing, shape[2], shape[0], shape[1])  # (…, rect, la, lb)
        u0, v0, w0, _, _, _, _ = cell_samples(cx[None], cy[None], boxes, disc, origin, basis,
                                              inv, n, *none, *spacing_shape)
        u, v, w, _, _, tx, ty = cell_samples(cx[None], cy[None], boxes, disc, origin, basis,
                                             inv, n, grid, whole.ravel(), *spacing_shape)
        r0 = np.hypot(u0, v0)
        x0 = centre[0] + scale * (1.0 + kappa * r0 * r0) * u0  # the samples' MLA points
        y0 = centre[1] + scale * (1.0 + kappa * r0 * r0) * v0
        n1x, n1y, n2x, n2y, gap = ff._two_cells(lat, x0, y0)

        w1, w2 = (whole[tuple(np.rint(inv @ np.vstack([nx - origin[0], ny - origin[1]]))
                              .astype(int) - np.array([[i0], [j0]]))]
                  for nx, ny in ((n1x, n1y), (n2x, n2y)))
        if basis[0, 1] == 0.0:
            keep = ~w1
            assert np.array_equal(u, u0[keep]) and np.array_equal(w, w0[keep])
            assert tx.size == 0
            continue
        share = np.clip(0.5 - gap / share_spacing, 0.0, 0.5)
        keep = ~(w1 & ((share == 0.0) | w2))
        fac = np.where(w1, share, np.where(w2 & (share > 0.0), 1.0 - share, 1.0))[keep]
        assert np.count_nonzero(w1 & ~keep) > 1000  # (whole cells' samples left out)
        assert np.count_nonzero((fac > 0.0) & (fac < 1.0)) > 100  # (border samples)
        assert np.allclose(u, u0[keep], rtol=0, atol=1e-12)
        assert np.allclose(w, w0[keep] * fac, rtol=1e-12, atol=0)
        moved = np.isfinite(tx)
        assert np.array_equal(moved, fac < 1.0)
        to = np.where(w1[keep], n2x[keep], n1x[keep]), np.where(w1[keep], n2y[keep],
                                                                n1y[keep])
        assert np.allclose(tx[moved], to[0][moved]) and np.allclose(ty[moved], to[1][moved])


def _hexagonal_blur(monkeypatch):
    """System 2 with a hexagonal MLA and a point at 3400 mm behind a 1 m focus (~580 lit
    lenslets): profile, geometry, moments box, the point, and its moments with every cell
    sampled 24 × 24 (normalised)."""
    prof = apply_overrides(load_profile("system2"),
                           {**CAMERA, "mla": {"focus_mm": 1000.0, "grid": "hex"}})
    geom = truth_geometry(prof, (SIZE, SIZE))
    mom = _moments_box(prof, geom)
    pts = _line_points(prof, 3400.0, count=1)
    monkeypatch.setattr(ff, "CELLS_WHOLE", False)
    want = _normalised(ff.LensletModel(prof, geom, mom, 1000, cells=24).simulate(pts))
    return prof, geom, mom, pts, want


def test_whole_hexagonal_cells_keep_a_large_blurs_moments(monkeypatch):
    # system 2 with a hexagonal MLA, a point at 3400 mm behind a 1 m focus (~580 lit
    # lenslets): with the cells it lights whole integrated by the ring of six, the model's
    # moments stay as close to every cell sampled 24 × 24 as the sampled model's at n = 4
    # and 6 (measured 2.9e-3 and 1.9e-3; sampled 3.1e-3 and 1.4e-3) on a quarter of its
    # samples, and the pupil's area in all is π. Each hexagon's light spread as one
    # parallelogram of its second moments, and a rim cell's spread over pixels of two
    # lenslets by the product of its marginals, left 5.9e-3 at n = 6 (docs/distance.md,
    # "Whole hexagonal cells (stop 45)")
    prof, geom, mom, pts, want = _hexagonal_blur(monkeypatch)
    lit = np.count_nonzero(want[:, 0] > 0.05 * want[:, 0].max())
    sampled = {n: ff.LensletModel(prof, geom, mom, 1000, cells=n)._cell_samples(pts)[0].size
               for n in (4, 6)}
    monkeypatch.setattr(ff, "CELLS_WHOLE", True)
    monkeypatch.setattr(ff, "CELLS_RIM", False)  # (the rim's cells sampled: stop 45)
    for n, bound in ((4, 3.5e-3), (6, 2.5e-3)):
        model = ff.LensletModel(prof, geom, mom, 1000, cells=n)
        assert model.whole and not model.rule.rect
        got = _normalised(model.simulate(pts))
        assert not model.folded
        u, _, w, _, _, _, _, whole, _ = model._cell_samples(pts)
        assert whole[0].size > 0.7 * lit  # (measured 433 of 579)
        assert u.size < 0.3 * sampled[n]  # (measured 0.26, 0.25)
        assert abs((w.sum() + whole[5].sum()) / math.pi - 1.0) < 1e-4
        assert np.linalg.norm(got - want) / np.linalg.norm(want) < bound
    # without the coarse rule n = 2 stays sampled on a hexagonal lattice (four samples a cell
    # against six points)
    monkeypatch.setattr(ff, "CELLS_COARSE_HEX", False)
    assert not ff.LensletModel(prof, geom, mom, 1000, cells=2).whole


def test_whole_cell_spread_across_a_slanted_label_border_is_a_dense_samples():
    # a hexagonal cell's landing piece (a sheared parallelogram) across two lenslets' pixels
    # whose border runs diagonally: each pixel's share of it, cut into CELL_SPLIT² pieces,
    # within 4e-3 of 57 600 samples of it binned to their pixels (measured ≤ 7.2e-4 cut
    # 3 × 3, ≤ 3.3e-3 cut 4 × 4; the product of the whole parallelogram's marginals, as a
    # rectangular cell's, 0.02-0.06 off)
    labels = np.zeros((12, 12), dtype=np.int64)
    rr, cc = np.mgrid[0:12, 0:12]
    labels[(rr + cc) > 11] = 1
    centres = np.array([[3.0, 3.0], [9.0, 9.0]])
    for spot, e in (((5.6, 5.7), (1.1, 0.35, -0.3, 0.8)), ((5.9, 5.4), (0.8, 0.0, 0.4, 0.69)),
                    ((5.7, 5.6), (0.9, -0.5, 0.1, 0.7))):
        # (as a hexagonal cell's piece: one, the parallelogram itself, e its map's columns)
        out, ref = _deposit_pair(spot, e, labels, centres,
                                 pieces=np.array([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]]))
        assert 0.3 < ref[0, 0] < 0.7  # (the border cuts it)
        assert np.abs(out[:, 0] - ref[:, 0]).max() < 4e-3


def test_large_point_on_a_hexagonal_lattice_steps_with_the_fine_models_jacobian():
    # system 2 with a hexagonal MLA, a point at 3500 mm on the axis behind a 1 m focus (~650
    # lenslets), the data a 2 000 000-ray model's moments at the source: a hexagonal cell's
    # borders cut n = 2's sub-cells, so the steps after the coarse stage take the fine cells
    # model's own Jacobian (as the line fit's). On n = 2's the cells' fit came out +0.87 % and
    # the rays' answer from it +0.17 % (measured with the fine model's: +0.087 % and
    # +0.075 %; the rays alone, +0.06 %: their own sample's noise; docs/distance.md, "Whole
    # hexagonal cells (stop 45)")
    import dataclasses

    prof = apply_overrides(load_profile("system2"),
                           {**CAMERA, "mla": {"focus_mm": 1000.0, "grid": "hex"}})
    geom = truth_geometry(prof, (SIZE, SIZE))
    mom = _moments_box(prof, geom, half_px=330)
    frame = ff.SourceFrame(prof)
    src = np.array([0.0, 0.0, prof.main_lens.front_vertex_z_mm - 3500.0])
    dense = ff.LensletModel(prof, geom, mom, 2_000_000).simulate(src[None])
    mom = dataclasses.replace(mom, data=dense, norm=float(np.sqrt((dense * dense).sum())))
    stages = ff.point_fit_stages(prof, geom, np.zeros((SIZE, SIZE)), None, mom=mom)
    first, fit = next(stages), next(stages)
    assert first.ok and fit.ok
    assert abs((frame.z_front - first.source_mm[2]) / 3500.0 - 1.0) < 1.5e-3
    assert abs((frame.z_front - fit.source_mm[2]) / 3500.0 - 1.0) < 1e-3


def _disc_polygon_area(poly, centre, radius):
    """Area of a convex polygon (V, 2) inside a disc, by quadrature over x of the overlap of
    the polygon's and the disc's vertical chords (scipy's adaptive quad, every corner and the
    disc's ends as breakpoints): independent of the kernel's line-cut."""
    from scipy.integrate import quad

    x, y = poly[:, 0] - centre[0], poly[:, 1] - centre[1]
    edges = list(zip(range(len(x)), np.roll(np.arange(len(x)), -1), strict=True))

    def chord(t):
        ys = []
        for a, b in edges:
            if (x[a] - t) * (x[b] - t) <= 0 and x[a] != x[b]:
                ys.append(y[a] + (t - x[a]) / (x[b] - x[a]) * (y[b] - y[a]))
        if len(ys) < 2 or abs(t) >= radius:
            return 0.0
        h = math.sqrt(radius * radius - t * t)
        return max(0.0, min(max(ys), h) - max(min(ys), -h))

    lo, hi = max(x.min(), -radius), min(x.max(), radius)
    if hi <= lo:
        return 0.0
    # (breakpoints: the corners and where the edges cross the circle, between which the
    # chord's length is smooth)
    marks = list(x)
    for a, b in edges:
        dx, dy = x[b] - x[a], y[b] - y[a]
        qa, qb = dx * dx + dy * dy, 2 * (x[a] * dx + y[a] * dy)
        qc = x[a] ** 2 + y[a] ** 2 - radius ** 2
        disc = qb * qb - 4 * qa * qc
        if disc > 0:
            marks += [x[a] + t * dx for t in ((-qb - math.sqrt(disc)) / (2 * qa),
                                              (-qb + math.sqrt(disc)) / (2 * qa)) if 0 < t < 1]
    cuts = sorted({lo, hi, *[v for v in marks if lo < v < hi]})
    return sum(quad(chord, a, b, epsabs=1e-13, limit=400)[0] for a, b in zip(cuts, cuts[1:],
                                                                          strict=False))


@pytest.mark.parametrize("kappa", [0.0, 0.3])
def test_rim_cut_keeps_each_cells_area_inside_the_rims_circle(kappa):
    # a radial map (the rim's image a circle of radius scale·(1 + κ), 14 pitches): every
    # hexagonal cell the circle crosses, cut by kernels._rim_cut along the rim's line,
    # against the cell's exact area inside the circle. The line is the tangent where the
    # chord is centred, moved in by a third of the curve's depth at the chord's ends: the
    # area a parabola keeps (docs/distance.md, "Rim cells cut by the rim's line (stop 46)")
    from lfcam.measure.kernels import _rim_cut

    scale, centre = 14.0 / (1.0 + kappa), (0.3, -0.2)
    cx, cy = _radial_map(scale, kappa, centre)
    basis = np.array([[1.0, 0.5], [0.0, math.sqrt(3.0) / 2.0]])
    origin = np.array([0.1, 0.05])
    rule = ff.cell_rule(_lattice(origin, basis))
    cell_area = abs(np.linalg.det(basis))
    radius = scale * (1.0 + kappa)
    worst, cut = 0.0, 0
    ox, oy = np.zeros(4), np.zeros(4)
    for i in range(-20, 21):
        for j in range(-20, 21):
            node = origin + basis @ [i, j]
            d = math.hypot(node[0] - centre[0], node[1] - centre[1])
            if abs(d - radius) > 0.7:
                continue
            poly = rule.polygon + node
            exact = _disc_polygon_area(poly, centre, radius)
            if not 1e-3 * cell_area < exact < (1.0 - 1e-3) * cell_area:
                continue
            # the node's pupil point and the map's inverse Jacobian there
            (u,), (v,) = _radial_preimage([node[0]], [node[1]], scale, kappa, centre)
            r2 = u * u + v * v
            jac = scale * ((1.0 + kappa * r2) * np.eye(2)
                           + 2.0 * kappa * np.outer([u, v], [u, v]))
            inv = np.linalg.inv(jac)
            got = _rim_cut(cx, cy, node[0], node[1], u, v, inv[0, 0], inv[0, 1], inv[1, 0],
                           inv[1, 1], rule.polygon, len(rule.polygon), np.empty((9, 2)), ox, oy,
                           0, cell_area)
            worst = max(worst, abs(got - exact) / cell_area)
            cut += 1
    assert cut > 60  # (a ring of 14 pitches crosses ~90 cells)
    assert worst < 2e-4  # (measured 8.3e-5 of a cell)


def test_rim_cells_moment_rule_integrates_quadratics_exactly():
    # a hexagon with a corner cut off (counter-clockwise): kernels._moment_rule's four points
    # and the area against the polygon's exact integrals of 1, x, y, x², xy, y², from a fan
    # of triangles each integrated by its edge midpoints (exact for quadratics on a
    # triangle); a cubic it does not integrate (its degree)
    from lfcam.measure.kernels import RIM_SIDES, _moment_rule

    ang = np.radians(30.0 + 60.0 * np.arange(6))
    hexagon = 0.3 * np.column_stack([np.cos(ang), np.sin(ang)])
    cut = [hexagon[0] + 0.4 * (hexagon[1] - hexagon[0]),
           hexagon[1] + 0.7 * (hexagon[2] - hexagon[1])]  # (a line across corner 1)
    poly = np.vstack([hexagon[:1], cut, hexagon[2:]]) + [0.04, -0.02]
    ox, oy = np.zeros(4), np.zeros(4)
    area = _moment_rule(poly, len(poly), ox, oy, 0)

    def exact(f):
        total = 0.0
        for k in range(1, len(poly) - 1):
            a, b, c = poly[0], poly[k], poly[k + 1]
            tri = 0.5 * abs((b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]))
            mids = [(a + b) / 2, (b + c) / 2, (c + a) / 2]
            total += tri * sum(f(*m) for m in mids) / 3.0
        return total

    assert area == pytest.approx(exact(lambda x, y: 1.0), rel=1e-13)
    for f in (lambda x, y: x, lambda x, y: y, lambda x, y: x * x, lambda x, y: x * y,
              lambda x, y: y * y, lambda x, y: (x - 0.1) * (y + 0.3)):
        got = area / 4.0 * sum(f(px, py) for px, py in zip(ox, oy, strict=True))
        assert got == pytest.approx(exact(f), rel=1e-12, abs=1e-15)
    # (the cubic: the fan's rule is not exact for it either, so the polygon's own x³ by its
    # Green's theorem sum: Σ (x₀ + x₁)(x₀² + x₁²) · cross / 20)
    x0, y0 = poly[:, 0], poly[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    cubic = float(np.sum((x0 + x1) * (x0 * x0 + x1 * x1) * (x0 * y1 - x1 * y0)) / 20.0)
    assert abs(area / 4.0 * np.sum(ox**3) / cubic - 1.0) > 0.01
    # its rectangle: sides √6/2 × the differences across each pair, so a uniform rectangle
    # of those sides has the polygon's second moments
    sides = RIM_SIDES.T @ np.column_stack([ox, oy])
    rect_cov = (sides.T @ sides) / 12.0
    cov = np.array([[exact(lambda x, y: x * x), exact(lambda x, y: x * y)],
                    [exact(lambda x, y: x * y), exact(lambda x, y: y * y)]]) / area
    c = np.array([exact(lambda x, y: x), exact(lambda x, y: y)]) / area
    assert np.allclose(rect_cov, cov - np.outer(c, c), rtol=1e-10, atol=1e-15)


def _moments_error(monkeypatch, prof, geom, mom, pts, want, n, **flags):
    """The cells model's (n, whole cells, ``flags`` set on fastfit) normalised moments' error
    against ``want``: the norm of the difference over the norm."""
    monkeypatch.setattr(ff, "CELLS_WHOLE", True)
    for name, value in flags.items():
        monkeypatch.setattr(ff, name, value)
    model = ff.LensletModel(prof, geom, mom, 1000, cells=n)
    got = _normalised(model.simulate(pts))
    assert not model.folded
    return np.linalg.norm(got - want) / np.linalg.norm(want)


def test_hexagonal_rim_cells_cut_keep_a_large_blurs_moments(monkeypatch):
    # the blur above with the rim's cells cut by the rim's line (kernels._rim_cut) and
    # integrated by their 4-point rule: no sample left at n = 4, the pupil's area π to 1e-5
    # (measured 2e-6; 5e-7 with the first pass on the exact map), and the moments closer to
    # every cell sampled 24 × 24 than the rim sampled 4 × 4 (measured 1.9e-3 against
    # 2.9e-3; 6 × 6: 1.9e-3; docs/distance.md, "Rim cells cut by the rim's line (stop 46)")
    prof, geom, mom, pts, want = _hexagonal_blur(monkeypatch)
    err = {rim: _moments_error(monkeypatch, prof, geom, mom, pts, want, 4, CELLS_RIM=rim)
           for rim in (False, True)}
    model = ff.LensletModel(prof, geom, mom, 1000, cells=4)
    u, _, w, _, _, _, _, whole, _ = model._cell_samples(pts)
    assert u.size == 0 and whole[8].size > 60  # (measured 84 cut cells)
    assert abs((whole[5].sum() + whole[13].sum()) / math.pi - 1.0) < 1e-5
    assert err[True] < 2.3e-3
    assert err[True] < 0.75 * err[False]


def test_hexagonal_coarse_rule_and_its_parallelogram_keep_the_hexagons_moments():
    # CellRule.coarse, n = 2's rule on a hexagonal lattice: three points integrate every
    # polynomial up to degree 2 over the hexagon (closed form), not its cubics; the parallelogram
    # its light is spread over, its sides the landing's linear map (here the identity) of
    # the side coefficients, has the hexagon's second moments
    pitch = 0.25
    radius = pitch / math.sqrt(3.0)
    area = 1.5 * math.sqrt(3.0) * radius**2
    for b2 in ((0.5, math.sqrt(3.0) / 2.0), (-0.5, math.sqrt(3.0) / 2.0)):
        rule = ff.cell_rule(_lattice((0.3, 0.1), pitch * np.array([[1.0, b2[0]], [0.0, b2[1]]])))
        coarse = rule.coarse
        assert len(coarse.points) == 3 and coarse.pieces.shape[0] == 0
        x, y = coarse.points.T
        for px in range(3):
            for py in range(3 - px):
                want = _hexagon_moment(radius, px, py) / area
                got = float((coarse.weights * x**px * y**py).sum())
                assert got == pytest.approx(want, abs=1e-15 + 1e-12 * radius ** (px + py))
        cubics = [abs(float((coarse.weights * x**a * y**(3 - a)).sum())) for a in range(4)]
        assert max(cubics) > 0.01 * radius**3  # (the hexagon's are all 0)
        sides = coarse.sides.T @ coarse.points  # (2, 2): each side, landing = the MLA offset
        cov = sum(np.outer(v, v) for v in sides) / 12.0  # a uniform parallelogram's
        want = np.array([[_hexagon_moment(radius, 2, 0), _hexagon_moment(radius, 1, 1)],
                         [_hexagon_moment(radius, 1, 1), _hexagon_moment(radius, 0, 2)]]) / area
        assert np.allclose(cov, want, rtol=1e-12, atol=1e-18)


def test_hexagonal_coarse_model_is_closer_to_a_dense_sample(monkeypatch):
    # the large hexagonal blur: n = 2 with the coarse rule and the rim's cut cells against
    # every cell sampled 24 × 24 (measured 7.3e-3; n = 2 sampled 4.7e-2)
    prof, geom, mom, pts, want = _hexagonal_blur(monkeypatch)
    err = {coarse: _moments_error(monkeypatch, prof, geom, mom, pts, want, 2,
                                  CELLS_COARSE_HEX=coarse)
           for coarse in (False, True)}
    assert ff.LensletModel(prof, geom, mom, 1000, cells=2).whole  # (and without it, not)
    assert err[True] < 1e-2 and err[True] < 0.3 * err[False]


@pytest.mark.parametrize("scale, resolved", [(14.0, True), (2.5, False)])
def test_a_point_whose_nodes_are_all_resolved_has_nothing_left_to_sample(scale, resolved):
    # cell_centres with the rim's cut cells on a hexagonal lattice and a bent radial map: a
    # blur 14 pitches across has every node whole, cut or dark (unresolved 0), and
    # cell_samples over its whole box, with the skip table, indeed returns no sample; a blur
    # 2.5 pitches across has patches over CELL_WHOLE_MAX_PATCH, nodes left, and samples
    from lfcam.measure.kernels import CELL_WHOLE_MARGIN, cell_centres

    kappa, centre = 0.3, (0.3, -0.2)
    cx, cy = _radial_map(scale, kappa, centre)
    basis = np.array([[1.0, 0.5], [0.0, math.sqrt(3.0) / 2.0]])
    origin = np.array([0.1, 0.05])
    rule = ff.cell_rule(_lattice(origin, basis))
    reach = scale * (1.0 + kappa) + 2.0
    boxes = np.array([[centre[0] - reach, centre[0] + reach, centre[1] - reach,
                       centre[1] + reach]])
    disc = np.array([[centre[0], centre[1], reach]])
    inv = np.linalg.inv(basis)
    out = cell_centres(cx[None], cy[None], boxes, disc, origin, basis, inv, CELL_WHOLE_MARGIN,
                       rule.corners, rule.points, rule.weights, rule.polygon)
    shape = ff._cell_shape(_lattice(origin, basis))
    u, v, w, *_ = cell_samples(cx[None], cy[None], boxes, disc, origin, basis, inv, 4,
                               out[6], out[7], ff.CELL_SHARE / 4, shape[2], shape[0], shape[1])
    assert (out[14][0] == 0) == resolved
    assert (u.size == 0) == resolved
    # the pupil's area in all: whole cells, cut cells and samples
    assert abs((out[5].sum() + out[13].sum() + w.sum()) / math.pi - 1.0) < 2e-3


def test_one_to_one_reads_the_radial_maps_fold_and_squeeze_analytically():
    # X = s·(1 + κ r²)·u: |det| = s²·(1 + κ r²)(1 + 3κ r²), zero at r² = −1/(3κ). With κ = −0.3
    # it stays positive on the disc (at the rim 0.7 · 0.1 = 0.07 of its centre's); with
    # κ = −0.34 it changes sign at r = 0.99 (a fold inside the rim); with κ = −0.325 its rim's
    # |det| is 0.675 · 0.025 = 0.017 of the centre's, under FOLD_MIN_DET_RATIO (0.03): the
    # cells could not resolve that squeeze. Behind focus the map is turned over (s < 0).
    cases = ((0.6, -0.3, True), (-0.6, -0.3, True), (0.6, -0.34, False), (-0.6, -0.34, False),
             (0.6, -0.325, False), (0.6, 0.5, True))
    for scale, kappa, want in cases:
        cx, cy = _radial_map(scale, kappa, (1.5, -0.7))
        assert bool(ff._one_to_one(cx[None], cy[None])[0]) is want, (scale, kappa)


def test_one_to_one_agrees_with_a_dense_exact_trace_of_the_pupils_diameter():
    # system 2 on the axis, a 1 m focus: in front of it the MLA cuts the caustic of the lens's
    # spherical aberration (the landing along a pupil diameter turns back inside the rim:
    # at 380 mm near r = 0.95), far in front and behind focus it does not. Each point's
    # polynomial map is fitted to its ring of traced rays (as the model's); the truth is 401
    # rays traced exactly along the diameter, monotone or not
    from lfcam.measure.kernels import trace_model_rays

    prof, geom = _system2()
    lens = prof.main_lens
    packed = ff._packed_lens(lens)
    half = 0.5 * lens.pupil_diameter_mm
    ring, pinv, _ = ff._cell_ring()
    args = (packed.table, packed.coef, float(lens.front_vertex_z_mm), float(lens.rim_z_mm),
            float(geom.d_in_mm), float(prof.mla.focal_length_mm))
    u = np.linspace(-1.0, 1.0, 401)
    seen = []
    for d in (250.0, 300.0, 380.0, 420.0, 560.0, 2200.0, 3400.0):
        pts = np.array([[0.0, 0.0, lens.front_vertex_z_mm - d]])
        maps = ff.compiled_pupil_maps(lens, pts, packed)
        x = trace_model_rays(pts, maps, np.array([[1.0, 0.0]]), u * half, 0.0 * u, *args)[0]
        steps = np.diff(x)
        monotone = bool(np.all(steps > 0) or np.all(steps < 0))
        xr, yr = trace_model_rays(pts, maps, np.array([[1.0, 0.0]]), ring[:, 0] * half,
                                  ring[:, 1] * half, *args)[:2]
        got = bool(ff._one_to_one((pinv @ xr)[None], (pinv @ yr)[None])[0])
        assert got is monotone, d
        seen.append(got)
    assert seen == [True, True, False, False, False, True, True]  # (both kinds are tested)
