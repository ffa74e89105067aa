"""Scene description for the renderer: objects, exposure, sensor effects (schema: docs/simulate.md).

Every object is a frozen dataclass; :func:`scene_from_dict` validates a parsed JSON mapping
and raises :class:`~lfcam.errors.SceneError` naming the offending key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lfcam.camera import BAYER_PATTERNS
from lfcam.errors import SceneError
from lfcam.validate import Fields, read_json

MAX_RAYS = 500_000_000  # per source; bounds the work an untrusted scene can ask for
MAX_TOTAL_RAYS = 2_000_000_000  # whole scene (~20 min on one core); `simulate --max-rays`
MAX_SAMPLES = 4096
TEXTURES = ("checkerboard", "random", "uniform")


@dataclass(frozen=True)
class PointSource:
    """Isotropic point source ``distance_mm`` before the front vertex at lateral (x, y)."""

    distance_mm: float
    x_mm: float = 0.0
    y_mm: float = 0.0
    intensity: float = 1.0  # power per steradian
    rays: int | None = None

    @property
    def offset_mm(self) -> float:
        """Height above the axis (the seed's Δh)."""
        return math.hypot(self.x_mm, self.y_mm)


@dataclass(frozen=True)
class LineSource:
    """Uniform line source between two lateral endpoints on the plane ``distance_mm``."""

    distance_mm: float
    start_mm: tuple[float, float]
    end_mm: tuple[float, float]
    intensity: float = 1.0  # power per steradian per mm of line
    points: int | None = None
    rays: int | None = None

    @property
    def length_mm(self) -> float:
        """Length of the segment."""
        return math.hypot(self.end_mm[0] - self.start_mm[0], self.end_mm[1] - self.start_mm[1])


@dataclass(frozen=True)
class TexturedPlane:
    """Lambertian plane perpendicular to the axis, ``distance_mm`` before the front vertex."""

    distance_mm: float
    texture: str = "checkerboard"
    square_mm: float = 10.0  # checker square / random-cell size
    low: float = 0.1  # radiance of dark squares / lower bound of random values
    high: float = 1.0
    center_mm: tuple[float, float] = (0.0, 0.0)
    size_mm: tuple[float, float] | None = None  # finite extent (width, height); None = infinite
    seed: int = 0


@dataclass(frozen=True)
class WhiteScene:
    """Uniform radiance filling the whole field (a white-image capture)."""

    radiance: float = 1.0


@dataclass(frozen=True)
class SensorEffects:
    """Sensor effects, each off by default."""

    photon_noise: bool = False
    full_well_e: float = 20000.0
    read_noise_e: float = 0.0
    bayer: str | None = None  # overrides the profile's pattern
    bayer_gains: tuple[float, float, float] = (0.55, 1.0, 0.75)  # R, G, B
    bit_depth: int | None = None
    black_level: int | None = None
    white_level: int | None = None
    hot_pixels: int = 0
    hot_value: float = 1.0  # fraction of full scale


@dataclass(frozen=True)
class Scene:
    """A complete scene: objects (possibly none: a dark frame), exposure, sampling, sensor."""

    objects: tuple = ()
    seed: int = 0
    exposure_peak: float | None = 0.9  # brightest pixel as a fraction of full scale
    exposure_scale: float | None = None  # or: absolute full-scale fraction per unit signal
    rays_per_source: int = 1_000_000
    samples_per_pixel: int = 32  # backward samples for micro-image boundary pixels
    interior_samples: int = 4  # backward samples for fully lit pixels (textured planes)
    sensor: SensorEffects = field(default_factory=SensorEffects)
    camera: dict = field(default_factory=dict)  # profile overrides, merged before rendering
    output_format: str | None = None


_FIELDS = Fields(SceneError)
_num = _FIELDS.number
_int = _FIELDS.integer
_pair = _FIELDS.pair
_keys = _FIELDS.known_keys


def _lateral(obj: dict, where: str) -> tuple[float, float]:
    """(x, y) from ``position_mm`` or from ``offset_mm`` + ``azimuth_deg`` (default +y)."""
    if "position_mm" in obj:
        if "offset_mm" in obj:
            raise SceneError(f"{where}: give position_mm or offset_mm, not both")
        return _pair(f"{where}.position_mm", obj["position_mm"])
    off = _num(f"{where}.offset_mm", obj.get("offset_mm", 0.0))
    az = math.radians(_num(f"{where}.azimuth_deg", obj.get("azimuth_deg", 90.0)))
    return (off * math.cos(az), off * math.sin(az))


def _object(obj: Any, i: int):
    where = f"objects[{i}]"
    if not isinstance(obj, dict):
        raise SceneError(f"{where}: expected an object, got {obj!r}")
    kind = obj.get("type")
    if kind == "point":
        _keys(obj, where, {"type", "distance_mm", "offset_mm", "azimuth_deg", "position_mm",
                           "intensity", "rays"})
        x, y = _lateral(obj, where)
        return PointSource(
            distance_mm=_num(f"{where}.distance_mm", obj.get("distance_mm"), positive=True),
            x_mm=x,
            y_mm=y,
            intensity=_num(f"{where}.intensity", obj.get("intensity", 1.0), nonneg=True),
            rays=None if "rays" not in obj else _int(f"{where}.rays", obj["rays"], 1, MAX_RAYS),
        )
    if kind == "line":
        _keys(obj, where, {"type", "distance_mm", "start_mm", "end_mm", "intensity", "points",
                           "rays"})
        if "start_mm" not in obj or "end_mm" not in obj:
            raise SceneError(f"{where}: a line needs start_mm and end_mm ([x, y] each)")
        line = LineSource(
            distance_mm=_num(f"{where}.distance_mm", obj.get("distance_mm"), positive=True),
            start_mm=_pair(f"{where}.start_mm", obj["start_mm"]),
            end_mm=_pair(f"{where}.end_mm", obj["end_mm"]),
            intensity=_num(f"{where}.intensity", obj.get("intensity", 1.0), nonneg=True),
            points=None if "points" not in obj else _int(f"{where}.points", obj["points"], 2,
                                                         100_000),
            rays=None if "rays" not in obj else _int(f"{where}.rays", obj["rays"], 1, MAX_RAYS),
        )
        if line.length_mm == 0.0:
            raise SceneError(f"{where}: start_mm and end_mm coincide (use a point source)")
        return line
    if kind == "plane":
        _keys(obj, where, {"type", "distance_mm", "texture", "square_mm", "low", "high",
                           "center_mm", "size_mm", "seed"})
        texture = obj.get("texture", "checkerboard")
        if texture not in TEXTURES:
            raise SceneError(f"{where}.texture: must be one of {TEXTURES}, got {texture!r}")
        size = None
        if obj.get("size_mm") is not None:
            size = _pair(f"{where}.size_mm", obj["size_mm"])
            if min(size) <= 0:
                raise SceneError(f"{where}.size_mm: both sides must be positive")
        return TexturedPlane(
            distance_mm=_num(f"{where}.distance_mm", obj.get("distance_mm"), positive=True),
            texture=texture,
            square_mm=_num(f"{where}.square_mm", obj.get("square_mm", 10.0), positive=True),
            low=_num(f"{where}.low", obj.get("low", 0.1), nonneg=True),
            high=_num(f"{where}.high", obj.get("high", 1.0), nonneg=True),
            center_mm=_pair(f"{where}.center_mm", obj.get("center_mm", [0.0, 0.0])),
            size_mm=size,
            seed=_int(f"{where}.seed", obj.get("seed", 0), 0, 2**63 - 1),
        )
    if kind == "white":
        _keys(obj, where, {"type", "radiance"})
        return WhiteScene(radiance=_num(f"{where}.radiance", obj.get("radiance", 1.0),
                                        nonneg=True))
    raise SceneError(f"{where}.type: must be point, line, plane or white, got {kind!r}")


def _sensor(data: Any) -> SensorEffects:
    if not isinstance(data, dict):
        raise SceneError("sensor: expected an object")
    _keys(data, "sensor", {"photon_noise", "full_well_e", "read_noise_e", "bayer", "bayer_gains",
                           "bit_depth", "black_level", "white_level", "hot_pixels", "hot_value"})
    bayer = data.get("bayer")
    if bayer is not None and bayer not in BAYER_PATTERNS:
        raise SceneError(f"sensor.bayer: must be one of {BAYER_PATTERNS}, got {bayer!r}")
    gains = data.get("bayer_gains", [0.55, 1.0, 0.75])
    if not isinstance(gains, (list, tuple)) or len(gains) != 3:
        raise SceneError("sensor.bayer_gains: expected [r, g, b]")
    photon = data.get("photon_noise", False)
    if not isinstance(photon, bool):
        raise SceneError("sensor.photon_noise: expected true or false")
    bit_depth = None if data.get("bit_depth") is None else _int("sensor.bit_depth",
                                                                 data["bit_depth"], 1, 16)
    top = 2 ** (bit_depth or 16) - 1
    return SensorEffects(
        photon_noise=photon,
        full_well_e=_num("sensor.full_well_e", data.get("full_well_e", 20000.0), positive=True),
        read_noise_e=_num("sensor.read_noise_e", data.get("read_noise_e", 0.0), nonneg=True),
        bayer=bayer,
        bayer_gains=tuple(_num(f"sensor.bayer_gains[{k}]", g, nonneg=True)
                          for k, g in enumerate(gains)),
        bit_depth=bit_depth,
        black_level=None if data.get("black_level") is None else _int(
            "sensor.black_level", data["black_level"], 0, top),
        white_level=None if data.get("white_level") is None else _int(
            "sensor.white_level", data["white_level"], 1, top),
        hot_pixels=_int("sensor.hot_pixels", data.get("hot_pixels", 0), 0, 10_000_000),
        hot_value=_num("sensor.hot_value", data.get("hot_value", 1.0), nonneg=True),
    )


def scene_from_dict(data: Any) -> Scene:
    """Validate a parsed scene mapping (docs/simulate.md) and build a :class:`Scene`.

    Raises
    ------
    SceneError
        Naming the offending key for any missing, mistyped or out-of-range value.
    """
    if not isinstance(data, dict):
        raise SceneError("scene: expected a JSON object at the top level")
    _keys(data, "scene", {"objects", "seed", "exposure", "rays_per_source", "samples_per_pixel",
                          "interior_samples", "sensor", "camera", "format", "comment"})
    objs = data.get("objects", [])
    if not isinstance(objs, list):
        raise SceneError("objects: expected a list")
    if len(objs) > 10_000:
        raise SceneError(f"objects: at most 10000 objects, got {len(objs)}")
    exposure = data.get("exposure", {"peak": 0.9})
    if not isinstance(exposure, dict) or len(exposure) != 1 or not (
        set(exposure) <= {"peak", "scale"}
    ):
        raise SceneError('exposure: expected {"peak": fraction} or {"scale": value}')
    peak = scale = None
    if "peak" in exposure:
        peak = _num("exposure.peak", exposure["peak"], positive=True)
    else:
        scale = _num("exposure.scale", exposure["scale"], positive=True)
    camera = data.get("camera", {})
    if not isinstance(camera, dict):
        raise SceneError("camera: expected an object of profile overrides")
    fmt = data.get("format")
    if fmt is not None and fmt not in ("png", "tiff"):
        raise SceneError(f"format: must be png or tiff, got {fmt!r}")
    return Scene(
        objects=tuple(_object(o, i) for i, o in enumerate(objs)),
        seed=_int("seed", data.get("seed", 0), 0, 2**63 - 1),
        exposure_peak=peak,
        exposure_scale=scale,
        rays_per_source=_int("rays_per_source", data.get("rays_per_source", 1_000_000), 1,
                             MAX_RAYS),
        samples_per_pixel=_int("samples_per_pixel", data.get("samples_per_pixel", 32), 1,
                               MAX_SAMPLES),
        interior_samples=_int("interior_samples", data.get("interior_samples", 4), 1,
                              MAX_SAMPLES),
        sensor=_sensor(data.get("sensor", {})),
        camera=camera,
        output_format=fmt,
    )


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene JSON file."""
    return scene_from_dict(read_json(path, SceneError, "scene", 16 * 1024 * 1024))


def _strata(n: int) -> int:
    """Rays actually traced for a request of ``n`` (rounded up to a k×k square)."""
    k = max(1, math.ceil(math.sqrt(n)))
    return k * k


def ray_count(scene: Scene, n_pixels: int) -> int:
    """Upper bound of the rays rendering ``scene`` on a sensor of ``n_pixels`` traces.

    Point sources trace ``rays`` (rounded up to a square); line sources ``points`` times
    the per-point share; white and textured scenes at most four corner rays plus
    ``max(samples_per_pixel, interior_samples)`` (rounded up to squares) per pixel.
    """
    total = 0
    backward = False
    for obj in scene.objects:
        if isinstance(obj, PointSource):
            total += _strata(obj.rays or scene.rays_per_source)
        elif isinstance(obj, LineSource):
            n_pts = obj.points or max(16, int(math.ceil(obj.length_mm / 0.05)))
            per_pt = max(1, (obj.rays or scene.rays_per_source) // n_pts)
            total += n_pts * _strata(per_pt)
        else:
            backward = True
    if backward:
        per_px = max(_strata(scene.samples_per_pixel), _strata(scene.interior_samples))
        total += n_pixels * (4 + per_px)
    return total


def check_ray_budget(scene: Scene, n_pixels: int, max_rays: int = MAX_TOTAL_RAYS) -> int:
    """Refuse a scene whose :func:`ray_count` exceeds ``max_rays``; returns the count.

    Raises
    ------
    SceneError
        Naming the count and the budget (``lfcam simulate --max-rays`` raises it).
    """
    n = ray_count(scene, n_pixels)
    if n > max_rays:
        raise SceneError(f"scene needs about {n:.3g} rays, over the budget of {max_rays:.3g} "
                         "(fewer objects or rays, or raise it with --max-rays)")
    return n
