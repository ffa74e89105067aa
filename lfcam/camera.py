"""Camera description: one frozen dataclass per physical part, and the TOML profile loader.

Conventions (docs/conventions.md): lengths in millimetres, optical axis z, origin at the main-lens
centre (mid-thickness), +z toward the sensor. The profile schema is docs/profiles.md; keys this
module adds where the contract is silent are documented in ``docs/profiles.md``.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from lfcam.errors import OpticsError, ProfileError
from lfcam.optics.lens import Prescription, ideal_lens
from lfcam.validate import Fields

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on 3.10 only
    import tomli as tomllib

GRIDS = ("rect", "hex")
BAYER_PATTERNS = ("none", "RGGB", "BGGR", "GRBG", "GBRG")
FOCAL_LENGTH_RTOL = 1e-4  # docs/profiles.md: a stated focal length must agree to 0.01 %


@dataclass(frozen=True)
class BlackBox:
    """What is known of a main lens whose prescription is not (CONTRACT §2a, black-box form).

    Parameters
    ----------
    focal_length_mm : float
        Focal length printed on the barrel or stored by the camera.
    f_number : float
        Infinity f-number.
    exit_pupil_mm : float or None
        Exit pupil → MLA distance (positive when the exit pupil lies in front of the MLA),
        when known (Lytro metadata ``exitPupilOffset``).
    """

    focal_length_mm: float
    f_number: float
    exit_pupil_mm: float | None = None

    def to_dict(self) -> dict:
        """The ``[main_lens]`` table of this form."""
        out = {"focal_length_mm": self.focal_length_mm, "f_number": self.f_number}
        if self.exit_pupil_mm is not None:
            out["exit_pupil_mm"] = self.exit_pupil_mm
        return out


@dataclass(frozen=True)
class MainLens:
    """The main lens: a sequential prescription placed in lfcam's optical-axis frame.

    Two forms (docs/profiles.md). The seed paper's **singlet** (``radius_mm``,
    ``thickness_mm``, ``refractive_index``, ``pupil_diameter_mm``) is the two-surface
    prescription :meth:`Prescription.from_singlet` (aperture stop = the front rim circle,
    diameter D) with the frame origin at the lens centre (mid-thickness), so ``d_in_mm`` keeps
    the seed's meaning (lens centre → MLA). A general **prescription** (``prescription``) has
    its origin at its front vertex, so ``d_in_mm`` is front vertex → MLA. Every property
    below comes from the prescription (paraxial y–nu traces, :mod:`lfcam.optics.lens`), never
    from singlet formulas, and is in this frame.

    Parameters
    ----------
    radius_mm, thickness_mm, refractive_index : float or None
        Singlet form: R of both surfaces, centre thickness T, glass index n.
    pupil_diameter_mm : float or None
        Singlet form: the clear aperture D at the front rim (the stop). Filled in for a
        prescription with the diameter of the aperture seen from object space (see
        :attr:`rim_z_mm`).
    prescription : Prescription or None
        General form; leave the singlet fields unset.
    black_box : BlackBox or None
        Set for the **black-box** form (focal length and f-number only): ``prescription`` is
        then only a *seed* ideal lens (:func:`lfcam.optics.lens.ideal_lens`), good for
        drawing and first guesses; distances need the lens learned from target captures
        (``lfcam calibrate --targets``, :mod:`lfcam.calibrate.lensfit`).
    """

    radius_mm: float | None = None
    thickness_mm: float | None = None
    refractive_index: float | None = None
    pupil_diameter_mm: float | None = None
    prescription: Prescription | None = field(default=None, compare=True)
    black_box: BlackBox | None = None

    def __post_init__(self) -> None:
        if self.black_box is not None and self.prescription is None:
            raise ProfileError("main lens: a black box needs its seed prescription")
        singlet = (self.radius_mm, self.thickness_mm, self.refractive_index)
        if self.prescription is None:
            if any(v is None for v in singlet) or self.pupil_diameter_mm is None:
                raise ProfileError("main lens: give R, T, n, D (singlet) or a prescription")
            p = Prescription.from_singlet(
                self.radius_mm, self.thickness_mm, self.refractive_index, self.pupil_diameter_mm
            )
            object.__setattr__(self, "_rx", p)
        else:
            if any(v is not None for v in singlet):
                raise ProfileError("main lens: give either the singlet keys or a prescription")
            object.__setattr__(self, "_rx", self.prescription)
            if self.pupil_diameter_mm is None:
                object.__setattr__(self, "pupil_diameter_mm", self._rx.stop_pupils[1])

    # ------------------------------------------------------------------ form and frame

    @property
    def is_singlet(self) -> bool:
        """True for the seed's symmetric biconvex singlet form."""
        return self.prescription is None

    @property
    def is_black_box(self) -> bool:
        """True for the black-box form: the prescription is a seed, not the lens."""
        return self.black_box is not None

    @property
    def as_prescription(self) -> Prescription:
        """The lens as a :class:`~lfcam.optics.lens.Prescription` (the singlet's two
        surfaces for the singlet form). Its z frame starts at the front vertex; add
        :attr:`front_vertex_z_mm` to get this lens's frame."""
        return self._rx

    @property
    def front_vertex_z_mm(self) -> float:
        """z of the front vertex (−T/2 for the singlet, 0 for a prescription)."""
        return -0.5 * self.thickness_mm if self.is_singlet else 0.0

    @property
    def back_vertex_z_mm(self) -> float:
        """z of the last (rear) vertex."""
        return self.front_vertex_z_mm + self._rx.last_vertex_z_mm

    # ------------------------------------------------------------------ paraxial data

    @property
    def focal_length_mm(self) -> float:
        """Effective focal length (paraxial trace)."""
        return self._rx.paraxial.efl_mm

    @property
    def front_principal_z_mm(self) -> float:
        """z of the object-side principal plane H1."""
        return self.front_vertex_z_mm + self._rx.paraxial.front_principal_z_mm

    @property
    def back_principal_z_mm(self) -> float:
        """z of the image-side principal plane H2."""
        return self.front_vertex_z_mm + self._rx.paraxial.back_principal_z_mm

    @property
    def principal_depth_mm(self) -> float:
        """Front vertex → H1 along +z (for the symmetric singlet also H2 → back vertex)."""
        return self.front_principal_z_mm - self.front_vertex_z_mm

    @property
    def rim_z_mm(self) -> float:
        """z of the aperture as object-space rays meet it: the plane of the stop's edge
        circle when the stop is the first surface (the seed's front rim), else the paraxial
        entrance pupil of that circle."""
        return self.front_vertex_z_mm + self._rx.stop_pupils[0]

    @property
    def rim_sag_mm(self) -> float:
        """Front vertex → aperture plane (:attr:`rim_z_mm`) along +z."""
        return self.rim_z_mm - self.front_vertex_z_mm

    @property
    def edge_radius_mm(self) -> float:
        """Singlet: height at which the two spherical surfaces meet (the lens edge).
        Prescription: the largest clear semi-diameter."""
        if self.is_singlet:
            r, t = self.radius_mm, self.thickness_mm
            return math.sqrt(max(r * r - (r - 0.5 * t) ** 2, 0.0))
        return max(s.semi_diameter_mm for s in self._rx.surfaces)

    @property
    def exit_pupil_z_mm(self) -> float:
        """Paraxial z of the exit pupil: the stop's edge circle imaged by the surfaces
        behind it (:attr:`Prescription.stop_pupils`)."""
        return self.front_vertex_z_mm + self._rx.stop_pupils[2]

    @property
    def exit_pupil_diameter_mm(self) -> float:
        """Paraxial diameter of the exit pupil (the stop's edge circle imaged backward)."""
        return self._rx.stop_pupils[3]

    @property
    def f_number(self) -> float:
        """Working f-number at infinity focus, f / D."""
        return self.focal_length_mm / self.pupil_diameter_mm

    def image_distance_mm(self, distance_mm: np.ndarray | float) -> np.ndarray | float:
        """Paraxial image distance behind H2 for an object ``distance_mm`` before the front
        vertex.

        Infinite distances give f. Objects at or inside the front focal plane give ``inf`` or a
        negative (virtual) image distance.
        """
        f = self.focal_length_mm
        s = np.asarray(distance_mm, dtype=np.float64) + self.principal_depth_mm
        with np.errstate(divide="ignore"):
            out = 1.0 / (1.0 / f - 1.0 / s)
        return out if out.ndim else float(out)

    def d_in_for_focus(self, focus_mm: float) -> float:
        """MLA distance d_in (frame origin → MLA) that paraxially focuses an object at
        ``focus_mm`` (from the front vertex; ``math.inf`` for infinity focus).

        Raises
        ------
        OpticsError
            If the object is at or inside the front focal point (no real image).
        """
        focus = float(focus_mm)
        if math.isnan(focus) or focus <= 0:
            raise OpticsError(f"focus distance must be positive, got {focus_mm}")
        s_img = self.image_distance_mm(focus)
        if not math.isfinite(s_img) or s_img <= 0:
            raise OpticsError(
                f"focus {focus} mm is at or inside the front focal point "
                f"(f = {self.focal_length_mm:.3f} mm): no real image to put the MLA at"
            )
        return self.back_principal_z_mm + s_img

    def focus_for_d_in(self, d_in_mm: float) -> float:
        """Object distance (from the front vertex) in paraxial focus on an MLA at ``d_in_mm``;
        ``inf`` when the MLA sits at the back focal plane or closer."""
        s_img = float(d_in_mm) - self.back_principal_z_mm
        f = self.focal_length_mm
        if s_img <= f:
            return math.inf
        return 1.0 / (1.0 / f - 1.0 / s_img) - self.principal_depth_mm

    def to_prescription_z(self, z_mm):
        """This frame's z → the prescription's (front vertex = 0)."""
        return z_mm - self.front_vertex_z_mm

    def to_dict(self) -> dict:
        """The ``[main_lens]`` table of a profile (singlet keys, ``surfaces`` or black box)."""
        if self.black_box is not None:
            return self.black_box.to_dict()
        if self.is_singlet:
            return {
                "radius_mm": self.radius_mm, "thickness_mm": self.thickness_mm,
                "refractive_index": self.refractive_index,
                "pupil_diameter_mm": self.pupil_diameter_mm,
            }
        from lfcam.optics.zmx import prescription_to_toml_dict

        table = prescription_to_toml_dict(self._rx)["main_lens"]
        return {"name": self._rx.name, **table} if self._rx.name else table


