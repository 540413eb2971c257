"""Visual hull: carving lookup, the hull's logit volume, and the tighter working sphere around it."""

import numpy as np
import pytest
import torch
import trimesh

from dvr.data import load_scene
from dvr.hull import hull_bounding_sphere, hull_logits, outside_hull


def test_bounding_sphere_contains_the_object_and_is_tight(small_ws):
    data = load_scene(small_ws, torch.device("cpu"))
    c, r = hull_bounding_sphere(data.P, data.masks, 64, 1, 1.1)
    v = np.asarray(trimesh.load(small_ws / "gt" / "mesh.ply").vertices)  # the torus, radius 0.7
    d = np.linalg.norm(v - c, axis=1)
    assert d.max() < r and r < 0.95  # everything inside, and tighter than the unit sphere
    assert d.max() > 0.7 * r  # not loose


def test_bounding_sphere_none_when_empty_or_filling(small_ws):
    data = load_scene(small_ws, torch.device("cpu"))
    assert hull_bounding_sphere(data.P, torch.zeros_like(data.masks)) is None  # empty masks: no hull
    assert hull_bounding_sphere(data.P, torch.ones_like(data.masks)) is None  # full masks: fills the sphere


def test_outside_hull_and_logits(small_ws):
    data = load_scene(small_ws, torch.device("cpu"))
    pts = torch.tensor([[0.7, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.9]])  # on the torus ring, hole, above
    out = outside_hull(pts, data.P, data.masks)
    assert out.tolist() == [False, True, True]
    lg = hull_logits(data.P, data.masks, res=32)
    assert lg.shape == (33, 33, 33) and torch.isfinite(lg).all()
    with pytest.raises(Exception):
        outside_hull(pts[:, :2], data.P, data.masks)
