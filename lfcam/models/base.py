"""Shared result type and status codes of the distance models."""

from __future__ import annotations

from enum import IntEnum
from typing import NamedTuple

import numpy as np

from lfcam.status import RegionStatus


class Status(IntEnum):
    """Per-element outcome of an inversion (``status`` strings of docs/conventions.md via
    :attr:`label`)."""

    OK = 0
    NO_SOLUTION = 1  # the rim rays do not meet in front of the lens (no real source)
    ILL_CONDITIONED = 2  # an answer exists but rounding/cancellation swamps it
    OUT_OF_DOMAIN = 3  # heights outside what the lens can produce / model assumptions broken
    INVALID_INPUT = 4  # NaN or inf in the input

    @property
    def label(self) -> str:
        """Contract spelling (:class:`lfcam.status.RegionStatus`): ``ok``, ``no-solution``, …"""
        return RegionStatus[self.name].value


STATUS_LABELS = np.array([s.label for s in Status])


class Inversion(NamedTuple):
    """Distances and offsets recovered from rim-ray heights, with a status per element.

    ``distance_mm`` and ``offset_mm`` are NaN exactly where ``status != Status.OK``.
    """

    distance_mm: np.ndarray
    offset_mm: np.ndarray
    status: np.ndarray  # uint8 Status codes

    def labels(self) -> np.ndarray:
        """Status codes as contract strings."""
        return STATUS_LABELS[self.status]


def as_heights(y1_mm, y2_mm) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
    """Broadcast two height arrays to flat float64 copies (float32 input is promoted)."""
    a, b = np.broadcast_arrays(
        np.asarray(y1_mm, dtype=np.float64), np.asarray(y2_mm, dtype=np.float64)
    )
    return a.ravel().copy(), b.ravel().copy(), a.shape


def finish(distance: np.ndarray, offset: np.ndarray, status: np.ndarray, shape) -> Inversion:
    """Blank the numbers of non-ok elements and restore the input shape."""
    bad = status != Status.OK
    distance = np.where(bad, np.nan, distance)
    offset = np.where(bad, np.nan, offset)
    return Inversion(distance.reshape(shape), offset.reshape(shape), status.reshape(shape))
