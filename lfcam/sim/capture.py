"""Synthetic captures: render a scene, apply the sensor, build the truth, write the files.

Outputs of ``simulate(..., out="NAME.png")`` (or ``.tif``/``.tiff``):

* ``NAME.png`` — the raw raster (16-bit grey, Bayer-mosaicked if the sensor has a CFA);
* ``NAME.profile.toml`` — the camera profile used (scene overrides applied, d_in explicit);
* ``NAME.truth.json`` — ground truth (see docs/simulate.md).

``NAME.lfr`` / ``NAME.lfp`` write a Lytro container instead of the raster (10-bit sensors in the
Illum layout, 12-bit in the F01 layout, with Lytro-style metadata: :mod:`lfcam.sim.lytro`).
:data:`WRITERS` maps a suffix to a writer.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from lfcam.atomic import atomic_write
from lfcam.camera import CameraProfile, profile_from_dict
from lfcam.errors import LfcamError, SceneError
from lfcam.optics.mla import MlaGrid
from lfcam.optics.trace import forward
from lfcam.progress import Progress
from lfcam.sim.render import Renderer, RenderResult
from lfcam.sim.scene import MAX_TOTAL_RAYS, LineSource, PointSource, Scene, check_ray_budget
from lfcam.sim.sensor import apply_sensor

TRUTH_VERSION = 1


def profile_to_dict(profile: CameraProfile) -> dict:
    """Profile as a docs/profiles.md mapping, with the MLA position made explicit
    (``mla.distance_mm`` for the singlet form, ``mla.gap_mm`` for a prescription)."""
    ml, mla, s = profile.main_lens, profile.mla, profile.sensor
    sensor = {k: v for k, v in asdict(s).items() if v is not None}
    if "axis_px" in sensor:
        sensor["axis_px"] = list(sensor["axis_px"])
    where = ({"distance_mm": profile.d_in_mm} if ml.is_singlet
             else {"gap_mm": profile.gap_mm})
    return {
        "name": profile.name,
        "main_lens": ml.to_dict(),
        "mla": {
            "focal_length_mm": mla.focal_length_mm, "pitch_mm": mla.pitch_mm, "grid": mla.grid,
            **where, "rotation_rad": mla.rotation_rad,
            "offset_mm": list(mla.offset_mm), "fill_factor": mla.fill_factor,
        },
        "sensor": sensor,
    }


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, (list, tuple)):
        if v and isinstance(v[0], dict):  # a table array (surfaces): one row a line
            return "[\n" + "".join(f"  {_toml_value(x)},\n" for x in v) + "]"
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("inf" if v > 0 else "-inf")
    return str(v)


def profile_to_toml(profile: CameraProfile) -> str:
    """TOML text of a profile (loads back with :func:`lfcam.camera.load_profile`)."""
    d = profile_to_dict(profile)
    lines = [f"name = {_toml_value(d['name'])}"]
    for section in ("main_lens", "mla", "sensor"):
        lines.append(f"\n[{section}]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in d[section].items()]
    return "\n".join(lines) + "\n"


def apply_overrides(profile: CameraProfile, camera: dict) -> CameraProfile:
    """Merge a scene's ``camera`` overrides (same tables as a profile) and re-validate."""
    if not camera:
        return profile
    d = profile_to_dict(profile)
    for section, values in camera.items():
        if section not in ("main_lens", "mla", "sensor") or not isinstance(values, dict):
            raise SceneError(f"camera.{section}: overrides must be main_lens, mla or sensor tables")
        d[section].update(values)
        if section == "mla" and ({"focus_mm", "gap_mm"} & set(values)) and (
                "distance_mm" not in values):
            d["mla"].pop("distance_mm", None)
        if section == "mla" and ({"focus_mm", "distance_mm"} & set(values)) and (
                "gap_mm" not in values):
            d["mla"].pop("gap_mm", None)
        if section == "main_lens" and "surfaces" in values:
            for key in ("radius_mm", "thickness_mm", "refractive_index", "pupil_diameter_mm"):
                d["main_lens"].pop(key, None)
    return profile_from_dict(d, source=f"{profile.source} + scene overrides")


def _sensor_profile(profile: CameraProfile, scene: Scene) -> CameraProfile:
    e = scene.sensor
    s = profile.sensor
    bit_depth = e.bit_depth or s.bit_depth
    if bit_depth > 16:
        raise SceneError(f"sensor.bit_depth {bit_depth}: the simulator writes at most 16 bits")
    top = 2**bit_depth - 1
    white = e.white_level if e.white_level is not None else min(s.white_level, top)
    black = e.black_level if e.black_level is not None else min(s.black_level, top)
    if white <= black:
        raise SceneError(f"sensor white level {white} must exceed black level {black}")
    # with photon noise the written profile states the simulated sensor's full well (the
    # gain the distance fits take where a capture cannot measure its own: docs/profiles.md)
    return replace(profile, sensor=replace(s, bit_depth=bit_depth, white_level=white,
                                           black_level=black, bayer=e.bayer or s.bayer,
                                           full_well_e=(float(e.full_well_e) if e.photon_noise
                                                        else s.full_well_e)))


