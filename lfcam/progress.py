"""One progress protocol for the command line: ``progress(stage, done, total)``.

A :data:`Progress` callable is told the current stage (a short name such as ``"regions"``),
how many of its steps are done and how many there are. :class:`TerminalProgress` renders it
as one self-overwriting line on stderr, only when stderr is a terminal, so pipes, logs and
tests see nothing. The library's long calls (calibration, rendering, distance, batch) take a
:data:`Progress` and call it the same way.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import TextIO

Progress = Callable[[str, int, int], None]


def silent(stage: str, done: int, total: int) -> None:
    """A :data:`Progress` that shows nothing."""


class TerminalProgress:
    """Render ``(stage, done, total)`` as ``stage [#####.....]  42.0%`` on one line.

    Parameters
    ----------
    stream : file, optional
        Where to draw (default ``sys.stderr``).
    enabled : bool, optional
        Default: only when ``stream`` is a terminal.
    min_interval_s : float
        Redraw at most this often (the last step of a stage is always drawn).
    """

    WIDTH = 30

    def __init__(self, stream: TextIO | None = None, enabled: bool | None = None,
                 min_interval_s: float = 0.1) -> None:
        self.stream = stream if stream is not None else sys.stderr
        if enabled is None:
            isatty = getattr(self.stream, "isatty", None)
            enabled = bool(isatty and isatty())
        self.enabled = enabled
        self.min_interval_s = min_interval_s
        self._last = -1.0
        self._drawn = False
        self._stage = ""

    def __call__(self, stage: str, done: int, total: int) -> None:
        """Draw the line (rate-limited, except for a new stage or the last step)."""
        if not self.enabled:
            return
        now = time.monotonic()
        final = total > 0 and done >= total
        if stage == self._stage and not final and now - self._last < self.min_interval_s:
            return
        self._last, self._stage = now, stage
        frac = min(max(done / total, 0.0), 1.0) if total > 0 else 0.0
        n = int(self.WIDTH * frac)
        self.stream.write(f"\r{stage[:18]:<18} [{'#' * n}{'.' * (self.WIDTH - n)}] "
                          f"{100 * frac:5.1f}%")
        self.stream.flush()
        self._drawn = True

    def close(self) -> None:
        """End the line (if anything was drawn)."""
        if self._drawn:
            self.stream.write("\n")
            self.stream.flush()
            self._drawn = False

    def __enter__(self) -> TerminalProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def terminal_progress(quiet: bool = False) -> TerminalProgress:
    """The CLI's renderer: on stderr when it is a terminal, never with ``quiet``."""
    return TerminalProgress(enabled=False) if quiet else TerminalProgress()

