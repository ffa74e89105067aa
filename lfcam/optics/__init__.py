"""Optics shared by every stage: the exact ray trace through the main lens and the MLA grid.

Paraxial properties of the main lens are methods of :class:`lfcam.camera.MainLens`.
"""

from lfcam.optics.trace import TraceStatus, forward, trace_rays

__all__ = ["TraceStatus", "forward", "trace_rays"]
