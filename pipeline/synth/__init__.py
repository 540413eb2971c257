"""Synthetic scenes with ground truth: ``python -m pipeline synth SCENE.yaml OUT``."""

from .render import write_scene
from .scene import Scene, load_scene_file, scene_from_dict

__all__ = ["Scene", "load_scene_file", "scene_from_dict", "write_scene"]
