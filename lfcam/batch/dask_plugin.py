"""Dask worker plugin of :mod:`lfcam.batch` (imported only when Dask is used)."""

from __future__ import annotations

from distributed import WorkerPlugin

from lfcam.batch.worker import init_worker


class CalibrationPlugin(WorkerPlugin):
    """Parse the batch's calibration once per worker process, when the worker starts."""

    def __init__(self, calibration_bytes: bytes) -> None:
        self.calibration_bytes = calibration_bytes

    def setup(self, worker) -> None:
        """Dask hook: called once on every current and future worker."""
        init_worker(self.calibration_bytes)
