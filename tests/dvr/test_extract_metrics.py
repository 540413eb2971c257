"""Extraction (hierarchical marching cubes) and metrics."""

import numpy as np
import pytest
import torch
import trimesh

from dvr.extract import extract_mesh, footprint_occupancy, logit_volume
from dvr.fields import SupportClip
from dvr.metrics import chamfer_fscore


class SphereField(torch.nn.Module):
    def __init__(self, r=0.5):
        super().__init__()
        self.r = torch.nn.Parameter(torch.tensor(r))

    def occupancy(self, p):
        return 10.0 * (self.r - p.norm(dim=-1))

    def texture(self, p):
        return (p * 0.5 + 0.5).clamp(0, 1)


def test_sphere_radius_and_orientation():
    v, f, c = extract_mesh(SphereField(), resolution=64, coarse_factor=4, refine_steps=2)
    m = trimesh.Trimesh(v, f, process=False)
    r = np.linalg.norm(v, axis=1)
    assert abs(r.mean() - 0.5) < 1e-3 and r.std() < 1e-3
    assert m.volume > 0  # outward normals
    assert c.shape == v.shape and c.dtype == np.uint8


def test_hierarchical_only_evaluates_near_surface():
    vol, n_fine = logit_volume(SphereField().occupancy, resolution=128, coarse_factor=4)
    assert vol.shape == (129, 129, 129)
    assert n_fine < 0.25 * 129 ** 3
    # exact where it matters: compare with a dense evaluation near the surface
    lin = torch.linspace(-1, 1, 129)
    g = torch.stack(torch.meshgrid(lin, lin, lin, indexing="ij"), -1).view(-1, 3)
    dense = SphereField().occupancy(g).detach().view(129, 129, 129).numpy()
    near = np.abs(dense) < 0.5
    assert np.allclose(vol[near], dense[near], atol=1e-5)
    assert np.all(np.sign(vol[~near]) == np.sign(dense[~near]))


def test_empty_field_gives_empty_mesh():
    class Empty(SphereField):
        def occupancy(self, p):
            return -torch.ones(p.shape[0])

    v, f, _ = extract_mesh(Empty(), resolution=32)
    assert len(v) == 0 and len(f) == 0


def test_bad_resolution():
    with pytest.raises(ValueError, match="multiple"):
        logit_volume(SphereField().occupancy, resolution=30, coarse_factor=4)


def test_chamfer_fscore_known_offset():
    """Concentric spheres 0.2 apart: Chamfer ≈ 0.2 (+ sampling spacing), F-score 0; same mesh: ≈ 0 and 1."""
    a = trimesh.creation.icosphere(5, radius=1.0)
    b = trimesh.creation.icosphere(5, radius=1.2)
    r = chamfer_fscore(a, b, n=50000)
    assert 0.2 <= r["chamfer"] < 0.21
    assert r["fscore"] == 0.0 and r["chamfer_rel"] == pytest.approx(r["chamfer"] / r["diag"])
    r2 = chamfer_fscore(a, a, n=50000)
    assert r2["chamfer"] < 0.01 and r2["fscore"] > 0.99
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int))
    assert chamfer_fscore(empty, a)["fscore"] == 0.0


class SlabField(SupportClip, torch.nn.Module):
    """A box 0.1 < z < 0.5, |x|, |y| < 0.4 over the floor z = 0: its lowest strip (0 ≤ z ≤ 0.1) missing, as when the
    contact shadow took it from the masks."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.tensor(1.0))
        self.set_support([0.0, 0.0, 1.0, 0.0])

    def occupancy(self, p):
        d = torch.stack([0.4 - p[:, 0].abs(), 0.4 - p[:, 1].abs(), 0.2 - (p[:, 2] - 0.3).abs()], -1)
        return self.clip_to_support(p, 20.0 * self.w * d.min(-1).values)

    def texture(self, p):
        return torch.full_like(p, 0.5)


def test_footprint_extrudes_the_lowest_band_down_to_the_support():
    f = SlabField()
    v0, _, _ = extract_mesh(f, resolution=64, coarse_factor=4)
    v1, faces, _ = extract_mesh(f, resolution=64, coarse_factor=4, footprint=0.15)
    assert v0[:, 2].min() > 0.09  # without it the strip stays missing
    assert v1[:, 2].min() < 0.02 and v1[:, 2].min() > -0.02  # the slab stands on the floor, capped flat
    side = v1[(v1[:, 2] > 0.02) & (v1[:, 2] < 0.08)]
    assert len(side) and np.abs(np.abs(side[:, :2]).max(1) - 0.4).max() < 0.02  # straight down, no skirt
    m = trimesh.Trimesh(v1, faces)
    assert m.is_watertight and m.volume == pytest.approx(0.8 * 0.8 * 0.5, rel=0.05)


def test_footprint_leaves_the_field_alone_above_the_band_and_below_the_floor():
    f = SlabField()
    occ = footprint_occupancy(f, 0.15)
    above = torch.tensor([[0.0, 0.0, 0.3], [0.39, 0.0, 0.2], [0.6, 0.0, 0.2]])
    assert torch.equal(occ(above), f.occupancy(above))
    below = torch.tensor([[0.0, 0.0, -0.05], [0.0, 0.0, -0.01]])
    assert (occ(below) < 0).all()
    assert footprint_occupancy(f, 0.0) == f.occupancy  # off
    f.set_support(None)
    assert footprint_occupancy(f, 0.15) == f.occupancy  # no support plane: nothing to extrude onto
