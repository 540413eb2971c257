"""Fields: the dense grid's axis order, and the support clip (nothing below the floor; a flat, closed underside)."""

import numpy as np
import torch
import trimesh

from dvr.extract import extract_mesh
from dvr.fields import SUPPORT_SLOPE, FieldConfig, GridField, make_field
from dvr.hull import grid_points
from dvr.trainer import load_model, save_model


def _ball_field(res=48, radius=0.5, centre=(0.0, 0.0, 0.0)):
    f = GridField(FieldConfig(base_res=res, plane_res=(16,), hidden=8))
    p = grid_points(res)
    f.init_occupancy((10 * (radius - (p - torch.tensor(centre)).norm(dim=-1))).view(res + 1, res + 1, res + 1))
    return f


def test_grid_axis_order_matches_its_points():
    """init_occupancy takes a volume indexed [x, y, z]: a ramp along x reads back along x."""
    f = GridField(FieldConfig(base_res=16, plane_res=(8,), hidden=8))
    p = grid_points(16)
    f.init_occupancy((p[:, 0] * 5).view(17, 17, 17))
    q = torch.tensor([[0.5, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 0.5]])
    assert torch.allclose(f.occupancy(q), torch.tensor([2.5, 0.0, 0.0]), atol=1e-5)


def test_support_clip_frees_everything_below_the_plane():
    f = _ball_field()
    plane = np.array([0.0, 0.0, 1.0, 0.3])  # z = −0.3 cuts the ball
    p = torch.tensor([[0.0, 0.0, -0.4], [0.0, 0.0, 0.0], [0.0, 0.0, 0.3]])
    before = f.occupancy(p)
    f.set_support(plane)
    after = f.occupancy(p)
    assert before[0] > 0 and after[0] <= SUPPORT_SLOPE * (-0.1) + 1e-3  # below the floor: free
    assert torch.allclose(after[1:], before[1:])  # well above it: unchanged
    f.set_support(None)
    assert torch.allclose(f.occupancy(p), before)
    mlp = make_field(FieldConfig(kind="mlp", hidden=8, mlp_layers=1))
    mlp.set_support(plane)
    assert mlp.occupancy(torch.tensor([[0.0, 0.0, -0.9]])) < 0


def test_clipped_object_meshes_closed_with_a_flat_underside():
    f = _ball_field()
    f.set_support(np.array([0.0, 0.0, 1.0, 0.3]))
    v, faces, _ = extract_mesh(f, resolution=64, coarse_factor=4, refine_steps=2)
    m = trimesh.Trimesh(v, faces, process=True)
    assert m.is_watertight
    assert abs(v[:, 2].min() + 0.3) < 0.01  # the underside lies on the plane
    bottom = (np.abs(m.triangles_center[:, 2] + 0.3) < 0.005) & (m.face_normals[:, 2] < -0.95)
    assert m.area_faces[bottom].sum() > 0.6 * np.pi * (0.5 ** 2 - 0.3 ** 2)  # a flat cap: most of the cut's disc


def test_support_survives_save_and_load(tmp_path):
    f = _ball_field()
    f.set_support(np.array([0.0, 0.0, 1.0, 0.3]))
    save_model(tmp_path / "m.pt", f, f.cfg, np.eye(4))
    g, _, _ = load_model(tmp_path / "m.pt", torch.device("cpu"))
    p = torch.tensor([[0.0, 0.0, -0.4], [0.1, 0.0, 0.2]])
    assert torch.allclose(g.occupancy(p), f.occupancy(p))
    f.set_support(None)
    save_model(tmp_path / "n.pt", f, f.cfg, np.eye(4))
    assert load_model(tmp_path / "n.pt", torch.device("cpu"))[0].support is None