@dataclass(frozen=True)
class MicrolensArray:
    """Microlens array (thin ideal lenslets).

    Parameters
    ----------
    focal_length_mm : float
        Lenslet focal length f_x; the sensor lies f_x behind the MLA.
    pitch_mm : float
        Lenslet pitch D_m (centre to centre, along a grid row).
    grid : str
        ``"rect"`` or ``"hex"`` (hex: rows offset by half a pitch, row spacing pitch·√3/2).
    distance_mm : float or None
        d_in, main-lens centre to MLA. ``None`` when it comes from ``focus_mm`` or calibration.
    focus_mm : float or None
        Object distance (from the front vertex) in focus on the MLA; ``inf`` allowed.
    rotation_rad : float
        Rotation of the grid rows against the sensor x axis.
    offset_mm : tuple of float
        (x, y) of one lenslet centre relative to the optical axis, on the MLA plane.
    fill_factor : float
        Fraction of the pitch that is clear aperture (1 = lenslets touch).
    """

    focal_length_mm: float
    pitch_mm: float
    grid: str = "rect"
    distance_mm: float | None = None
    focus_mm: float | None = None
    rotation_rad: float = 0.0
    offset_mm: tuple[float, float] = (0.0, 0.0)
    fill_factor: float = 1.0


@dataclass(frozen=True)
class Sensor:
    """Image sensor.

    Parameters
    ----------
    pixel_pitch_mm : float
        Pixel pitch (square pixels).
    width_px, height_px : int
        Sensor size in pixels.
    bit_depth : int
        Bits per stored sample.
    bayer : str
        Colour filter pattern or ``"none"``.
    black_level, white_level : int
        Raw value of no light and of saturation.
    axis_px : tuple of float or None
        (x_px, y_px) where the optical axis meets the sensor; ``None`` = sensor centre.
    full_well_e : float or None
        Photo-electrons at the white level (optional: a datasheet figure or one
        photon-transfer measurement). The noise model's photon gain where a capture cannot
        measure its own (one small sharp blur: docs/profiles.md, docs/distance.md "A sensor
        gain for captures that cannot measure one (stop 49)").
    """

    pixel_pitch_mm: float
    width_px: int
    height_px: int
    bit_depth: int = 16
    bayer: str = "none"
    black_level: int = 0
    white_level: int = 65535
    axis_px: tuple[float, float] | None = None
    full_well_e: float | None = None

    @property
    def axis_xy_px(self) -> tuple[float, float]:
        """(x_px, y_px) of the optical axis on the sensor."""
        if self.axis_px is not None:
            return self.axis_px
        return (0.5 * (self.width_px - 1), 0.5 * (self.height_px - 1))


