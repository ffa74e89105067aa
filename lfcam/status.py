"""The one status vocabulary of a distance estimate (docs/conventions.md, "Statuses").

Every region of ``regions.csv``, every model inversion and every per-region fit reports one
of these. :class:`RegionStatus` members are ``str`` subclasses whose text is the contract
spelling, so they compare equal to, print as and serialise as ``"ok"``, ``"near-focus"``, ….
Three statuses carry a parameter and are built by :func:`fragment_of`, :func:`failed` and
:func:`unsupported`. The distance models' numeric codes (:class:`lfcam.models.base.Status`)
map onto the first five members.
"""

from __future__ import annotations

from enum import Enum


class RegionStatus(str, Enum):
    """Outcome of one estimate; only ``OK`` carries numbers."""

    OK = "ok"
    NO_SOLUTION = "no-solution"  # the rim rays do not meet in front of the lens
    ILL_CONDITIONED = "ill-conditioned"  # rounding or cancellation swamps the answer
    OUT_OF_DOMAIN = "out-of-domain"  # heights the lens cannot produce; assumptions broken
    INVALID_INPUT = "invalid-input"  # NaN or infinite input
    NEAR_FOCUS = "near-focus"  # no measurable defocus
    EMPTY = "empty"  # no light to fit in the region
    POOR_FIT = "poor-fit"  # neither a point nor a line explains the pixels
    UNEXPLAINED_FOOTPRINT = "unexplained-footprint"  # light the fitted source cannot make

    def __str__(self) -> str:
        return self.value


def fragment_of(region_id: int) -> str:
    """``fragment-of-N``: the region is part of region ``N``'s blur."""
    return f"fragment-of-{int(region_id)}"


def failed(reason: str) -> str:
    """``failed: <reason>``: the region's measurement failed numerically."""
    return f"failed: {reason}"


def unsupported(kind: str) -> str:
    """``unsupported-<kind>``: no method measures regions of this kind."""
    return f"unsupported-{kind}"
