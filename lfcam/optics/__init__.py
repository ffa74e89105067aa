"""Optics shared by every stage: paraxial thick-lens helpers and the exact ray trace.

General sequential lenses: :mod:`lfcam.optics.lens` (model, paraxial data),
:mod:`lfcam.optics.raytrace` (exact tracer; not re-exported here, its ``trace`` would shadow
the legacy :mod:`lfcam.optics.trace` module) and :mod:`lfcam.optics.zmx` (lens files).
"""

from lfcam.optics.lens import Prescription, Surface
from lfcam.optics.paraxial import d_in_for_focus, focus_for_d_in
from lfcam.optics.raytrace import RayStatus
from lfcam.optics.trace import TraceStatus, forward, trace_rays
from lfcam.optics.zmx import load_zmx

__all__ = [
    "Prescription",
    "RayStatus",
    "Surface",
    "TraceStatus",
    "d_in_for_focus",
    "focus_for_d_in",
    "forward",
    "load_zmx",
    "trace_rays",
]
