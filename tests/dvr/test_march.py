"""Surface finding: smoke, bad input, shapes, first surface, memory independent of n_steps."""

import pytest
import torch

from dvr.march import HIT, INSIDE, MISS, find_surface, secant


def sphere(r=0.5, c=(0.0, 0.0, 0.0), k=10.0):
    c = torch.tensor(c)
    return lambda p: k * (r - (p - c.to(p)).norm(dim=-1))


def rays(n=5):
    o = torch.tensor([[-3.0, 0.0, 0.0]]).repeat(n, 1)
    o[:, 1] = torch.linspace(-0.3, 0.3, n)
    w = torch.tensor([[1.0, 0.0, 0.0]]).repeat(n, 1)
    return o, w


def test_smoke_sphere_depth():
    o, w = rays()
    res = find_surface(sphere(), o, w, n_steps=64, n_secant=8)
    assert (res.status == HIT).all()
    expect = 3.0 - torch.sqrt(0.25 - o[:, 1] ** 2)
    assert torch.allclose(res.depth, expect, atol=1e-5)


def test_bad_input():
    o, w = rays()
    with pytest.raises(ValueError, match="origins"):
        find_surface(sphere(), o[:, :2], w)
    with pytest.raises(ValueError, match="dirs"):
        find_surface(sphere(), o, w[:2])
    with pytest.raises(ValueError, match="n_steps"):
        find_surface(sphere(), o, w, n_steps=1)


def test_shapes_dtypes():
    o, w = rays(7)
    res = find_surface(sphere(), o, w)
    for t in (res.depth, res.near, res.far, res.max_depth):
        assert t.shape == (7,) and t.dtype == torch.float32 and torch.isfinite(t).all()
    assert res.status.dtype == torch.int8


def test_chunking_gives_same_result_and_bounded_batch():
    """max_points bounds every field call, whatever n_steps: memory does not grow with n_steps."""
    o, w = rays(16)
    seen = []
    f = sphere()

    def spy(p):
        seen.append(p.shape[0])
        return f(p)

    big = find_surface(spy, o, w, n_steps=512, max_points=256)
    assert max(seen) <= 256
    ref = find_surface(f, o, w, n_steps=512)
    assert torch.allclose(big.depth, ref.depth) and torch.equal(big.status, ref.status)


def test_more_rays_than_max_points():
    """Blocks of a single sample (rays > max_points) give the same surfaces."""
    o, w = rays(64)
    small = find_surface(sphere(), o, w, n_steps=32, max_points=16)
    ref = find_surface(sphere(), o, w, n_steps=32)
    assert torch.allclose(small.depth, ref.depth) and torch.equal(small.status, ref.status)


def test_secant_converges_in_bracket():
    f = sphere()
    o, w = rays(3)
    lo, hi = torch.full((3,), 2.0), torch.full((3,), 3.0)
    d = secant(f, o, w, lo, hi, f(o + lo[:, None] * w), f(o + hi[:, None] * w), n_iter=30)
    assert torch.all((d >= lo) & (d <= hi))
    assert f(o + d[:, None] * w).abs().max() < 1e-4


def test_every_secant_evaluation_narrows_the_root():
    """The root is the secant of the LAST bracket, not the point evaluated last (which would throw the last of the
    ``n_iter`` field evaluations away: 1 round would give the same root as 0). On a sphere the error falls
    with each round, 100-fold in three."""
    f = sphere()
    o, w = rays(16)
    lo, hi = torch.full((16,), 2.0, dtype=torch.float64), torch.full((16,), 3.0, dtype=torch.float64)
    o, w = o.double(), w.double()
    f_lo, f_hi = f(o + lo[:, None] * w), f(o + hi[:, None] * w)
    truth = secant(f, o, w, lo, hi, f_lo, f_hi, n_iter=60)
    err = [(secant(f, o, w, lo, hi, f_lo, f_hi, n_iter=k) - truth).abs().max().item() for k in range(4)]
    assert all(b < a for a, b in zip(err, err[1:])) and err[3] < 0.01 * err[0], err


def test_jitter_keeps_order_and_endpoints():
    from dvr.march import sample_depths

    near, far = torch.zeros(100), torch.full((100,), 2.0)
    d = sample_depths(near, far, 32, jitter=True)
    assert torch.all(d[:, 1:] >= d[:, :-1])
    assert torch.equal(d[:, 0], near) and torch.equal(d[:, -1], far)


def test_status_codes_are_distinct():
    assert len({MISS, HIT, INSIDE}) == 3


# ------------------------------------------------------------------ fixed shapes (what a CUDA graph holds)
def two_balls(p: torch.Tensor) -> torch.Tensor:
    """Logit > 0 inside either of two balls (a ray can cross twice: the first crossing counts)."""
    a = 0.35 - (p - torch.tensor([0.3, 0.0, 0.0]).to(p)).norm(dim=-1)
    b = 0.25 - (p - torch.tensor([-0.4, 0.1, 0.0]).to(p)).norm(dim=-1)
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


@pytest.mark.parametrize("n_secant,jitter,level", [(0, False, 0.0), (3, True, 0.0), (8, True, 1.5)])
def test_fixed_shapes_find_the_same_surfaces(n_secant, jitter, level):
    """find_surface_fixed with the fractions find_surface draws (same seed) finds the same surfaces."""
    from dvr.march import find_surface_fixed, sample_fractions

    o, d = mixed_rays()
    torch.manual_seed(3)
    ref = find_surface(two_balls, o, d, n_steps=64, n_secant=n_secant, level=level, jitter=jitter)
    torch.manual_seed(3)
    fractions = sample_fractions(o.shape[0], 64, jitter, o.device, o.dtype)
    got = find_surface_fixed(two_balls, o, d, fractions, n_secant, level)
    assert {int(c) for c in ref.status.unique()} == {HIT, MISS, INSIDE}  # every case is exercised
    assert torch.equal(got.status, ref.status)
    assert torch.allclose(got.depth, ref.depth, atol=1e-6) and torch.isfinite(got.depth).all()
    assert torch.allclose(got.max_depth, ref.max_depth, atol=1e-6)
    assert torch.equal(got.near, ref.near) and torch.equal(got.far, ref.far)
    assert got.depth.shape == got.status.shape == (o.shape[0],) and got.status.dtype == torch.int8


def test_fixed_shapes_bad_fractions():
    from dvr.march import find_surface_fixed

    o, w = rays(4)
    with pytest.raises(ValueError, match="fractions must be"):
        find_surface_fixed(sphere(), o, w, torch.zeros(3, 16))
    with pytest.raises(ValueError, match="fractions must be"):
        find_surface_fixed(sphere(), o, w, torch.zeros(4, 1))
    with pytest.raises(ValueError, match="dirs"):
        find_surface_fixed(sphere(), o, w[:2], torch.zeros(4, 16))


def test_fractions_and_depths_as_sample_depths():
    from dvr.march import depths_at, sample_depths, sample_fractions

    near, far = torch.rand(50), 1.0 + torch.rand(50)
    torch.manual_seed(1)
    ref = sample_depths(near, far, 24, jitter=True)
    torch.manual_seed(1)
    t = sample_fractions(50, 24, True, near.device, near.dtype)
    assert torch.equal(depths_at(near, far, t), ref) and t.shape == (50, 24)
    assert torch.equal(t[:, 0], torch.zeros(50)) and torch.equal(t[:, -1], torch.ones(50))