def _rim_truth(profile: CameraProfile, renderer: Renderer, distance_mm: float, x_mm: float,
               y_mm: float, direction: tuple[float, float] | None = None) -> dict:
    off = math.hypot(x_mm, y_mm)
    if direction is None:
        direction = (x_mm / off, y_mm / off) if off > 0 else (0.0, 1.0)
    ux, uy = direction
    res = forward(profile, None, distance_mm, off)
    mla = forward(profile, None, distance_mm, off, z_plane_mm=profile.d_in_mm)
    y1, y2 = float(res.y1_mm), float(res.y2_mm)
    out = {
        "distance_mm": distance_mm, "offset_mm": off, "position_mm": [x_mm, y_mm],
        "meridian": [ux, uy], "y1_mm": y1, "y2_mm": y2, "diameter_mm": abs(y1 - y2),
        "y1_mla_mm": float(mla.y1_mm), "y2_mla_mm": float(mla.y2_mm),
        "status": int(res.status),
    }
    if math.isfinite(y1) and math.isfinite(y2):
        p1 = renderer.mm_to_px(y1 * ux, y1 * uy)
        p2 = renderer.mm_to_px(y2 * ux, y2 * uy)
        out["rim_points_px"] = [[float(p1[0]), float(p1[1])], [float(p2[0]), float(p2[1])]]
    return out


def build_truth(profile: CameraProfile, scene: Scene, renderer: Renderer, res: RenderResult,
                exposure_scale: float) -> dict:
    """Ground-truth mapping for a rendered capture (schema in docs/simulate.md)."""
    grid = MlaGrid.from_mla(profile.mla)
    sources = []
    by_index = {s["index"]: s for s in res.sources}
    for k, obj in enumerate(scene.objects):
        entry: dict = {"index": k}
        info = by_index.get(k)
        if isinstance(obj, PointSource):
            entry["kind"] = "point"
            entry.update(_rim_truth(profile, renderer, obj.distance_mm, obj.x_mm, obj.y_mm))
            entry["intensity"] = obj.intensity
        elif isinstance(obj, LineSource):
            entry["kind"] = "line"
            entry["distance_mm"] = obj.distance_mm
            entry["length_mm"] = obj.length_mm
            entry["points"] = info["points"]
            dx, dy = obj.end_mm[0] - obj.start_mm[0], obj.end_mm[1] - obj.start_mm[1]
            fallback = (dx / obj.length_mm, dy / obj.length_mm)
            ends = []
            for ex, ey in (obj.start_mm, obj.end_mm):
                off = math.hypot(ex, ey)
                ends.append(_rim_truth(profile, renderer, obj.distance_mm, ex, ey,
                                       None if off > 0 else fallback))
            entry["endpoints"] = ends
        else:
            entry["kind"] = type(obj).__name__
            entry.update({k2: (list(v) if isinstance(v, tuple) else v)
                          for k2, v in asdict(obj).items()})
        if info is not None:
            pos = info["power_on_sensor"]
            entry["power_through_aperture"] = info["power_through_aperture"]
            entry["power_on_sensor"] = pos
            entry["centroid_px"] = ([info["sum_x"] / pos, info["sum_y"] / pos] if pos > 0
                                    else None)
        sources.append(entry)
    lit = res.lens_weight > 0
    cen = res.lens_centroid_px
    lenses = {
        "count": int(lit.sum()),
        "index_ij": np.stack([res.lens_i[lit], res.lens_j[lit]], 1).tolist(),
        "centre_mm": np.round(res.lens_centre_mm[lit], 6).tolist(),
        "centroid_px": np.round(cen[lit], 5).tolist(),
        "weight": [float(f"{w:.6g}") for w in res.lens_weight[lit] / res.lens_weight.max()]
        if lit.any() else [],
        "complete": res.lens_complete[lit].astype(int).tolist(),
    }
    pp = profile.sensor.pixel_pitch_mm
    ax, ay = profile.sensor.axis_xy_px
    basis = grid.basis_mm
    return {
        "lfcam_truth_version": TRUTH_VERSION,
        "profile": profile.name,
        "d_in_mm": profile.d_in_mm,
        "sensor_z_mm": profile.sensor_z_mm,
        "exit_pupil_z_mm": profile.main_lens.exit_pupil_z_mm,
        "axis_px": [ax, ay],
        "seed": scene.seed,
        "exposure_scale": exposure_scale,
        "mla": {
            "grid": grid.grid, "pitch_mm": grid.pitch_mm, "rotation_rad": grid.rotation_rad,
            "offset_mm": list(grid.offset_mm), "fill_factor": grid.fill_factor,
            "focal_length_mm": profile.mla.focal_length_mm,
            "pitch_px": grid.pitch_mm / pp,
            "offset_px": [grid.offset_mm[0] / pp + ax, grid.offset_mm[1] / pp + ay],
            "basis_px": (basis / pp).tolist(),
        },
        "sources": sources,
        "lenses": lenses,
        "render_stats": res.stats,
    }


