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
    """The root is the secant of the LAST bracket: until stop 43 it was the point evaluated last, so the last of the
    ``n_iter`` field evaluations was thrown away (1 round gave the same root as 0). On a sphere the error falls
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
