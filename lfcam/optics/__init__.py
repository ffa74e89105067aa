"""Optics shared by every stage: the main lens model, its exact ray trace and the MLA grid.

Every main lens is a sequential prescription (:mod:`lfcam.optics.lens`; the seed singlet is the
two-surface case), placed in a profile's frame by :class:`lfcam.camera.MainLens`, traced by
the one exact tracer :mod:`lfcam.optics.raytrace` (not re-exported here: its ``trace`` would
shadow the :mod:`lfcam.optics.trace` module, the stages' thin wrappers over it). Lens files:
:mod:`lfcam.optics.zmx`; exact metric refocus: :mod:`lfcam.optics.refocus`; docs/lenses.md.
"""

from lfcam.optics.lens import Prescription, Surface
from lfcam.optics.raytrace import RayStatus
from lfcam.optics.trace import TraceStatus, forward, trace_rays
from lfcam.optics.zmx import load_zmx

__all__ = ["Prescription", "RayStatus", "Surface", "TraceStatus", "forward", "load_zmx",
           "trace_rays"]
