"""Error hierarchy. Every failure a user can cause is an :class:`LfcamError` subclass.

The CLI prints ``str(error)`` on one line and exits with status 1.
"""

from __future__ import annotations


class LfcamError(Exception):
    """Base class of every error lfcam raises on bad input or impossible requests."""


class ProfileError(LfcamError):
    """A camera profile is missing a key, has an invalid value, or is inconsistent."""


class ZmxError(ProfileError):
    """A Zemax ``.zmx`` lens file is unreadable or uses something lfcam does not support."""


class UsageError(LfcamError):
    """Command-line flags that do not fit together."""


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


class CalibrationQualityError(CalibrationError):
    """A calibration failed its quality gates (coverage, lattice residual, model misfit)."""


class CalibrationMismatchError(CalibrationError):
    """A profile and a calibration disagree (e.g. on the micro-image pitch)."""


class OutputPathError(LfcamError):
    """An output path would overwrite an input, or its folder cannot be written."""


# ----------------------------------------------------------------------------- loaders (lfcam.io)


class UnsupportedFormatError(InputFileError):
    """The file's content (magic bytes) matches no capture format lfcam reads."""


class TruncatedFileError(InputFileError):
    """The file ends before a header, section or pixel buffer it announces."""


class ContainerError(FormatError):
    """An LFP/LFR container violates its layout (magic, version, lengths, names, padding)."""


class ChecksumError(FormatError):
    """An LFP section's sha1 name does not match the sha1 of its bytes."""


class MetadataError(FormatError):
    """Capture metadata is not UTF-8, not valid JSON, or lacks / mistypes a required key."""


class RawDataError(FormatError):
    """A raw pixel buffer has absurd dimensions or a size that disagrees with its metadata."""


class NoRawFrameError(InputFileError):
    """A well-formed container holds no raw sensor frame (e.g. a processed Lytro picture)."""


class ResourceLimitError(InputFileError):
    """A file announces more pixels or bytes than lfcam will decode (limits in docs)."""


class SaturatedCaptureError(InputFileError):
    """Most pixels of a capture sit at the white level: nothing can be measured."""


class WhiteImageNotFoundError(InputFileError):
    """No white (modulation) image in a calibration folder fits the capture."""


# ----------------------------------------------------------------------------- renderer (lfcam.sim)


class SceneError(LfcamError):
    """A simulation scene description is missing a key, has an invalid value or is too large."""


class BatchError(LfcamError):
    """Bad ``lfcam batch`` arguments: input folder, output folder, Dask scheduler."""
