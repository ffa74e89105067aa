"""Refocusing against the exact thick-lens trace and Hahne's refocusing distance.

Truth here never comes from ``lfcam.decode``: view positions of a scene point come from the
exact 3-D trace (``lfcam.optics.trace.trace_rays``) — a ray's angular coordinate is the pixel it
reaches behind its lenslet relative to the micro-image centre (the chief ray through the
paraxial exit pupil), its spatial coordinate is where it crosses the MLA, in lenslets.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.optimize import least_squares

from lfcam.calibrate import Calibration
from lfcam.camera import load_profile
from lfcam.decode import (
    LightField,
    decode,
    distance_for_shift,
    focal_stack,
    refocus,
    shift_for_distance,
)
from lfcam.errors import OpticsError
from lfcam.models import hahne
from lfcam.optics.trace import trace_rays
from tests.decode.synth import encode, lattice

PROFILE = load_profile("system1")


def meridian(profile, distance_mm, pupil_fraction=0.999, n=401):
    """Exact trace of an on-axis source's meridional fan: (u_px, s_lenslets) per ray."""
    lens = profile.main_lens
    d_in = profile.d_in_mm
    h = np.linspace(-0.5, 0.5, n) * lens.pupil_diameter_mm * pupil_fraction
    origins = np.tile([0.0, 0.0, lens.front_vertex_z_mm - distance_mm], (n, 1))
    targets = np.column_stack([h, np.zeros(n), np.full(n, lens.rim_z_mm)])
    res = trace_rays(lens, origins, targets - origins, d_in)
    assert np.all(res.status == 0)
    x = res.points[:, 0]
    slope = res.directions[:, 0] / res.directions[:, 2]
    d_a = d_in - lens.exit_pupil_z_mm
    u = profile.mla.focal_length_mm * (slope - x / d_a) / profile.sensor.pixel_pitch_mm
    return u, x / profile.mla.pitch_mm


