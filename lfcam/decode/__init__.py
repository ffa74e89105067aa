"""Light-field decoding (raw + calibration → ``L[v, u, t, s]``), view export and refocusing."""

from lfcam.decode.lightfield import LightField, decode, default_n_views, to_grey
from lfcam.decode.refocus import (
    Refocused,
    distance_for_shift,
    focal_stack,
    refocus,
    refocus_distance,
    shift_for_distance,
)

__all__ = [
    "LightField", "Refocused", "decode", "default_n_views", "distance_for_shift",
    "focal_stack", "refocus", "refocus_distance",
    "shift_for_distance", "to_grey",
]