@dataclass(frozen=True)
class CameraProfile:
    """A complete plenoptic 1.0 camera: main lens, MLA and sensor."""

    name: str
    main_lens: MainLens
    mla: MicrolensArray
    sensor: Sensor
    source: str = field(default="", compare=False)

    @property
    def d_in_mm(self) -> float:
        """MLA distance d_in: stated, else derived from ``focus_mm`` through the principal planes.

        Raises
        ------
        ProfileError
            If the profile states neither ``mla.distance_mm`` nor ``mla.focus_mm``.
        """
        if self.mla.distance_mm is not None:
            return self.mla.distance_mm
        if self.mla.focus_mm is not None:
            return self.main_lens.d_in_for_focus(self.mla.focus_mm)
        if self.main_lens.is_black_box:
            raise ProfileError(
                f"profile {self.name!r}: the main lens is a black box (focal length, f-number) "
                "and the MLA distance is unknown: calibrate with --targets first, or give "
                "--d-in / --focus"
            )
        raise ProfileError(
            f"profile {self.name!r}: mla.distance_mm (d_in) is unknown: set mla.distance_mm or "
            "mla.focus_mm, or calibrate it from a reference-plane capture"
        )

    @property
    def sensor_z_mm(self) -> float:
        """z of the sensor plane, d_in + f_x."""
        return self.d_in_mm + self.mla.focal_length_mm

    @property
    def mla_z_mm(self) -> float:
        """z of the MLA plane in the lens frame (= ``d_in_mm``; docs/conventions.md)."""
        return self.d_in_mm

    @property
    def gap_mm(self) -> float:
        """Last lens vertex → MLA (the prescription form's ``mla.gap_mm``)."""
        return self.d_in_mm - self.main_lens.back_vertex_z_mm

    def with_d_in(self, d_in_mm: float) -> CameraProfile:
        """Return a copy with the MLA distance set (and ``focus_mm`` cleared)."""
        _check_positive("mla.distance_mm", d_in_mm)
        return replace(self, mla=replace(self.mla, distance_mm=float(d_in_mm), focus_mm=None))

    def with_focus(self, focus_mm: float) -> CameraProfile:
        """Return a copy focused at ``focus_mm`` (object distance from the front vertex)."""
        return self.with_d_in(self.main_lens.d_in_for_focus(focus_mm))


