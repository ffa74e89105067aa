"""Ray-traced raw images of a plenoptic 1.0 camera (exact thick main lens + ideal MLA).

Two renderers share one accumulator (image + per-lenslet intensity moments):

* **forward** (point and line sources): stratified samples of the front-rim disk, traced from
  the source through the exact main lens (:func:`lfcam.optics.trace.trace_source_fast`) to the
  MLA plane; each ray enters the lenslet whose clear aperture it hits and lands on the sensor
  at ``C_k + f_x·(dx/dz, dy/dz)`` (ideal thin lenslet); its power is added to the pixel that
  contains the landing point (pixel integration). Ray weights are the solid angle each sample
  represents, so the summed power equals ``I·Ω`` of the aperture.
* **backward** (white scene, textured planes): for sensor point X and lenslet k the incoming
  slope is ``(X − C_k)/f_x`` wherever the ray crossed the lenslet; rays are traced back through
  the main lens (:func:`lfcam.optics.trace.trace_backward_fast`) and pass if they leave the front
  surface within D/2. Pixels whose every (pixel point, lenslet point) pair provably passes or
  fails are decided from the traced pixel-corner rays alone; only boundary pixels are sampled.

Irradiance at X through lenslet k is ``L·∫ cos⁴θ dA_P / f_x²`` over the lenslet aperture
(radiance is conserved by ideal lenses); pixel values are that irradiance times pixel area.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lfcam.camera import CameraProfile
from lfcam.errors import SceneError
from lfcam.optics.mla import MlaGrid
from lfcam.optics.trace import pupil_map, trace_backward_fast, trace_source_fast
from lfcam.sim.scene import LineSource, PointSource, Scene, TexturedPlane, WhiteScene

CHUNK_RAYS = 1 << 20
MAX_PIXELS = 64_000_000


@dataclass
class Accumulator:
    """Image and per-lenslet moments (Σw, Σw·x_px, Σw·y_px) accumulated over rays."""

    height: int
    width: int
    n_lenses: int
    image: np.ndarray = field(init=False)
    lens_w: np.ndarray = field(init=False)
    lens_wx: np.ndarray = field(init=False)
    lens_wy: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.image = np.zeros(self.height * self.width)
        self.lens_w = np.zeros(self.n_lenses)
        self.lens_wx = np.zeros(self.n_lenses)
        self.lens_wy = np.zeros(self.n_lenses)

    def add(self, x_px, y_px, w, lens_idx, centre_x_px=None, centre_y_px=None) -> None:
        """Deposit weights at continuous sensor positions (binned to the containing pixel).

        ``centre_*_px`` (optional) are the positions used for the lenslet moments when they
        differ from the binning position (a whole pixel deposited at once).
        """
        col = np.floor(x_px + 0.5).astype(np.int64)
        row = np.floor(y_px + 0.5).astype(np.int64)
        on = (col >= 0) & (col < self.width) & (row >= 0) & (row < self.height) & (w != 0)
        flat = row[on] * self.width + col[on]
        self.image += np.bincount(flat, weights=w[on], minlength=self.image.size)
        mx = x_px if centre_x_px is None else centre_x_px
        my = y_px if centre_y_px is None else centre_y_px
        lk = lens_idx[on]
        good = lk >= 0
        lk, wo = lk[good], w[on][good]
        self.lens_w += np.bincount(lk, weights=wo, minlength=self.n_lenses)
        self.lens_wx += np.bincount(lk, weights=wo * mx[on][good], minlength=self.n_lenses)
        self.lens_wy += np.bincount(lk, weights=wo * my[on][good], minlength=self.n_lenses)


@dataclass
class RenderResult:
    """Unscaled sensor signal and the ray-derived truth."""

    signal: np.ndarray  # (H, W) float64, power per pixel (arbitrary consistent units)
    lens_i: np.ndarray
    lens_j: np.ndarray
    lens_centre_mm: np.ndarray  # (N, 2)
    lens_weight: np.ndarray  # Σw per lenslet
    lens_centroid_px: np.ndarray  # (N, 2), NaN where Σw = 0
    lens_complete: np.ndarray  # bool: backward-rendered micro-image box fully on the sensor
    sources: list  # per-source dicts (forward renderer)
    stats: dict


def _concentric_disk(s: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Area-preserving map of the unit square to the unit disk (Shirley–Chiu)."""
    a = 2.0 * s - 1.0
    b = 2.0 * t - 1.0
    first = np.abs(a) > np.abs(b)
    r = np.where(first, a, b)
    with np.errstate(divide="ignore", invalid="ignore"):
        phi = np.where(first, (math.pi / 4) * (b / a), (math.pi / 2) - (math.pi / 4) * (a / b))
    phi = np.where((a == 0.0) & (b == 0.0), 0.0, phi)
    return r * np.cos(phi), r * np.sin(phi)


