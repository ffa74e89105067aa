"""``describe_file``: what a capture is, as a JSON-ready dict (backs ``lfcam info``)."""

from __future__ import annotations

import math
from dataclasses import asdict
from pathlib import Path
from typing import Any

from lfcam.errors import LfcamError, MetadataError
from lfcam.io import lytro_meta as lm
from lfcam.io.capture import load_capture, sniff_kind
from lfcam.io.lfp import describe_processed, read_lfp


def _clean(v: Any) -> Any:
    if isinstance(v, float) and not math.isfinite(v):
        return None if math.isnan(v) else ("inf" if v > 0 else "-inf")
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    return v


def _camera(meta: dict, priv: dict) -> dict | None:
    if not meta:
        return None
    cam: dict[str, Any] = {
        "make": lm.get_path(meta, "camera.make"),
        "model": lm.get_path(meta, "camera.model"),
        "firmware": lm.get_path(meta, "camera.firmware"),
        "serial": lm.get_path(priv, "camera.serialNumber"),
    }
    return cam


def _optics(meta: dict, priv: dict) -> dict | None:
    if not meta:
        return None
    try:
        c = lm.lytro_camera(meta, priv)
    except LfcamError as exc:
        return {"error": str(exc)}
    return {
        "lens": asdict(c.optics),
        "mla": {"pitch_mm": c.mla.pitch_mm, "grid": c.mla.grid,
                "rotation_rad": c.mla.rotation_rad, "offset_mm": list(c.mla.offset_mm),
                "separation_mm": c.mla_separation_mm,
                "scale_factor": list(c.mla_scale_factor)},
        "sensor": {"pixel_pitch_mm": c.sensor.pixel_pitch_mm, "width_px": c.sensor.width_px,
                   "height_px": c.sensor.height_px, "bit_depth": c.sensor.bit_depth,
                   "bayer": c.sensor.bayer, "black_level": c.sensor.black_level,
                   "white_level": c.sensor.white_level},
    }


def describe_file(path: str | Path, verify: str = "error") -> dict:
    """Describe a capture file without decoding more than needed.

    LFP containers are fully checked (layout, sha1, JSON); a raw frame, when present, is
    unpacked to prove its size and packing. Processed pictures (no raw) describe fine.

    Raises
    ------
    LfcamError
        For damaged or unsupported files (the CLI turns it into one line, exit 1).
    """
    p = Path(path)
    kind = sniff_kind(p)
    out: dict[str, Any] = {"file": str(p), "size_bytes": p.stat().st_size}
    if kind == "lfp":
        c = read_lfp(p, verify=verify)
        out["kind"] = "lytro-lfp"
        out["container_version"] = c.version
        out["sections"] = [{"kind": s.kind, "name": s.name, "offset": s.offset,
                            "length": s.length} for s in c.sections]
        meta = c.camera_metadata
        fr = c.light_field_frame or (c.frames[0] if c.frames else None)
        priv = fr.private_metadata if fr else {}
        out["camera"] = _camera(meta, priv)
        out["raw_frame"] = c.has_raw
        out["white_frame"] = c.white_frame is not None
        out["frames"] = len(c.frames)
        if c.has_raw:
            img = c.raw_image()
            out["raw"] = {"width_px": int(img.shape[1]), "height_px": int(img.shape[0])}
            fmt = lm.raw_format(c.light_field_frame.metadata)
            out["raw"].update(bits_per_pixel=fmt.bits_per_pixel, endianness=fmt.endianness,
                              bayer=fmt.bayer, black_level=fmt.black_level,
                              white_level=fmt.white_level)
        else:
            why = "frame metadata not inside" if not meta else "pixels not inside"
            out["note"] = (f"processed picture: no raw sensor frame inside ({why}); holds "
                           f"{describe_processed(c)}")
        out["optics"] = _optics(meta, priv)
        if c.checksum_failures:
            out["checksum_failures"] = list(c.checksum_failures)
        return _clean(out)
    cap = load_capture(p, verify=verify)
    out["kind"] = cap.source_kind
    out["raw_frame"] = True
    out["raw"] = {"width_px": cap.shape[1], "height_px": cap.shape[0],
                  "dtype": str(cap.raw.dtype), "bayer": cap.bayer,
                  "black_level": cap.black_level, "white_level": cap.white_level}
    if cap.source_kind == "lytro-raw":
        priv = cap.metadata.get("privateMetadata", {})
        out["camera"] = _camera(cap.metadata["frame"], priv)
        out["optics"] = _optics(cap.metadata["frame"], priv)
        out["sidecar"] = cap.metadata.get("sidecar")
    elif cap.source_kind == "camera-raw":
        out["camera"] = None
    if not isinstance(out.get("raw"), dict):  # pragma: no cover - defensive
        raise MetadataError(f"{p}: could not describe")
    return _clean(out)


def format_text(d: dict) -> str:
    """Human-readable lines for :func:`describe_file` output."""
    lines = [f"file:       {d['file']} ({d['size_bytes']} bytes)", f"kind:       {d['kind']}"]
    cam = d.get("camera")
    if cam:
        lines.append(f"camera:     {cam.get('make')} {cam.get('model')} "
                     f"(firmware {cam.get('firmware')}, serial {cam.get('serial')})")
    elif d["kind"] == "lytro-lfp":
        lines.append("camera:     unknown (frame metadata not inside)")
    lines.append(f"raw frame:  {'yes' if d.get('raw_frame') else 'no'}")
    if d.get("raw"):
        r = d["raw"]
        lines.append("raw:        " + ", ".join(f"{k}={v}" for k, v in r.items()))
    if d.get("note"):
        lines.append(f"note:       {d['note']}")
    if d.get("sections"):
        lines.append(f"sections:   {len(d['sections'])}")
        for s in d["sections"]:
            lines.append(f"  {s['kind']} {s['name']} {s['length']} bytes @ {s['offset']}")
    opt = d.get("optics")
    if opt and "lens" in opt:
        ln, mla, sen = opt["lens"], opt["mla"], opt["sensor"]
        lines.append(f"lens:       f = {ln['focal_length_mm']:.4g} mm, f/{ln['f_number']:.3g}, "
                     f"zoom step {ln['zoom_step']}, focus step {ln['focus_step']}, exit pupil "
                     f"{ln['exit_pupil_offset_mm']} mm")
        lines.append(f"mla:        pitch {mla['pitch_mm'] * 1e3:.4g} um ({mla['grid']}), "
                     f"rotation {mla['rotation_rad']:.4g} rad, separation "
                     f"{mla['separation_mm'] * 1e3:.4g} um")
        lines.append(f"sensor:     {sen['width_px']}x{sen['height_px']} px, pitch "
                     f"{sen['pixel_pitch_mm'] * 1e3:.4g} um, {sen['bit_depth']} bit, "
                     f"{sen['bayer']}, black {sen['black_level']}, white {sen['white_level']}")
    elif opt and "error" in opt:
        lines.append(f"optics:     unavailable ({opt['error']})")
    return "\n".join(lines)
