"""Point- and line-source captures from a second rendering path: per-pixel irradiance by the
Jacobian of the exact ray map (no random ray binning, no :mod:`lfcam.sim`, no
:mod:`lfcam.measure`). A line is the midpoint rule over point renders along it
(:func:`render_line`, docs/simulate.md).

Camera model (the contract of ``lfcam.sim`` and of the lenslet fit, docs/simulate.md): a point
source S sends rays toward points ``q`` of the aperture plane ``z = rim_z`` (the front rim of
the singlet); each ray is traced exactly through the main lens (:mod:`lfcam.optics.raytrace`,
the one part shared with ``lfcam.sim``) to the MLA plane ``z = d_in``, enters the lenslet k whose
cell (clear aperture) it crosses there and, ideal thin lenslet focused at infinity, lands on
the sensor at ``s = C_k + f_x·σ`` with ``σ = (dx/dz, dy/dz)`` its slope after the lens. A ray
carries ``I·dΩ = I·lz/r³ dq`` (``lz`` source → aperture plane along z, ``r`` source → q).

Irradiance. Within one lenslet cell, ``s(q) = C_k + f_x·σ(q)`` is smooth and one-to-one, and
``σ`` does not depend on k. So the irradiance at sensor point s is

    E(s) = Σ_k  I·lz/r³(q_k) / (f_x² · |det ∂σ/∂q (q_k)|),   σ(q_k) = (s − C_k)/f_x,

a term counting only if ``q_k`` lies in the aperture disc, the ray passes every clear aperture
of the lens (exact trace) and it crosses the MLA inside cell k. ``q_k`` is found by Newton
iterations on the exact trace (finite-difference Jacobian), started from a polynomial fit of
the inverse map ``q(σ)`` over a coarse pupil grid (one map for every lenslet).

Pixels. A coarse pupil grid (``coarse`` × ``coarse`` rays, traced without clipping so that it
extends past the rim) gives every lenslet that can receive light — the cell each ray hits and
any cell within ε of it on the MLA (ε = 1.5 × the grid's MLA footprint spacing) — and a box on
the sensor that provably holds the lenslet's micro-image (the grid points' images widened by
1.5 × their sensor spacing). Each box is integrated by the midpoint rule on a sub-pixel grid
aligned with the pixels: at least ``n_sub`` × ``n_sub`` points a pixel, more for micro-images
that are small (a defocused point lights each lenslet with a spot of a fraction of a pixel):
at least ``min_across`` points across the lenslet's spot (the narrow side of its box, or the
square root of its lit area when that is smaller; at most ``max_samples`` points a lenslet).
The boundaries of the light (pupil rim, the lens's clear apertures, the sides of the lenslet's
aperture) are level sets of smooth functions of q; carried to the sensor by the inverse Jacobian
each is a straight edge across a sub-pixel cell, which is weighted by its share on the lit side
(:func:`_square_share`, exact for a straight edge). Pixel value = mean of E × share over its
points × pixel area; overlapping micro-images add.

Sensor (as the project's benchmarks): brightest pixel at ``peak`` of full scale, Poisson photon
noise at ``full_well_e``, Gaussian read noise ``read_noise_e``, rounded to ``bit_depth`` bits
and clipped; the image is returned as float64 in [0, 1].

Run:  python benchmarks/render_independent.py [--system system2] [--size 384]
      [--focus 1000] [--distance 600] [--field 0.5]
It renders one capture, and prints the flux check (image sum against a polar Gauss–Legendre
quadrature of the ray weights over the pupil) and the render time.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lfcam.camera import CameraProfile  # noqa: E402
from lfcam.optics import raytrace as rt  # noqa: E402
from lfcam.optics.mla import MlaGrid  # noqa: E402
from lfcam.optics.trace import pupil_map  # noqa: E402

POLY_DEGREE = 5  # degree of the inverse-map fit q(σ) that starts Newton
NEWTON_TOL_MM = 1e-8  # |f_x·(σ(q) − σ_target)| at convergence, mm on the sensor
NEWTON_MAX = 12
CHUNK = 200_000  # sensor sample points per Newton batch
# Line sources: nodes of the midpoint rule, and each node's sampling. The sum over nodes
# smooths the image along the line, and each node's edges are weighted by their exact share,
# so a node needs less sampling than a lone point (measured in docs/simulate.md).
LINE_MIN_POINTS = 32
LINE_N_SUB = 8
LINE_MIN_ACROSS = 16  # 8 made point sources behind focus fit +0.07 % long (0.00-0.11), 16 and 32
#                       agree within 0.04 % (docs/simulate.md)


@dataclass
class PointRender:
    """Noise-free render of one point source.

    Attributes
    ----------
    signal : (H, W) ndarray
        Power per pixel (``I·sr`` units, as ``lfcam.sim``'s signal).
    lens_ij : (N, 2) ndarray of int64
        Lattice indices (i, j) of the lenslets that put light on the sensor.
    lens_energy : (N,) ndarray
        Each lenslet's power on the sensor (sum of its share of the pixels).
    stats : dict
        Sample and trace counts, Newton failures.
    """

    signal: np.ndarray
    lens_ij: np.ndarray
    lens_energy: np.ndarray
    stats: dict


class IndependentRenderer:
    """Jacobian-irradiance renderer of point sources for one camera profile.

    Parameters
    ----------
    profile : CameraProfile
        Needs a known d_in (``mla.distance_mm`` or ``mla.focus_mm``).
    n_sub : int
        Minimum sub-pixel grid per pixel (``n_sub`` × ``n_sub`` points).
    min_across : int
        Minimum points across the narrow side of each micro-image box.
    max_samples : int
        Most sample points per lenslet (bounds thin slivers).
    coarse : int
        Coarse pupil grid, ``coarse`` × ``coarse`` rays.
    """

    def __init__(self, profile: CameraProfile, n_sub: int = 4, min_across: int = 32,
                 max_samples: int = 40_000, coarse: int = 256) -> None:
        self.profile = profile
        self.lens = profile.main_lens
        self.rx = self.lens.as_prescription
        self.fv = self.lens.front_vertex_z_mm
        self.rim_z = self.lens.rim_z_mm
        self.d_in = profile.d_in_mm
        self.f_x = profile.mla.focal_length_mm
        self.grid = MlaGrid.from_mla(profile.mla)
        s = profile.sensor
        self.pp = s.pixel_pitch_mm
        self.width, self.height = s.width_px, s.height_px
        self.ax, self.ay = s.axis_xy_px
        self.n_sub = int(n_sub)
        self.min_across = int(min_across)
        self.max_samples = int(max_samples)
        self.coarse = int(coarse)

    # ------------------------------------------------------------------ the exact ray map
    def _trace(self, src: np.ndarray, qx: np.ndarray, qy: np.ndarray,
               with_ratio: bool = False):
        """Rays from ``src`` toward aperture-plane points (qx, qy), unclipped, to the MLA.

        Returns
        -------
        mx, my : ndarray
            MLA-plane crossing (mm); NaN where the trace fails (misses a surface, TIR).
        sx, sy : ndarray
            Slopes dx/dz, dy/dz after the lens.
        ok : ndarray of bool
            The ray passes every clear aperture (ρ² ≤ semi-diameter²·(1 + tolerance));
            with ``with_ratio`` the measure ρ²/semi-diameter² itself (max over surfaces).
        """
        sxs, sys_, szs = src
        res = rt.trace_components(self.rx, sxs, sys_, szs - self.fv, qx - sxs, qy - sys_,
                                  self.rim_z - szs, self.d_in - self.fv, clip=False, ratio=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            slx = res.dx / res.dz
            sly = res.dy / res.dz
        fin = (res.status == 0) & np.isfinite(res.x) & np.isfinite(slx) & np.isfinite(sly)
        if with_ratio:
            return res.x, res.y, slx, sly, res.ratio, fin
        ok = fin & (res.ratio <= 1.0 + rt.RIM_TOLERANCE)
        return res.x, res.y, slx, sly, ok, fin

    def _weight(self, src: np.ndarray, qx: np.ndarray, qy: np.ndarray) -> np.ndarray:
        """Solid angle per unit aperture-plane area, ``lz/r³`` (unit intensity)."""
        lz = self.rim_z - src[2]
        r2 = (qx - src[0]) ** 2 + (qy - src[1]) ** 2 + lz * lz
        return lz / (r2 * np.sqrt(r2))

    def aperture(self, src: np.ndarray) -> tuple[float, float, float, bool]:
        """Aperture-plane disc of the pupil parameter: (centre x, centre y, radius, exact).

        For a stop on the front surface (the singlet) it is the rim, exactly (``exact``);
        otherwise a disc 10 % larger than the real stop's image from the source, the real stop
        being enforced by the exact trace.
        """
        half = 0.5 * self.lens.pupil_diameter_mm
        if self.rx.stop_index == 0:
            return 0.0, 0.0, half, True
        cx, cy, ex, ey = pupil_map(self.lens, tuple(src))
        return cx, cy, 1.1 * half * max(abs(ex), abs(ey)), False

    def in_domain(self, src, qx, qy) -> np.ndarray:
        """Whether aperture-plane points are inside the pupil disc (:meth:`aperture`)."""
        cx, cy, rad, _ = self.aperture(src)
        return (qx - cx) ** 2 + (qy - cy) ** 2 <= rad * rad

    # ------------------------------------------------------------------ one source
    def _coarse(self, src: np.ndarray):
        """Coarse grid over the pupil: inverse-map fit, lenslet boxes and sampling steps."""
        cx, cy, rad, _ = self.aperture(src)
        g = self.coarse
        dq = 2.0 * rad * (1.0 + 2.0 / g) / (g - 1)
        ax = (np.arange(g) - 0.5 * (g - 1)) * dq
        qy, qx = np.meshgrid(cy + ax, cx + ax, indexing="ij")
        mx, my, slx, sly, _, fin = self._trace(src, qx, qy)
        # Lipschitz bounds of the maps q → m (MLA) and q → σ, from grid differences
        def lip(a, b):
            ga = np.stack([np.diff(a, axis=0)[:, :-1], np.diff(a, axis=1)[:-1, :]])
            gb = np.stack([np.diff(b, axis=0)[:, :-1], np.diff(b, axis=1)[:-1, :]])
            fro = np.sqrt((ga ** 2).sum(0) + (gb ** 2).sum(0)) / dq
            return float(np.nanmax(fro))
        near = fin & ((qx - cx) ** 2 + (qy - cy) ** 2 <= (rad + dq) ** 2)
        # sensor area (px²) each grid cell's rays cover: f_x²·|det ∂σ/∂q|·dq² / pp²
        with np.errstate(invalid="ignore"):
            gxx, gxy = np.gradient(slx, dq)
            gyx, gyy = np.gradient(sly, dq)
        cell_px2 = np.abs(gxx * gyy - gxy * gyx) * (dq * self.f_x / self.pp) ** 2
        lit = self.in_domain(src, qx, qy) & _ok_mask(self, src, qx, qy)
        if not near.any():
            return None
        lip_m = lip(np.where(fin, mx, np.nan), np.where(fin, my, np.nan))
        lip_s = lip(np.where(fin, slx, np.nan), np.where(fin, sly, np.nan))
        eps = 1.5 * lip_m * dq  # MLA reach of a grid cell (≥ 2× the worst half-diagonal)
        delta = 1.5 * lip_s * dq * self.f_x / self.pp  # sensor reach, px
        mx, my, slx, sly = mx[near], my[near], slx[near], sly[near]
        cell_px2 = np.where(lit[near] & np.isfinite(cell_px2[near]), cell_px2[near], 0.0)
        qxn, qyn = qx[near], qy[near]
        # inverse map q(σ): least squares polynomial in normalised σ
        mu = np.array([slx.mean(), sly.mean()])
        sc = max(float(np.ptp(slx)), float(np.ptp(sly)), 1e-12) / 2.0
        dom = self.in_domain(src, qxn, qyn)
        basis = _poly_basis((slx[dom] - mu[0]) / sc, (sly[dom] - mu[1]) / sc)
        coef, *_ = np.linalg.lstsq(basis, np.stack([qxn[dom], qyn[dom]], 1), rcond=None)
        # candidate lenslets: the cell of each grid point and every cell within eps of it
        ang = np.arange(8) * (math.pi / 4)
        offs = np.concatenate([[[0.0, 0.0]], eps * np.stack([np.cos(ang), np.sin(ang)], 1)])
        ii, jj, pts = [], [], []
        idx = np.arange(mx.size)
        for ox, oy in offs:
            i, j, _, _ = self.grid.nearest(mx + ox, my + oy)
            ii.append(i)
            jj.append(j)
            pts.append(idx)
        ii, jj, pts = np.concatenate(ii), np.concatenate(jj), np.concatenate(pts)
        i0, j0 = int(ii.min()), int(jj.min())
        nj = int(jj.max()) - j0 + 1
        key = (ii - i0) * nj + (jj - j0)
        ukey, inv = np.unique(key, return_inverse=True)
        lci, lcj = ukey // nj + i0, ukey % nj + j0
        ccx, ccy = self.grid.centre_mm(lci, lcj)
        spx = (ccx[inv] + self.f_x * slx[pts]) / self.pp + self.ax
        spy = (ccy[inv] + self.f_x * sly[pts]) / self.pp + self.ay
        n = ukey.size
        lo_x = np.full(n, np.inf)
        hi_x = np.full(n, -np.inf)
        lo_y = np.full(n, np.inf)
        hi_y = np.full(n, -np.inf)
        np.minimum.at(lo_x, inv, spx)
        np.maximum.at(hi_x, inv, spx)
        np.minimum.at(lo_y, inv, spy)
        np.maximum.at(hi_y, inv, spy)
        # the sampling step follows the lenslet's own spot: the images of the grid points
        # inside its cell (the box above also holds its neighbours' reach, a superset)
        core = np.zeros(spx.size, dtype=bool)
        core[: mx.size] = True  # offset (0, 0) comes first
        cw = np.full(n, np.inf)
        cl = np.full(n, np.inf)
        ch = np.full(n, -np.inf)
        cr = np.full(n, -np.inf)
        np.minimum.at(cl, inv[core], spx[core])
        np.maximum.at(cr, inv[core], spx[core])
        np.minimum.at(cw, inv[core], spy[core])
        np.maximum.at(ch, inv[core], spy[core])
        # ... and its lit area: a micro-image of several parts (a spot and a caustic arc, when
        # the aberrated beam crosses the MLA near its focus) is resolved by its area
        area = np.bincount(inv[core], weights=cell_px2, minlength=n)
        narrow = np.minimum(np.minimum(cr - cl, ch - cw) + 2.0 * delta, np.sqrt(area))
        narrow = np.where(np.isfinite(narrow) & (narrow > 0), narrow, 2.0 * delta)
        lo_x -= delta
        hi_x += delta
        lo_y -= delta
        hi_y += delta
        return {"coef": coef, "mu": mu, "sc": sc, "i": lci, "j": lcj, "cx": ccx, "cy": ccy,
                "box": (lo_x, hi_x, lo_y, hi_y), "narrow_px": narrow, "eps_mm": eps,
                "delta_px": delta,
                "dq_mm": dq}

    def _start(self, c: dict, tx: np.ndarray, ty: np.ndarray):
        b = _poly_basis((tx - c["mu"][0]) / c["sc"], (ty - c["mu"][1]) / c["sc"])
        q = b @ c["coef"]
        return q[:, 0], q[:, 1]

    def _solve(self, src, c, tx, ty):
        """Newton: pupil points whose slope after the lens is (tx, ty).

        Returns
        -------
        dict
            ``qx, qy`` solution; ``conv`` converged; ``jac`` (n, 2, 2) ∂σ/∂q there and
            ``jm`` (n, 2, 2) ∂m/∂q (m: MLA crossing, also returned as ``mx, my``); ``ratio``
            and ``gratio`` (n, 2): the trace's vignetting measure (ρ²/semi-diameter², ≤ 1
            passes) and its gradient in q.
        """
        qx, qy = self._start(c, tx, ty)
        n = tx.size
        out = {"conv": np.zeros(n, dtype=bool), "jac": np.full((n, 2, 2), np.nan),
               "jm": np.full((n, 2, 2), np.nan), "mx": np.full(n, np.nan),
               "my": np.full(n, np.nan), "ratio": np.full(n, np.inf),
               "gratio": np.zeros((n, 2)), "traced": 0}
        cx0, cy0, rad, _ = self.aperture(src)
        h = 1e-6 * rad
        # samples whose start lies far outside the pupil cannot have a solution inside it
        act = np.flatnonzero((qx - cx0) ** 2 + (qy - cy0) ** 2 <= (1.2 * rad) ** 2)
        tol = NEWTON_TOL_MM / self.f_x
        for _ in range(NEWTON_MAX):
            if act.size == 0:
                break
            ax_, ay_ = qx[act], qy[act]
            m = act.size
            px = np.concatenate([ax_, ax_ + h, ax_])
            py = np.concatenate([ay_, ay_, ay_ + h])
            rmx, rmy, rsx, rsy, rat, rfin = self._trace(src, px, py, with_ratio=True)
            out["traced"] += px.size
            a0, a1, a2 = slice(0, m), slice(m, 2 * m), slice(2 * m, 3 * m)
            f0x, f0y = rsx[a0] - tx[act], rsy[a0] - ty[act]
            j11 = (rsx[a1] - rsx[a0]) / h
            j21 = (rsy[a1] - rsy[a0]) / h
            j12 = (rsx[a2] - rsx[a0]) / h
            j22 = (rsy[a2] - rsy[a0]) / h
            d = j11 * j22 - j12 * j21
            good = rfin[a0] & rfin[a1] & rfin[a2] & np.isfinite(d) & (d != 0.0)
            done = good & (np.hypot(f0x, f0y) <= tol)
            # converged at the evaluated point: keep its Jacobians, crossing and vignetting
            sel = act[done]
            out["conv"][sel] = True
            out["jac"][sel] = np.stack([np.stack([j11, j12], -1),
                                        np.stack([j21, j22], -1)], -2)[done]
            out["jm"][sel] = np.stack([
                np.stack([(rmx[a1] - rmx[a0]) / h, (rmx[a2] - rmx[a0]) / h], -1),
                np.stack([(rmy[a1] - rmy[a0]) / h, (rmy[a2] - rmy[a0]) / h], -1)], -2)[done]
            out["mx"][sel], out["my"][sel] = rmx[a0][done], rmy[a0][done]
            out["ratio"][sel] = rat[a0][done]
            out["gratio"][sel] = np.stack([(rat[a1] - rat[a0]) / h,
                                           (rat[a2] - rat[a0]) / h], -1)[done]
            step = good & ~done
            with np.errstate(invalid="ignore", divide="ignore"):
                dx = (j22 * f0x - j12 * f0y) / d
                dy = (-j21 * f0x + j11 * f0y) / d
            # damp steps longer than a tenth of the pupil radius (starts are close)
            ln = np.hypot(dx, dy)
            fac = np.where(ln > 0.1 * rad, 0.1 * rad / np.where(ln > 0, ln, 1.0), 1.0)
            nxt = act[step]
            qx[nxt] = ax_[step] - fac[step] * dx[step]
            qy[nxt] = ay_[step] - fac[step] * dy[step]
            # leave samples that have wandered far outside the pupil
            keep = (qx[nxt] - cx0) ** 2 + (qy[nxt] - cy0) ** 2 <= (1.3 * rad) ** 2
            act = nxt[keep]
        out["qx"], out["qy"] = qx, qy
        return out

    def _coverage(self, src, sol, ci, cj, h_px) -> np.ndarray:
        """Share of each sub-pixel cell (side ``h_px``) inside lenslet (ci, cj)'s light.

        Every boundary of the light — the pupil disc, the lens's clear apertures (the trace's
        ρ² ≤ semi-diameter²) and the sides of the lenslet's clear aperture on the MLA — is a
        level set ``g = 0`` of a smooth function of the pupil point. Carried to the sensor by
        the inverse Jacobian it is a straight edge across the cell to first order, cut
        exactly (:func:`_square_share`); the cell keeps the smallest share.
        """
        qx, qy = sol["qx"], sol["qy"]
        jac = sol["jac"]
        det = jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0]
        scale = self.pp / self.f_x  # sensor px per unit of f_x·σ … as mm → px

        def to_px(gqx, gqy):
            # ∇_s g = ∇_q g · (f_x·∂σ/∂q)⁻¹, per sensor pixel
            gx = (gqx * jac[:, 1, 1] - gqy * jac[:, 1, 0]) / det * scale
            gy = (-gqx * jac[:, 0, 1] + gqy * jac[:, 0, 0]) / det * scale
            return gx, gy

        cx, cy, rad, _ = self.aperture(src)
        ex, ey = qx - cx, qy - cy
        r = np.maximum(np.hypot(ex, ey), 1e-300)
        share = _square_share(rad - r, *to_px(-ex / r, -ey / r), h_px)
        lim = 1.0 + rt.RIM_TOLERANCE
        share = np.minimum(share, _square_share(lim - sol["ratio"],
                                                *to_px(-sol["gratio"][:, 0],
                                                       -sol["gratio"][:, 1]), h_px))
        lcx, lcy = self.grid.centre_mm(ci, cj)
        dmx, dmy = sol["mx"] - lcx, sol["my"] - lcy
        half = 0.5 * self.grid.pitch_mm * self.grid.fill_factor
        jm = sol["jm"]
        for nx, ny in _edge_normals(self.grid):
            proj = dmx * nx + dmy * ny
            # ∇_q (n·m) = n·∂m/∂q
            gqx = nx * jm[:, 0, 0] + ny * jm[:, 1, 0]
            gqy = nx * jm[:, 0, 1] + ny * jm[:, 1, 1]
            gx, gy = to_px(gqx, gqy)
            # the strip −half ≤ n·(m − C) ≤ half, both sides at once (a thin strip can lie
            # inside one cell): P(below the upper side) − P(below the lower side)
            strip = (_square_share(half - proj, -gx, -gy, h_px)
                     + _square_share(half + proj, gx, gy, h_px) - 1.0)
            share = np.minimum(share, np.maximum(strip, 0.0))
        return np.where(sol["conv"] & np.isfinite(share), share, 0.0)

    def render_point(self, source_xyz: tuple[float, float, float],
                     intensity: float = 1.0) -> PointRender:
        """Noise-free image of one point source at ``source_xyz`` (profile frame, mm).

        Parameters
        ----------
        source_xyz : tuple of float
            Source position; ``z = front_vertex_z − distance``.
        intensity : float
            Power per steradian.

        Returns
        -------
        PointRender
        """
        src = np.asarray(source_xyz, dtype=np.float64)
        img = np.zeros(self.height * self.width)
        stats = {"samples": 0, "traced_rays": 0, "not_converged": 0, "lenslets": 0}
        c = self._coarse(src)
        if c is None:
            return PointRender(img.reshape(self.height, self.width), np.zeros((0, 2), np.int64),
                               np.zeros(0), stats)
        lo_x, hi_x, lo_y, hi_y = c["box"]
        # clip the boxes to the sensor
        lo_x, hi_x = np.maximum(lo_x, -0.5), np.minimum(hi_x, self.width - 0.5)
        lo_y, hi_y = np.maximum(lo_y, -0.5), np.minimum(hi_y, self.height - 0.5)
        live = (hi_x > lo_x) & (hi_y > lo_y)
        bw, bh = np.where(live, hi_x - lo_x, 0.0), np.where(live, hi_y - lo_y, 0.0)
        narrow = np.maximum(np.minimum(np.minimum(bw, bh), c["narrow_px"]), 1e-6)
        nk = np.maximum(self.n_sub, np.ceil(self.min_across / narrow))
        cap = np.floor(np.sqrt(self.max_samples / np.maximum(bw * bh, 1e-12)))
        nk = np.maximum(self.n_sub, np.minimum(nk, cap)).astype(np.int64)
        a0 = np.floor((lo_x + 0.5) * nk).astype(np.int64)
        a1 = np.ceil((hi_x + 0.5) * nk).astype(np.int64)
        b0 = np.floor((lo_y + 0.5) * nk).astype(np.int64)
        b1 = np.ceil((hi_y + 0.5) * nk).astype(np.int64)
        a0, b0 = np.maximum(a0, 0), np.maximum(b0, 0)
        a1 = np.minimum(a1, self.width * nk)
        b1 = np.minimum(b1, self.height * nk)
        wa, wb = np.maximum(a1 - a0, 0), np.maximum(b1 - b0, 0)
        count = np.where(live, wa * wb, 0)
        lens_energy = np.zeros(count.size)
        stats["lenslets"] = int((count > 0).sum())
        order = np.flatnonzero(count > 0)
        cum = np.cumsum(count[order])
        start = 0
        area = self.pp * self.pp
        ff = self.f_x * self.f_x
        while start < order.size:
            base = cum[start - 1] if start else 0
            stop = int(np.searchsorted(cum, base + CHUNK, side="right"))
            stop = max(stop, start + 1)
            ids = order[start:stop]
            start = stop
            cnt = count[ids]
            lk = np.repeat(ids, cnt)
            t = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
            a = a0[lk] + t % wa[lk]
            b = b0[lk] + t // wa[lk]
            n_k = nk[lk]
            xpx = -0.5 + (a + 0.5) / n_k
            ypx = -0.5 + (b + 0.5) / n_k
            tx = ((xpx - self.ax) * self.pp - c["cx"][lk]) / self.f_x
            ty = ((ypx - self.ay) * self.pp - c["cy"][lk]) / self.f_x
            sol = self._solve(src, c, tx, ty)
            stats["samples"] += int(tx.size)
            stats["traced_rays"] += sol["traced"]
            share = self._coverage(src, sol, c["i"][lk], c["j"][lk], 1.0 / n_k)
            jac = sol["jac"]
            det = np.abs(jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0])
            lit = share > 0
            e = np.zeros(tx.size)
            e[lit] = (intensity * self._weight(src, sol["qx"][lit], sol["qy"][lit])
                      / (ff * det[lit]) * share[lit])
            stats["not_converged"] += int((~sol["conv"] & self.in_domain(
                src, sol["qx"], sol["qy"])).sum())
            val = e * area / (n_k * n_k)
            img += np.bincount((b // n_k) * self.width + a // n_k, weights=val,
                               minlength=img.size)
            lens_energy += np.bincount(lk, weights=val, minlength=count.size)
        keep = lens_energy > 0
        return PointRender(img.reshape(self.height, self.width),
                           np.stack([c["i"], c["j"]], 1)[keep], lens_energy[keep], stats)

    # ------------------------------------------------------------------ checks
    def pupil_flux(self, source_xyz: tuple[float, float, float], intensity: float = 1.0,
                   n_radial: int = 256, n_angular: int = 512, on_sensor: bool = True) -> float:
        """Power through the pupil by quadrature (the independent flux check).

        Polar Gauss–Legendre nodes over the aperture disc (exact disc boundary), each weighted
        by ``I·lz/r³`` where the exact trace passes, the ray crosses a lenslet's clear aperture
        and (``on_sensor``) lands on the sensor.
        """
        src = np.asarray(source_xyz, dtype=np.float64)
        cx, cy, rad, _ = self.aperture(src)
        xr, wr = np.polynomial.legendre.leggauss(n_radial)
        r = 0.5 * rad * (xr + 1.0)
        wr = 0.5 * rad * wr * r
        th = (np.arange(n_angular) + 0.5) * (2.0 * math.pi / n_angular)
        rr, tt = np.meshgrid(r, th, indexing="ij")
        wq = np.repeat(wr, n_angular) * (2.0 * math.pi / n_angular)
        qx = cx + (rr * np.cos(tt)).ravel()
        qy = cy + (rr * np.sin(tt)).ravel()
        mx, my, slx, sly, ok, _ = self._trace(src, qx, qy)
        mxs, mys = np.where(ok, mx, 0.0), np.where(ok, my, 0.0)
        _, _, gcx, gcy = self.grid.nearest(mxs, mys)
        ok &= self.grid.in_aperture(mxs - gcx, mys - gcy)
        if on_sensor:
            px = (gcx + self.f_x * np.where(ok, slx, 0.0)) / self.pp + self.ax
            py = (gcy + self.f_x * np.where(ok, sly, 0.0)) / self.pp + self.ay
            ok &= (px >= -0.5) & (px < self.width - 0.5) & (py >= -0.5) & (
                py < self.height - 0.5)
        return float(intensity * (wq * self._weight(src, qx, qy))[ok].sum())


def _edge_normals(grid: MlaGrid) -> list[tuple[float, float]]:
    """Unit normals of the clear aperture's pairs of sides (rect: 2, hex: 3), as the lattice
    defines them (docs/conventions.md): at the rotation and, for hex, +60° and +120°."""
    t = grid.rotation_rad
    angles = (0.0, math.pi / 2) if grid.grid == "rect" else (0.0, math.pi / 3, 2 * math.pi / 3)
    return [(math.cos(t + a), math.sin(t + a)) for a in angles]


def _square_share(g0: np.ndarray, gx: np.ndarray, gy: np.ndarray, h) -> np.ndarray:
    """Share of an axis-aligned square of side ``h`` (px), centred where ``g = g0``, on the
    side ``g ≥ 0`` of the linear function with gradient (gx, gy) per px: the distribution of
    n·x over the square is the convolution of two uniforms (widths |nx|·h, |ny|·h), so the
    share is its trapezoid CDF at the signed distance ``g0/|∇g|``."""
    norm = np.hypot(gx, gy)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(norm > 0, g0 / np.where(norm > 0, norm, 1.0), np.sign(g0) * np.inf)
        u = np.abs(gx) / np.where(norm > 0, norm, 1.0) * h
        v = np.abs(gy) / np.where(norm > 0, norm, 1.0) * h
        a, b = np.maximum(u, v), np.minimum(u, v)
        lo, mid = 0.5 * (a + b), 0.5 * (a - b)
        ab2 = np.where(b > 0, 2.0 * a * b, 1.0)
        out = np.where(np.abs(t) <= mid, 0.5 + t / np.where(a > 0, a, 1.0), 0.0)
        out = np.where((t < -mid) & (t > -lo), (t + lo) ** 2 / ab2, out)
        out = np.where((t > mid) & (t < lo), 1.0 - (lo - t) ** 2 / ab2, out)
        out = np.where(t >= lo, 1.0, out)
    return np.where(np.isfinite(g0), out, 0.0)


def _ok_mask(ren: IndependentRenderer, src, qx, qy) -> np.ndarray:
    """Pass flags of the exact trace at aperture-plane points (any shape)."""
    return ren._trace(src, qx, qy)[4]


def _poly_basis(u: np.ndarray, v: np.ndarray, degree: int = POLY_DEGREE) -> np.ndarray:
    """Monomials u^a v^b, a + b ≤ degree, as columns."""
    cols = [u ** a * v ** (d - a) for d in range(degree + 1) for a in range(d + 1)]
    return np.stack(cols, axis=-1)


def source_xyz(profile: CameraProfile, distance_mm: float,
               position_mm: tuple[float, float]) -> tuple[float, float, float]:
    """Profile-frame position of a source ``distance_mm`` before the front vertex (Ad)."""
    return (float(position_mm[0]), float(position_mm[1]),
            profile.main_lens.front_vertex_z_mm - float(distance_mm))


def render_capture(profile: CameraProfile, sources: list[dict], seed: int = 0,
                   peak: float = 0.8, full_well_e: float = 20000.0, read_noise_e: float = 3.0,
                   bit_depth: int = 16, noise: bool = True, n_sub: int = 4,
                   min_across: int = 32,
                   line_per_pitch: float = 8.0) -> tuple[np.ndarray, dict]:
    """A noisy capture of point and line sources, and its truth.

    Parameters
    ----------
    profile : CameraProfile
        The camera as rendered (d_in known, overrides applied).
    sources : list of dict
        ``{"distance_mm": Ad, "position_mm": [x, y]}`` each, or ``{"type": "line",
        "distance_mm": Ad, "start_mm": [x, y], "end_mm": [x, y]}`` (the scene schema of
        docs/simulate.md; Ad from the front vertex; a line's ``intensity`` is per mm of line,
        as ``lfcam.sim``'s). Lines: :func:`render_line`.
    seed : int
        Noise seed.
    peak : float
        Brightest noise-free pixel as a fraction of full scale.
    full_well_e, read_noise_e : float
        Electrons at full scale; Gaussian read noise σ (electrons).
    bit_depth : int
        Quantisation of the output (values are multiples of 1/(2**bit_depth − 1)).
    noise : bool
        Photon and read noise (else the scaled expectation, unquantised).
    n_sub, min_across : int
        Sampling of point sources (:class:`IndependentRenderer`).
    line_per_pitch : float
        Line sources: points a lenslet pitch of the line's image on the MLA.

    Returns
    -------
    image : (H, W) float64 in [0, 1]
    truth : dict
        ``sources``: per source ``xyz_mm``, ``distance_mm``, ``position_mm``,
        ``power_on_sensor``, ``centroid_px`` (noise-free intensity centroid, x, y) and
        ``lens_ij``/``lens_energy``; ``exposure_scale``; ``signal`` (noise-free, unscaled);
        ``render_s``; ``stats``.
    """
    t0 = time.perf_counter()
    ren = IndependentRenderer(profile, n_sub=n_sub, min_across=min_across)
    line_ren = IndependentRenderer(profile, n_sub=LINE_N_SUB, min_across=LINE_MIN_ACROSS)
    total = np.zeros((profile.sensor.height_px, profile.sensor.width_px))
    out = []
    stats: list[dict] = []
    yy, xx = np.indices(total.shape)
    for obj in sources:
        if obj.get("type", "point") == "line":
            r, entry = render_line(line_ren, obj, line_per_pitch)
        else:
            xyz = source_xyz(profile, obj["distance_mm"], obj.get("position_mm", (0.0, 0.0)))
            r = ren.render_point(xyz, float(obj.get("intensity", 1.0)))
            entry = {"xyz_mm": list(xyz),
                     "position_mm": list(map(float, obj.get("position_mm", (0.0, 0.0)))),
                     "lens_ij": r.lens_ij, "lens_energy": r.lens_energy}
        total += r.signal
        p = float(r.signal.sum())
        cen = ([float((r.signal * xx).sum() / p), float((r.signal * yy).sum() / p)] if p > 0
               else None)
        out.append({**entry, "distance_mm": float(obj["distance_mm"]), "power_on_sensor": p,
                    "centroid_px": cen})
        stats.append(r.stats)
    mx = float(total.max())
    scale = peak / mx if mx > 0 else 1.0
    frac = total * scale
    if noise:
        rng = np.random.default_rng(np.random.SeedSequence([seed, 7]))
        el = rng.poisson(np.maximum(frac * full_well_e, 0.0)).astype(np.float64)
        el += rng.normal(0.0, read_noise_e, el.shape)
        top = 2 ** bit_depth - 1
        frac = np.clip(np.rint(el / full_well_e * top), 0, top) / top
    truth = {"sources": out, "exposure_scale": scale, "signal": total,
             "render_s": time.perf_counter() - t0, "stats": stats}
    return frac, truth


def line_points(profile: CameraProfile, obj: dict, per_pitch: float = 8.0
                ) -> tuple[np.ndarray, float]:
    """Midpoint-rule nodes of a line source and the weight of each (intensity × length / K).

    K = max(``LINE_MIN_POINTS``, ⌈``per_pitch`` × the line's length on the MLA in pitches⌉),
    the length on the MLA being that of its chief rays through the lens centre
    (``length · d_in / (Ad + T/2)``, paraxial).
    """
    a = np.asarray(obj["start_mm"], dtype=np.float64)
    b = np.asarray(obj["end_mm"], dtype=np.float64)
    length = float(np.hypot(*(b - a)))
    if length <= 0.0:
        raise ValueError("a line needs two distinct endpoints")
    on_mla = length * profile.d_in_mm / (float(obj["distance_mm"])
                                         + 0.5 * profile.main_lens.thickness_mm)
    k = max(LINE_MIN_POINTS, math.ceil(per_pitch * on_mla / profile.mla.pitch_mm))
    t = (np.arange(k) + 0.5) / k
    xy = a[None, :] + t[:, None] * (b - a)[None, :]
    z = profile.main_lens.front_vertex_z_mm - float(obj["distance_mm"])
    nodes = np.column_stack([xy, np.full(k, z)])
    return nodes, float(obj.get("intensity", 1.0)) * length / k


def render_line(ren: IndependentRenderer, obj: dict, per_pitch: float = 8.0
                ) -> tuple[PointRender, dict]:
    """Noise-free image of a uniform line source: a sum of point renders at midpoint nodes.

    Each node is rendered exactly (:meth:`IndependentRenderer.render_point`); only the
    integral along the line is discretised. Between adjacent nodes the chief-ray image moves
    1/``per_pitch`` of a lenslet pitch; the line's per-lenslet energies are smooth in the node
    position, so the midpoint rule converges as 1/K² on them (the convergence is measured in
    docs/simulate.md).

    Returns
    -------
    PointRender
        Summed signal; ``lens_ij``/``lens_energy`` merged over the nodes; ``stats`` summed
        with ``points``.
    dict
        Truth entry: ``xyz_mm`` (midpoint), ``start_mm``, ``end_mm``, ``points``.
    """
    nodes, w = line_points(ren.profile, obj, per_pitch)
    signal = np.zeros((ren.height, ren.width))
    energy: dict[tuple[int, int], float] = {}
    stats = {"samples": 0, "traced_rays": 0, "not_converged": 0, "lenslets": 0,
             "points": int(len(nodes))}
    for node in nodes:
        r = ren.render_point(tuple(node), w)
        signal += r.signal
        for (i, j), e in zip(r.lens_ij.tolist(), r.lens_energy.tolist(), strict=True):
            energy[(i, j)] = energy.get((i, j), 0.0) + e
        for key in ("samples", "traced_rays", "not_converged"):
            stats[key] += r.stats[key]
    stats["lenslets"] = len(energy)
    ij = np.array(sorted(energy), dtype=np.int64).reshape(-1, 2)
    lens = PointRender(signal, ij, np.array([energy[tuple(k)] for k in ij.tolist()]), stats)
    entry = {"xyz_mm": list(map(float, nodes[len(nodes) // 2])),
             "start_mm": list(map(float, obj["start_mm"])),
             "end_mm": list(map(float, obj["end_mm"])), "points": int(len(nodes))}
    return lens, entry


def main() -> None:
    """Render one capture and print its checks."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--system", default="system2")
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--focus", type=float, default=1000.0)
    ap.add_argument("--distance", type=float, default=600.0)
    ap.add_argument("--field", type=float, default=0.0, help="x offset of the source, mm")
    ap.add_argument("--n-sub", type=int, default=4)
    args = ap.parse_args()
    from lfcam.camera import load_profile

    root = Path(__file__).resolve().parents[1]
    prof = with_overrides(load_profile(root / "calibration" / f"{args.system}.toml"),
                           args.focus, args.size)
    src = {"distance_mm": args.distance, "position_mm": [args.field, 0.0]}
    t0 = time.perf_counter()
    img, truth = render_capture(prof, [src], n_sub=args.n_sub)
    t1 = time.perf_counter()
    ren = IndependentRenderer(prof)
    xyz = truth["sources"][0]["xyz_mm"]
    flux = ren.pupil_flux(xyz)
    s = truth["signal"].sum()
    print(f"{args.system} {args.size}² focus {args.focus:g} mm, d_in {prof.d_in_mm:.4f} mm; "
          f"source Ad {args.distance:g} mm at x {args.field:g} mm")
    print(f"render {t1 - t0:.2f} s; {truth['stats'][0]}")
    print(f"image sum {s:.8e}  pupil quadrature {flux:.8e}  ratio {s / flux:.6f}")
    print(f"centroid {truth['sources'][0]['centroid_px']}, peak DN fraction {img.max():.3f}")


def with_overrides(profile: CameraProfile, focus_mm: float, size: int | None) -> CameraProfile:
    """The profile focused at ``focus_mm`` (``inf`` allowed) with a centred square sensor crop
    of ``size`` px (the axis stays at the crop's centre), as ``focus_grid``'s scene overrides.
    """
    p = profile.with_focus(focus_mm)
    if size:
        p = replace(p, sensor=replace(p.sensor, width_px=int(size), height_px=int(size)))
    return p

if __name__ == "__main__":
    main()
