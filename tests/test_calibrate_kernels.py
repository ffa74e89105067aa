"""The own-light fit's compiled seam passes (:mod:`lfcam.calibrate.kernels`) against the numpy
chains they replaced (written out here as the reference), on random lenses, including
repeated seam pixels (neighbouring lenses) and cut discs."""

from __future__ import annotations

import numpy as np
import pytest

from lfcam.calibrate import kernels


@pytest.fixture(scope="module")
def lenses():
    rng = np.random.default_rng(7)
    h, w, half = 60, 80, 8
    wp = w
    off = np.arange(-half, half + 1)
    ox, oy = (a.ravel() for a in np.meshgrid(off, off))
    g = np.hypot(ox, oy)
    seam = (g > 4.0) & (g < 8.0) & (ox > -2)  # any subset of the patch will do
    outer = (g > 4.0) & (g < 8.0) & ~seam
    lin = (oy * wp + ox).astype(np.int64)
    n = 40
    base = np.column_stack([rng.integers(10, w - 10, n), rng.integers(10, h - 10, n)])
    base[1] = base[0] + [3, 2]  # overlapping patches: seam pixels repeat across lenses
    f32 = np.float32
    d = dict(
        n=n, ns=int(seam.sum()),
        bflat=(base[:, 1] * wp + base[:, 0]).astype(np.int64),
        lin_s=lin[seam], oxs=ox[seam].astype(f32), oys=oy[seam].astype(f32),
        oxo=ox[outer].astype(f32), oyo=oy[outer].astype(f32),
        frac=rng.uniform(-0.6, 0.6, (n, 2)).astype(f32),
        coef=np.column_stack([rng.uniform(50, 100, n), rng.uniform(-3, 3, (n, 2))]).astype(f32),
        sup=f32(6.3), inv2w=f32(0.5 / 0.8),
        flat=rng.uniform(0.0, 120.0, h * w).astype(f32),
    )
    d["plane"] = np.maximum(d["coef"][:, :1] + d["coef"][:, 1:2] * d["oxs"]
                            + d["coef"][:, 2:] * d["oys"], 0.0).astype(f32)
    d["p_s"] = d["flat"][d["bflat"][:, None] + d["lin_s"]]
    d["p_o"] = d["flat"][d["bflat"][:, None] + lin[outer]]
    d["lin"] = lin
    return d


def _model(d, k):
    ux = d["oxs"] - d["frac"][k, :1]
    uy = d["oys"] - d["frac"][k, 1:]
    t = np.clip((d["sup"] - np.sqrt(ux * ux + uy * uy)) * d["inv2w"], 0.0, 1.0)
    return t * d["plane"][k]


def test_seam_models_and_scatter_are_the_numpy_definition(lenses):
    d = lenses
    n, ns = d["n"], d["ns"]
    m_cur = np.random.default_rng(1).uniform(0, 50, (n, ns)).astype(np.float32)
    m_ref = m_cur.copy()
    total = np.zeros(d["flat"].size, np.float32)
    ref = np.zeros(d["flat"].size, np.float64)
    ks = np.arange(3, n, 2)
    delta = np.empty((ks.size, ns), np.float32)
    kernels.seam_models(ks, d["frac"], d["oxs"], d["oys"], d["sup"], d["inv2w"], d["coef"],
                        m_cur, delta)
    kernels.scatter_seams(total, d["bflat"], ks, d["lin_s"], delta)
    mk = _model(d, ks)
    np.testing.assert_allclose(m_cur[ks], mk, rtol=1e-6, atol=1e-5)
    untouched = np.setdiff1d(np.arange(n), ks)
    assert np.array_equal(m_cur[untouched], m_ref[untouched])
    np.testing.assert_allclose(delta, mk - m_ref[ks], rtol=1e-6, atol=1e-4)
    np.add.at(ref, d["bflat"][ks, None] + d["lin_s"], (mk - m_ref[ks]).astype(np.float64))
    np.testing.assert_allclose(total, ref, rtol=1e-5, atol=1e-3)
    assert np.count_nonzero(total) > ks.size * ns // 2  # the scatter reached the pixels


