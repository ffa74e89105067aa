"""Distance models: blur geometry (rim-ray sensor heights) → object distance and offset.

Point-source models share one signature, ``invert(profile, d_in_mm, y1_mm, y2_mm) ->
Inversion``, and are listed in :data:`POINT_MODELS`. The line model takes two endpoints
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


def point_model(name: str) -> Callable[..., Inversion]:
    """Look up a point-source model by name.

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


__all__ = ["POINT_MODELS", "Inversion", "Status", "hahne", "line", "point_model"]
