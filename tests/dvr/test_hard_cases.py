"""Hard cases of docs/design.md ("Hard cases"): no NaN/Inf in losses, gradients or parameters, correct hit/miss/inside
classification, and for each guard a test that fails when the guard is removed."""

import copy

import numpy as np
import pytest
import torch

from dvr import cameras as camera_mod
from dvr import losses as L
from dvr.config import FieldConfig, LossWeights, TrainConfig
from dvr.data import load_scene
from dvr.hull import hull_logits
from dvr.implicit import implicit_depth
from dvr.march import HIT, INSIDE, MISS, find_surface
from dvr.trainer import Trainer


def sphere(r=0.5, c=(0.0, 0.0, 0.0), k=10.0):
    c = torch.tensor(c)
    return lambda p: k * (r - (p - c.to(p)).norm(dim=-1))


def tiny_cfg(**kw):
    base = dict(iterations=6, batch_rays=256, depth_rays=32, carve_points=256, n_steps=32, n_steps_final=32,
                hull_res=32, coarse_res=0, checkpoint_every=3, log_every=1, preview_every=0, progress=False,
                device="cpu",
                field=FieldConfig(base_res=32, plane_res=(16, 32), hidden=16))
    base.update(kw)
    return TrainConfig(**base)


def assert_all_finite(trainer: Trainer):
    for n, p in trainer.model.named_parameters():
        assert torch.isfinite(p).all(), n


# ------------------------------------------------------------------ rays
def test_grazing_rays_finite_gradients():
    """Rays tangent to a sphere (∇f·w → 0 at the root): finite depth gradients for every parameter."""
    r = torch.tensor(0.5, requires_grad=True)
    f = lambda p: 10.0 * (r - p.norm(dim=-1))  # noqa: E731
    ys = torch.tensor([0.49, 0.499, 0.4999, 0.49999])
    o = torch.stack([torch.full_like(ys, -3.0), ys, torch.zeros_like(ys)], -1)
    w = torch.tensor([[1.0, 0.0, 0.0]]).repeat(4, 1)
    res = find_surface(f, o, w, n_steps=2048, n_secant=16)
    h = res.status == HIT
    assert h.any()
    d = implicit_depth(f, [r], o[h], w[h], res.depth[h], eps=0.05)
    (g,) = torch.autograd.grad(d.sum(), [r])
    assert torch.isfinite(g).all()


