"""Error hierarchy. Every failure a user can cause is an :class:`LfcamError` subclass.

The CLI prints ``str(error)`` on one line and exits with status 1.
"""

from __future__ import annotations


class LfcamError(Exception):
    """Base class of every error lfcam raises on bad input or impossible requests."""


class ProfileError(LfcamError):
    """A camera profile is missing a key, has an invalid value, or is inconsistent."""


class OpticsError(LfcamError):
    """An optics request is outside what the lens can do (e.g. focus closer than f)."""


class ModelError(LfcamError):
    """A distance model was asked for something it cannot do (unknown name, bad shapes)."""


class InputFileError(LfcamError):
    """An input file is missing, unreadable, truncated or of an unsupported kind."""


class FormatError(InputFileError):
    """An input file is readable but its content violates its format."""


class CalibrationError(LfcamError):
    """A calibration could not be computed or a calibration file is invalid."""


class SceneError(LfcamError):
    """A simulation scene description is missing a key, has an invalid value or is too large."""