# ----------------------------------------------------------------------------- loading


_FIELDS = Fields(ProfileError)
_number = _FIELDS.number
_integer = _FIELDS.integer
_pair = _FIELDS.pair
_known_keys = _FIELDS.known_keys


MAX_VALUE = 1e9  # no length (mm), index or count of a camera comes near; keeps the optics finite


def _check_positive(key: str, value: Any) -> float:
    v = _FIELDS.number(key, value, positive=True)
    if v > MAX_VALUE:
        raise ProfileError(f"{key}: implausibly large, got {value!r} (at most {MAX_VALUE:g})")
    return v


def _table(data: dict, key: str) -> dict:
    if key not in data:
        raise ProfileError(f"missing table [{key}]")
    if not isinstance(data[key], dict):
        raise ProfileError(f"[{key}] must be a table")
    return data[key]


def _required(table: dict, section: str, key: str) -> Any:
    if key not in table:
        raise ProfileError(f"missing key {section}.{key}")
    return table[key]


_SINGLET_KEYS = {"radius_mm", "thickness_mm", "refractive_index", "pupil_diameter_mm",
                 "focal_length_mm"}


_BLACK_BOX_KEYS = {"focal_length_mm", "f_number", "exit_pupil_mm", "name"}


def _black_box_from_table(ml: dict, mt: dict) -> MainLens:
    """The black-box ``[main_lens]`` (CONTRACT §2a) and its seed ideal lens.

    The seed: principal plane at the lens front; the MLA at ``mla.distance_mm`` when given,
    else where ``mla.focus_mm`` (default infinity) is in paraxial focus; the exit pupil
    ``exit_pupil_mm`` in front of that MLA, else on the principal plane.
    """
    _known_keys(ml, "main_lens", _BLACK_BOX_KEYS)
    if "f_number" not in ml:
        raise ProfileError(
            "main_lens: a lens given by its focal length alone also needs f_number (black-box "
            "form), or the singlet keys / surfaces"
        )
    f = _check_positive("main_lens.focal_length_mm", _required(ml, "main_lens", "focal_length_mm"))
    n_f = _check_positive("main_lens.f_number", ml["f_number"])
    if n_f < 0.3 or n_f > 1000.0:
        raise ProfileError(f"main_lens.f_number: implausible, got {n_f} (0.3 to 1000)")
    xp = None
    if "exit_pupil_mm" in ml:
        xp = _number("main_lens.exit_pupil_mm", ml["exit_pupil_mm"])
        if abs(xp) > 100.0 * f:
            raise ProfileError(
                f"main_lens.exit_pupil_mm: implausible, {xp} mm for a {f} mm lens"
            )
    name = ml.get("name", "black box")
    if not isinstance(name, str):
        raise ProfileError("main_lens.name: expected a string")
    box = BlackBox(focal_length_mm=f, f_number=n_f, exit_pupil_mm=xp)
    d_in = mt.get("distance_mm") if isinstance(mt, dict) else None
    if isinstance(d_in, (int, float)) and not isinstance(d_in, bool) and d_in > 0:
        d_in = float(d_in)
    else:
        focus = mt.get("focus_mm", math.inf) if isinstance(mt, dict) else math.inf
        if isinstance(focus, (int, float)) and not isinstance(focus, bool) and focus > f:
            d_in = 1.0 / (1.0 / f - 1.0 / focus)  # thin lens; an infinite focus gives f
        else:
            d_in = f
    seed = ideal_lens(f, n_f, 0.0, None if xp is None else d_in - xp, name=name)
    return MainLens(prescription=seed, black_box=box)