def test_ray_starting_inside_is_flagged_never_depth_zero_hit():
    """Field occupied at the sphere entry, free, then occupied again: INSIDE, not a hit on the second shell.
    Without the first-sample check the march would report the second crossing as the surface."""
    f = lambda p: torch.maximum(5.0 * (p.norm(dim=-1) - 0.9), 5.0 * (0.3 - p.norm(dim=-1)))  # noqa: E731
    o = torch.tensor([[-3.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    w = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    res = find_surface(f, o, w, n_steps=64)
    assert res.status[0].item() == INSIDE
    assert res.depth[0].item() == pytest.approx(2.0)  # the sphere entry, not the camera
    assert res.status[1].item() == INSIDE  # camera inside the object


def test_rays_missing_everything():
    o = torch.tensor([[-3.0, 0.9, 0.0], [-3.0, 5.0, 0.0]])  # passes the object; misses the unit sphere
    w = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    res = find_surface(sphere(), o, w)
    assert res.status.tolist() == [MISS, MISS]
    for t in (res.depth, res.near, res.far, res.max_depth):
        assert torch.isfinite(t).all()


def test_sphere_bounds_miss_no_nan_without_clamp_fails(monkeypatch):
    """The discriminant clamp keeps missing rays finite; sqrt of the raw (negative) discriminant gives NaN."""
    o, w = torch.tensor([[-3.0, 5.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]])
    near, far, valid = camera_mod.sphere_bounds(o, w)
    assert not valid.any() and torch.isfinite(near).all() and torch.isfinite(far).all()
    b = (o * w).sum(-1)
    raw = torch.sqrt(b * b - ((o * o).sum(-1) - 1.0))
    assert torch.isnan(raw).all()


def test_thin_structure_found_with_enough_steps():
    """A plate 0.01 thick: found (first face) once the step is below its thickness; never non-finite."""
    f = lambda p: 200.0 * (0.005 - p[:, 0].abs())  # noqa: E731
    o = torch.tensor([[-3.0, 0.1, 0.2]])
    w = torch.tensor([[1.0, 0.0, 0.0]])
    coarse = find_surface(f, o, w, n_steps=16)
    fine = find_surface(f, o, w, n_steps=512)
    assert torch.isfinite(coarse.depth).all()
    assert fine.status.item() == HIT
    assert fine.depth.item() == pytest.approx(3.0 - 0.005, abs=1e-4)


def test_several_surfaces_returns_first():
    f1, f2 = sphere(0.2, (-0.5, 0, 0)), sphere(0.2, (0.5, 0, 0))
    f = lambda p: torch.maximum(f1(p), f2(p))  # noqa: E731
    o, w = torch.tensor([[-3.0, 0.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]])
    res = find_surface(f, o, w, n_steps=128)
    assert res.status.item() == HIT and res.depth.item() == pytest.approx(2.3, abs=1e-4)


# ------------------------------------------------------------------ losses and training
def test_empty_subsets_give_zero_not_nan():
    z = torch.zeros(0)
    for v in (L.freespace_loss(z), L.occupancy_loss(z), L.depth_loss(z, z), L.rgb_loss(z.view(0, 3), z.view(0, 3))):
        assert v.item() == 0.0
    # removing the guard (plain mean) gives NaN on the same input
    assert torch.isnan(z.mean())


def test_bce_stable_for_extreme_logits():
    lg = torch.tensor([-1e4, 1e4, 0.0], requires_grad=True)
    v = L.freespace_loss(lg) + L.occupancy_loss(lg)
    v.backward()
    assert torch.isfinite(v) and torch.isfinite(lg.grad).all()


def _train_data(ws, **mod):
    data = load_scene(ws, torch.device("cpu"))
    if "masks" in mod:
        data.masks = mod["masks"](data.masks)
    if "images" in mod:
        data.images = mod["images"](data.images)
    return data


@pytest.mark.parametrize("which", ["empty", "full"])
def test_empty_and_full_masks_train_finite(small_ws, tmp_path, which):
    fill = 0.0 if which == "empty" else 1.0
    data = _train_data(small_ws, masks=lambda m: torch.full_like(m, fill))
    tr = Trainer(tiny_cfg(), data, tmp_path)
    tr.fit()
    assert tr.skipped == 0
    assert_all_finite(tr)


def test_hull_of_empty_masks_is_finite():
    P = torch.tensor([[[100.0, 0, 32, 0], [0, 100.0, 32, 0], [0, 0, 1, 3.0]]])
    lg = hull_logits(P, torch.zeros(1, 64, 64), res=16)
    assert torch.isfinite(lg).all() and (lg < 0).all()


def test_all_black_images_train_finite(small_ws, tmp_path):
    data = _train_data(small_ws, images=lambda im: torch.zeros_like(im))
    tr = Trainer(tiny_cfg(), data, tmp_path)
    stats = tr.fit()
    assert np.isfinite(stats["loss"]) and np.isfinite(stats["psnr"])
    assert_all_finite(tr)


def test_psnr_floor_for_perfect_prediction():
    x = torch.zeros(10, 3)
    assert np.isfinite(L.psnr(x, x))


def test_very_few_views(small_ws, tmp_path):
    data = load_scene(small_ws, torch.device("cpu"), views=[0, 4])
    tr = Trainer(tiny_cfg(), data, tmp_path)
    tr.fit()
    assert_all_finite(tr)


@pytest.mark.parametrize("scale,offset", [(1e-4, [0.0, 0.0, 0.0]), (1e4, [3e4, -2e4, 5e3])])
def test_extreme_scene_scales_normalize_exactly(tmp_path, scale, offset):
    """The same scene at SfM scales 1e-4 and 1e4 (far from the origin) gives the same normalized rays."""
    from synth import write_scene
    from tests.conftest import small_scene

    write_scene(small_scene(world_scale=1.0), tmp_path / "ref")
    write_scene(small_scene(world_scale=scale, world_offset=offset), tmp_path / "x")
    a = load_scene(tmp_path / "ref", torch.device("cpu"))
    b = load_scene(tmp_path / "x", torch.device("cpu"))
    assert np.allclose(a.cams.centers, b.cams.centers, atol=1e-6)
    assert torch.allclose(a.P / a.P[:, 2:, 3:], b.P / b.P[:, 2:, 3:], rtol=1e-4, atol=1e-3)
    tr = Trainer(tiny_cfg(iterations=3), b, tmp_path / "m")
    tr.fit()
    assert_all_finite(tr)


def test_nonfinite_step_is_skipped(small_ws, tmp_path, monkeypatch):
    """A NaN loss or an Inf gradient never reaches the parameters; without the check Adam writes NaN."""
    data = _train_data(small_ws)
    tr = Trainer(tiny_cfg(), data, tmp_path)
    before = copy.deepcopy(tr.model.state_dict())
    real = tr.losses

    def poisoned(step):
        total, stats = real(step)
        return total + tr.model.base.sum() * float("inf"), stats

    monkeypatch.setattr(tr, "losses", poisoned)
    tr.train_step(0)
    assert tr.skipped == 1
    for k, v in tr.model.state_dict().items():
        assert torch.equal(v, before[k]), k
    # the same poisoned gradient applied without the guard corrupts the parameters
    tr.opt.zero_grad()
    total, _ = poisoned(0)
    total.backward()
    tr.opt.step()
    assert not torch.isfinite(tr.model.base).all()


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_one_nonfinite_gradient_element_skips_the_step(small_ws, tmp_path, bad):
    """A finite loss whose gradient holds one NaN or Inf (in one cell of the grid) never reaches the parameters;
    without the check Adam writes it into the grid."""
    tr = Trainer(tiny_cfg(), _train_data(small_ws), tmp_path)
    before = copy.deepcopy(tr.model.state_dict())

    def poison(grad):
        grad = grad.clone()
        grad.view(-1)[7] = bad
        return grad

    handle = tr.model.base.register_hook(poison)
    tr.train_step(0)
    assert tr.skipped == 1
    for k, v in tr.model.state_dict().items():
        assert torch.equal(v, before[k]), k
    tr.opt.zero_grad()
    total, _ = tr.losses(0)
    assert torch.isfinite(total)
    total.backward()
    handle.remove()
    tr.opt.step()
    assert not torch.isfinite(tr.model.base).all()


def test_all_finite_sees_one_element_of_any_tensor():
    from dvr.trainer import all_finite

    ts = [torch.zeros(()), torch.ones(5, 4), torch.full((3, 3, 3), 1e30)]
    assert bool(all_finite(ts)) and bool(all_finite([]))
    for bad in (float("nan"), float("inf"), -float("inf")):
        for i in range(len(ts)):
            poisoned = [t.clone() for t in ts]
            poisoned[i].view(-1)[-1] = bad
            assert not bool(all_finite(poisoned)), (bad, i)
    opposite = [torch.tensor([float("inf")]), torch.tensor([-float("inf")])]
    assert not bool(all_finite(opposite))


def test_weights_dataclass_has_every_term():
    w = LossWeights()
    assert {"rgb", "freespace", "occupancy", "depth", "carve", "tv", "normal"} <= set(vars(w))
