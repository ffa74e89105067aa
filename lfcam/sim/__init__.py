"""Synthetic plenoptic 1.0 captures: exact main-lens ray tracing, ideal MLA, sensor model."""

from lfcam.sim.capture import simulate, write_capture
from lfcam.sim.render import Renderer
from lfcam.sim.scene import Scene, load_scene, scene_from_dict

__all__ = ["Renderer", "Scene", "load_scene", "scene_from_dict", "simulate", "write_capture"]
