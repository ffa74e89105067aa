"""Frozen copy of lfcam's former hand-unrolled singlet tracer (before issue 14), kept only as
the speed reference of ``benchmarks/raytrace.py``. lfcam itself traces every lens, the singlet
included, with :mod:`lfcam.optics.raytrace`.

Former docstring: exact ray trace through the thick main lens (two spherical surfaces, Snell's law).

Two implementations that share no code on purpose, so each checks the other in the tests:

* :func:`trace_rays` / :func:`trace_from_front` — general skew rays in 3-D, vector Snell.
* :func:`meridional_rim_heights` — the meridional rim ray parametrised by its object-side
  slope, the inner loop of the exact inverse model.

Rays that cannot pass are reported by a :class:`TraceStatus` code and carry NaN positions;
callers must look at the status, never at NaN.
"""

from __future__ import annotations

from enum import IntEnum
from typing import Any as CameraProfile
from typing import Any as MainLens
from typing import NamedTuple

import numpy as np

RIM_TOLERANCE = 1e-9  # relative slack on the aperture test (rim rays sit exactly on it)


class TraceStatus(IntEnum):
    """Why a ray did or did not reach the target plane."""

    OK = 0
    VIGNETTED = 1  # hits the front surface outside the aperture (or misses it)
    EDGE = 2  # leaves the glass through the edge (back surface beyond where surfaces meet)
    TIR = 3  # total internal reflection at the back surface
    BACKWARD = 4  # does not travel toward the target plane / source behind the lens


class TraceResult(NamedTuple):
    """Positions and directions at the target plane, and a status per ray."""

    points: np.ndarray  # (N, 3) mm, NaN where status != OK
    directions: np.ndarray  # (N, 3) unit vectors after the lens
    status: np.ndarray  # (N,) uint8 TraceStatus codes


class ForwardResult(NamedTuple):
    """Sensor heights of the two meridional rim rays of a point source."""

    y1_mm: np.ndarray  # ray entering at the upper front rim (+D/2)
    y2_mm: np.ndarray  # ray entering at the lower front rim (−D/2)
    status: np.ndarray  # worst TraceStatus of the two rays


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)


def _refract(d: np.ndarray, n: np.ndarray, eta: float) -> tuple[np.ndarray, np.ndarray]:
    """Vector Snell's law. ``n`` must face against ``d``; returns (direction, TIR mask)."""
    cos_i = -_dot(n, d)
    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
    tir = k < 0.0
    root = np.sqrt(np.where(tir, 0.0, k))
    t = eta * d + (eta * cos_i - root)[:, None] * n
    return t, tir


