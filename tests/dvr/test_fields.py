"""Fields: the dense grid's axis order, the support clip (nothing below the floor; a flat, closed underside), the
:class:`~dvr.fields.Field` interface of both kinds, and :func:`~dvr.fields.evaluate_in_chunks`."""

import numpy as np
import pytest
import torch
import trimesh
from torch.autograd import gradcheck

from dvr.checkpoint import load_model, save_model
from dvr.config import FieldConfig
from dvr.extract import extract_mesh
from dvr.fields import SUPPORT_SLOPE, Field, GridField, evaluate_in_chunks, make_field
from dvr.hull import grid_points


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


def test_support_plane_moves_to_the_points_device_once():
    """The plane is kept on the device of the points it clips (a copy per call waited for the GPU 14 times a
    training step); "meta" stands in for another device here."""
    f = _ball_field()
    f.set_support(np.array([0.0, 0.0, 1.0, 0.3]))
    out = f.clip_to_support(torch.zeros(4, 3, device="meta"), torch.zeros(4, device="meta"))
    assert out.device.type == "meta" and out.shape == (4,)
    assert f.support.device.type == "meta"


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


# ------------------------------------------------------------------ the Field interface
KINDS = ["grid", "mlp"]


@pytest.fixture(params=["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                                               reason="needs CUDA"))])
def device(request):
    return torch.device(request.param)


def _tiny(kind, **over):
    cfg = dict(kind=kind, base_res=8, plane_res=(8,), hidden=8, mlp_layers=1, mlp_frequencies=2)
    cfg.update(over)
    return make_field(FieldConfig(**cfg))


@pytest.mark.parametrize("kind", KINDS)
def test_both_fields_implement_the_interface_with_the_documented_shapes(kind, device):
    f = _tiny(kind).to(device)
    assert isinstance(f, Field) and isinstance(f, torch.nn.Module)
    p = torch.rand(37, 3, device=device) * 2 - 1
    occ, tex = f.occupancy(p), f.texture(p)
    assert occ.shape == (37,) and occ.dtype == torch.float32 and occ.device.type == device.type
    assert tex.shape == (37, 3) and tex.device.type == device.type and 0 <= tex.min() and tex.max() <= 1
    tv = f.tv_loss()
    assert tv.shape == () and tv.device.type == device.type
    every = {id(q) for q in f.parameters()}
    assert f.occupancy_parameters() and {id(q) for q in f.occupancy_parameters()} <= every
    assert {id(q) for q in f.grid_parameters()} <= every
    # the occupancy parameters are what the occupancy depends on: each gets a gradient
    f.occupancy(p).sum().backward()
    assert all(q.grad is not None for q in f.occupancy_parameters())


def test_parameter_groups_and_state_dict_keys_are_unchanged():
    """Checkpoints of earlier runs load: the fields' state_dict keys are those the interface did not change."""
    g = _tiny("grid", occ_plane_res=(4,))
    assert set(g.state_dict()) == {"base", "occ_planes.planes.0", "occ_head.0.weight", "occ_head.0.bias",
                                   "occ_head.2.weight", "occ_head.2.bias", "tex_planes.planes.0",
                                   "tex_head.0.weight", "tex_head.0.bias", "tex_head.2.weight", "tex_head.2.bias"}
    assert [id(q) for q in g.grid_parameters()] == [id(g.base), id(g.occ_planes.planes[0]),
                                                    id(g.tex_planes.planes[0])]
    m = _tiny("mlp")
    assert set(m.state_dict()) == {"freqs", *(f"{n}.{i}.{w}" for n in ("occ", "tex") for i in (0, 2)
                                              for w in ("weight", "bias"))}
    assert m.grid_parameters() == [] and len(m.occupancy_parameters()) == 4


def test_field_is_abstract():
    class Partial(Field):
        def occupancy(self, p):
            return p[:, 0]

    with pytest.raises(TypeError, match="abstract"):
        Partial()


def test_grid_is_stored_zyx_and_sampled_at_xyz():
    """``base`` is stored [z, y, x] (grid_sample's order): a linear function a·x + b·y + c·z written into the
    storage that way reads back exactly at any point; with the axes swapped it would not."""
    f = GridField(FieldConfig(base_res=4, plane_res=(4,), hidden=8))
    lin = torch.linspace(-1, 1, 5)
    a, b, c = 1.0, 10.0, 100.0
    zz, yy, xx = torch.meshgrid(lin, lin, lin, indexing="ij")  # storage indices [k, j, i] = [z, y, x]
    with torch.no_grad():
        f.base.copy_((a * xx + b * yy + c * zz)[None, None])
    p = torch.rand(50, 3) * 2 - 1
    expect = a * p[:, 0] + b * p[:, 1] + c * p[:, 2]
    assert torch.allclose(f.occupancy(p), expect, atol=1e-3)
    # init_occupancy takes [x, y, z] and stores its transpose
    vol = torch.randn(5, 5, 5)
    f.init_occupancy(vol)
    assert torch.equal(f.base[0, 0], vol.permute(2, 1, 0))
    assert torch.allclose(f.occupancy(torch.tensor([[-1.0, 0.0, 1.0]])), vol[0, 2, 4:5])


@pytest.mark.parametrize("kind", KINDS)
def test_occupancy_gradcheck_wrt_points_float64(kind):
    torch.manual_seed(1)
    f = _tiny(kind, base_res=4, plane_res=(4,), occ_plane_res=(4,) if kind == "grid" else ()).double()
    if kind == "grid":
        with torch.no_grad():
            f.base.copy_(torch.randn_like(f.base))
            for q in f.occ_head.parameters():
                q.copy_(torch.randn_like(q))
    p = (torch.rand(6, 3, dtype=torch.float64) * 1.6 - 0.8).requires_grad_(True)
    assert gradcheck(f.occupancy, (p,), eps=1e-6, atol=1e-5)


def test_resize_base_keeps_the_occupancy_function():
    f = GridField(FieldConfig(base_res=8, plane_res=(8,), hidden=8))
    assert f.supports_resize and f.grid_resolution == 8
    with torch.no_grad():
        f.base.copy_(torch.randn_like(f.base))
    lattice = grid_points(8)
    p = torch.rand(500, 3) * 2 - 1
    before_l, before_p = f.occupancy(lattice), f.occupancy(p)
    old, new = f.resize_base(16)
    assert f.grid_resolution == 16 and new is f.base and old is not new
    assert f.grid_resolution_in(f.state_dict()) == 16
    assert torch.allclose(f.occupancy(lattice), before_l, atol=1e-5)  # exactly on the old lattice
    assert (f.occupancy(p) - before_p).abs().mean() < 0.2 * before_p.abs().mean()  # close between
    assert f.resize_base(16) == (f.base, f.base)  # same resolution: nothing to swap


def test_mlp_field_refuses_resize_clearly():
    m = _tiny("mlp")
    assert not m.supports_resize and m.grid_resolution is None and m.grid_resolution_in(m.state_dict()) is None
    with pytest.raises(NotImplementedError, match="supports_resize"):
        m.resize_base(16)


# ------------------------------------------------------------------ evaluate_in_chunks
def test_evaluate_in_chunks_matches_one_call_and_bounds_the_chunk():
    f = _tiny("grid")
    p = torch.rand(1000, 3) * 2 - 1
    sizes = []

    def tex(q):
        sizes.append(q.shape[0])
        return f.texture(q)

    with torch.no_grad():
        out = evaluate_in_chunks(tex, p, chunk=300, trailing_shape=(3,))
        assert torch.allclose(out, f.texture(p), atol=1e-6)
        assert torch.allclose(evaluate_in_chunks(f.occupancy, p, 7), f.occupancy(p), atol=1e-6)
    assert out.shape == (1000, 3) and sizes == [300, 300, 300, 100]


def test_evaluate_in_chunks_empty_input_has_the_trailing_shape():
    def never(q):
        raise AssertionError("fn must not be called on an empty input")

    empty = torch.zeros(0, 3)
    assert evaluate_in_chunks(never, empty, trailing_shape=(3,)).shape == (0, 3)
    assert evaluate_in_chunks(never, empty).shape == (0,)
    assert evaluate_in_chunks(never, empty, dtype=torch.bool).dtype == torch.bool
    with pytest.raises(ValueError):
        evaluate_in_chunks(never, torch.zeros(4, 3), chunk=0)
