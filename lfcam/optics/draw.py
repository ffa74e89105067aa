"""Cardinal data and a drawn section of a camera's main lens (``lfcam lens info``).

:func:`cardinal_data` lists the first-order data of the profile's lens in the profile's frame;
:func:`lens_section` draws the meridional section (surfaces, stop, MLA and sensor planes) with
the axial marginal rays (through the stop edge) and an off-axis bundle (chief ray and the two
stop-edge rays) with OpenCV.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from lfcam.camera import CameraProfile
from lfcam.errors import OpticsError
from lfcam.optics import raytrace as rt


def cardinal_data(profile: CameraProfile) -> dict:
    """First-order data of the profile's main lens (mm; z in the profile's frame)."""
    lens = profile.main_lens
    p = lens.as_prescription
    par = p.paraxial
    fv = lens.front_vertex_z_mm
    out = {
        "form": "singlet" if lens.is_singlet else "prescription",
        "name": p.name,
        "surfaces": len(p.surfaces),
        "stop_surface": p.stop_index,
        "frame_origin": "lens centre" if lens.is_singlet else "front vertex",
        "front_vertex_z_mm": fv,
        "back_vertex_z_mm": lens.back_vertex_z_mm,
        "efl_mm": par.efl_mm,
        "bfl_mm": par.bfl_mm,
        "ffl_mm": par.ffl_mm,
        "f_number": lens.f_number,
        "front_focal_z_mm": fv + par.front_focal_z_mm,
        "back_focal_z_mm": fv + par.back_focal_z_mm,
        "front_principal_z_mm": lens.front_principal_z_mm,
        "back_principal_z_mm": lens.back_principal_z_mm,
        "aperture_z_mm": lens.rim_z_mm,
        "aperture_diameter_mm": lens.pupil_diameter_mm,
        "exit_pupil_z_mm": lens.exit_pupil_z_mm,
        "exit_pupil_diameter_mm": lens.exit_pupil_diameter_mm,
    }
    try:
        out.update(d_in_mm=profile.d_in_mm, mla_z_mm=profile.mla_z_mm, gap_mm=profile.gap_mm,
                   sensor_z_mm=profile.sensor_z_mm,
                   focus_mm=lens.focus_for_d_in(profile.d_in_mm))
    except Exception:  # noqa: BLE001 - no MLA position in the profile: lens data only
        pass
    return out


def _surface_points(p, rays: rt.RayBundle, z_end: float) -> np.ndarray:
    """(n_rays, n_surfaces + 2, 2) meridional (z, y) path of each ray: start, every surface,
    the end plane; NaN after a ray fails."""
    n_s = len(p.surfaces)
    o, d = rays.origins, rays.directions
    pts = np.full((len(o), n_s + 2, 2), np.nan)
    pts[:, 0] = np.column_stack([o[:, 2], o[:, 1]])
    for j in range(n_s):
        res = rt.trace_components(p, o[:, 0], o[:, 1], o[:, 2], d[:, 0], d[:, 1], d[:, 2], None,
                                  surfaces=range(j + 1))
        pts[:, j + 1] = np.column_stack([res.z, res.y])
    res = rt.trace_components(p, o[:, 0], o[:, 1], o[:, 2], d[:, 0], d[:, 1], d[:, 2], z_end)
    pts[:, -1] = np.column_stack([res.z, res.y])
    return pts


def lens_section(profile: CameraProfile, width_px: int = 1400, object_distance_mm=None,
                 field_height_mm: float | None = None) -> np.ndarray:
    """BGR image of the lens section with marginal and chief rays.

    Parameters
    ----------
    profile : CameraProfile
        Needs an MLA position for the image planes (else the rear focal plane is drawn).
    width_px : int
        Image width; the height follows from the lens's aspect.
    object_distance_mm : float, optional
        Object distance of the drawn rays (default: the profile's focus, or infinity).
    field_height_mm : float, optional
        Sensor height of the off-axis bundle (default: 70 % of the sensor's half-height).
    """
    lens = profile.main_lens
    p = lens.as_prescription
    fv = lens.front_vertex_z_mm
    try:
        z_mla = profile.d_in_mm - fv
        z_sensor = profile.sensor_z_mm - fv
        focus = lens.focus_for_d_in(profile.d_in_mm)
    except Exception:  # noqa: BLE001 - lens only
        z_mla = z_sensor = p.paraxial.back_focal_z_mm
        focus = math.inf
    dist = focus if object_distance_mm is None else float(object_distance_mm)
    if field_height_mm is None:
        field_height_mm = 0.35 * profile.sensor.height_px * profile.sensor.pixel_pitch_mm
    efl = p.paraxial.efl_mm
    sds = np.array([s.semi_diameter_mm for s in p.surfaces])
    # object side: the rays start a little in front of the lens
    z0 = -0.25 * max(p.last_vertex_z_mm, efl * 0.3) - 2.0
    half = 1.15 * max(sds.max(), field_height_mm)
    z_lo, z_hi = z0, z_sensor + 0.03 * (z_sensor - z0)
    scale = (width_px - 40) / (z_hi - z_lo)
    height = int(2 * half * scale) + 40
    img = np.full((height, width_px, 3), 255, np.uint8)

    def px(z, y):
        return (int(round(20 + (z - z_lo) * scale)), int(round(height / 2 - y * scale)))

    cv2.line(img, px(z_lo, 0), px(z_hi, 0), (160, 160, 160), 1, cv2.LINE_AA)
    vz = p.vertex_z_mm
    curves = []
    for i, s in enumerate(p.surfaces):
        h = np.linspace(-s.semi_diameter_mm, s.semi_diameter_mm, 81)
        z = vz[i] + np.asarray(s.sag_mm(h))
        curves.append((z, h))
        colour = (0, 0, 200) if s.stop else (60, 60, 60)
        pts = np.array([px(a, b) for a, b in zip(z, h, strict=True)], np.int32)
        cv2.polylines(img, [pts], False, colour, 2 if s.stop else 1, cv2.LINE_AA)
        if s.stop:  # stop blades beyond the clear aperture
            for sign in (1.0, -1.0):
                cv2.line(img, px(z[-1 if sign > 0 else 0], sign * s.semi_diameter_mm),
                         px(z[-1 if sign > 0 else 0], sign * 1.1 * sds.max()), (0, 0, 200), 2)
    for i in range(len(p.surfaces) - 1):  # element edges: glass between surfaces i, i+1
        if p.surfaces[i].refractive_index > 1.0:
            (za, ha), (zb, hb) = curves[i], curves[i + 1]
            for k in (0, -1):
                cv2.line(img, px(za[k], ha[k]), px(zb[k], hb[k]), (60, 60, 60), 1, cv2.LINE_AA)
    for z, colour in ((z_mla, (0, 140, 0)), (z_sensor, (0, 0, 0))):
        y = 0.5 * profile.sensor.height_px * profile.sensor.pixel_pitch_mm
        cv2.line(img, px(z, -y), px(z, y), colour, 2)
    # rays: axial stop-edge rays (blue), off-axis chief (red) and stop-edge rays (orange)
    pupil = np.array([[0.0, 1.0], [0.0, -1.0], [0.0, 0.5], [0.0, -0.5]])
    far = not math.isfinite(dist)
    try:
        if far:
            axial = rt.aim_rays(p, pupil, field_directions=np.array([0.0, 0.0, 1.0]))
            theta = math.atan2(field_height_mm, efl)
            off = rt.aim_rays(p, np.array([[0.0, 0.0], [0.0, 1.0], [0.0, -1.0]]),
                              field_directions=np.array([0.0, -math.sin(theta), math.cos(theta)]))
        else:
            axial = rt.aim_rays(p, pupil, points_mm=np.array([0.0, 0.0, -dist]))
            gap = z_mla - lens.back_principal_z_mm + fv
            h_obj = field_height_mm * (dist + lens.principal_depth_mm) / max(gap, 1e-9)
            off = rt.aim_rays(p, np.array([[0.0, 0.0], [0.0, 1.0], [0.0, -1.0]]),
                              points_mm=np.array([0.0, -h_obj, -dist]))
    except OpticsError:
        return img
    for bundle, colours in ((axial, [(200, 80, 0)] * 4), (off, [(0, 0, 230), (0, 140, 255),
                                                                (0, 140, 255)])):
        # start the drawn rays on the plane z0
        t = (z0 - bundle.origins[:, 2]) / bundle.directions[:, 2]
        start = bundle.origins + t[:, None] * bundle.directions
        b = rt.RayBundle(start, bundle.directions, bundle.pupil_xy, bundle.aimed)
        paths = _surface_points(p, b, z_sensor)
        for path, colour in zip(paths, colours, strict=True):
            good = np.isfinite(path).all(axis=1)
            pts = np.array([px(z, y) for z, y in path[good]], np.int32)
            if len(pts) > 1:
                cv2.polylines(img, [pts], False, colour, 1, cv2.LINE_AA)
    label = (f"{p.name or profile.name}: f {p.paraxial.efl_mm:.2f} mm, F/{lens.f_number:.2f}, "
             f"object {'inf' if far else f'{dist:.0f} mm'}")
    cv2.putText(img, label, (20, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    return img
