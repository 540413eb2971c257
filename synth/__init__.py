"""The scene generator: synthetic captures with ground truth, for the tests and the benchmark (``python -m synth
SCENE.yaml OUT``, ``make synth``). It sits above ``pipeline/`` (it writes the workspace layout the stages read)
and ``pipeline/`` never imports it."""

from synth.render import write_scene
from synth.scene import Scene, load_scene_file, scene_from_dict

__all__ = ["Scene", "load_scene_file", "scene_from_dict", "write_scene"]