class Renderer:
    """Renders scenes for one camera profile.

    Parameters
    ----------
    profile : CameraProfile
        Needs a known d_in (``mla.distance_mm`` or ``mla.focus_mm``).
    """

    def __init__(self, profile: CameraProfile) -> None:
        self.profile = profile
        self.lens = profile.main_lens
        self.grid = MlaGrid.from_mla(profile.mla)
        self.d_in = profile.d_in_mm
        self.f_x = profile.mla.focal_length_mm
        s = profile.sensor
        if s.width_px * s.height_px > MAX_PIXELS:
            raise SceneError(f"sensor of {s.width_px}×{s.height_px} px exceeds the renderer's "
                             f"limit of {MAX_PIXELS} pixels")
        self.pp = s.pixel_pitch_mm
        self.width, self.height = s.width_px, s.height_px
        self.ax, self.ay = s.axis_xy_px
        margin = 2.0 * self.grid.pitch_mm
        x0 = (-0.5 - self.ax) * self.pp - margin
        x1 = (self.width - 0.5 - self.ax) * self.pp + margin
        y0 = (-0.5 - self.ay) * self.pp - margin
        y1 = (self.height - 0.5 - self.ay) * self.pp + margin
        self.li, self.lj, self.lcx, self.lcy = self.grid.lenslets_in_box(x0, x1, y0, y1)
        if self.li.size > 4_000_000:
            raise SceneError(f"{self.li.size} lenslets over the sensor: too many to render")
        self.i0, self.j0 = int(self.li.min()), int(self.lj.min())
        ni, nj = int(self.li.max()) - self.i0 + 1, int(self.lj.max()) - self.j0 + 1
        self.table = np.full((ni, nj), -1, dtype=np.int64)
        self.table[self.li - self.i0, self.lj - self.j0] = np.arange(self.li.size)

    # ------------------------------------------------------------------ helpers
    def mm_to_px(self, x_mm, y_mm):
        """Sensor-plane millimetres → pixel coordinates (docs/conventions.md)."""
        return np.asarray(x_mm) / self.pp + self.ax, np.asarray(y_mm) / self.pp + self.ay

    def px_to_mm(self, x_px, y_px):
        """Pixel coordinates → sensor-plane millimetres."""
        return (np.asarray(x_px) - self.ax) * self.pp, (np.asarray(y_px) - self.ay) * self.pp

    def lens_index(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Compact lenslet index (−1 outside the table) for lattice indices."""
        ii = i - self.i0
        jj = j - self.j0
        ok = (ii >= 0) & (ii < self.table.shape[0]) & (jj >= 0) & (jj < self.table.shape[1])
        out = np.full(ii.shape, -1, dtype=np.int64)
        out[ok] = self.table[ii[ok], jj[ok]]
        return out

    def _mla_to_sensor(self, x, y, dx, dy, dz, ok):
        """Ideal lenslets: rays at MLA points (x, y) with directions → sensor px, lens idx."""
        x, y = np.where(ok, x, 0.0), np.where(ok, y, 0.0)  # failed rays carry NaN
        dz = np.where(ok, dz, 1.0)
        i, j, cx, cy = self.grid.nearest(x, y)
        ok = ok & self.grid.in_aperture(x - cx, y - cy)
        sx = cx + self.f_x * dx / dz
        sy = cy + self.f_x * dy / dz
        px, py = self.mm_to_px(sx, sy)
        idx = self.lens_index(i, j)
        return px, py, idx, ok

    # ------------------------------------------------------------------ forward
    def trace_point(
        self, source_xyz: tuple[float, float, float], n_rays: int, rng: np.random.Generator,
        intensity: float = 1.0, z_plane_mm: float | None = None,
    ):
        """Yield chunks of (FastTrace at ``z_plane`` (default MLA), weights) for a point source.

        ``n_rays`` is rounded up to a square k² of jittered strata on the rim disk.
        """
        k = max(1, math.ceil(math.sqrt(n_rays)))
        n = k * k
        half_d = 0.5 * self.lens.pupil_diameter_mm
        sx, sy, sz = source_xyz
        # the real stop seen from the source, on the aperture plane (identity for the singlet,
        # whose stop is the front rim); a 3 % margin, the tracer clips at the real stop
        cx, cy, ex, ey = pupil_map(self.lens, source_xyz)
        if not self.lens.as_prescription.stop_index == 0:
            ex, ey = 1.03 * ex, 1.03 * ey
        area = math.pi * half_d * half_d * abs(ex * ey)
        lz = self.lens.rim_z_mm - sz
        z_plane = self.d_in if z_plane_mm is None else z_plane_mm
        rows_per_chunk = max(1, CHUNK_RAYS // k)
        for r0 in range(0, k, rows_per_chunk):
            rows = np.arange(r0, min(k, r0 + rows_per_chunk))
            gi, gj = np.meshgrid(np.arange(k), rows, indexing="xy")
            s = (gi.ravel() + rng.random(gi.size)) / k
            t = (gj.ravel() + rng.random(gi.size)) / k
            ux, uy = _concentric_disk(s, t)
            qx, qy = cx + ex * half_d * ux, cy + ey * half_d * uy
            dist2 = (qx - sx) ** 2 + (qy - sy) ** 2 + lz * lz
            w = intensity * (area / n) * lz / (dist2 * np.sqrt(dist2))
            tr = trace_source_fast(self.lens, (sx, sy, sz), qx, qy, z_plane, map_pupil=False)
            yield tr, w

    def _forward_source(self, xyz, intensity, n_rays, rng, acc) -> dict:
        through = on_sensor = sum_x = sum_y = 0.0
        for tr, w in self.trace_point(xyz, n_rays, rng, intensity):
            wp = np.where(tr.ok, w, 0.0)
            through += float(wp.sum())
            px, py, idx, ok = self._mla_to_sensor(tr.x, tr.y, tr.dx, tr.dy, tr.dz, tr.ok)
            wl = np.where(ok, w, 0.0)
            inside = ok & (px >= -0.5) & (px < self.width - 0.5) & (py >= -0.5) & (
                py < self.height - 0.5)
            wi = np.where(inside, w, 0.0)
            on_sensor += float(wi.sum())
            sum_x += float((wi * np.where(inside, px, 0.0)).sum())
            sum_y += float((wi * np.where(inside, py, 0.0)).sum())
            acc.add(np.where(ok, px, -1e9), np.where(ok, py, -1e9), wl, idx)
        return {"power_through_aperture": through, "power_on_sensor": on_sensor,
                "sum_x": sum_x, "sum_y": sum_y}

    # ------------------------------------------------------------------ backward
    def micro_image_radius_px(self) -> float:
        """Radius (px) of the on-axis micro-image: f_x·tan of the widest passing slope."""
        lo, hi = 0.0, 1.0
        zero = np.zeros(1)
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            tr = trace_backward_fast(self.lens, zero, zero, self.d_in, np.array([mid]), zero)
            lo, hi = (mid, hi) if tr.ok[0] else (lo, mid)
        return self.f_x * lo / self.pp

    def predicted_centres_px(self) -> np.ndarray:
        """Chief-ray micro-image centres: line from the paraxial exit-pupil centre through C_k."""
        z_ep = self.lens.exit_pupil_z_mm
        g = 1.0 + self.f_x / (self.d_in - z_ep)
        px, py = self.mm_to_px(self.lcx * g, self.lcy * g)
        return np.stack([px, py], axis=1)

    def _rho(self, px_x, px_y, cx, cy, pdx=0.0, pdy=0.0):
        """Vignetting measure of the backward ray (sensor px, lenslet point): ρ/(D/2) at the
        front exit for the singlet (stop = front rim), else the largest ρ/semi-diameter over the
        surfaces (unclipped trace); < 1 exactly where the ray passes."""
        xm, ym = self.px_to_mm(px_x, px_y)
        bx, by = cx + pdx, cy + pdy
        singlet = self.lens.is_singlet
        tr = trace_backward_fast(self.lens, bx, by, self.d_in, (xm - cx) / self.f_x,
                                 (ym - cy) / self.f_x, ratio=not singlet)
        if singlet:
            rho = np.hypot(tr.x, tr.y) / (0.5 * self.lens.pupil_diameter_mm)
        else:
            rho = tr.rho
        rho = np.where(np.isfinite(rho), rho, 10.0)
        return np.where(tr.ok, rho, np.maximum(rho, 10.0)), tr

    def _aperture_offsets(self, rng, n):
        s, t = rng.random(n), rng.random(n)
        k = rng.integers(0, 3, n) if self.grid.grid == "hex" else None
        return self.grid.aperture_samples(s, t, k)

    def _aperture_vertices(self):
        if self.grid.grid == "rect":
            s = np.array([0.0, 1.0, 0.0, 1.0])
            t = np.array([0.0, 0.0, 1.0, 1.0])
            return self.grid.aperture_samples(s, t)
        k = np.concatenate([np.arange(3), np.arange(3)])
        t = np.concatenate([np.zeros(3), np.ones(3)])
        return self.grid.aperture_samples(np.ones(6), t, k)

    def _radiance(self, scene_planes, white, tr):
        """Radiance along backward rays that left the front surface (tr from the trace)."""
        out = np.full(tr.x.shape, white if white is not None else 0.0)
        hit = np.zeros(tr.x.shape, dtype=bool)
        for plane in scene_planes:  # nearest first
            z = self.lens.front_vertex_z_mm - plane.distance_mm
            t = (z - tr.z) / tr.dz
            hx = tr.x + t * tr.dx - plane.center_mm[0]
            hy = tr.y + t * tr.dy - plane.center_mm[1]
            inside = ~hit
            if plane.size_mm is not None:
                inside &= (np.abs(hx) <= 0.5 * plane.size_mm[0]) & (
                    np.abs(hy) <= 0.5 * plane.size_mm[1])
            out = np.where(inside, _texture(plane, hx, hy), out)
            hit |= inside
        return out

    def _backward(self, scene: Scene, rng: np.random.Generator, acc: Accumulator,
                  lens_complete: np.ndarray) -> dict:
        planes = sorted((o for o in scene.objects if isinstance(o, TexturedPlane)),
                        key=lambda p: p.distance_mm)
        whites = [o for o in scene.objects if isinstance(o, WhiteScene)]
        white = sum(w.radiance for w in whites) if whites else None
        only_white = not planes
        r_mi = self.micro_image_radius_px()
        h = int(math.ceil(1.15 * r_mi + 2.0))
        centres = self.predicted_centres_px()
        cpx = np.rint(centres[:, 0]).astype(np.int64)
        cpy = np.rint(centres[:, 1]).astype(np.int64)
        lens_complete[:] = (cpx - h >= 0) & (cpx + h < self.width) & (cpy - h >= 0) & (
            cpy + h < self.height)
        # keep lenslets whose box touches the sensor
        touch = (cpx + h >= 0) & (cpx - h < self.width) & (cpy + h >= 0) & (cpy - h < self.height)
        lens_ids = np.nonzero(touch)[0]
        nc = 2 * h + 2
        corner = np.arange(nc) - h - 0.5
        pix = np.arange(2 * h + 1) - h
        a_ap = self.grid.aperture_area_mm2
        scale = a_ap / (self.f_x * self.f_x) * self.pp * self.pp
        # Gauss–Legendre quadrature of cos⁴ over the aperture (4×4 on the square, 3×3 on each
        # of the hexagon's three rhombi: the maps are affine, so the rules stay exact for
        # polynomials of degree 7 / 5), for fully lit pixels
        if self.grid.grid == "rect":
            nodes, wts = np.polynomial.legendre.leggauss(4)
        else:
            nodes, wts = np.polynomial.legendre.leggauss(3)
        qs, qt = np.meshgrid(0.5 * (nodes + 1), 0.5 * (nodes + 1))
        qw = np.outer(wts, wts).ravel() / 4.0
        if self.grid.grid == "rect":
            qdx, qdy = self.grid.aperture_samples(qs.ravel(), qt.ravel())
        else:
            kk = np.repeat(np.arange(3), qw.size)
            qdx, qdy = self.grid.aperture_samples(np.tile(qs.ravel(), 3), np.tile(qt.ravel(), 3),
                                                  kk)
            qw = np.tile(qw, 3) / 3.0
        vdx, vdy = self._aperture_vertices()
        stats = {"corner_rays": 0, "boundary_pixels": 0, "full_pixels": 0, "boundary_rays": 0,
                 "interior_rays": 0, "box_edge_lit": 0, "micro_image_radius_px": r_mi,
                 "box_half_px": h}
        per_chunk = max(1, CHUNK_RAYS // (nc * nc))
        n_spp = scene.samples_per_pixel
        k_spp = max(1, int(round(math.sqrt(n_spp))))
        for c0 in range(0, lens_ids.size, per_chunk):
            ids = lens_ids[c0:c0 + per_chunk]
            m = ids.size
            cx = self.lcx[ids][:, None, None]
            cy = self.lcy[ids][:, None, None]
            gx = cpx[ids][:, None, None] + corner[None, None, :]
            gy = cpy[ids][:, None, None] + corner[None, :, None]
            gx, gy = np.broadcast_arrays(gx, gy)
            cxb = np.broadcast_to(cx, gx.shape)
            cyb = np.broadcast_to(cy, gx.shape)
            rho, _ = self._rho(gx.ravel(), gy.ravel(), cxb.ravel(), cyb.ravel())
            rho = rho.reshape(m, nc, nc)
            stats["corner_rays"] += rho.size
            # margin: how much moving the crossing point over the lenslet aperture changes ρ
            probe = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]]) * (0.7 * r_mi)
            px_probe = centres[ids][:, None, :] + probe[None, :, :]  # (m, 4, 2)
            base, _ = self._rho(px_probe[..., 0].ravel(), px_probe[..., 1].ravel(),
                                np.repeat(self.lcx[ids], 4), np.repeat(self.lcy[ids], 4))
            worst = np.zeros(m * 4)
            for vx, vy in zip(vdx, vdy, strict=True):
                moved, _ = self._rho(px_probe[..., 0].ravel(), px_probe[..., 1].ravel(),
                                     np.repeat(self.lcx[ids], 4), np.repeat(self.lcy[ids], 4),
                                     vx, vy)
                both = (moved < 5.0) & (base < 5.0)
                worst = np.maximum(worst, np.where(both, np.abs(moved - base), 0.0))
            margin = 1.5 * worst.reshape(m, 4).max(axis=1)[:, None, None] + 1e-3
            c00, c01 = rho[:, :-1, :-1], rho[:, :-1, 1:]
            c10, c11 = rho[:, 1:, :-1], rho[:, 1:, 1:]
            rmax = np.maximum(np.maximum(c00, c01), np.maximum(c10, c11))
            rmin = np.minimum(np.minimum(c00, c01), np.minimum(c10, c11))
            full = rmax + margin < 1.0
            empty = rmin - (rmax - rmin) - margin > 1.0
            bnd = ~(full | empty)
            edge = np.ones((2 * h + 1, 2 * h + 1), dtype=bool)
            edge[1:-1, 1:-1] = False
            stats["box_edge_lit"] += int((~empty & edge[None]).sum())
            ppx = np.broadcast_to(cpx[ids][:, None, None] + pix[None, None, :], full.shape)
            ppy = np.broadcast_to(cpy[ids][:, None, None] + pix[None, :, None], full.shape)
            lidx = np.broadcast_to(ids[:, None, None], full.shape)
            lcx = np.broadcast_to(cx, full.shape)
            lcy = np.broadcast_to(cy, full.shape)
            # ---- fully lit pixels
            fx, fy = ppx[full].astype(np.float64), ppy[full].astype(np.float64)
            fl, fcx, fcy = lidx[full], lcx[full], lcy[full]
            stats["full_pixels"] += fx.size
            xm, ym = self.px_to_mm(fx, fy)
            c4 = np.zeros(fx.size)
            for ddx, ddy, ww in zip(qdx, qdy, qw, strict=True):
                q2 = ((xm - fcx - ddx) ** 2 + (ym - fcy - ddy) ** 2) / (self.f_x ** 2)
                c4 += ww / (1.0 + q2) ** 2
            if only_white:
                acc.add(fx, fy, white * scale * c4, fl)
            else:
                # radiance by Monte Carlo, the cos⁴ integral by quadrature (no aperture loss)
                self._sample_pixels(fx, fy, fl, fcx, fcy, scene.interior_samples, 1, rng, acc,
                                    planes, white, scale, stats, "interior_rays", c4)
            # ---- boundary pixels
            bx, by = ppx[bnd].astype(np.float64), ppy[bnd].astype(np.float64)
            stats["boundary_pixels"] += bx.size
            self._sample_pixels(bx, by, lidx[bnd], lcx[bnd], lcy[bnd], k_spp * k_spp, k_spp,
                                rng, acc, planes, white, scale, stats, "boundary_rays")
        return stats

    def _sample_pixels(self, px, py, lidx, lcx, lcy, n_s, k_s, rng, acc, planes, white, scale,
                       stats, key, cos4=None) -> None:
        """Integrate pixels with ``n_s`` backward rays each (k_s×k_s jittered strata)."""
        if px.size == 0:
            return
        per = max(1, CHUNK_RAYS // n_s)
        if k_s * k_s == n_s:
            gi, gj = np.meshgrid(np.arange(k_s), np.arange(k_s), indexing="xy")
            gi, gj = gi.ravel(), gj.ravel()
        for p0 in range(0, px.size, per):
            sl = slice(p0, p0 + per)
            m = px[sl].size
            if k_s * k_s == n_s:
                jx = (np.tile(gi, m) + rng.random(m * n_s)) / k_s - 0.5
                jy = (np.tile(gj, m) + rng.random(m * n_s)) / k_s - 0.5
            else:
                jx = rng.random(m * n_s) - 0.5
                jy = rng.random(m * n_s) - 0.5
            sx = np.repeat(px[sl], n_s) + jx
            sy = np.repeat(py[sl], n_s) + jy
            cx = np.repeat(lcx[sl], n_s)
            cy = np.repeat(lcy[sl], n_s)
            ddx, ddy = self._aperture_offsets(rng, m * n_s)
            xm, ym = self.px_to_mm(sx, sy)
            bx, by = cx + ddx, cy + ddy
            tr = trace_backward_fast(self.lens, bx, by, self.d_in, (xm - cx) / self.f_x,
                                     (ym - cy) / self.f_x)
            q2 = ((xm - bx) ** 2 + (ym - by) ** 2) / (self.f_x ** 2)
            rad = self._radiance(planes, white, tr)
            c4 = 1.0 / (1.0 + q2) ** 2 if cos4 is None else np.repeat(cos4[sl], n_s)
            w = np.where(tr.ok, rad * scale / n_s * c4, 0.0)
            stats[key] += sx.size
            acc.add(sx, sy, w, np.repeat(lidx[sl], n_s))

    # ------------------------------------------------------------------ public
    def render(self, scene: Scene, progress=None) -> RenderResult:
        """Render a scene's noiseless signal and its ray-derived truth.

        ``progress("rendering", done, total)`` (:data:`lfcam.progress.Progress`), if given,
        is called after the backward pass and after
        each source.
        """
        acc = Accumulator(self.height, self.width, self.li.size)
        seq = np.random.SeedSequence(scene.seed)
        streams = [np.random.default_rng(s) for s in seq.spawn(len(scene.objects) + 1)]
        complete = np.zeros(self.li.size, dtype=bool)
        stats: dict = {}
        backward = any(isinstance(o, (WhiteScene, TexturedPlane)) for o in scene.objects)
        n_forward = sum(isinstance(o, (PointSource, LineSource)) for o in scene.objects)
        steps, done = n_forward + int(backward), 0
        if backward:
            stats = self._backward(scene, streams[-1], acc, complete)
            done += 1
            if progress is not None:
                progress("rendering", done, steps)
        sources = []
        z_front = self.lens.front_vertex_z_mm
        for k, obj in enumerate(scene.objects):
            rng = streams[k]
            if progress is not None and isinstance(obj, (PointSource, LineSource)):
                progress("rendering", done, steps)
                done += 1
            if isinstance(obj, PointSource):
                n = obj.rays or scene.rays_per_source
                before = acc.image.copy()
                info = self._forward_source((obj.x_mm, obj.y_mm, z_front - obj.distance_mm),
                                            obj.intensity, n, rng, acc)
                info["index"] = k
                info["kind"] = "point"
                info["energy_image"] = float((acc.image - before).sum())
                sources.append(info)
            elif isinstance(obj, LineSource):
                n_pts = obj.points or max(16, int(math.ceil(obj.length_mm / 0.05)))
                n_rays = obj.rays or scene.rays_per_source
                per_pt = max(1, n_rays // n_pts)
                tpos = (np.arange(n_pts) + rng.random(n_pts)) / n_pts
                total = {"power_through_aperture": 0.0, "power_on_sensor": 0.0, "sum_x": 0.0,
                         "sum_y": 0.0}
                for t in tpos:
                    x = obj.start_mm[0] + t * (obj.end_mm[0] - obj.start_mm[0])
                    y = obj.start_mm[1] + t * (obj.end_mm[1] - obj.start_mm[1])
                    info = self._forward_source((x, y, z_front - obj.distance_mm),
                                                obj.intensity * obj.length_mm / n_pts, per_pt,
                                                rng, acc)
                    for key in total:
                        total[key] += info[key]
                total.update(index=k, kind="line", points=n_pts)
                sources.append(total)
        if progress is not None and n_forward:
            progress("rendering", steps, steps)
        with np.errstate(invalid="ignore", divide="ignore"):
            cen = np.stack([acc.lens_wx / acc.lens_w, acc.lens_wy / acc.lens_w], axis=1)
        cen[acc.lens_w <= 0] = np.nan
        return RenderResult(
            signal=acc.image.reshape(self.height, self.width),
            lens_i=self.li, lens_j=self.lj,
            lens_centre_mm=np.stack([self.lcx, self.lcy], axis=1),
            lens_weight=acc.lens_w, lens_centroid_px=cen, lens_complete=complete,
            sources=sources, stats=stats,
        )


def _texture(plane: TexturedPlane, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Radiance of a textured plane at plane coordinates (mm, relative to its centre)."""
    if plane.texture == "uniform":
        return np.full(x.shape, plane.high)
    ix = np.floor(x / plane.square_mm).astype(np.int64)
    iy = np.floor(y / plane.square_mm).astype(np.int64)
    if plane.texture == "checkerboard":
        return np.where((ix + iy) % 2 == 0, plane.high, plane.low)
    # random: a hash of the cell index and the plane's seed → uniform value in [low, high]
    h = (ix * np.int64(73856093)) ^ (iy * np.int64(19349663)) ^ np.int64(plane.seed * 83492791
                                                                            % (2**31))
    h = (h * np.int64(2654435761)) % np.int64(2**32)
    u = h.astype(np.float64) / 2.0**32
    return plane.low + (plane.high - plane.low) * u