def test_patch_gathers_and_sums_are_the_definition(lenses):
    d = lenses
    h, w = 60, 80
    image = d["flat"].reshape(h, w)
    base = np.array([[5, 5], [40, 30], [78, 2], [0, 59], [-3, 70], [30, 20]], np.int64)
    ks = np.array([0, 1, 2, 3, 4], np.int64)  # (lens 5 not asked for)
    off = np.arange(-8, 9)
    ox, oy = (a.ravel().astype(np.int64) for a in np.meshgrid(off, off))
    out = np.full((len(base), ox.size), -1.0, np.float32)
    kernels.gather_patch(image, base, ks, ox, oy, out)
    x, y = base[ks, :1] + ox, base[ks, 1:] + oy
    on = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    ref = np.where(on, image[np.clip(y, 0, h - 1), np.clip(x, 0, w - 1)], 0.0)
    assert np.array_equal(out[ks], ref)
    assert np.all(out[5] == -1.0)
    assert (~on).any(axis=1)[[0, 2, 3, 4]].all() and not on[4].any()  # cut, and all off
    got = kernels.patch_sums(image, base, ks, ox, oy)
    pix = ref.astype(np.float64)
    np.testing.assert_allclose(got, np.stack([pix.sum(1), pix @ ox, pix @ oy], axis=1),
                               rtol=1e-12, atol=1e-9)


def test_own_light_sums_are_the_numpy_definition(lenses):
    d = lenses
    n = d["n"]
    ks = np.arange(n, dtype=np.int64)
    m_cur = np.stack([_model(d, np.array([k]))[0] for k in range(n)]).astype(np.float32)
    m_cur[4] = 0.0  # a lens with no model: its seam share is 0, not NaN
    total = np.zeros(d["flat"].size, np.float32)
    np.add.at(total, d["bflat"][:, None] + d["lin_s"], m_cur)
    got = kernels.own_light_sums(ks, d["frac"], d["sup"], m_cur, total, d["bflat"], d["lin_s"],
                                 d["p_s"], d["oxs"], d["oys"], d["p_o"], d["oxo"], d["oyo"])
    big = np.maximum(np.maximum(total[d["bflat"][:, None] + d["lin_s"]], m_cur), 1e-30)
    q = d["p_s"].astype(np.float64) * m_cur / big
    ux, uy = d["oxo"] - d["frac"][:, :1], d["oyo"] - d["frac"][:, 1:]
    po = d["p_o"] * (ux * ux + uy * uy < d["sup"] ** 2)
    ref = np.stack([q.sum(1) + po.sum(1), q @ d["oxs"] + po @ d["oxo"],
                    q @ d["oys"] + po @ d["oyo"]], axis=1)
    scale = np.abs(ref).max(axis=0)  # the shares are float32: ~1e-7 of each sum's scale
    np.testing.assert_allclose(got / scale, ref / scale, atol=1e-6)
    shared = q[1] < d["p_s"][1] * (m_cur[1] > 0) - 1e-3  # lens 1 shares seams with lens 0
    assert shared.any()


