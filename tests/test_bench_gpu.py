"""bench/gpu.py's fixed-shape surface finding (what a CUDA graph can hold) against dvr.march.find_surface."""

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.gpu import find_surface_static  # noqa: E402
from dvr.march import HIT, INSIDE, MISS, find_surface  # noqa: E402


def two_balls(p: torch.Tensor) -> torch.Tensor:
    """Logit > 0 inside either of two balls (a ray can cross twice: the first crossing counts)."""
    a = 0.35 - (p - torch.tensor([0.3, 0.0, 0.0])).norm(dim=-1)
    b = 0.25 - (p - torch.tensor([-0.4, 0.1, 0.0])).norm(dim=-1)
    return 20.0 * torch.maximum(a, b)


def mixed_rays(n: int = 400):
    """Rays from outside towards the balls, rays that miss the unit sphere, and rays from inside a ball."""
    g = torch.Generator().manual_seed(0)
    o = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * 2.5
    target = torch.randn(n, 3, generator=g) * 0.4
    d = torch.nn.functional.normalize(target - o, dim=-1)
    d[:40] = torch.nn.functional.normalize(torch.cross(o[:40], torch.randn(40, 3, generator=g), dim=-1), dim=-1)
    o[40:80] = torch.tensor([0.3, 0.0, 0.0]) + 0.1 * torch.randn(40, 3, generator=g)  # inside the first ball
    return o, d


@pytest.mark.parametrize("n_secant", [0, 3, 8])
def test_fixed_shapes_find_the_same_surfaces(n_secant):
    o, d = mixed_rays()
    ref = find_surface(two_balls, o, d, n_steps=64, n_secant=n_secant)
    got = find_surface_static(two_balls, o, d, 64, n_secant)
    assert {int(c) for c in ref.status.unique()} == {HIT, MISS, INSIDE}  # every case is exercised
    assert torch.equal(got.status, ref.status)
    assert torch.allclose(got.depth, ref.depth, atol=1e-6) and torch.isfinite(got.depth).all()
    assert torch.allclose(got.max_depth, ref.max_depth, atol=1e-6)
    assert got.depth.shape == ref.depth.shape == (o.shape[0],)