def _main_lens_from_table(ml: dict, source: str = "", mla_table: dict | None = None) -> MainLens:
    """``[main_lens]``: the singlet keys, ``surfaces = [...]``, ``zmx = "lens.zmx"`` or the
    black box (``focal_length_mm``, ``f_number``, optional ``exit_pupil_mm``)."""
    if {"f_number", "exit_pupil_mm"} & set(ml) or set(ml) <= {"focal_length_mm", "name"}:
        return _black_box_from_table(ml, mla_table if mla_table is not None else {})
    forms = [k for k in ("surfaces", "zmx") if k in ml]
    if forms:
        if len(forms) > 1 or set(ml) & (_SINGLET_KEYS - {"focal_length_mm"}):
            raise ProfileError(
                "main_lens: give one form: the singlet keys (radius_mm, ...), surfaces = [...] "
                "or zmx = \"file.zmx\""
            )
        _known_keys(ml, "main_lens", {"surfaces", "zmx", "focal_length_mm", "name"})
        from lfcam.optics.zmx import load_zmx, prescription_from_toml_dict

        if "zmx" in ml:
            if not isinstance(ml["zmx"], str):
                raise ProfileError(f"main_lens.zmx: expected a path, got {ml['zmx']!r}")
            path = Path(ml["zmx"]).expanduser()
            if not path.is_absolute() and source:
                path = Path(source).parent / path
            if not path.is_file():
                raise ProfileError(f"main_lens.zmx: file not found: {path}")
            rx = load_zmx(path).prescription
        else:
            rx = prescription_from_toml_dict(ml)
        if "name" in ml:
            if not isinstance(ml["name"], str):
                raise ProfileError("main_lens.name: expected a string")
            rx = Prescription(rx.surfaces, name=ml["name"])
        try:
            efl = rx.paraxial.efl_mm
        except OpticsError as exc:
            raise ProfileError(f"main_lens.surfaces: {exc}") from None
        if not efl > 0.0:
            raise ProfileError(f"main_lens.surfaces: not a converging lens (EFL {efl:.4g} mm)")
        lens = MainLens(prescription=rx)
    else:
        _known_keys(ml, "main_lens", _SINGLET_KEYS)
        lens = _singlet_from_table(ml)
    if "focal_length_mm" in ml:
        stated = _check_positive("main_lens.focal_length_mm", ml["focal_length_mm"])
        derived = lens.focal_length_mm
        if abs(stated - derived) > FOCAL_LENGTH_RTOL * derived:
            raise ProfileError(
                f"main_lens.focal_length_mm: stated {stated} mm disagrees with {derived:.4f} mm "
                "derived from the lens by more than 0.01 %"
            )
    return lens


