"""Lens files: Zemax sequential ``.zmx`` import and the profile's ``[main_lens] surfaces`` form.

Zemax support (read only): ``UNIT MM``; ``SURF`` blocks of ``TYPE STANDARD`` with ``CURV``
(curvature, 1/mm), ``DISZ`` (thickness; ``INFINITY`` on the object surface), ``CONI``,
``DIAM`` (semi-diameter), ``STOP`` and ``GLAS``; ``TYPE PARAXIAL`` (an ideal surface,
``PARM 1`` = its focal length; :class:`~lfcam.optics.lens.Surface`). A glass is either a name from
:data:`GLASS_ND` or the explicit model form ``GLAS ___BLANK 1 0 <nd> <vd> ...`` (the index is
the 4th token). Everything is taken at the d line (587.56 nm): lfcam is monochromatic.
The object surface (``SURF 0``) and the image surface (the last one) are dropped; the last
lens surface keeps its ``DISZ`` (the design's image gap) as ``thickness_mm``, which the
model ignores. Files may be UTF-16 (LE/BE, with BOM — Zemax's default) or UTF-8/ASCII.

Not supported (clear :class:`~lfcam.errors.ZmxError` naming the surface): other surface
types (even asphere, coordinate breaks, gratings…), mirrors, decentres/tilts,
glasses not in the table, other units.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, NamedTuple

from lfcam.errors import ProfileError, ZmxError
from lfcam.optics.lens import Prescription, Surface

# SCHOTT catalogue nd (d line, 587.56 nm), as listed in the SCHOTT optical glass data sheets
# (values checked against the catalogue shipped with the `opticalglass` package). SK16 is the
# lead-containing predecessor of N-SK16 (same nd in the SCHOTT catalogue of the 1990s).
GLASS_ND: dict[str, float] = {
    "N-BK7": 1.51680,
    "BK7": 1.51680,
    "N-K5": 1.52249,
    "N-BAK1": 1.57250,
    "N-BAK4": 1.56883,
    "N-BALF4": 1.57956,
    "N-SK2": 1.60738,
    "N-SK4": 1.61272,
    "N-SK5": 1.58913,
    "N-SK14": 1.60311,
    "N-SK16": 1.62041,
    "SK16": 1.62041,
    "N-SSK2": 1.62229,
    "N-SSK8": 1.61773,
    "N-BAF10": 1.67003,
    "N-LAK8": 1.71300,
    "N-LAK9": 1.69100,
    "N-LAK10": 1.72003,
    "N-LAK22": 1.65113,
    "N-LAF2": 1.74397,
    "N-LASF9": 1.85025,
    "N-LASF44": 1.80420,
    "F2": 1.62004,
    "N-F2": 1.62005,
    "F5": 1.60342,
    "SF2": 1.64769,
    "N-SF2": 1.64769,
    "SF4": 1.75520,
    "N-SF4": 1.75513,
    "SF5": 1.67270,
    "N-SF5": 1.67271,
    "SF6": 1.80518,
    "N-SF6": 1.80518,
    "N-SF10": 1.72828,
    "SF11": 1.78472,
    "N-SF11": 1.78472,
    "SF57": 1.84666,
    "N-SF57": 1.84666,
}

_BLANK = "___BLANK"


class ZmxLens(NamedTuple):
    """A parsed ``.zmx`` file."""

    prescription: Prescription
    object_distance_mm: float  # object surface DISZ (inf for an object at infinity)
    image_gap_mm: float  # last lens vertex → image surface in the design
    name: str


def _decode(raw: bytes) -> str:
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        return raw.decode("utf-16")
    if raw.startswith(b"\xef\xbb\xbf"):
        return raw[3:].decode("utf-8", errors="replace")
    head = raw[:200]
    if head and head.count(b"\x00") > len(head) // 4:  # UTF-16 without a BOM
        return raw.decode("utf-16-le" if head[1:2] == b"\x00" else "utf-16-be")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def _number(token: str, what: str, surf: int) -> float:
    if token.upper() in ("INFINITY", "INF"):
        return math.inf
    try:
        return float(token)
    except ValueError:
        raise ZmxError(f"SURF {surf}: {what} {token!r} is not a number") from None


def parse_zmx(text: str) -> ZmxLens:
    """Parse the text of a Zemax sequential lens file.

    Parameters
    ----------
    text : str
        File content (already decoded; see :func:`load_zmx` for bytes).

    Returns
    -------
    ZmxLens

    Raises
    ------
    ZmxError
        On unsupported units, surface types or glasses, missing data, or a prescription that
        fails validation; the message names the Zemax surface number.
    """
    name = ""
    blocks: list[dict[str, Any]] = []
    current: dict[str, Any] | None = None
    for line_no, raw_line in enumerate(text.splitlines(), start=1):
        line = raw_line.strip()
        if not line:
            continue
        tokens = line.split()
        key = tokens[0].upper()
        if not raw_line[:1].isspace() and key != "SURF":
            current = None  # a top-level keyword ends the surface block
        if key == "MODE" and len(tokens) > 1 and tokens[1].upper() != "SEQ":
            raise ZmxError(f"line {line_no}: only sequential (MODE SEQ) files are supported")
        if key == "NAME" and current is None:
            name = line[4:].strip()
        elif key == "UNIT" and current is None:
            unit = tokens[1].upper() if len(tokens) > 1 else ""
            if unit != "MM":
                raise ZmxError(
                    f"line {line_no}: lens units {unit or '?'!r}; only UNIT MM is supported"
                )
        elif key == "SURF":
            try:
                number = int(tokens[1])
            except (IndexError, ValueError):
                raise ZmxError(f"line {line_no}: SURF without a surface number") from None
            current = {
                "number": number,
                "type": "STANDARD",
                "curv": 0.0,
                "disz": 0.0,
                "coni": 0.0,
                "diam": None,
                "stop": False,
                "glass": None,
                "parm": {},
            }
            blocks.append(current)
        elif current is not None:
            n = current["number"]
            if key == "TYPE":
                current["type"] = tokens[1].upper() if len(tokens) > 1 else ""
            elif key == "CURV":
                current["curv"] = _number(tokens[1], "CURV", n)
            elif key == "DISZ":
                current["disz"] = _number(tokens[1], "DISZ", n)
            elif key == "CONI":
                current["coni"] = _number(tokens[1], "CONI", n)
            elif key == "DIAM":
                current["diam"] = _number(tokens[1], "DIAM", n)
            elif key == "STOP":
                current["stop"] = True
            elif key == "GLAS":
                current["glass"] = tokens[1:]
            elif key == "PARM" and len(tokens) > 2:
                current["parm"][int(_number(tokens[1], "PARM index", n))] = _number(
                    tokens[2], "PARM", n
                )
    return _build(blocks, name)


def _glass_index(glass: list[str] | None, surf: int) -> float:
    if glass is None or not glass:
        return 1.0
    gname = glass[0].upper()
    if gname in ("MIRROR", "MIRR"):
        raise ZmxError(f"SURF {surf}: mirrors are not supported (refracting lenses only)")
    if gname == _BLANK:
        if len(glass) < 4:
            raise ZmxError(f"SURF {surf}: GLAS {_BLANK} without an index (4th token)")
        return _number(glass[3], "GLAS index", surf)
    if gname in GLASS_ND:
        return GLASS_ND[gname]
    raise ZmxError(
        f"SURF {surf}: glass {glass[0]!r} is not in lfcam's table ({', '.join(sorted(GLASS_ND))}); "
        f"replace it by the model form 'GLAS {_BLANK} 1 0 <nd> <vd>'"
    )


def _build(blocks: list[dict[str, Any]], name: str) -> ZmxLens:
    if len(blocks) < 3:
        raise ZmxError(
            "a lens file needs an object surface, at least one lens surface and an image"
        )
    blocks = sorted(blocks, key=lambda b: b["number"])
    obj, lens_blocks = blocks[0], blocks[1:-1]
    if _glass_index(obj["glass"], obj["number"]) != 1.0:
        raise ZmxError(f"SURF {obj['number']}: object space must be air")
    if obj["stop"] or blocks[-1]["stop"]:
        raise ZmxError("the stop must be a lens surface, not the object or image surface")
    surfaces = []
    for b in lens_blocks:
        n = b["number"]
        if b["type"] not in ("STANDARD", "PARAXIAL"):
            raise ZmxError(
                f"SURF {n}: surface TYPE {b['type']} is not supported (STANDARD, PARAXIAL)"
            )
        ideal = None
        if b["type"] == "PARAXIAL":  # PARM 1 = focal length; flat, air after it
            ideal = b["parm"].get(1)
            if ideal is None or ideal == 0.0:
                raise ZmxError(
                    f"SURF {n}: a PARAXIAL surface needs a non-zero PARM 1 (focal length)"
                )
        if b["diam"] is None or not b["diam"] > 0.0:
            raise ZmxError(f"SURF {n}: needs a positive DIAM (semi-diameter)")
        if not math.isfinite(b["disz"]):
            raise ZmxError(f"SURF {n}: DISZ INFINITY is only allowed on the object surface")
        radius = math.inf if b["curv"] == 0.0 else 1.0 / b["curv"]
        try:
            surfaces.append(
                Surface(
                    radius_mm=radius,
                    thickness_mm=b["disz"],
                    refractive_index=_glass_index(b["glass"], n),
                    semi_diameter_mm=b["diam"],
                    conic=b["coni"],
                    stop=b["stop"],
                    focal_length_mm=ideal,
                )
            )
        except ProfileError as err:
            raise ZmxError(f"SURF {n}: {err}") from None
    try:
        prescription = Prescription(tuple(surfaces), name=name)
    except ProfileError as err:
        raise ZmxError(f"{err} (main_lens.surfaces[i] is Zemax SURF i+1)") from None
    return ZmxLens(prescription, float(obj["disz"]), float(lens_blocks[-1]["disz"]), name)


def load_zmx(path: str | Path) -> ZmxLens:
    """Read a ``.zmx`` file (UTF-16 with BOM, or UTF-8/ASCII). See :func:`parse_zmx`."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as err:
        raise ZmxError(f"{p}: cannot read ({err.strerror})") from None
    try:
        return parse_zmx(_decode(raw))
    except ZmxError as err:
        raise ZmxError(f"{p.name}: {err}") from None


