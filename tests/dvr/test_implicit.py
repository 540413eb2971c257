"""The implicit depth gradient: smoke, bad input, shapes, and gradcheck (float64) against finite differences
of the march + secant root finder itself."""

import pytest
import torch
from torch.autograd import gradcheck

from dvr import implicit
from dvr.implicit import guard_denominator, implicit_depth, implicit_depth_reference
from dvr.march import HIT, find_surface

D = torch.float64


def _rays():
    o = torch.tensor([[-2.5, 0.1, 0.05], [0.2, -2.4, 0.3], [0.1, 0.2, 2.6], [-1.5, -1.5, 0.4]], dtype=D)
    t = torch.tensor([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, -0.1, 0.0], [0.0, 0.0, 0.1]], dtype=D)
    w = t - o
    return o, w / w.norm(dim=-1, keepdim=True)


def _sphere(c, r, k=4.0):
    return lambda p: k * (r - (p - c).norm(dim=-1))


def _depth_of(fn, o, w):
    res = find_surface(fn, o, w, n_steps=64, n_secant=60)
    assert bool((res.status == HIT).all())
    return res.depth


def test_smoke_value_is_root():
    o, w = _rays()
    c, r = torch.tensor([0.05, -0.02, 0.03], dtype=D), torch.tensor(0.5, dtype=D)
    d = _depth_of(_sphere(c, r), o, w)
    out = implicit_depth(_sphere(c, r), [c, r], o, w, d)
    assert torch.equal(out, d)
    assert _sphere(c, r)(o + out[:, None] * w).abs().max() < 1e-9


def test_bad_input():
    o, w = _rays()
    f = _sphere(torch.zeros(3, dtype=D), torch.tensor(0.5, dtype=D))
    with pytest.raises(ValueError, match="origins"):
        implicit_depth(f, [], o[:, :2], w, torch.ones(4, dtype=D))
    with pytest.raises(ValueError, match="dirs"):
        implicit_depth(f, [], o, w[:3], torch.ones(4, dtype=D))
    with pytest.raises(ValueError, match="depth"):
        implicit_depth(f, [], o, w, torch.ones(3, dtype=D))
    with pytest.raises(ValueError, match="eps"):
        implicit_depth(f, [], o, w, torch.ones(4, dtype=D), eps=0.0)


def test_shapes_and_grad_shapes():
    o, w = _rays()
    o.requires_grad_(True)
    w.requires_grad_(True)
    c = torch.zeros(3, dtype=D, requires_grad=True)
    r = torch.tensor(0.5, dtype=D, requires_grad=True)
    d = _depth_of(_sphere(c, r), o.detach(), w.detach())
    out = implicit_depth(_sphere(c, r), [c, r], o, w, d)
    assert out.shape == (4,)
    out.sum().backward()
    assert o.grad.shape == (4, 3) and w.grad.shape == (4, 3) and c.grad.shape == (3,) and r.grad.shape == ()


def test_gradcheck_analytic_field_params_origins_dirs():
    o0, w0 = _rays()

    def fn(c, r, o, w):
        f = _sphere(c, r)
        d = _depth_of(f, o.detach(), w.detach())  # the real march + secant, re-run for every FD probe
        return implicit_depth(f, [c, r], o, w, d)

    c = torch.tensor([0.05, -0.02, 0.03], dtype=D, requires_grad=True)
    r = torch.tensor(0.5, dtype=D, requires_grad=True)
    assert gradcheck(fn, (c, r, o0.clone().requires_grad_(True), w0.clone().requires_grad_(True)),
                     eps=1e-6, atol=1e-5, rtol=1e-4)


class _Net(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.l1 = torch.nn.Linear(3, 8).double()
        self.l2 = torch.nn.Linear(8, 1).double()
        with torch.no_grad():
            self.l2.weight.mul_(0.3)


def test_gradcheck_small_network():
    torch.manual_seed(3)
    net = _Net()
    o, w = _rays()
    names = [n for n, _ in net.named_parameters()]

    def field(params):
        def f(p):
            h = torch.nn.functional.softplus(p @ params[0].T + params[1], beta=5.0)
            return (h @ params[2].T + params[3]).view(-1) + 4.0 * (0.5 - p.norm(dim=-1))
        return f

    def fn(*params):
        f = field(params)
        d = _depth_of(f, o, w)
        return implicit_depth(f, params, o, w, d)

    params = tuple(p.detach().clone().requires_grad_(True) for p in net.parameters())
    assert len(names) == 4
    assert gradcheck(fn, params, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_reference_matches_function():
    o, w = _rays()
    c = torch.tensor([0.05, -0.02, 0.03], dtype=D, requires_grad=True)
    r = torch.tensor(0.5, dtype=D, requires_grad=True)
    d = _depth_of(_sphere(c, r), o, w)
    g1 = torch.autograd.grad(implicit_depth(_sphere(c, r), [c, r], o, w, d).sum(), [c, r])
    g2 = torch.autograd.grad(implicit_depth_reference(_sphere(c, r), o, w, d).sum(), [c, r])
    for a, b in zip(g1, g2):
        assert torch.allclose(a, b, atol=1e-10)


def test_guard_keeps_sign():
    x = torch.tensor([0.0, -0.0, 1e-9, -1e-9, 0.5, -0.5], dtype=D)
    g = guard_denominator(x, 1e-3)
    assert g.tolist() == [1e-3, -1e-3, 1e-3, -1e-3, 0.5, -0.5]


def test_guarded_gradient_has_true_sign():
    """Root where f decreases along the ray (∇f·w = −1) with eps = 2 > |∇f·w|: the guarded gradient must keep
    the sign of the true ∂d/∂θ = +1 (the original DVR clamp to +eps gives −0.5)."""
    o = torch.tensor([[-2.0, 0.0, 0.0]], dtype=D)
    w = torch.tensor([[1.0, 0.0, 0.0]], dtype=D)
    th = torch.tensor(0.3, dtype=D, requires_grad=True)
    f = lambda p: th - p[:, 0]  # noqa: E731 - root at x = θ, d = 2 + θ
    d = torch.tensor([2.3], dtype=D)
    (g,) = torch.autograd.grad(implicit_depth(f, [th], o, w, d, eps=2.0).sum(), [th])
    assert g.item() > 0  # true derivative +1, guarded magnitude 0.5
    assert g.item() == pytest.approx(0.5)


def test_zero_denominator_is_finite_and_fails_without_guard(monkeypatch):
    """Grazing root with ∇f·w = 0 exactly (f = θ·x³ at x = 0): finite gradients with the guard, Inf/NaN without."""
    o = torch.tensor([[-2.0, 0.0, 0.0]], dtype=D, requires_grad=True)
    w = torch.tensor([[1.0, 0.0, 0.0]], dtype=D, requires_grad=True)
    th = torch.tensor(1.0, dtype=D, requires_grad=True)
    f = lambda p: th * p[:, 0] ** 3 + (th - 1.0)  # noqa: E731
    d = torch.tensor([2.0], dtype=D)
    grads = torch.autograd.grad(implicit_depth(f, [th], o, w, d).sum(), [th, o, w])
    assert all(torch.isfinite(g).all() for g in grads)
    monkeypatch.setattr(implicit, "guard_denominator", lambda x, eps: x)
    grads = torch.autograd.grad(implicit_depth(f, [th], o, w, d).sum(), [th, o, w])
    assert not all(torch.isfinite(g).all() for g in grads)
