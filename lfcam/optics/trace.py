"""The stages' ray-trace API on the main lens, in the lens's frame (:class:`MainLens`).

Every function here is a thin wrapper over the one general tracer
(:mod:`lfcam.optics.raytrace`) for any main lens: the seed singlet is its two-surface
prescription, a general lens its own. Coordinates are the profile's frame (origin at the
singlet's centre, or at a prescription's front vertex; :attr:`MainLens.front_vertex_z_mm`).

* :func:`trace_rays` / :func:`trace_from_front` — (N, 3) rays to a plane.
* :func:`forward` — the two meridional stop-edge rays' sensor heights (y1, y2).
* :func:`meridional_rim_heights` — a stop-edge ray's height as a function of its slope (the
  inner loop of the exact inverse).
* :func:`trace_source_fast`, :func:`trace_backward_fast` — component-wise forward and backward
  traces for the renderer and the fitters.

Rays that cannot pass are reported by a :class:`TraceStatus` code and carry NaN positions;
callers must look at the status, never at NaN.
"""

from __future__ import annotations

from enum import IntEnum
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from lfcam.optics import raytrace as rt

if TYPE_CHECKING:
    from lfcam.camera import CameraProfile, MainLens

RIM_TOLERANCE = rt.RIM_TOLERANCE  # relative slack on every clear aperture


class TraceStatus(IntEnum):
    """Why a ray did or did not reach the target plane."""

    OK = 0
    VIGNETTED = 1  # outside the front surface's clear aperture (or misses it)
    EDGE = 2  # outside a later surface's clear aperture (the singlet: its edge)
    TIR = 3  # total internal reflection
    BACKWARD = 4  # does not travel toward the target plane / source behind the lens


class TraceResult(NamedTuple):
    """Positions and directions at the target plane, and a status per ray."""

    points: np.ndarray  # (N, 3) mm, NaN where status != OK
    directions: np.ndarray  # (N, 3) unit vectors after the lens
    status: np.ndarray  # (N,) uint8 TraceStatus codes


class ForwardResult(NamedTuple):
    """Sensor heights of the two meridional stop-edge rays of a point source."""

    y1_mm: np.ndarray  # ray through the upper stop edge (the singlet: front rim +D/2)
    y2_mm: np.ndarray  # ray through the lower stop edge (−D/2)
    status: np.ndarray  # worst TraceStatus of the two rays


def legacy_status(status: np.ndarray, surface: np.ndarray) -> np.ndarray:
    """:class:`~lfcam.optics.raytrace.RayStatus` (+ failing surface) → :class:`TraceStatus`."""
    status = np.asarray(status)
    out = np.zeros(status.shape, dtype=np.uint8)
    clipped = (status == rt.RayStatus.VIGNETTED) | (status == rt.RayStatus.MISSED)
    out[clipped & (surface <= 0)] = TraceStatus.VIGNETTED
    out[clipped & (surface > 0)] = TraceStatus.EDGE
    out[status == rt.RayStatus.TIR] = TraceStatus.TIR
    out[status == rt.RayStatus.BACKWARD] = TraceStatus.BACKWARD
    return out


