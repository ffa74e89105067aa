"""Microlens-array grid geometry: lenslet centres, nearest lenslet, clear apertures.

All coordinates are lateral (x, y) in millimetres on the MLA plane, origin on the optical
axis (docs/conventions.md). The lattice is ``C(i, j) = offset + i·a1 + j·a2`` with

* rect: ``a1 = p·(cos θ, sin θ)``, ``a2 = p·(−sin θ, cos θ)``;
* hex: ``a1`` as above and ``a2 = p·(cos(θ+60°), sin(θ+60°))`` — rows along the rotated x axis,
  row spacing ``p·√3/2``, each row shifted by half a pitch against the previous one.

The clear aperture of a lenslet is its Voronoi cell (square or regular hexagon) scaled by the
fill factor about the lenslet centre. Calibration and decoding reuse this module.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lfcam.camera import GRIDS, MicrolensArray
from lfcam.errors import ProfileError

HEX_BASIS = np.array([[1.0, 0.5], [0.0, math.sqrt(3.0) / 2.0]])
RECT_BASIS = np.eye(2)


def lattice_basis(grid: str) -> np.ndarray:
    """Unit-pitch lattice basis (columns = the two lattice vectors) for ``grid``.

    The one lattice convention of lfcam: lens ``(i, j)`` sits at
    ``offset + pitch · R(θ) · B · (i, j)`` with ``B = [[1, 0], [0, 1]]`` (rect) or
    ``B = [[1, 1/2], [0, √3/2]]`` (hex), in millimetres on the MLA plane (:class:`MlaGrid`) and
    in pixels on the sensor (:class:`lfcam.calibrate.Calibration`).
    """
    return HEX_BASIS if grid == "hex" else RECT_BASIS


def rotation_matrix(angle_rad: float) -> np.ndarray:
    """2×2 rotation by ``angle_rad`` (x toward y; in image coordinates y points down)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s], [s, c]])