def _singlet_from_table(ml: dict) -> MainLens:
    """The seed singlet's keys, validated."""
    r = _check_positive("main_lens.radius_mm", _required(ml, "main_lens", "radius_mm"))
    t = _check_positive("main_lens.thickness_mm", _required(ml, "main_lens", "thickness_mm"))
    n = _check_positive(
        "main_lens.refractive_index", _required(ml, "main_lens", "refractive_index")
    )
    d = _check_positive(
        "main_lens.pupil_diameter_mm", _required(ml, "main_lens", "pupil_diameter_mm")
    )
    if n <= 1.0:
        raise ProfileError(f"main_lens.refractive_index: must exceed 1, got {n}")
    if d >= 2.0 * r:
        raise ProfileError(
            f"main_lens.pupil_diameter_mm: D = {d} must be smaller than 2R = {2 * r}"
        )
    if t >= 2.0 * r:
        raise ProfileError("main_lens.thickness_mm: T must be smaller than 2R")
    edge = math.sqrt(max(r * r - (r - 0.5 * t) ** 2, 0.0))
    if 0.5 * d >= edge:
        raise ProfileError(
            f"main_lens.pupil_diameter_mm: D/2 = {0.5 * d} reaches the lens "
            f"edge ({edge:.4g} mm, where the surfaces meet); increase "
            "main_lens.thickness_mm or reduce the pupil"
        )
    lens = MainLens(radius_mm=r, thickness_mm=t, refractive_index=n, pupil_diameter_mm=d)
    if lens.focal_length_mm <= 0.0:
        raise ProfileError("main_lens: R, T, n give a non-positive focal length")
    return lens


