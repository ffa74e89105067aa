"""Distance models: blur geometry (rim-ray sensor heights) → object distance and offset.

Point-source models share one signature, ``invert(profile, d_in_mm, y1_mm, y2_mm) ->
Inversion``, and are listed in :data:`POINT_MODELS`. :data:`DISTANCE_MODELS` is the one list
of what ``lfcam distance --model`` and ``lfcam batch --model`` accept: the point models, plus
``auto`` (per region the cheapest that meets the tolerance, :mod:`lfcam.models.auto`) and
``refocus`` (Hahne's depth from refocus). The line model takes two endpoints
(:mod:`lfcam.models.line`); Hahne's refocusing distance maps a refocus shift to a distance
(:mod:`lfcam.models.hahne`).
"""

from __future__ import annotations

from collections.abc import Callable

from lfcam.errors import ModelError
from lfcam.models import exact, hahne, line, offaxis, onaxis, thin
from lfcam.models.base import Inversion, Status

POINT_MODELS: dict[str, Callable[..., Inversion]] = {
    "exact": exact.invert,
    "offaxis": offaxis.invert,
    "onaxis": onaxis.invert,
    "thin": thin.invert,
}

DISTANCE_MODELS: tuple[str, ...] = ("auto", *POINT_MODELS, "refocus")


def check_distance_model(name: str) -> str:
    """``name`` if it is one of :data:`DISTANCE_MODELS`.

    Parameters
    ----------
    name : str

    Returns
    -------
    str

    Raises
    ------
    ModelError
        For an unknown name (the message lists the known ones).
    """
    if name not in DISTANCE_MODELS:
        raise ModelError(f"unknown model {name!r} (choose from {', '.join(DISTANCE_MODELS)})")
    return name


def point_model(name: str) -> Callable[..., Inversion]:
    """Look up a point-source model by name.

    Parameters
    ----------
    name : str
        One of :data:`POINT_MODELS`.

    Returns
    -------
    callable
        ``invert(profile, d_in_mm, y1_mm, y2_mm) -> Inversion``.

    Raises
    ------
    ModelError
        For an unknown name (the message lists the known ones).
    """
    try:
        return POINT_MODELS[name]
    except KeyError:
        known = ", ".join(POINT_MODELS)
        raise ModelError(f"unknown model {name!r} (choose from {known})") from None


__all__ = ["DISTANCE_MODELS", "POINT_MODELS", "Inversion", "Status", "check_distance_model",
           "hahne", "line", "point_model"]