def view_positions(profile, distance_mm, du, dv):
    """(s, t) offset, in lenslets, at which view (du, dv) sees an on-axis point (exact trace).

    Rays of an on-axis point stay in their meridional plane, so the radial profile s(r) of the
    meridional fan gives every view. Returns NaN outside the pupil's image.
    """
    u, s = meridian(profile, distance_mm)
    order = np.argsort(u)
    r = np.hypot(du, dv)
    radial = np.interp(r, u[order], s[order], left=np.nan, right=np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos, sin = np.where(r > 0, du / r, 0.0), np.where(r > 0, dv / r, 0.0)
    return radial * cos, radial * sin, float(u.max())


@pytest.mark.parametrize("distance_mm", [300.0, 700.0, 1500.0, 3500.0, 8000.0])
def test_hahne_shift_is_the_exact_trace_slope_near_the_axis(distance_mm):
    u, s = meridian(PROFILE, distance_mm, pupil_fraction=1e-3)
    slope = np.polyfit(u, s, 1)[0]
    params = hahne.parameters_for(PROFILE)
    a = float(hahne.shift_for_distance(
        params, distance_mm + hahne.mla_to_front_vertex_mm(PROFILE)))
    assert a == pytest.approx(-slope, abs=1e-6)


@pytest.mark.parametrize("distance_mm", [300.0, 700.0, 1500.0, 3500.0])
def test_shift_for_distance_is_the_least_rms_shift_of_the_full_aperture(distance_mm):
    """The metric refocus shift minimises the point's refocused RMS blur (exact trace, full
    pupil): the area-weighted meridional fan gives the same shift."""
    u, s = meridian(PROFILE, distance_mm, n=4001)
    w = np.abs(np.linspace(-1.0, 1.0, u.size))  # ring area ∝ radius
    a_fan = -np.sum(w * s * u) / np.sum(w * u * u)
    a = float(shift_for_distance(PROFILE, distance_mm))
    assert a == pytest.approx(a_fan, abs=2e-3 * max(1.0, abs(a)))

    def rms(shift):
        return np.sqrt(np.sum(w * (s + shift * u) ** 2) / np.sum(w))

    assert rms(a) < rms(float(shift_for_distance(PROFILE, 0.9 * distance_mm)))
    assert rms(a) < rms(float(shift_for_distance(PROFILE, 1.1 * distance_mm)))


@pytest.mark.parametrize("a", [1.0, 2.0, 0.25, 0.05])
def test_shift_round_trips_through_hahne_refocus_distance(a):
    d = float(distance_for_shift(PROFILE, a))
    assert 100.0 < d < 5000.0
    assert float(shift_for_distance(PROFILE, d)) == pytest.approx(a, abs=1e-9)


def test_bad_refocus_requests():
    with pytest.raises(OpticsError, match="positive"):
        shift_for_distance(PROFILE, -5.0)
    lf = LightField(np.zeros((3, 3, 4, 4), np.float32), np.ones((3, 3, 4, 4), np.float32),
                    Calibration.from_lattice("rect", 10.0), (10.0, 10.0))
    with pytest.raises(OpticsError, match="finite"):
        refocus(lf, float("nan"))


def _texture(s, t):
    return (0.5 + 0.2 * np.sin(2 * np.pi * s / 7.3 + 0.4) + 0.15 * np.cos(2 * np.pi * t / 9.7)
            + 0.1 * np.sin(2 * np.pi * (s + t) / 11.1))


def test_integer_shift_realigns_views_exactly():
    n, size, a = 5, 40, 2.0
    vv, uu, tt, ss = np.meshgrid(*(np.arange(k, dtype=float) for k in (n, n, size, size)),
                                 indexing="ij")
    c = (n - 1) / 2
    data = _texture(ss + a * (uu - c), tt + a * (vv - c)).astype(np.float32)
    lf = LightField(data, np.ones_like(data), Calibration.from_lattice("rect", 10.0), (10.0, 10.0))
    out = refocus(lf, a)
    inner = (slice(8, 32), slice(8, 32))
    truth = _texture(*np.meshgrid(np.arange(size, dtype=float), np.arange(size, dtype=float),
                                  indexing="xy"))
    np.testing.assert_allclose(out.image[inner], truth[inner], atol=1e-5)
    assert out.weight[inner].min() == pytest.approx(n * n)


def _raw_of(f, pitch=18.0, lenses=40, rot=0.0, off=(9.0, 9.0)):
    cx, cy, sp, tp = lattice("rect", pitch, rot, off, lenses, lenses)
    shape = (int(pitch * lenses), int(pitch * lenses))
    return encode(f, shape, cx, cy, sp, tp, rot, 0.5 * pitch), (cx, cy, sp, tp, shape)


def test_textured_plane_views_shift_by_the_traced_disparity():
    """A plane at 1000 mm (system 1): neighbouring views shift as the exact trace says."""
    d = 1000.0
    u_axis, s_axis = meridian(PROFILE, d)
    order = np.argsort(u_axis)

    def radial(r):
        return np.interp(r, u_axis[order], s_axis[order])

    def f(du, dv, s, t):
        r = np.hypot(du, dv)
        k = np.where(r > 0, radial(r) / np.where(r > 0, r, 1.0), 0.0)
        return _texture(s - k * du, t - k * dv)  # view (du, dv) sees the plane shifted

    raw, _ = _raw_of(f, off=(9.37, 8.81), rot=0.004)
    lf = decode(raw, Calibration.from_lattice("rect", 18.0, 0.004, (9.37, 8.81)), n_views=9)
    vc, uc = lf.angular_centre
    inner = (slice(4, 34), slice(4, 34))
    tt, ss = np.meshgrid(np.arange(lf.data.shape[2]) + lf.first_t,
                         np.arange(lf.data.shape[3]) + lf.first_s, indexing="ij")

    def shift_of(v, u):
        img = lf.data[v, u][inner]
        res = least_squares(
            lambda p: (_texture(ss[inner] - p[0], tt[inner] - p[1]) - img).ravel(), [0.0, 0.0])
        return res.x

    measured = [shift_of(int(vc), u)[0] for u in range(2, 7)]
    du = np.arange(2, 7) - uc
    truth = np.array([radial(abs(x)) * np.sign(x) for x in du])
    np.testing.assert_allclose(np.diff(measured), np.diff(truth), atol=0.005)
    # Hahne's paraxial shift is the disparity of the central pair (0.17 lenslet per view);
    # farther views drift from it by the main lens's spherical aberration, as traced above
    a = float(hahne.shift_for_distance(hahne.parameters_for(PROFILE),
                                       d + hahne.mla_to_front_vertex_mm(PROFILE)))
    assert measured[3] - measured[2] == pytest.approx(-a, abs=0.01)


def _second_moment(img, centre, half=12):
    y0, x0 = int(round(centre[1])), int(round(centre[0]))
    win = img[y0 - half:y0 + half + 1, x0 - half:x0 + half + 1].astype(np.float64)
    yy, xx = np.mgrid[-half:half + 1, -half:half + 1]
    tot = win.sum()
    mx, my = (win * xx).sum() / tot, (win * yy).sum() / tot
    return ((win * (xx - mx) ** 2).sum() / tot, (win * (yy - my) ** 2).sum() / tot)


SLOW = replace(PROFILE, main_lens=replace(PROFILE.main_lens, pupil_diameter_mm=25.0))


@pytest.mark.parametrize("profile", [PROFILE, SLOW], ids=["f2", "f4"])
def test_point_source_refocus_blur_is_the_traced_blur(profile):
    """System 1 (F/2, and stopped to F/4), point at 700 mm: refocused second moments vs the
    exact trace's prediction, at its own distance and at 300, 1500, 3500 mm."""
    d, sigma0, s0, t0 = 700.0, 0.8, 20.0, 20.0
    _, _, r_pupil = view_positions(profile, d, 0.0, 0.0)

    def f(du, dv, s, t):
        ps, pt, _ = view_positions(profile, d, du, dv)
        ps, pt = np.nan_to_num(ps), np.nan_to_num(pt)
        return np.exp(-((s - s0 - ps) ** 2 + (t - t0 - pt) ** 2) / (2 * sigma0**2))

    raw, (cx, cy, sp, tp, shape) = _raw_of(f)
    white = encode(lambda du, dv, s, t: (np.hypot(du, dv) <= r_pupil).astype(float), shape,
                   cx, cy, sp, tp, 0.0, 9.0)
    grid = Calibration.from_lattice("rect", 18.0, 0.0, (9.0, 9.0))
    lf = decode(raw, grid, white=white, n_views=17)
    vc, uc = lf.angular_centre
    vv, uu = np.meshgrid(np.arange(17) - vc, np.arange(17) - uc, indexing="ij")
    in_pupil = np.hypot(uu, vv) <= r_pupil
    assert np.array_equal(lf.weight[:, :, 20, 20] > 0, in_pupil)
    ps, pt, _ = view_positions(profile, d, uu[in_pupil], vv[in_pupil])

    a_own = float(shift_for_distance(profile, d))
    others = [float(shift_for_distance(profile, x)) for x in (300.0, 1500.0, 3500.0)]
    stack = focal_stack(lf, [a_own, *others])
    for out in stack:
        # exact-trace prediction: view (u, v) puts the spot at s0 + p(u, v) + a·(u, v)
        px = ps + out.shift * uu[in_pupil]
        py = pt + out.shift * vv[in_pupil]
        pred = (sigma0**2 + px.var(), sigma0**2 + py.var())
        meas = _second_moment(out.image, (s0 + px.mean() - lf.first_s, t0 + py.mean()))
        # bilinear resampling adds at most 1/4 px² (a shift f spreads by f(1 − f))
        for m, p in zip(meas, pred, strict=True):
            assert p - 0.02 <= m <= p + 0.25, (out.shift, meas, pred)
    own = max(_second_moment(stack[0].image, (s0, t0)))
    others = [min(_second_moment(o.image, (s0, t0))) for o in stack[1:]]
    if profile is SLOW:
        # F/4: sharp at its own distance (own size 0.64 + ≤ 0.25 for aberration and resampling)
        assert own < sigma0**2 + 0.25
        # 300 mm: ~2× the own-plane spread (bilinear resampling of the fractional shift adds
        # up to 0.25 px² to the own plane)
        assert own < min(others) and others[0] > 1.8 * own
    else:
        # F/2: the singlet's spherical aberration moves the least-blur plane away from the
        # paraxial (Hahne) one; the trace predicts it and the decoder reproduces it
        assert own < sigma0**2 + 0.6