def profile_from_dict(data: dict, source: str = "") -> CameraProfile:
    """Validate a parsed profile mapping and build a :class:`CameraProfile`.

    Parameters
    ----------
    data : dict
        Parsed TOML (docs/profiles.md).
    source : str
        Where it came from, for messages.

    Returns
    -------
    CameraProfile

    Raises
    ------
    ProfileError
        Naming the offending key for every missing, mistyped, non-finite, negative or
        inconsistent value.
    """
    if not isinstance(data, dict):
        raise ProfileError("profile must be a TOML table")
    name = data.get("name", Path(source).stem if source else "unnamed")
    if not isinstance(name, str):
        raise ProfileError(f"name: expected a string, got {name!r}")

    ml = _table(data, "main_lens")
    mt = _table(data, "mla")
    lens = _main_lens_from_table(ml, source, mt)

    _known_keys(
        mt,
        "mla",
        {
            "focal_length_mm", "pitch_mm", "grid", "distance_mm", "focus_mm", "gap_mm",
            "rotation_rad", "offset_mm", "fill_factor",
        },
    )
    grid = mt.get("grid", "rect")
    if grid not in GRIDS:
        raise ProfileError(f"mla.grid: must be one of {GRIDS}, got {grid!r}")
    distance = mt.get("distance_mm")
    focus = mt.get("focus_mm")
    if "gap_mm" in mt:
        if distance is not None:
            raise ProfileError("mla.gap_mm and mla.distance_mm: give only one of them")
        gap = _FIELDS.number("mla.gap_mm", mt["gap_mm"])
        distance = lens.back_vertex_z_mm + gap
        if distance <= 0.0 or gap <= 0.0:
            raise ProfileError(f"mla.gap_mm: the MLA must lie behind the last vertex, got {gap}")
    if focus is not None:
        if isinstance(focus, str) and focus.lower() in ("inf", "infinity"):
            focus = math.inf
        elif isinstance(focus, (int, float)) and not isinstance(focus, bool) and focus == math.inf:
            focus = math.inf
        else:
            focus = _check_positive("mla.focus_mm", focus)
    fill = _check_positive("mla.fill_factor", mt.get("fill_factor", 1.0))
    if fill > 1.0:
        raise ProfileError(f"mla.fill_factor: must be in (0, 1], got {fill}")
    mla = MicrolensArray(
        focal_length_mm=_check_positive(
            "mla.focal_length_mm", _required(mt, "mla", "focal_length_mm")
        ),
        pitch_mm=_check_positive("mla.pitch_mm", _required(mt, "mla", "pitch_mm")),
        grid=grid,
        distance_mm=None if distance is None else _check_positive("mla.distance_mm", distance),
        focus_mm=focus,
        rotation_rad=_number("mla.rotation_rad", mt.get("rotation_rad", 0.0)),
        offset_mm=_pair("mla.offset_mm", mt.get("offset_mm", [0.0, 0.0])),
        fill_factor=fill,
    )

    st = _table(data, "sensor")
    _known_keys(
        st,
        "sensor",
        {
            "pixel_pitch_mm", "width_px", "height_px", "bit_depth", "bayer",
            "black_level", "white_level", "axis_px", "full_well_e",
        },
    )
    bit_depth = _integer("sensor.bit_depth", st.get("bit_depth", 16), 1, 32)
    bayer = st.get("bayer", "none")
    if bayer not in BAYER_PATTERNS:
        raise ProfileError(f"sensor.bayer: must be one of {BAYER_PATTERNS}, got {bayer!r}")
    max_value = 2**bit_depth - 1
    black = _integer("sensor.black_level", st.get("black_level", 0), 0, max_value)
    white = _integer("sensor.white_level", st.get("white_level", max_value), 1, max_value)
    if white <= black:
        raise ProfileError(f"sensor.white_level ({white}) must exceed sensor.black_level ({black})")
    axis = st.get("axis_px")
    sensor = Sensor(
        pixel_pitch_mm=_check_positive(
            "sensor.pixel_pitch_mm", _required(st, "sensor", "pixel_pitch_mm")
        ),
        width_px=_integer("sensor.width_px", _required(st, "sensor", "width_px"), 1, 100_000),
        height_px=_integer("sensor.height_px", _required(st, "sensor", "height_px"), 1, 100_000),
        bit_depth=bit_depth,
        bayer=bayer,
        black_level=black,
        white_level=white,
        axis_px=None if axis is None else _pair("sensor.axis_px", axis),
        full_well_e=(None if st.get("full_well_e") is None
                     else _check_positive("sensor.full_well_e", st["full_well_e"])),
    )
    profile = CameraProfile(name=name, main_lens=lens, mla=mla, sensor=sensor, source=source)
    if distance is not None and focus is not None:
        derived = lens.d_in_for_focus(focus)
        if abs(derived - float(distance)) > 1e-3:
            raise ProfileError(
                f"mla.distance_mm ({distance}) and mla.focus_mm ({focus}) disagree: focus "
                f"{focus} mm needs d_in = {derived:.4f} mm; give only one of them"
            )
    elif focus is not None:
        profile.d_in_mm  # noqa: B018 - validates that the focus is reachable
    return profile


def shipped_profile_dir() -> Path:
    """Folder of the profiles shipped with lfcam (``calibration/`` in a checkout)."""
    here = Path(__file__).resolve().parent
    for candidate in (here / "_calibration", here.parent / "calibration"):
        if candidate.is_dir():
            return candidate
    return here.parent / "calibration"


def load_profile(name_or_path: str | Path) -> CameraProfile:
    """Load a camera profile by shipped name (``system1``, ``system2``) or by TOML path.

    Raises
    ------
    ProfileError
        If the file is missing, not valid TOML, or fails validation.
    """
    text = str(name_or_path)
    path = Path(text)
    if not path.suffix and not path.exists():
        path = shipped_profile_dir() / f"{text}.toml"
        if not path.is_file():
            names = sorted(p.stem for p in shipped_profile_dir().glob("*.toml"))
            raise ProfileError(f"no profile named {text!r} (shipped: {', '.join(names)})")
    if not path.is_file():
        raise ProfileError(f"profile file not found: {path}")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise ProfileError(f"{path}: not UTF-8 text ({exc.reason})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ProfileError(f"{path}: invalid TOML: {exc}") from None
    try:
        return profile_from_dict(data, source=str(path))
    except ProfileError as exc:  # name the file: the key alone does not say which profile
        raise ProfileError(f"{path}: {exc}") from None
    except (ArithmeticError, ValueError) as exc:  # values valid alone, impossible together
        raise ProfileError(f"{path}: the optics of these values cannot be computed "
                           f"({type(exc).__name__}: {exc})") from None