def test_edge_sums_are_the_numpy_definition(lenses):
    d = lenses
    n = d["n"]
    rng = np.random.default_rng(3)
    ks = np.arange(n, dtype=np.int64)
    total = (d["flat"] * 0.7).astype(np.float32)
    cut_row = np.full(n, -1, np.int64)
    cut_row[[2, 11]] = [0, 1]
    ins_s = rng.random((2, d["ns"])) < 0.6
    ins_o = rng.random((2, d["oxo"].size)) < 0.6
    got = kernels.edge_sums(ks, d["frac"], d["coef"], d["sup"], d["inv2w"], total, d["bflat"],
                            d["lin_s"], d["p_s"], d["oxs"], d["oys"], d["p_o"], d["oxo"],
                            d["oyo"], cut_row, ins_s, ins_o)
    cf = d["coef"].astype(np.float64)
    ref = np.zeros((n, 5))
    for ox_, oy_, seam in ((d["oxs"], d["oys"], True), (d["oxo"], d["oyo"], False)):
        ux = (ox_ - d["frac"][:, :1]).astype(np.float64)
        uy = (oy_ - d["frac"][:, 1:]).astype(np.float64)
        dist = np.sqrt(ux * ux + uy * uy)
        t = (float(d["sup"]) - dist) * float(d["inv2w"])
        band = (t > 0) & (t < 1)
        b = (d["plane"].astype(np.float64) if seam else
             np.maximum(cf[:, 1:2] * ox_ + cf[:, 2:] * oy_ + cf[:, :1], 0.0))
        gsc = b / np.maximum(dist, 1e-6) * float(d["inv2w"]) * band
        t = np.clip(t, 0.0, 1.0)
        r = (d["p_s"] - total[d["bflat"][:, None] + d["lin_s"]] if seam
             else d["p_o"] - b * t)
        on = np.ones_like(t)
        on[[2, 11]] = ins_s if seam else ins_o
        gsc, t = gsc * on, t * on
        jx = gsc * ux - cf[:, 1:2] * t
        jy = gsc * uy - cf[:, 2:] * t
        ref += np.stack([(jx * jx).sum(1), (jy * jy).sum(1), (jx * jy).sum(1),
                         (jx * r).sum(1), (jy * r).sum(1)], axis=1)
    scale = np.abs(ref).max(axis=0)
    np.testing.assert_allclose(got / scale, ref / scale, atol=2e-5)
    # the cut discs' masks matter: without them the sums differ
    full = kernels.edge_sums(ks, d["frac"], d["coef"], d["sup"], d["inv2w"], total, d["bflat"],
                             d["lin_s"], d["p_s"], d["oxs"], d["oys"], d["p_o"], d["oxo"],
                             d["oyo"], np.full(n, -1, np.int64), ins_s, ins_o)
    assert np.abs(full[2] - got[2]).max() > 1e-2 * scale.max()
    assert np.array_equal(full[3], got[3])


@pytest.fixture(scope="module")
def discs():
    """Overlapping discs on a small sensor, some cut by its border."""
    from lfcam.calibrate.microimage import DiscModel

    rng = np.random.default_rng(11)
    h, w = 70, 90
    gx, gy = np.meshgrid(np.arange(-6.0, w + 6, 11.0), np.arange(-6.0, h + 6, 9.5))
    c = np.column_stack([gx.ravel(), gy.ravel()]) + rng.uniform(-0.7, 0.7, (gx.size, 2))
    coef = np.column_stack([rng.uniform(80, 120, len(c)), rng.uniform(-2, 2, (len(c), 2))])
    image = rng.uniform(0.0, 150.0, (h, w))
    return dict(h=h, w=w, c=c, coef=coef, image=image, model=DiscModel(6.2, 0.9, 0.0))


def test_disc_models_are_the_numpy_definition(discs):
    from lfcam.calibrate.microimage import _disc_terms, _Patches

    d = discs
    m = d["model"]
    half = m.patch_half_px()
    total = np.zeros(d["h"] * d["w"])
    kernels.disc_models(d["h"], d["w"], d["c"], d["coef"].astype(np.float32), half,
                        np.float32(m.support_px), np.float32(0.5 / m.edge_px), total)
    p = _Patches((d["h"], d["w"]), d["c"], half)
    _, _, _, cov, _, b = _disc_terms(p, d["c"], d["coef"], m)
    mk = np.maximum(b, 0.0) * cov
    ref = np.bincount(p.flat[p.inside], weights=mk[p.inside], minlength=total.size)
    np.testing.assert_allclose(total, ref, rtol=1e-6, atol=1e-6 * ref.max())
    assert ref.max() > 150.0  # overlapping: seams hold two discs' light


def test_disc_step_sums_are_the_numpy_definition(discs):
    from lfcam.calibrate.microimage import _disc_terms, _Patches

    d = discs
    m = d["model"]
    half = m.patch_half_px()
    flat = d["image"].ravel()
    total = np.random.default_rng(2).uniform(0.0, 150.0, flat.size)
    ks = np.arange(len(d["c"]), dtype=np.int64)
    got = kernels.disc_step_sums(d["h"], d["w"], d["c"], d["coef"].astype(np.float32), half,
                                 np.float32(m.support_px), np.float32(0.5 / m.edge_px), flat,
                                 total, ks)
    p = _Patches((d["h"], d["w"]), d["c"], half)
    dx, dy, dist, cov, band, b = _disc_terms(p, d["c"], d["coef"], m)
    n = len(dx)
    r = np.where(p.inside, flat[p.flat] - total[p.flat], 0.0).astype(np.float64)
    inv = np.where(band, b / (2.0 * m.edge_px * np.where(dist > 0, dist, 1.0)), 0.0)
    cf = d["coef"]
    jx = (-cf[:, 1, None, None] * cov + dx * inv).reshape(n, -1).astype(np.float64)
    jy = (-cf[:, 2, None, None] * cov + dy * inv).reshape(n, -1).astype(np.float64)
    rr = r.reshape(n, -1)
    ref = np.stack([(jx * jx).sum(1), (jy * jy).sum(1), (jx * jy).sum(1), (jx * rr).sum(1),
                    (jy * rr).sum(1)], axis=1)
    scale = np.abs(ref).max(axis=0)
    np.testing.assert_allclose(got / scale, ref / scale, atol=2e-6)
    assert np.count_nonzero(got[:, 0] > 0) >= len(got) - 2  # (a corner disc is off-sensor)