# ----------------------------------------------------------------------------- profile TOML

_REQUIRED = ("radius_mm", "thickness_mm", "refractive_index", "semi_diameter_mm")
_OPTIONAL = ("conic", "stop")
_IDEAL_REQUIRED = ("focal_length_mm", "thickness_mm", "semi_diameter_mm")
_IDEAL_OPTIONAL = ("spherical", "stop")


def prescription_to_toml_dict(prescription: Prescription, gap_mm: float | None = None) -> dict:
    """The profile form ``{"main_lens": {"surfaces": [...]}}`` (plus ``[mla] gap_mm``).

    ``conic`` is written only when non-zero, ``stop`` only on the stop surface; a flat
    surface has ``radius_mm = inf`` (TOML ``inf``).
    """
    rows = []
    for s in prescription.surfaces:
        if s.is_ideal:
            row = {
                "focal_length_mm": s.focal_length_mm,
                "thickness_mm": s.thickness_mm,
                "semi_diameter_mm": s.semi_diameter_mm,
            }
            if s.spherical:
                row["spherical"] = list(s.spherical)
            if s.stop:
                row["stop"] = True
            rows.append(row)
            continue
        row: dict[str, Any] = {
            "radius_mm": s.radius_mm,
            "thickness_mm": s.thickness_mm,
            "refractive_index": s.refractive_index,
            "semi_diameter_mm": s.semi_diameter_mm,
        }
        if s.conic != 0.0:
            row["conic"] = s.conic
        if s.stop:
            row["stop"] = True
        rows.append(row)
    out: dict[str, Any] = {"main_lens": {"surfaces": rows}}
    if gap_mm is not None:
        out["mla"] = {"gap_mm": float(gap_mm)}
    return out


