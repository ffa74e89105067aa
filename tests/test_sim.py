"""Tests of the synthetic renderer (lfcam.sim) against independent truth."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from lfcam.camera import load_profile
from lfcam.cli.main import main
from lfcam.errors import SceneError
from lfcam.optics.mla import MlaGrid
from lfcam.optics.trace import forward, trace_backward_fast, trace_rays, trace_source_fast
from lfcam.sim.capture import apply_overrides, simulate, write_capture
from lfcam.sim.render import Renderer
from lfcam.sim.scene import scene_from_dict


def small(name: str, size: int = 192, **mla) -> object:
    """A shipped profile with a small sensor (and optional MLA overrides)."""
    p = load_profile(name)
    p = replace(p, sensor=replace(p.sensor, width_px=size, height_px=size))
    if mla:
        p = replace(p, mla=replace(p.mla, **mla))
    return p


# ----------------------------------------------------------------------------- trace fast paths
def test_fast_forward_trace_matches_trace_rays():
    p = load_profile("system1")
    rng = np.random.default_rng(1)
    src = (4.0, -7.0, p.main_lens.front_vertex_z_mm - 750.0)
    r = 0.5 * p.main_lens.pupil_diameter_mm * np.sqrt(rng.random(5000))
    a = rng.random(5000) * 2 * math.pi
    qx, qy = r * np.cos(a), r * np.sin(a)
    fast = trace_source_fast(p.main_lens, src, qx, qy, p.d_in_mm)
    d = np.stack([qx - src[0], qy - src[1], np.full(qx.shape, p.main_lens.rim_z_mm - src[2])], 1)
    ref = trace_rays(p.main_lens, np.tile(src, (qx.size, 1)), d, p.d_in_mm)
    assert fast.ok.all() and (ref.status == 0).all()
    assert np.abs(fast.x - ref.points[:, 0]).max() < 1e-9
    assert np.abs(fast.y - ref.points[:, 1]).max() < 1e-9


def test_backward_trace_retraces_forward_rays():
    p = load_profile("system2")
    lens = p.main_lens
    src = (0.0, 3.0, lens.front_vertex_z_mm - 400.0)
    rng = np.random.default_rng(2)
    qx, qy = rng.uniform(-14, 14, 2000), rng.uniform(-14, 14, 2000)
    f = trace_source_fast(lens, src, qx, qy, p.d_in_mm)
    b = trace_backward_fast(lens, f.x, f.y, p.d_in_mm, f.dx / f.dz, f.dy / f.dz)
    assert (b.ok == f.ok).all()
    # the retraced ray points back at the source
    t = (src[2] - b.z) / b.dz
    assert np.abs(b.x + t * b.dx - src[0])[b.ok].max() < 1e-8
    assert np.abs(b.y + t * b.dy - src[1])[b.ok].max() < 1e-8


# ----------------------------------------------------------------------------- MLA geometry
@pytest.mark.parametrize("grid", ["rect", "hex"])
def test_nearest_lenslet_matches_brute_force(grid):
    g = MlaGrid(pitch_mm=0.25, grid=grid, rotation_rad=0.3, offset_mm=(0.07, -0.11))
    i, j, cx, cy = g.lenslets_in_box(-2, 2, -2, 2)
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-1.5, 1.5, 3000), rng.uniform(-1.5, 1.5, 3000)
    brute = np.argmin((x[:, None] - cx[None]) ** 2 + (y[:, None] - cy[None]) ** 2, axis=1)
    ni, nj, ncx, ncy = g.nearest(x, y)
    assert (ni == i[brute]).all() and (nj == j[brute]).all()
    # the lattice really is what the docstring says
    if grid == "hex":
        inner = np.hypot(cx, cy) < 1.5
        d = np.hypot(cx[inner, None] - cx[None], cy[inner, None] - cy[None])
        near = np.sort(d, axis=1)[:, 1:8]
        assert np.allclose(near[:, :6], 0.25)  # six neighbours at one pitch,
        assert np.allclose(near[:, 6], 0.25 * math.sqrt(3))  # the next ring at √3 pitch


@pytest.mark.parametrize("grid", ["rect", "hex"])
def test_aperture_samples_cover_the_clear_aperture_uniformly(grid):
    g = MlaGrid(pitch_mm=1.0, grid=grid, rotation_rad=0.2, fill_factor=0.8)
    rng = np.random.default_rng(4)
    n = 200_000
    k = rng.integers(0, 3, n) if grid == "hex" else None
    dx, dy = g.aperture_samples(rng.random(n), rng.random(n), k)
    assert g.in_aperture(dx, dy).all()
    # the fraction of a bounding square that in_aperture accepts = aperture area / square area
    ux, uy = rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n)
    frac = g.in_aperture(ux, uy).mean()
    expect = 0.64 * (1.0 if grid == "rect" else math.sqrt(3) / 2)
    assert abs(frac - expect) < 0.005
    assert abs(dx.mean()) < 0.003 and abs(dy.mean()) < 0.003


# ----------------------------------------------------------------------------- forward renderer
@pytest.mark.parametrize(("name", "distance", "offset"),
                         [("system1", 300.0, 0.0), ("system1", 900.0, 10.0),
                          ("system2", 300.0, 5.0), ("system2", 450.0, 5.0)])
def test_point_source_extent_on_mla_equals_exact_rim_rays(name, distance, offset):
    p = load_profile(name)
    r = Renderer(small(name))
    lens = p.main_lens
    k = 1000
    ys = []
    for tr, _ in r.trace_point((0.0, offset, lens.front_vertex_z_mm - distance), k * k,
                               np.random.default_rng(5)):
        ys.append(tr.y[tr.ok])
    y = np.concatenate(ys)
    ref = forward(p, None, distance, offset, z_plane_mm=p.d_in_mm)
    hi, lo = max(ref.y1_mm, ref.y2_mm), min(ref.y1_mm, ref.y2_mm)
    # independent extent: a dense meridional fan through the (N, 3) reference tracer
    q = np.linspace(-0.5, 0.5, 20001) * lens.pupil_diameter_mm
    src = np.array([0.0, offset, lens.front_vertex_z_mm - distance])
    d = np.stack([np.zeros_like(q), q - offset, np.full(q.shape, lens.rim_z_mm - src[2])], 1)
    fan = trace_rays(lens, np.tile(src, (q.size, 1)), d, p.d_in_mm).points[:, 1]
    # samples reach within one stratum (D/2 / (k/2)) of the rim: scaled to the MLA plane
    tol = 2.0 * (lens.pupil_diameter_mm / k) * (hi - lo) / lens.pupil_diameter_mm + 1e-6
    assert abs(y.max() - fan.max()) < tol and abs(y.min() - fan.min()) < tol
    if distance == 300.0:  # defocus-dominated: the rim rays are the extremes
        assert abs(fan.max() - hi) < 1e-3 and abs(fan.min() - lo) < 1e-3
        assert abs(y.max() - hi) < tol + 1e-3 and abs(y.min() - lo) < tol + 1e-3
    else:  # spherical aberration: a zone ray lands outside the rim rays (docs/simulate.md)
        assert fan.max() > hi + 1e-4 or fan.min() < lo - 1e-4


def test_energy_through_aperture_is_the_solid_angle():
    p = small("system1", 384)
    lens = p.main_lens
    for distance in (300.0, 3000.0):
        scene = scene_from_dict({"objects": [{"type": "point", "distance_mm": distance,
                                              "intensity": 2.0}], "rays_per_source": 250_000})
        res = Renderer(p).render(scene)
        a = 0.5 * lens.pupil_diameter_mm
        big_l = distance + lens.rim_sag_mm
        omega = 2 * math.pi * (1 - big_l / math.hypot(big_l, a))
        src = res.sources[0]
        assert src["power_through_aperture"] == pytest.approx(2.0 * omega, rel=1e-5)
        # fill factor 1: every ray reaches a lenslet and (blur inside the sensor) the image
        assert res.signal.sum() == pytest.approx(src["power_through_aperture"], rel=1e-9)


def test_fill_factor_scales_energy_by_its_square():
    p = small("system1", 512, fill_factor=0.7)
    scene = scene_from_dict({"objects": [{"type": "point", "distance_mm": 300.0}],
                             "rays_per_source": 250_000})
    res = Renderer(p).render(scene)
    # the 300 mm blur covers ~100 lenslets, so the blocked share averages to 1 − 0.7²
    ratio = res.signal.sum() / res.sources[0]["power_through_aperture"]
    assert ratio == pytest.approx(0.49, abs=0.01)


# ----------------------------------------------------------------------------- backward renderer
def test_white_centroids_follow_the_exit_pupil_chief_ray():
    p = small("system1", 320)
    r = Renderer(p)
    res = r.render(scene_from_dict({"objects": [{"type": "white"}]}))
    assert res.stats["box_edge_lit"] == 0
    ok = res.lens_complete
    assert ok.sum() >= 300
    pred = r.predicted_centres_px()[ok]
    d = res.lens_centroid_px[ok] - pred
    radius = np.hypot(pred[:, 0] - r.ax, pred[:, 1] - r.ay)
    # measured: centroid = paraxial chief ray scaled by (1 − 0.11 %) about the axis (pupil
    # aberration of the real lens), + < 0.03 px RMS; allow 0.2 % of the radius + 0.05 px
    assert (np.hypot(d[:, 0], d[:, 1]) <= 0.002 * radius + 0.05).all()
    v = pred - [r.ax, r.ay]
    scale = (d * v).sum() / (v * v).sum()
    assert -0.002 < scale < 0.0
    resid = d - scale * v
    assert np.sqrt((resid ** 2).sum(1).mean()) < 0.04


def test_white_interior_pixel_value_is_analytic():
    # a fully lit pixel right under the on-axis lenslet: L·A_ap/f_x²·pp²·mean(cos⁴)
    p = small("system1", 64)
    r = Renderer(p)
    res = r.render(scene_from_dict({"objects": [{"type": "white", "radiance": 3.0}]}))
    g = r.grid
    xs = (np.arange(400) + 0.5) / 400 - 0.5
    sx, sy = np.meshgrid(xs * g.pitch_mm, xs * g.pitch_mm)
    x_px = 32.0  # pixel 32 is half a pixel off the axis (axis at 31.5)
    xm = (x_px - r.ax) * r.pp
    c4 = (1.0 / (1.0 + ((xm - sx) ** 2 + (0.5 * r.pp - sy) ** 2) / r.f_x ** 2) ** 2).mean()
    expect = 3.0 * g.aperture_area_mm2 / r.f_x ** 2 * r.pp ** 2 * c4
    assert res.signal[32, 32] == pytest.approx(expect, rel=2e-3)


def test_uniform_plane_renders_like_the_white_scene():
    p = small("system1", 96)  # no micro-image overlap: the brightest pixels are fully lit
    r = Renderer(p)
    white = r.render(scene_from_dict({"objects": [{"type": "white"}]})).signal
    plane = r.render(scene_from_dict({"objects": [{"type": "plane", "distance_mm": 800,
                                                   "texture": "uniform", "high": 1.0}],
                                      "samples_per_pixel": 64})).signal
    # fully lit pixels: every traced ray reaches the plane with radiance 1
    lit = white > 0.8 * white.max()
    assert lit.sum() > 300
    assert np.median(np.abs(plane[lit] / white[lit] - 1)) < 1e-9
    # boundary pixels are Monte Carlo in both renders: compare the totals
    assert abs(plane.sum() / white.sum() - 1) < 0.003


@pytest.mark.parametrize("grid", ["rect", "hex"])
def test_grid_rotation_and_offset_are_honoured(grid):
    rot, off = 0.12, (0.31, -0.17)
    p = small("system1", 256, grid=grid, rotation_rad=rot, offset_mm=off)
    r = Renderer(p)
    res = r.render(scene_from_dict({"objects": [{"type": "white"}]}))
    ok = res.lens_complete
    cen = res.lens_centroid_px
    key = {(i, j): n for n, (i, j) in enumerate(zip(res.lens_i, res.lens_j, strict=True))}
    step1, step2 = [], []
    for n in np.nonzero(ok)[0]:
        i, j = res.lens_i[n], res.lens_j[n]
        for (di, dj), acc in (((1, 0), step1), ((0, 1), step2)):
            m = key.get((i + di, j + dj))
            if m is not None and ok[m]:
                acc.append(cen[m] - cen[n])
    g = 1 + r.f_x / (r.d_in - p.main_lens.exit_pupil_z_mm)
    pitch_px = p.mla.pitch_mm / p.sensor.pixel_pitch_mm * g
    second = rot + (math.pi / 2 if grid == "rect" else math.pi / 3)
    for steps, ang in ((step1, rot), (step2, second)):
        s = np.mean(steps, axis=0)
        assert np.hypot(*s) == pytest.approx(pitch_px, rel=2e-3)
        assert math.atan2(s[1], s[0]) == pytest.approx(ang, abs=1e-3)
    # lens (0, 0) sits at the offset: its micro-image centroid near g·offset from the axis
    n00 = key[(0, 0)]
    expect = np.array([r.ax + g * off[0] / r.pp, r.ay + g * off[1] / r.pp])
    assert np.hypot(*(cen[n00] - expect)) < 0.1


# ----------------------------------------------------------------------------- sensor + output
def test_bayer_dark_and_hot_pixels():
    p = small("system1", 64)
    scene = scene_from_dict({"objects": [], "sensor": {"black_level": 64, "hot_pixels": 5}})
    raw, _, _ = simulate(p, scene)
    assert (raw == 64).sum() == 64 * 64 - 5 and (raw == 65535).sum() == 5
    scene = scene_from_dict({"objects": [{"type": "white"}], "sensor": {"bayer": "GRBG"},
                             "exposure": {"scale": 1.0}})
    raw, used, _ = simulate(small("system1", 64), scene)
    assert used.sensor.bayer == "GRBG"
    sig = Renderer(used).render(scene).signal
    # GRBG: top-left green (gain 1), top-right red (0.55), bottom-left blue (0.75)
    np.testing.assert_array_equal(raw[0::2, 0::2], np.rint(sig[0::2, 0::2] * 65535))
    np.testing.assert_array_equal(raw[0::2, 1::2], np.rint(sig[0::2, 1::2] * 0.55 * 65535))
    np.testing.assert_array_equal(raw[1::2, 0::2], np.rint(sig[1::2, 0::2] * 0.75 * 65535))


def test_output_is_byte_identical_for_a_seed(tmp_path):
    p = small("system2", 96)
    body = {"seed": 11, "rays_per_source": 20000,
            "objects": [{"type": "white"}, {"type": "point", "distance_mm": 500}],
            "sensor": {"photon_noise": True, "read_noise_e": 3.0, "bayer": "RGGB",
                       "hot_pixels": 3, "bit_depth": 12, "white_level": 4095}}
    outs = []
    for k, seed in enumerate((11, 11, 12)):
        raw, used, truth = simulate(p, scene_from_dict(dict(body, seed=seed)))
        img, _, tru = write_capture(tmp_path / f"c{k}.png", raw, used, truth)
        outs.append((img.read_bytes(), tru.read_bytes()))
        assert raw.max() <= 4095
    assert outs[0] == outs[1]
    assert outs[0][0] != outs[2][0]


def test_cli_simulate_writes_capture_and_truth(tmp_path, capsys):
    scene = tmp_path / "s.json"
    scene.write_text(json.dumps({"rays_per_source": 40000, "objects": [
        {"type": "point", "distance_mm": 1000, "offset_mm": 5},
        {"type": "line", "distance_mm": 600, "start_mm": [-15, 0], "end_mm": [-15, 10]}],
        "camera": {"sensor": {"width_px": 256, "height_px": 256}}}))
    out = tmp_path / "cap.tiff"
    assert main(["simulate", "--profile", "system1", "--scene", str(scene), "-o", str(out)]) == 0
    truth = json.loads((tmp_path / "cap.truth.json").read_text())
    assert load_profile(tmp_path / "cap.profile.toml").sensor.width_px == 256
    pt = truth["sources"][0]
    ref = forward(load_profile("system1"), None, 1000.0, 5.0)
    assert pt["y1_mm"] == pytest.approx(float(ref.y1_mm), abs=1e-12)
    # blur centroid sits between the two rim rays on the meridian (+y image is inverted: −y)
    cy_mm = (pt["centroid_px"][1] - 127.5) * 0.08375
    assert min(pt["y1_mm"], pt["y2_mm"]) < cy_mm < max(pt["y1_mm"], pt["y2_mm"])
    assert len(truth["sources"][1]["endpoints"]) == 2
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"objects": [{"type": "point", "distance_mm": -3}]}))
    capsys.readouterr()
    assert main(["simulate", "--profile", "system1", "--scene", str(bad), "-o",
                 str(tmp_path / "x.png")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "distance_mm" in err


@pytest.mark.parametrize("body", [
    {"objects": {"type": "white"}},
    {"objects": [{"type": "sphere"}]},
    {"objects": [{"type": "line", "distance_mm": 5, "start_mm": [0, 0], "end_mm": [0, 0]}]},
    {"rays_per_source": 10**12},
    {"exposure": {"peak": 0.5, "scale": 2}},
    {"sensor": {"bayer": "XYZW"}},
    {"camera": {"mla": {"grid": "tri"}}},
])
def test_bad_scenes_raise_scene_errors(body):
    from lfcam.errors import LfcamError

    with pytest.raises(LfcamError):
        scene = scene_from_dict(body)
        apply_overrides(load_profile("system1"), scene.camera)
    with pytest.raises(SceneError):
        scene_from_dict([1, 2])