def row_column(grid: str, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lens row ``t`` and column ``s`` of lattice index ``(i, j)``.

    Rows run along the first lattice vector; in a hex lattice odd rows sit half a pitch to
    the right of even ones, so ``s = i + ⌊j/2⌋`` (rect: ``s = i``) and ``t = j``.
    """
    i = np.asarray(i, dtype=np.int64)
    j = np.asarray(j, dtype=np.int64)
    return j, (i + np.floor_divide(j, 2) if grid == "hex" else i)


def lattice_index(grid: str, t: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lattice index ``(i, j)`` of lens row ``t``, column ``s`` (inverse of :func:`row_column`)."""
    t = np.asarray(t, dtype=np.int64)
    s = np.asarray(s, dtype=np.int64)
    return (s - np.floor_divide(t, 2) if grid == "hex" else s), t


@dataclass(frozen=True)
class MlaGrid:
    """Lenslet lattice of a microlens array.

    Parameters
    ----------
    pitch_mm : float
        Centre-to-centre distance of neighbouring lenslets.
    grid : str
        ``"rect"`` or ``"hex"``.
    rotation_rad : float
        Angle of the lattice rows against the x axis.
    offset_mm : tuple of float
        (x, y) of lenslet (0, 0) relative to the optical axis.
    fill_factor : float
        Clear-aperture scale of the Voronoi cell, in (0, 1].
    """

    pitch_mm: float
    grid: str = "rect"
    rotation_rad: float = 0.0
    offset_mm: tuple[float, float] = (0.0, 0.0)
    fill_factor: float = 1.0

    def __post_init__(self) -> None:
        if self.grid not in GRIDS:
            raise ProfileError(f"mla.grid: must be one of {GRIDS}, got {self.grid!r}")
        if not (math.isfinite(self.pitch_mm) and self.pitch_mm > 0):
            raise ProfileError(f"mla.pitch_mm: must be positive, got {self.pitch_mm}")
        if not 0.0 < self.fill_factor <= 1.0:
            raise ProfileError(f"mla.fill_factor: must be in (0, 1], got {self.fill_factor}")

    @classmethod
    def from_mla(cls, mla: MicrolensArray) -> MlaGrid:
        """Grid of a profile's :class:`~lfcam.camera.MicrolensArray`."""
        return cls(
            pitch_mm=mla.pitch_mm,
            grid=mla.grid,
            rotation_rad=mla.rotation_rad,
            offset_mm=tuple(mla.offset_mm),
            fill_factor=mla.fill_factor,
        )

    # ------------------------------------------------------------------ lattice
    @property
    def basis_mm(self) -> np.ndarray:
        """2×2 matrix whose columns are the lattice vectors a1, a2 (mm)."""
        return self.pitch_mm * rotation_matrix(self.rotation_rad) @ lattice_basis(self.grid)

    @property
    def cell_area_mm2(self) -> float:
        """Area of one lattice cell (pitch² for rect, pitch²·√3/2 for hex)."""
        return abs(float(np.linalg.det(self.basis_mm)))

    @property
    def aperture_area_mm2(self) -> float:
        """Clear-aperture area of one lenslet."""
        return self.cell_area_mm2 * self.fill_factor ** 2

    def centre_mm(self, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centre (x, y) of lenslet(s) (i, j)."""
        m = self.basis_mm
        i = np.asarray(i, dtype=np.float64)
        j = np.asarray(j, dtype=np.float64)
        return (
            self.offset_mm[0] + m[0, 0] * i + m[0, 1] * j,
            self.offset_mm[1] + m[1, 0] * i + m[1, 1] * j,
        )

    def lattice_coords(self, x_mm: np.ndarray, y_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Continuous lattice coordinates (u, v) of points: ``xy = offset + u·a1 + v·a2``."""
        inv = np.linalg.inv(self.basis_mm)
        rx = np.asarray(x_mm, dtype=np.float64) - self.offset_mm[0]
        ry = np.asarray(y_mm, dtype=np.float64) - self.offset_mm[1]
        return inv[0, 0] * rx + inv[0, 1] * ry, inv[1, 0] * rx + inv[1, 1] * ry

    def nearest(
        self, x_mm: np.ndarray, y_mm: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Lenslet whose Voronoi cell contains each point.

        Returns
        -------
        i, j : ndarray of int64
            Lattice indices.
        cx, cy : ndarray
            Lenslet centres (mm).
        """
        x = np.asarray(x_mm, dtype=np.float64)
        y = np.asarray(y_mm, dtype=np.float64)
        u, v = self.lattice_coords(x, y)
        if self.grid == "rect":
            i = np.rint(u)
            j = np.rint(v)
            cx, cy = self.centre_mm(i, j)
            return i.astype(np.int64), j.astype(np.int64), cx, cy
        # hex: the nearest lattice point is a vertex of the containing parallelogram cell
        fu = np.floor(u)
        fv = np.floor(v)
        best_d = np.full(x.shape, np.inf)
        bi = np.zeros(x.shape)
        bj = np.zeros(x.shape)
        for du in (0.0, 1.0):
            for dv in (0.0, 1.0):
                ci, cj = fu + du, fv + dv
                px, py = self.centre_mm(ci, cj)
                d2 = (x - px) ** 2 + (y - py) ** 2
                better = d2 < best_d
                best_d = np.where(better, d2, best_d)
                bi = np.where(better, ci, bi)
                bj = np.where(better, cj, bj)
        cx, cy = self.centre_mm(bi, bj)
        return bi.astype(np.int64), bj.astype(np.int64), cx, cy

    def _edge_normals(self) -> list[tuple[float, float]]:
        t = self.rotation_rad
        angles = (0.0, math.pi / 2) if self.grid == "rect" else (0.0, math.pi / 3, 2 * math.pi / 3)
        return [(math.cos(t + a), math.sin(t + a)) for a in angles]

    def in_aperture(self, dx_mm: np.ndarray, dy_mm: np.ndarray) -> np.ndarray:
        """Whether offsets (dx, dy) from a lenslet centre fall inside its clear aperture."""
        half = 0.5 * self.pitch_mm * self.fill_factor * (1.0 + 1e-12)
        ok = np.ones(np.shape(dx_mm), dtype=bool)
        for nx, ny in self._edge_normals():
            ok &= np.abs(dx_mm * nx + dy_mm * ny) <= half
        return ok

    def aperture_samples(self, s: np.ndarray, t: np.ndarray, k: np.ndarray | None = None):
        """Map unit-square samples to offsets uniformly covering the clear aperture.

        Parameters
        ----------
        s, t : ndarray
            Uniform samples in [0, 1).
        k : ndarray of int, optional
            Hex only: which of the three rhombi (0, 1, 2) tiling the hexagon.

        Returns
        -------
        dx, dy : ndarray
            Offsets from the lenslet centre (mm).
        """
        f = self.fill_factor
        if self.grid == "rect":
            m = self.basis_mm * f
            a, b = s - 0.5, t - 0.5
            return m[0, 0] * a + m[0, 1] * b, m[1, 0] * a + m[1, 1] * b
        if k is None:
            raise ValueError("hex aperture samples need the rhombus index k")
        # hexagon vertices V_m at angle θ+30°+60°m, circumradius f·p/√3; V_m + V_{m+2} = V_{m+1}
        rad = f * self.pitch_mm / math.sqrt(3.0)
        ang0 = self.rotation_rad + math.pi / 6 + (2.0 * math.pi / 3) * np.asarray(k)
        ang1 = ang0 + 2.0 * math.pi / 3
        return (
            rad * (s * np.cos(ang0) + t * np.cos(ang1)),
            rad * (s * np.sin(ang0) + t * np.sin(ang1)),
        )

    def lenslets_in_box(
        self, x_min: float, x_max: float, y_min: float, y_max: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every lenslet whose centre lies in the box; returns (i, j, cx, cy)."""
        corners_x = np.array([x_min, x_max, x_min, x_max])
        corners_y = np.array([y_min, y_min, y_max, y_max])
        u, v = self.lattice_coords(corners_x, corners_y)
        span = 1e7
        if max(np.ptp(u), np.ptp(v)) > span:
            raise ProfileError("MLA lattice too fine for the requested area (over 1e7 lenslets)")
        iu = np.arange(math.floor(u.min()) - 1, math.ceil(u.max()) + 2)
        jv = np.arange(math.floor(v.min()) - 1, math.ceil(v.max()) + 2)
        ii, jj = np.meshgrid(iu, jv, indexing="xy")
        ii, jj = ii.ravel(), jj.ravel()
        cx, cy = self.centre_mm(ii, jj)
        keep = (cx >= x_min) & (cx <= x_max) & (cy >= y_min) & (cy <= y_max)
        return ii[keep].astype(np.int64), jj[keep].astype(np.int64), cx[keep], cy[keep]