def test_core_plane_sums_are_the_definition(discs):
    d = discs
    half, core = 8, 4.3
    flat = d["image"].ravel()
    got = kernels.core_plane_sums(d["h"], d["w"], d["c"], half, core, flat)
    ys, xs = np.mgrid[0:d["h"], 0:d["w"]]
    for k in range(len(d["c"])):
        cx, cy = d["c"][k]
        bx, by = np.rint(cx), np.rint(cy)
        dx, dy = xs - cx, ys - cy
        m = ((np.abs(xs - bx) <= half) & (np.abs(ys - by) <= half)
             & (np.hypot(dx, dy) < core)).ravel()
        dx, dy, v = dx.ravel()[m], dy.ravel()[m], flat[m]
        ref = [m.sum(), dx.sum(), dy.sum(), (dx * dx).sum(), (dx * dy).sum(), (dy * dy).sum(),
               v.sum(), (v * dx).sum(), (v * dy).sum()]
        np.testing.assert_allclose(got[k], ref, rtol=1e-12, atol=1e-9)
    assert np.any(got[:, 0] == 0) and np.any(got[:, 0] > 50)  # off-sensor and whole cores


def test_flat_score_is_the_numpy_chain():
    rng = np.random.default_rng(5)
    mean = rng.uniform(0.0, 100.0, (40, 50)).astype(np.float32)
    sq = (mean * mean + rng.uniform(-50.0, 400.0, mean.shape)).astype(np.float32)  # var < 0 too
    var = sq - mean * mean
    np.maximum(var, 0.0, out=var)
    np.sqrt(var, out=var)
    var *= 2.0
    ref = mean - var
    got = mean.copy()
    kernels.flat_score(got, sq)
    assert np.array_equal(got, ref)
    assert np.any(sq < mean * mean) and np.any(got < mean)


def test_projective_normal_is_the_jacobian_chain():
    """The projective fit's normal equations (one compiled pass) against the (2N × 8)
    Jacobian the fit built before, written out here, with zero and fractional weights."""
    rng = np.random.default_rng(11)
    ij = rng.integers(-300, 300, (500, 2)).astype(np.float64)
    h = np.array([[14.3, 7.1, 3800.0], [0.2, 12.4, 2700.0], [3e-6, -2e-6, 1.0]])
    q = ij @ h[:, :2].T + h[:, 2]
    x, y, z = q[:, 0] / q[:, 2], q[:, 1] / q[:, 2], q[:, 2]
    pts = np.column_stack([x, y]) + rng.normal(0.0, 0.05, (500, 2))
    w = rng.uniform(0.0, 1.0, 500)
    w[::7] = 0.0
    one, zero = np.ones(500), np.zeros(500)
    i, j = ij[:, 0], ij[:, 1]
    jx = np.column_stack([i / z, j / z, one / z, zero, zero, zero, -x * i / z, -x * j / z])
    jy = np.column_stack([zero, zero, zero, i / z, j / z, one / z, -y * i / z, -y * j / z])
    jac = np.vstack([jx, jy])
    res = np.concatenate([pts[:, 0] - x, pts[:, 1] - y])
    ww = np.concatenate([w, w])
    a, b = kernels.projective_normal(ij, pts, w, h)
    np.testing.assert_allclose(a, (jac * ww[:, None]).T @ jac, rtol=1e-12)
    np.testing.assert_allclose(b, (jac * ww[:, None]).T @ res, rtol=1e-10,
                               atol=1e-12 * np.abs((jac * ww[:, None]).T).sum(axis=1).max())
