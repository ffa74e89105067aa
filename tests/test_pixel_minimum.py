"""The pixel fit's last step: the minimum of a least-squares quadratic surface of the misfit²
and its delete-one-block jackknife σ (lfcam.measure.pointfit._surface_minimum)."""

import math

import numpy as np
import pytest

from lfcam.measure.pointfit import _quadratic_basis, _quadratic_vertices, _surface_minimum


def test_quadratic_vertex_of_a_known_quadratic():
    rng = np.random.default_rng(0)
    m = rng.normal(size=(3, 3))
    h = m @ m.T + 0.5 * np.eye(3)  # positive definite
    x0 = np.array([0.3, -0.2, 0.7])
    t = rng.normal(size=(30, 3))
    vals = 0.5 * np.einsum("ni,ij,nj->n", t - x0, h, t - x0) + 2.0
    coef = np.linalg.lstsq(_quadratic_basis(t), vals, rcond=None)[0]
    both = _quadratic_vertices(np.vstack([coef, -coef]))
    np.testing.assert_allclose(both[0], x0, atol=1e-10)
    assert np.isnan(both[1]).all()  # no minimum: a maximum


class _LinearPatch:
    """A patch whose residual is linear in the source, A·(s − s₀) + noise, with an optional
    roughness in the distance (the rendered model's pupil sampling) on top."""

    def __init__(self, a, s0, noise, rough=0.0, shape=(40, 40)):
        self.a, self.s0, self.noise, self.rough, self.shape = a, s0, noise, rough, shape
        self.pattern = np.random.default_rng(5).normal(size=a.shape[0])

    def residual(self, s):
        r = self.a @ (np.asarray(s) - self.s0) + self.noise
        return r + self.rough * math.sin(2 * math.pi * (s[2] - self.s0[2]) / 3.0) * self.pattern

    def misfit(self, s):
        r = self.residual(s)
        return float(math.sqrt(r @ r))


def _setup(seed):
    rng = np.random.default_rng(seed)
    n = 1600
    a = rng.normal(size=(n, 3)) * np.array([2e-3, 2e-3, 2e-5])  # distance: the weak direction
    scale = 1e-3 * np.geomspace(0.2, 5.0, n)[rng.permutation(n)]  # heteroscedastic noise
    s0 = np.array([40.0, -25.0, -2700.0])
    pupil = np.array([0.0, 0.0, 30.0])
    return rng, a, scale, s0, pupil


def test_surface_minimum_is_the_least_squares_answer_and_its_sigma_the_spread():
    # residual linear in the source: the misfit² is exactly quadratic, its minimum the linear
    # least-squares answer (analytic); over noise draws the jackknife σ of the distance must
    # average to the analytic σ, (AᵀA)⁻¹Aᵀ Σ A(AᵀA)⁻¹, within 15 %
    rng, a, scale, s0, pupil = _setup(1)
    inv = np.linalg.inv(a.T @ a)
    true_sigma = math.sqrt((inv @ a.T @ np.diag(scale**2) @ a @ inv)[2, 2])
    sig, err = [], []
    for _ in range(60):
        noise = rng.normal(size=len(scale)) * scale
        lsq = s0 - inv @ a.T @ noise
        start = lsq + np.array([0.05, -0.03, 0.8 * true_sigma])
        f0 = math.sqrt(float(np.sum((a @ (start - s0) + noise) ** 2)))
        axis = start - pupil
        curv = float(np.sum((a @ axis) ** 2)) / f0
        src, _, s = _surface_minimum(_LinearPatch(a, s0, noise), pupil, start, f0, curv, 4)
        err.append(abs(src[2] - lsq[2]))
        sig.append(s)
    assert max(err) < 1e-6 * true_sigma * 1e3  # the exact minimum (to rounding)
    assert np.mean(sig) == pytest.approx(true_sigma, rel=0.15)


def test_surface_minimum_averages_out_a_rough_model():
    # a roughness of 3 mm period in the distance (0.7 % of the misfit², like the rendered
    # model's pupil sampling): a descent from a start 2 mm off (0.8σ) stays in its dip; the
    # surface spans several periods and lands within a quarter of the analytic σ of the
    # least-squares answer, and its jackknife σ stays within 30 % of that σ
    rng, a, scale, s0, pupil = _setup(2)
    inv = np.linalg.inv(a.T @ a)
    true_sigma = math.sqrt((inv @ a.T @ np.diag(scale**2) @ a @ inv)[2, 2])
    noise = rng.normal(size=len(scale)) * scale
    lsq = s0 - inv @ a.T @ noise
    patch = _LinearPatch(a, s0, noise, rough=0.17 * float(np.median(scale)))
    start = lsq + np.array([0.0, 0.0, 2.0])
    f0 = patch.misfit(start)
    # a descent along the distance in 0.01 mm steps from the start stops in a dip
    z, f, step = 0.0, f0, (0.01 if patch.misfit(start + [0.0, 0.0, 0.01]) < f0 else -0.01)
    while (g := patch.misfit(start + [0.0, 0.0, z + step])) < f:
        z, f = z + step, g
    assert abs(start[2] + z - lsq[2]) > 0.5 * true_sigma
    curv = float(np.sum((a @ (start - pupil)) ** 2)) / f0
    src, _, sigma = _surface_minimum(patch, pupil, start, f0, curv, 4)
    assert abs(src[2] - lsq[2]) < 0.25 * true_sigma
    assert sigma == pytest.approx(true_sigma, rel=0.3)
