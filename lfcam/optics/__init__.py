"""Optics shared by every stage: the exact ray trace through the main lens and the MLA grid.

Paraxial properties of the seed's singlet are methods of :class:`lfcam.camera.MainLens`.
General sequential lenses: :mod:`lfcam.optics.lens` (model, paraxial data),
:mod:`lfcam.optics.raytrace` (exact tracer; not re-exported here, its ``trace`` would shadow
the legacy :mod:`lfcam.optics.trace` module) and :mod:`lfcam.optics.zmx` (lens files);
see docs/lenses.md.
"""

from lfcam.optics.lens import Prescription, Surface
from lfcam.optics.raytrace import RayStatus
from lfcam.optics.trace import TraceStatus, forward, trace_rays
from lfcam.optics.zmx import load_zmx

__all__ = ["Prescription", "RayStatus", "Surface", "TraceStatus", "forward", "load_zmx",
           "trace_rays"]