def simulate(profile: CameraProfile, scene: Scene, max_rays: int = MAX_TOTAL_RAYS,
             progress: Progress | None = None,
             ) -> tuple[np.ndarray, CameraProfile, dict]:
    """Render a scene: returns (raw uint16 raster, profile used, truth mapping).

    ``max_rays`` bounds the total work (:func:`lfcam.sim.scene.check_ray_budget`, checked
    before rendering); ``progress("rendering", done, total)`` is called after each rendering
    step.
    """
    profile = apply_overrides(profile, scene.camera)
    profile = profile.with_d_in(profile.d_in_mm)
    profile = _sensor_profile(profile, scene)
    check_ray_budget(scene, profile.sensor.width_px * profile.sensor.height_px, max_rays)
    renderer = Renderer(profile)
    res = renderer.render(scene, progress=progress)
    peak = float(res.signal.max())
    if scene.exposure_scale is not None:
        scale = scene.exposure_scale
    else:
        scale = scene.exposure_peak / peak if peak > 0 else 1.0
    rng = np.random.default_rng(np.random.SeedSequence([scene.seed, 1]))
    s = profile.sensor
    raw = apply_sensor(res.signal, scene.sensor, s.bayer, s.bit_depth, s.black_level,
                       s.white_level, scale, rng)
    return raw, profile, build_truth(profile, scene, renderer, res, scale)


def _write_png(path: Path, raw: np.ndarray, profile: CameraProfile) -> None:
    import cv2

    def w(p: Path) -> None:
        if not cv2.imwrite(str(p), raw, [cv2.IMWRITE_PNG_COMPRESSION, 9]):
            raise LfcamError(f"could not write {p}")
    atomic_write(path, w)


def _write_tiff(path: Path, raw: np.ndarray, profile: CameraProfile) -> None:
    import tifffile

    atomic_write(path, lambda p: tifffile.imwrite(p, raw, compression="zlib"))


def _write_lytro(path: Path, raw: np.ndarray, profile: CameraProfile) -> None:
    from lfcam.sim.lytro import write_lytro_capture

    write_lytro_capture(path, raw, profile)


WRITERS: dict[str, Callable[[Path, np.ndarray, CameraProfile], None]] = {
    ".png": _write_png, ".tif": _write_tiff, ".tiff": _write_tiff,
    ".lfr": _write_lytro, ".lfp": _write_lytro,
}


def capture_paths(out: str | Path, fmt: str | None = None) -> tuple[Path, Path, Path]:
    """(raster, profile, truth) paths for an output name; no suffix → ``fmt`` or PNG."""
    out = Path(out)
    if out.suffix.lower() not in WRITERS:
        out = out.with_name(out.name + "." + (fmt or "png"))
    stem = out.with_suffix("")
    return out, Path(f"{stem}.profile.toml"), Path(f"{stem}.truth.json")


def write_capture(out: str | Path, raw: np.ndarray, profile: CameraProfile, truth: dict,
                  fmt: str | None = None) -> tuple[Path, Path, Path]:
    """Write raster, profile and truth atomically; returns their paths."""
    img, prof, tru = capture_paths(out, fmt)
    if not img.parent.is_dir():
        raise SceneError(f"output folder does not exist: {img.parent}")
    WRITERS[img.suffix.lower()](img, raw, profile)
    text = profile_to_toml(profile)
    atomic_write(prof, lambda p: p.write_text(text, encoding="utf-8"))
    body = json.dumps(_finite(truth), indent=1, allow_nan=False, default=_json_default)
    atomic_write(tru, lambda p: p.write_text(body + "\n", encoding="utf-8"))
    return img, prof, tru


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")


def _finite(o):
    """Replace non-finite floats by None (JSON has no NaN) throughout a nested structure."""
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite(v) for v in o]
    if isinstance(o, (float, np.floating)) and not math.isfinite(o):
        return None
    return o
