"""Optics shared by every stage: paraxial thick-lens helpers and the exact ray trace."""

from lfcam.optics.paraxial import d_in_for_focus, focus_for_d_in
from lfcam.optics.trace import TraceStatus, forward, trace_rays

__all__ = ["TraceStatus", "d_in_for_focus", "focus_for_d_in", "forward", "trace_rays"]