def trace_rays(
    lens: MainLens, origins_mm: np.ndarray, directions: np.ndarray, z_plane_mm: float
) -> TraceResult:
    """Trace rays from arbitrary origins in front of the lens to ``z = z_plane_mm``."""
    o = np.asarray(origins_mm, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    shift = np.array([0.0, 0.0, lens.front_vertex_z_mm])
    res = rt.trace(lens.as_prescription, o - shift, d, z_plane_mm - lens.front_vertex_z_mm)
    return TraceResult(res.points + shift, res.directions, legacy_status(res.status, res.surface))


def trace_from_front(
    lens: MainLens, entry_mm: np.ndarray, directions: np.ndarray, z_plane_mm: float
) -> TraceResult:
    """Trace rays that meet the front surface at known points to the plane ``z_plane_mm``
    (each started 1 mm before its entry point)."""
    entry = np.asarray(entry_mm, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    return trace_rays(lens, entry - d, d, z_plane_mm)


def forward(
    profile: CameraProfile,
    d_in_mm: float | None,
    distance_mm: np.ndarray | float,
    offset_mm: np.ndarray | float = 0.0,
    z_plane_mm: float | None = None,
) -> ForwardResult:
    """Sensor heights (y1, y2) of a point source's two meridional stop-edge rays.

    For the seed singlet these are its rim rays (docs/conventions.md); for any lens, the rays
    through the upper and lower edge of the real stop (docs/models.md).

    Parameters
    ----------
    profile : CameraProfile
    d_in_mm : float or None
        MLA distance; ``None`` takes the profile's.
    distance_mm : array_like
        Object plane → front vertex; ``inf`` allowed (axial source).
    offset_mm : array_like
        Source height above the axis (broadcast against ``distance_mm``).
    z_plane_mm : float, optional
        Plane to report heights at; default the sensor, ``d_in + f_x``.

    Returns
    -------
    ForwardResult
    """
    lens = profile.main_lens
    p = lens.as_prescription
    fv = lens.front_vertex_z_mm
    d_in = profile.d_in_mm if d_in_mm is None else float(d_in_mm)
    z_plane = d_in + profile.mla.focal_length_mm if z_plane_mm is None else float(z_plane_mm)
    dist, off = np.broadcast_arrays(
        np.asarray(distance_mm, dtype=np.float64), np.asarray(offset_mm, dtype=np.float64)
    )
    shape = dist.shape
    dist, off = dist.ravel(), off.ravel()
    if p.stop_index != 0:
        mh = rt.marginal_heights(p, dist, off, z_plane - fv)
        st = np.where(mh.status == rt.RayStatus.BACKWARD, TraceStatus.BACKWARD,
                      np.where(mh.status == 0, 0, TraceStatus.EDGE)).astype(np.uint8)
        return ForwardResult(mh.y1_mm.reshape(shape), mh.y2_mm.reshape(shape), st.reshape(shape))
    # stop on the front surface: the rim rays go straight from the source to the rim points
    half_d = 0.5 * lens.pupil_diameter_mm
    z_rim = p.stop_plane_z_mm
    along = dist + z_rim  # source → rim plane, along z
    far = np.isinf(dist)
    heights = {}
    statuses = []
    for sign in (1.0, -1.0):
        rise = sign * half_d - off
        dy = np.where(far, 0.0, rise)
        dz = np.where(far, 1.0, along)
        with np.errstate(invalid="ignore", divide="ignore"):
            inv = 1.0 / np.sqrt(dy * dy + dz * dz)
            dy, dz = dy * inv, dz * inv
        bad = ~(np.isfinite(dy) & np.isfinite(dz)) | (along <= 0.0) | np.isnan(dist) | np.isnan(off)
        dy = np.where(bad, 0.0, dy)
        dz = np.where(bad, 1.0, dz)
        res = rt.trace_components(p, 0.0, sign * half_d - dy, z_rim - dz, 0.0, dy, dz,
                                  z_plane - fv)
        st = legacy_status(res.status, res.surface)
        st[bad] = TraceStatus.BACKWARD
        heights[sign] = np.where(st == 0, res.y, np.nan)
        statuses.append(st)
    status = np.maximum(statuses[0], statuses[1])
    y1, y2 = heights[1.0], heights[-1.0]
    y1[status != 0] = np.nan
    y2[status != 0] = np.nan
    return ForwardResult(y1.reshape(shape), y2.reshape(shape), status.reshape(shape))


def meridional_rim_heights(
    lens: MainLens, rim_sign: float, slope: np.ndarray, z_plane_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """Height at ``z_plane_mm`` of the meridional ray through the stop edge ``rim_sign``
    (+1 upper, −1 lower) with slope ``slope`` just before the stop surface (the singlet:
    the rim ray's object-side slope). See :func:`lfcam.optics.raytrace.stop_edge_heights`.

    Returns
    -------
    y_mm : ndarray
        Height at the plane (NaN where the ray does not pass).
    ok : ndarray of bool
    """
    return rt.stop_edge_heights(
        lens.as_prescription, rim_sign, slope, z_plane_mm - lens.front_vertex_z_mm
    )


# ----------------------------------------------------------------------------- fast paths


class FastTrace(NamedTuple):
    """Component-wise trace result: positions, unit directions and a pass mask."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    dz: np.ndarray
    ok: np.ndarray  # bool, True where the ray passed
    rho: np.ndarray | None = None  # max over surfaces of ρ/semi-diameter (if asked for)


def pupil_map(lens: MainLens, source_xyz_mm) -> tuple[float, float, float, float]:
    """Where the real stop appears from a source, on the aperture plane :attr:`rim_z_mm`:
    ``(centre_x, centre_y, scale_x, scale_y)`` mapping the paraxial aperture disk (radius
    D/2 about the axis) onto the ellipse through the aimed stop-edge rays.

    Identity for a stop on the front surface (the singlet's rim is a real circle there).
    """
    p = lens.as_prescription
    if p.stop_index == 0:
        return 0.0, 0.0, 1.0, 1.0
    fv = lens.front_vertex_z_mm
    src = np.asarray(source_xyz_mm, dtype=np.float64) - [0.0, 0.0, fv]
    if not np.isfinite(src).all():
        return 0.0, 0.0, 1.0, 1.0
    pupil = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    b = rt.aim_rays(p, pupil, points_mm=src)
    if not b.aimed.all():
        return 0.0, 0.0, 1.0, 1.0
    z_ap = lens.rim_z_mm - fv
    t = (z_ap - b.origins[:, 2]) / b.directions[:, 2]
    hx = b.origins[:, 0] + t * b.directions[:, 0]
    hy = b.origins[:, 1] + t * b.directions[:, 1]
    half = 0.5 * lens.pupil_diameter_mm
    cx = 0.5 * (hx[0] + hx[1])
    cy = 0.5 * (hy[2] + hy[3])
    return float(cx), float(cy), float(0.5 * (hx[0] - hx[1]) / half), float(
        0.5 * (hy[2] - hy[3]) / half)


def trace_source_fast(
    lens: MainLens,
    source_xyz_mm: tuple[float, float, float],
    rim_x_mm: np.ndarray,
    rim_y_mm: np.ndarray,
    z_plane_mm: float,
    *,
    map_pupil: bool = True,
) -> FastTrace:
    """Trace rays from one point source through given points of the aperture plane.

    Each ray runs from the source toward ``(rim_x, rim_y, lens.rim_z_mm)`` and is traced
    exactly (vignetted by every clear aperture) to the plane ``z = z_plane_mm``. For a stop
    behind the front surface and ``map_pupil``, the aim points (given on the paraxial aperture
    disk) are first mapped onto the real stop's image from this source (:func:`pupil_map`),
    so samples uniform on the disk stay uniform on the real pupil.

    Returns
    -------
    FastTrace
        Positions at the target plane and unit directions after the lens.
    """
    rim_x, rim_y = np.broadcast_arrays(np.asarray(rim_x_mm, dtype=np.float64),
                                       np.asarray(rim_y_mm, dtype=np.float64))
    tr = trace_sources_fast(lens, np.asarray(source_xyz_mm, dtype=np.float64).reshape(1, 3),
                            rim_x, rim_y, z_plane_mm, map_pupil=map_pupil)
    return FastTrace(*(a.reshape(rim_x.shape) for a in tr[:7]))


def trace_sources_fast(
    lens: MainLens,
    sources_mm: np.ndarray,
    rim_x_mm: np.ndarray,
    rim_y_mm: np.ndarray,
    z_plane_mm: float,
    *,
    map_pupil: bool = True,
) -> FastTrace:
    """:func:`trace_source_fast` for ``M`` point sources in one trace: each source's rays aim
    at the same aperture points, or at its own (the pupil map applied per source).

    Parameters
    ----------
    sources_mm : (M, 3) array
    rim_x_mm, rim_y_mm : (n,) or (M, n) arrays
        Aim points on the paraxial aperture disk (per source: one row each).

    Returns
    -------
    FastTrace
        Arrays of shape ``(M, n)``.
    """
    src = np.asarray(sources_mm, dtype=np.float64).reshape(-1, 3)
    rim_x = np.asarray(rim_x_mm, dtype=np.float64)
    rim_y = np.asarray(rim_y_mm, dtype=np.float64)
    rim_x = rim_x.reshape(len(src), -1) if rim_x.ndim == 2 else rim_x.ravel()[None, :]
    rim_y = rim_y.reshape(len(src), -1) if rim_y.ndim == 2 else rim_y.ravel()[None, :]
    if map_pupil and lens.as_prescription.stop_index != 0:
        maps = np.array([pupil_map(lens, tuple(pt)) for pt in src])
        rim_x = maps[:, :1] + maps[:, 2:3] * rim_x
        rim_y = maps[:, 1:2] + maps[:, 3:4] * rim_y
    fv = lens.front_vertex_z_mm
    sx, sy, sz = src[:, :1], src[:, 1:2], src[:, 2:3]
    dx = rim_x - sx
    dy = rim_y - sy
    dz = np.broadcast_to(lens.rim_z_mm - sz, dx.shape)
    res = rt.trace_components(lens.as_prescription, sx, sy, sz - fv, dx, dy, dz, z_plane_mm - fv)
    return FastTrace(res.x, res.y, res.z + fv, res.dx, res.dy, res.dz, res.status == 0)


def trace_backward_fast(
    lens: MainLens,
    x_mm: np.ndarray,
    y_mm: np.ndarray,
    z_mm: float,
    slope_x: np.ndarray,
    slope_y: np.ndarray,
    *,
    ratio: bool = False,
) -> FastTrace:
    """Trace image-side rays backward through the lens to the front surface.

    A ray that travels toward +z with slopes ``(slope_x, slope_y) = (dx/dz, dy/dz)`` and
    crosses the plane ``z = z_mm`` (behind the lens) at ``(x, y)`` is followed back through
    every surface; it passes when it stays inside every clear aperture (the stop's included).

    Parameters
    ----------
    ratio : bool
        Also return ``rho``: the largest ρ/semi-diameter over the surfaces, traced without
        clipping (a continuous measure, ≤ 1 exactly where the ray passes).

    Returns
    -------
    FastTrace
        ``x, y, z``: where the ray leaves the front surface; ``dx, dy, dz``: unit direction
        toward the object (dz < 0); ``ok``: passed.
    """
    sx = np.asarray(slope_x, dtype=np.float64)
    sy = np.asarray(slope_y, dtype=np.float64)
    inv = 1.0 / np.sqrt(1.0 + sx * sx + sy * sy)
    fv = lens.front_vertex_z_mm
    res = rt.trace_components(
        lens.as_prescription, x_mm, y_mm, z_mm - fv, -sx * inv, -sy * inv, -inv, None, reverse=True,
        clip=not ratio, ratio=ratio,
    )
    rho = None
    ok = res.status == 0
    if ratio:
        rho = np.sqrt(res.ratio)
        ok = ok & (res.ratio <= 1.0 + RIM_TOLERANCE)
    return FastTrace(res.x, res.y, res.z + fv, res.dx, res.dy, res.dz, ok, rho)
