"""The camera profile of a capture: a named or sidecar profile, or the one a Lytro capture's
own metadata implies.

These read capture files and their metadata, so they live with the loaders (``io`` stands
above ``camera``: the profile model itself never reads a capture).
"""

from __future__ import annotations

from pathlib import Path

from lfcam.camera import CameraProfile, load_profile, profile_from_dict
from lfcam.errors import ProfileError
from lfcam.io import lytro_meta as lm
from lfcam.io.capture import read_sidecar_metadata, sniff_kind
from lfcam.io.lfp import merged_metadata, read_lfp


def profile_for_capture(capture: str | Path, profile: str | Path | None) -> CameraProfile:
    """``profile`` (a name or path) if given, else the ``<stem>.profile.toml`` beside the
    capture (what ``lfcam simulate`` writes), else, for a Lytro container or packed raw, the
    profile its metadata implies (:func:`profile_from_lytro`).

    Raises
    ------
    ProfileError
        No profile given and no sidecar, or an invalid profile.
    """
    if profile:
        return load_profile(profile)
    capture = Path(capture)
    sidecar = capture.with_name(capture.stem + ".profile.toml")
    if sidecar.is_file():
        return load_profile(sidecar)
    if capture.is_file() and sniff_kind(capture) in ("lfp", "lytro-raw"):
        return profile_from_lytro(capture)
    raise ProfileError(f"no --profile given and no {sidecar.name} beside the capture")


def profile_from_lytro(capture: str | Path) -> CameraProfile:
    """The camera profile a Lytro capture's own metadata implies (no hand-written profile).

    Sensor and MLA come from the frame metadata, the main lens is the black box seeded from
    ``devices.lens`` (:func:`lfcam.io.lytro_meta.profile_dict_from_lytro`); the MLA distance
    comes later from a target calibration (``lfcam calibrate --targets``).

    Parameters
    ----------
    capture : str or Path
        A Lytro ``.lfp``/``.lfr`` container (raw or white frame inside) or a bare packed
        ``.raw`` with its JSON/TXT sidecar.

    Returns
    -------
    CameraProfile

    Raises
    ------
    MetadataError
        Missing or mistyped metadata keys, or no sidecar beside a bare raw.
    ProfileError
        Metadata values that make no valid profile.
    """
    path = Path(capture)
    if sniff_kind(path) == "lfp":
        merged = merged_metadata(read_lfp(path))
        meta, private = merged["frame"], merged["privateMetadata"]
    else:
        meta, private, _ = read_sidecar_metadata(path)
    camera = lm.lytro_camera(meta, private, where=f"{path}: frame metadata")
    return profile_from_dict(lm.profile_dict_from_lytro(camera), source=str(path))