def prescription_from_toml_dict(data: dict) -> Prescription:
    """Parse ``[main_lens] surfaces = [...]`` (a whole profile dict or its ``main_lens`` table).

    Raises
    ------
    ProfileError
        Naming ``main_lens.surfaces[i].key`` for a missing, unknown or invalid entry.
    """
    table = data.get("main_lens", data) if isinstance(data, dict) else None
    if not isinstance(table, dict) or "surfaces" not in table:
        raise ProfileError("main_lens.surfaces: missing (a list of surface tables)")
    rows = table["surfaces"]
    if not isinstance(rows, list) or not rows:
        raise ProfileError("main_lens.surfaces: must be a non-empty list of tables")
    surfaces = []
    for i, row in enumerate(rows):
        where = f"main_lens.surfaces[{i}]"
        if not isinstance(row, dict):
            raise ProfileError(f"{where}: must be a table, got {row!r}")
        ideal = "focal_length_mm" in row
        required, optional = (
            (_IDEAL_REQUIRED, _IDEAL_OPTIONAL) if ideal else (_REQUIRED, _OPTIONAL)
        )
        unknown = sorted(set(row) - set(required) - set(optional))
        if unknown:
            what = " (an ideal surface takes focal_length_mm, thickness_mm, semi_diameter_mm, " \
                "spherical, stop)" if ideal else ""
            raise ProfileError(f"{where}: unknown key(s) {', '.join(unknown)}{what}")
        missing = [k for k in required if k not in row]
        if missing:
            raise ProfileError(f"{where}: missing {', '.join(missing)}")
        kwargs = dict(row)
        if ideal:
            kwargs.update(radius_mm=math.inf, refractive_index=1.0)
            if "spherical" in kwargs:
                sph = kwargs["spherical"]
                if not isinstance(sph, list):
                    raise ProfileError(f"{where}.spherical: expected a list of numbers")
                kwargs["spherical"] = tuple(sph)
        try:
            surfaces.append(Surface(**kwargs))
        except ProfileError as err:
            raise ProfileError(f"{where}.{err}") from None
    return Prescription(tuple(surfaces))