def trace_from_front(
    lens: MainLens, entry_mm: np.ndarray, directions: np.ndarray, z_plane_mm: float
) -> TraceResult:
    """Trace rays that meet the front surface at known points to the plane ``z = z_plane_mm``.

    Parameters
    ----------
    lens : MainLens
    entry_mm : (N, 3) array
        Points on the front surface where the rays enter.
    directions : (N, 3) array
        Unit directions of the incoming rays.
    z_plane_mm : float
        Target plane behind the lens.

    Returns
    -------
    TraceResult
    """
    entry = np.asarray(entry_mm, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    r, n_glass = lens.radius_mm, lens.refractive_index
    half_d = 0.5 * lens.pupil_diameter_mm
    status = np.zeros(len(entry), dtype=np.uint8)

    rho2 = entry[:, 0] ** 2 + entry[:, 1] ** 2
    status[rho2 > (half_d * half_d) * (1.0 + RIM_TOLERANCE)] = TraceStatus.VIGNETTED
    status[(d[:, 2] <= 0.0) & (status == 0)] = TraceStatus.BACKWARD

    c1 = np.array([0.0, 0.0, lens.front_vertex_z_mm + r])
    normal1 = (entry - c1) / r  # outward, faces the incoming light
    inside, tir1 = _refract(d, normal1, 1.0 / n_glass)
    status[tir1 & (status == 0)] = TraceStatus.TIR  # impossible from air, kept for safety

    c2 = np.array([0.0, 0.0, lens.back_vertex_z_mm - r])
    oc = entry - c2
    b = _dot(inside, oc)
    cc = _dot(oc, oc) - r * r
    disc = b * b - cc
    miss = disc < 0.0
    s_exit = -b + np.sqrt(np.where(miss, 0.0, disc))
    exit_pt = entry + s_exit[:, None] * inside
    edge2 = lens.edge_radius_mm ** 2
    beyond = (exit_pt[:, 0] ** 2 + exit_pt[:, 1] ** 2) > edge2
    status[(miss | beyond | (s_exit <= 0.0)) & (status == 0)] = TraceStatus.EDGE

    normal2 = -(exit_pt - c2) / r  # inward: faces the ray travelling out of the glass
    out, tir2 = _refract(inside, normal2, n_glass)
    status[tir2 & (status == 0)] = TraceStatus.TIR
    status[(out[:, 2] <= 0.0) & (status == 0)] = TraceStatus.BACKWARD

    ok = status == 0
    with np.errstate(divide="ignore", invalid="ignore"):
        s_plane = (z_plane_mm - exit_pt[:, 2]) / out[:, 2]
        points = exit_pt + s_plane[:, None] * out
    points[~ok] = np.nan
    return TraceResult(points=points, directions=out, status=status)


def trace_rays(
    lens: MainLens, origins_mm: np.ndarray, directions: np.ndarray, z_plane_mm: float
) -> TraceResult:
    """Trace rays from arbitrary origins in front of the lens to ``z = z_plane_mm``.

    The front-surface intersection uses the numerically stable near root, so sources up to
    1e6 mm away keep sub-nanometre entry points.
    """
    o = np.asarray(origins_mm, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    r = lens.radius_mm
    c1 = np.array([0.0, 0.0, lens.front_vertex_z_mm + r])
    oc = o - c1
    b = _dot(d, oc)
    cc = _dot(oc, oc) - r * r
    disc = b * b - cc
    miss = (disc < 0.0) | (b >= 0.0)
    root = np.sqrt(np.where(miss, 0.0, disc))
    with np.errstate(divide="ignore", invalid="ignore"):
        s_near = np.where(miss, 0.0, cc / (-b + root))
    entry = o + s_near[:, None] * d
    result = trace_from_front(lens, entry, d, z_plane_mm)
    status = result.status
    status[miss] = TraceStatus.VIGNETTED
    # an entry on the far cap of the front sphere is not the front surface
    status[(entry[:, 2] > lens.front_vertex_z_mm + r) & (status == 0)] = TraceStatus.VIGNETTED
    result.points[status != 0] = np.nan
    return result


def forward(
    profile: CameraProfile,
    d_in_mm: float | None,
    distance_mm: np.ndarray | float,
    offset_mm: np.ndarray | float = 0.0,
    z_plane_mm: float | None = None,
) -> ForwardResult:
    """Sensor heights (y1, y2) of a point source's two meridional rim rays (docs/conventions.md).

    Parameters
    ----------
    profile : CameraProfile
    d_in_mm : float or None
        MLA distance; ``None`` takes the profile's.
    distance_mm : array_like
        Object plane → front vertex; ``inf`` allowed.
    offset_mm : array_like
        Source height above the axis (broadcast against ``distance_mm``).
    z_plane_mm : float, optional
        Plane to report heights at; default the sensor, ``d_in + f_x``.

    Returns
    -------
    ForwardResult
        ``y1_mm`` (upper rim ray), ``y2_mm`` (lower rim ray), ``status`` (worst of the two).
    """
    lens = profile.main_lens
    d_in = profile.d_in_mm if d_in_mm is None else float(d_in_mm)
    z_plane = d_in + profile.mla.focal_length_mm if z_plane_mm is None else float(z_plane_mm)
    dist, off = np.broadcast_arrays(
        np.asarray(distance_mm, dtype=np.float64), np.asarray(offset_mm, dtype=np.float64)
    )
    shape = dist.shape
    dist, off = dist.ravel(), off.ravel()
    n = dist.size
    half_d = 0.5 * lens.pupil_diameter_mm
    z_rim = lens.rim_z_mm
    along = dist + lens.rim_sag_mm  # source → rim plane, along z
    far = np.isinf(dist)
    heights = {}
    statuses = []
    for sign in (1.0, -1.0):
        entry = np.zeros((n, 3))
        entry[:, 1] = sign * half_d
        entry[:, 2] = z_rim
        rise = sign * half_d - off
        direction = np.stack([np.zeros(n), np.where(far, 0.0, rise), np.where(far, 1.0, along)], 1)
        norm = np.linalg.norm(direction, axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            direction = direction / norm
        bad = ~np.isfinite(direction).all(axis=1) | (along <= 0.0) | np.isnan(dist) | np.isnan(off)
        direction[bad] = (0.0, 0.0, 1.0)
        res = trace_from_front(lens, entry, direction, z_plane)
        st = res.status.copy()
        st[bad] = TraceStatus.BACKWARD
        y = res.points[:, 1].copy()
        y[st != 0] = np.nan
        heights[sign] = y
        statuses.append(st)
    status = np.maximum(statuses[0], statuses[1])
    y1, y2 = heights[1.0], heights[-1.0]
    y1[status != 0] = np.nan
    y2[status != 0] = np.nan
    return ForwardResult(y1.reshape(shape), y2.reshape(shape), status.reshape(shape))


def meridional_rim_heights(
    lens: MainLens, rim_sign: float, slope: np.ndarray, z_plane_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """Height at ``z_plane_mm`` of the meridional ray entering the rim at ``rim_sign·D/2``.

    Parameters
    ----------
    lens : MainLens
    rim_sign : float
        +1 for the upper rim (ray 1), −1 for the lower rim (ray 2).
    slope : ndarray
        Object-side slope dy/dz of the incoming ray.
    z_plane_mm : float

    Returns
    -------
    y_mm : ndarray
        Height at the plane (NaN where the ray does not pass).
    ok : ndarray of bool
    """
    r, n_glass = lens.radius_mm, lens.refractive_index
    half_d = rim_sign * 0.5 * lens.pupil_diameter_mm
    z_a = lens.rim_z_mm
    # outward normal at the rim point (faces the incoming light)
    nz1 = (z_a - (lens.front_vertex_z_mm + r)) / r
    ny1 = half_d / r
    inv_len = 1.0 / np.sqrt(1.0 + slope * slope)
    dz, dy = inv_len, slope * inv_len
    eta = 1.0 / n_glass
    cos_i = -(nz1 * dz + ny1 * dy)
    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
    g = eta * cos_i - np.sqrt(np.maximum(k, 0.0))
    tz = eta * dz + g * nz1
    ty = eta * dy + g * ny1
    # back surface: sphere about (z_c2, 0)
    z_c2 = lens.back_vertex_z_mm - r
    oz = z_a - z_c2
    cc = oz * oz + half_d * half_d - r * r
    b = tz * oz + ty * half_d
    disc = b * b - cc
    s = -b + np.sqrt(np.maximum(disc, 0.0))
    qz = z_a + s * tz
    qy = half_d + s * ty
    # refraction out of the glass; normal faces the travelling ray
    mz = -(qz - z_c2) / r
    my = -qy / r
    cos_o = -(mz * tz + my * ty)
    k2 = 1.0 - n_glass * n_glass * (1.0 - cos_o * cos_o)
    g2 = n_glass * cos_o - np.sqrt(np.maximum(k2, 0.0))
    uz = n_glass * tz + g2 * mz
    uy = n_glass * ty + g2 * my
    y = qy + uy * ((z_plane_mm - qz) / uz)
    ok = (k2 >= 0.0) & (disc >= 0.0) & (uz > 0.0) & (qy * qy <= lens.edge_radius_mm ** 2)
    return y, ok


# ----------------------------------------------------------------------------- fast paths
# Component-wise (x, y, z arrays instead of (N, 3)) versions for the renderer (lfcam.sim),
# where tens of millions of rays are traced. They are checked against ``trace_rays`` in the
# tests; they share the geometry, not the code.


class FastTrace(NamedTuple):
    """Component-wise trace result: positions, unit directions and a pass mask."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    dz: np.ndarray
    ok: np.ndarray  # bool, True where the ray passed


def _refract_xyz(dx, dy, dz, nx, ny, nz, eta):
    """Vector Snell's law on components; ``n`` faces against ``d``. Returns (t, tir)."""
    cos_i = -(nx * dx + ny * dy + nz * dz)
    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
    tir = k < 0.0
    g = eta * cos_i - np.sqrt(np.maximum(k, 0.0))
    return eta * dx + g * nx, eta * dy + g * ny, eta * dz + g * nz, tir


def _sphere_entry(px, py, pz, dx, dy, dz, zc: float, r: float):
    """Near intersection of rays ``p + s·d`` entering a sphere (centre (0, 0, zc)) from outside.

    Uses the cancellation-free form ``s = cc/(−b + √disc)``, so sources 10⁶ mm away keep
    sub-nanometre entry points. Returns ``(x, y, z, hit)``.
    """
    oz = pz - zc
    b = dx * px + dy * py + dz * oz
    cc = px * px + py * py + oz * oz - r * r
    disc = b * b - cc
    hit = (disc >= 0.0) & (b < 0.0)
    s = cc / (-b + np.sqrt(np.maximum(disc, 0.0)))
    return px + s * dx, py + s * dy, pz + s * dz, hit


def _sphere_exit(px, py, pz, dx, dy, dz, zc: float, r: float):
    """Far intersection of rays ``p + s·d`` leaving a sphere (centre (0, 0, zc)) from inside.

    Returns ``(x, y, z, hit)``.
    """
    oz = pz - zc
    b = dx * px + dy * py + dz * oz
    cc = px * px + py * py + oz * oz - r * r
    disc = b * b - cc
    s = -b + np.sqrt(np.maximum(disc, 0.0))
    return px + s * dx, py + s * dy, pz + s * dz, disc >= 0.0


def trace_source_fast(
    lens: MainLens,
    source_xyz_mm: tuple[float, float, float],
    rim_x_mm: np.ndarray,
    rim_y_mm: np.ndarray,
    z_plane_mm: float,
) -> FastTrace:
    """Trace rays from one point source through given points of the front-rim plane.

    Each ray runs from the source toward ``(rim_x, rim_y, lens.rim_z_mm)``; it enters the
    front surface where that line meets the sphere (near root, stable for far sources) and is
    traced exactly to the plane ``z = z_plane_mm``. Rays through rim-plane points within D/2
    enter the front surface within D/2 (the cap is convex toward the source).

    Parameters
    ----------
    lens : MainLens
    source_xyz_mm : tuple of float
        Source position (z in front of the front vertex).
    rim_x_mm, rim_y_mm : ndarray
        Aim points on the rim plane.
    z_plane_mm : float
        Target plane behind the lens.

    Returns
    -------
    FastTrace
        Positions at the target plane and unit directions after the lens.
    """
    sx, sy, sz = (float(v) for v in source_xyz_mm)
    r, n_glass = lens.radius_mm, lens.refractive_index
    half_d = 0.5 * lens.pupil_diameter_mm
    dx = rim_x_mm - sx
    dy = rim_y_mm - sy
    dzs = lens.rim_z_mm - sz
    inv = 1.0 / np.sqrt(dx * dx + dy * dy + dzs * dzs)
    dx *= inv
    dy *= inv
    dz = dzs * inv
    # front sphere, centre on axis at zc1
    zc1 = lens.front_vertex_z_mm + r
    ex, ey, ez, ok = _sphere_entry(sx, sy, sz, dx, dy, dz, zc1, r)
    ok &= ex * ex + ey * ey <= (half_d * half_d) * (1.0 + RIM_TOLERANCE)
    nx, ny, nz = ex / r, ey / r, (ez - zc1) / r
    tx, ty, tz, tir = _refract_xyz(dx, dy, dz, nx, ny, nz, 1.0 / n_glass)
    ok &= ~tir
    # back sphere, centre zc2; far root from inside
    zc2 = lens.back_vertex_z_mm - r
    qx, qy, qz, hit = _sphere_exit(ex, ey, ez, tx, ty, tz, zc2, r)
    ok &= hit
    ok &= qx * qx + qy * qy <= lens.edge_radius_mm ** 2
    nx, ny, nz = -qx / r, -qy / r, -(qz - zc2) / r
    ux, uy, uz, tir = _refract_xyz(tx, ty, tz, nx, ny, nz, n_glass)
    ok &= ~tir & (uz > 0.0)
    t = (z_plane_mm - qz) / np.where(uz > 0.0, uz, 1.0)
    return FastTrace(qx + t * ux, qy + t * uy, np.full_like(qx, z_plane_mm), ux, uy, uz, ok)


def trace_backward_fast(
    lens: MainLens,
    x_mm: np.ndarray,
    y_mm: np.ndarray,
    z_mm: float,
    slope_x: np.ndarray,
    slope_y: np.ndarray,
) -> FastTrace:
    """Trace image-side rays backward through the lens to the front surface.

    A ray that travels toward +z with slopes ``(slope_x, slope_y) = (dx/dz, dy/dz)`` and
    crosses the plane ``z = z_mm`` (behind the lens) at ``(x, y)`` is followed back: into the
    back surface, through the glass, out of the front surface. It passes when it leaves the
    front surface within the clear aperture D/2 (the stop) and inside the lens edge.

    Returns
    -------
    FastTrace
        ``x, y, z``: where the ray leaves the front surface; ``dx, dy, dz``: unit direction
        toward the object (dz < 0); ``ok``: passed the aperture.
    """
    r, n_glass = lens.radius_mm, lens.refractive_index
    half_d = 0.5 * lens.pupil_diameter_mm
    inv = 1.0 / np.sqrt(1.0 + slope_x * slope_x + slope_y * slope_y)
    dx = -slope_x * inv
    dy = -slope_y * inv
    dz = -inv
    # back sphere (centre zc2 on axis), entered from outside
    zc2 = lens.back_vertex_z_mm - r
    qx, qy, qz, ok = _sphere_entry(x_mm, y_mm, z_mm, dx, dy, dz, zc2, r)
    edge2 = lens.edge_radius_mm ** 2
    ok &= qx * qx + qy * qy <= edge2
    # outward normal of the back surface faces the incoming (backward) ray
    tx, ty, tz, tir = _refract_xyz(dx, dy, dz, qx / r, qy / r, (qz - zc2) / r, 1.0 / n_glass)
    ok &= ~tir
    # front sphere (centre zc1), far root from inside
    zc1 = lens.front_vertex_z_mm + r
    ex, ey, ez, hit = _sphere_exit(qx, qy, qz, tx, ty, tz, zc1, r)
    ok &= hit
    ok &= ex * ex + ey * ey <= (half_d * half_d) * (1.0 + RIM_TOLERANCE)
    ux, uy, uz, tir = _refract_xyz(tx, ty, tz, -ex / r, -ey / r, -(ez - zc1) / r, n_glass)
    ok &= ~tir & (uz < 0.0)
    return FastTrace(ex, ey, ez, ux, uy, uz, ok)
