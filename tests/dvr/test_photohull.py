"""dvr/photohull.py: the photo hull opens a cup's inside, which no silhouette carves, keeps the wall, and never
opens a silhouette."""

import dataclasses

import numpy as np
import pytest
import torch

from dvr.cameras import to_sfm
from dvr.data import load_scene
from dvr.hull import grid_points, hull_inside
from dvr.photohull import _coverage, _surface, _visible, photo_carve
from tests.conftest import small_scene

RES = 64
LIGHT = {"kind": "lambertian", "ambient": 0.5, "lights": [[0.4, 0.5, 0.8, 0.6]]}
CUP = {"kind": "difference", "parts": [
    {"kind": "cylinder", "radius": 0.5, "minor": 0.04, "size": [0.0, 0.0, 0.4]},
    {"kind": "cylinder", "radius": 0.36, "minor": 0.03, "size": [0.0, 0.0, 0.45], "center": [0.0, 0.0, 0.2]}]}


CUP_PHOTOS = {"shape": CUP, "albedo": {"kind": "noise", "scale": 1.5, "contrast": 0.15}, "lighting": LIGHT,
              "cameras": {"n_views": 24, "width": 96, "height": 72, "elevation": [30, 70], "rings": 2}}
BALL_PHOTOS = {"shape": {"kind": "sphere", "radius": 0.6}, "albedo": {"kind": "noise", "scale": 6.0, "contrast": 0.6},
               "lighting": LIGHT,
               "cameras": {"n_views": 16, "width": 96, "height": 72, "elevation": [-20, 50], "rings": 2}}


def _photographed(ws, **scene_over):
    """The scene rendered into ``ws``: the scene, its data and its visual hull."""
    from synth import write_scene

    scene = small_scene(**scene_over)
    write_scene(scene, ws)
    data = load_scene(ws, torch.device("cpu"), use_depth=False)
    return scene, data, hull_inside(data.P, data.masks, RES)


@pytest.fixture(scope="module")
def cup(tmp_path_factory):
    """An open cup glazed like the bench's mug (weak texture, one light), 24 views of 96×72 looking down 30-70°:
    its scene data and visual hull."""
    return _photographed(tmp_path_factory.mktemp("cup"), **CUP_PHOTOS)


def _true_sdf(scene, data):
    """Signed distance (negative inside the solid) of every lattice point, and the lattice points in the world."""
    from synth.render import sdf

    world = to_sfm(grid_points(RES).double().numpy(), data.cams.scale_mat)
    d = sdf(scene.shape, torch.from_numpy(world)).numpy()
    return d.reshape((RES + 1,) * 3), world.reshape((RES + 1,) * 3 + (3,))


def _cup_hollow(world):
    """The lattice points in the cup's hollow (``world``: the lattice points in the scene's frame)."""
    return (np.hypot(world[..., 0], world[..., 1]) < 0.3) & (world[..., 2] > -0.1) & (world[..., 2] < 0.35)


def _judged(scene, data, inside, carved):
    """What a carving did: the share of the cup's hollow (inside the visual hull) it opened, and how many of the
    solid's points more than a cell and a half from its surface it carved."""
    d, world = _true_sdf(scene, data)
    cell = 2.0 / RES * np.linalg.norm(data.cams.scale_mat[:3, 0])
    hollow = _cup_hollow(world)
    return (~carved[hollow & inside]).mean(), int((inside & (d < -1.5 * cell) & ~carved).sum())


def test_opens_the_cups_inside_and_keeps_its_wall(cup):
    scene, data, inside = cup
    result = photo_carve(inside, data.P, data.images, data.masks, data.sizes)
    _, world = _true_sdf(scene, data)
    assert inside[_cup_hollow(world)].mean() > 0.99  # the visual hull fills the cup: nothing but colour can open it
    opened, deep_carved = _judged(scene, data, inside, result.inside)
    assert opened > 0.5 and deep_carved == 0
    assert result.carved > 0 and result.sweeps > 1 and np.isfinite(result.threshold)


def test_opens_the_cup_under_changing_exposure(tmp_path):
    """The cup photographed with exposure ±25 % and white balance ±8 % per view (a phone's auto exposure): the
    photo hull compares colours after each view's gains, so it opens the cup as it does with steady exposure."""
    scene, data, inside = _photographed(tmp_path, **CUP_PHOTOS,
                                        effects=[{"kind": "exposure", "amount": 0.25, "white_balance": 0.08}])
    result = photo_carve(inside, data.P, data.images, data.masks, data.sizes)
    opened, deep_carved = _judged(scene, data, inside, result.inside)
    assert opened > 0.5 and deep_carved == 0


def test_a_convex_object_loses_no_solid(tmp_path):
    scene, data, inside = _photographed(tmp_path, **BALL_PHOTOS)
    result = photo_carve(inside, data.P, data.images, data.masks, data.sizes)
    assert _judged(scene, data, inside, result.inside)[1] == 0


def test_a_mask_that_misses_a_bite_does_not_make_it_dig(tmp_path, monkeypatch):
    """Four views' masks miss the right-most 7 % of a glazed ball (an automatic mask's error): the visual hull
    loses that bite, and its surface there lies inside the solid, where the views that see it read different
    places of the true surface. Reading colours up to 3.5 cells outward finds that surface: nothing is carved;
    read at ±0.5 cells alone, the carving digs into the solid."""
    import dvr.photohull as photohull

    glazed = {**BALL_PHOTOS, "albedo": {"kind": "noise", "scale": 1.5, "contrast": 0.15}}
    scene, data, _ = _photographed(tmp_path, **glazed)
    masks = data.masks.clone()
    for v in range(0, len(masks), 4):
        ys, xs = torch.nonzero(masks[v] > 0.5, as_tuple=True)
        bite = xs > xs.min() + 0.93 * (xs.max() - xs.min())
        masks[v, ys[bite], xs[bite]] = 0
    bitten = hull_inside(data.P, masks, RES)
    result = photo_carve(bitten, data.P, data.images, masks, data.sizes)
    assert result.carved == 0
    monkeypatch.setattr(photohull, "NORMAL_SHIFTS", (-0.5, 0.5))
    near = photo_carve(bitten, data.P, data.images, masks, data.sizes)
    assert _judged(scene, data, bitten, near.inside)[1] > 500


def test_carving_never_opens_a_silhouette(cup):
    """Photos of noise, different in every view: every point disagrees, yet every view's silhouette stays
    covered by the carved lattice (what training's mask loss needs)."""
    _, data, inside = cup
    noise = torch.rand(data.images.shape, generator=torch.Generator().manual_seed(0))
    result = photo_carve(inside, data.P, noise, data.masks, data.sizes, spread_ratio=0.0, contrast_weight=0.0)
    assert result.restored > 0 and result.inside.any()
    pts = grid_points(RES)
    before = np.argwhere(_surface(inside))
    after = np.argwhere(_surface(result.inside))
    from dvr.cameras import project

    P = data.P / result.pool * torch.tensor([1.0, 1.0, result.pool])[None, :, None]
    h, w = -(-data.masks.shape[1] // result.pool), -(-data.masks.shape[2] // result.pool)
    lattice = pts.view(RES + 1, RES + 1, RES + 1, 3)
    cov_before = _coverage(*project(lattice[tuple(torch.from_numpy(before).T)], P), h, w)
    cov_after = _coverage(*project(lattice[tuple(torch.from_numpy(after).T)], P), h, w)
    assert not (cov_before & ~cov_after).any()


def test_an_empty_hull_and_unseen_points_change_nothing(cup):
    _, data, inside = cup
    empty = photo_carve(np.zeros_like(inside), data.P, data.images, data.masks, data.sizes)
    assert empty.carved == 0 and not empty.inside.any()
    unseen = photo_carve(inside, data.P, data.images, data.masks, data.sizes, min_views=len(data.P) + 1)
    assert unseen.carved == 0 and np.array_equal(unseen.inside, inside) and np.isnan(unseen.threshold)


def test_bad_input(cup):
    _, data, inside = cup
    with pytest.raises(ValueError, match="cubic"):
        photo_carve(inside[:, :, :-1], data.P, data.images, data.masks)
    with pytest.raises(ValueError, match="do not match"):
        photo_carve(inside, data.P[:-1], data.images, data.masks)
    with pytest.raises(ValueError, match="do not match"):
        photo_carve(inside, data.P, data.images[..., :1], data.masks)


def test_trainer_starts_from_the_photo_hull(cup, tmp_path):
    """``photo_hull``: the initial occupancy is the visual hull's less the photo hull's carving (free in the cup's
    inside, along its axis), its counts in model/photo_hull.json; without it the visual hull's (occupied all along
    the axis). Where the photo hull carves nothing (every view's photo the same grey: no colour disagrees), the
    start is the visual hull's exactly, not one at the photo hull's finer lattice."""
    import json

    from dvr.config import TrainConfig
    from dvr.trainer import Trainer

    _, data, _ = cup
    axis = torch.stack([torch.zeros(9), torch.zeros(9), torch.linspace(0.1, 0.35, 9)], 1)  # the cup's inside
    grey = dataclasses.replace(data, images=torch.full_like(data.images, 0.5))
    inits, logits = {}, {}
    for name, on, scene in (("visual", False, data), ("photo", True, data), ("grey", True, grey)):
        cfg = TrainConfig(photo_hull=on, photo_hull_res=2 * RES, hull_res=RES, fit_frame=False, progress=False)
        trainer = Trainer(cfg, scene, tmp_path / name)
        logits[name] = trainer._initial_logits()
        with torch.no_grad():
            inits[name] = trainer.model.occupancy(axis).reshape(-1)
    counts = json.loads((tmp_path / "photo" / "photo_hull.json").read_text())
    assert counts["carved"] > 0 and counts["sweeps"] > 1
    assert not (tmp_path / "visual" / "photo_hull.json").exists()
    assert (inits["visual"] > 0).all() and (inits["photo"] < 0).any()
    assert json.loads((tmp_path / "grey" / "photo_hull.json").read_text())["carved"] == 0
    assert logits["grey"].shape == logits["visual"].shape == (RES + 1,) * 3
    assert torch.equal(logits["grey"], logits["visual"])


def test_shallow_carves_are_put_back_and_deep_ones_kept():
    """A dent two cells deep in a ball's surface (a texture's nibble) comes back; a well ten cells deep (a cup's
    inside) stays carved."""
    from dvr.photohull import _shallow_carves

    n = 41
    g = np.indices((n,) * 3) - n // 2
    ball = (g ** 2).sum(0) <= 18 ** 2
    carved = ball.copy()
    dent = (np.abs(g[0]) <= 2) & (np.abs(g[1]) <= 2) & (g[2] >= 17)  # the ball's top, 2 cells deep
    well = (np.abs(g[0] - 10) <= 2) & (np.abs(g[1]) <= 2) & (g[2] >= 5)  # from the surface down 10 cells
    carved[dent | well] = False
    back = _shallow_carves(ball, carved, min_cells=5.0)
    assert back[ball & dent].all()
    assert not back[ball & well].any()
    assert not back[carved].any()  # only carved points come back


def test_a_textured_surface_keeps_its_nibbles_out(tmp_path):
    """At a threshold low enough to nibble a textured ball (no contrast term), the carved regions that reach less
    than ``min_depth`` into the hull are put back: most of the carving, and nearly all of it below the surface."""
    scene, data, inside = _photographed(tmp_path, **BALL_PHOTOS)
    kw = {"spread_ratio": 2.0, "contrast_weight": 0.0}
    every = photo_carve(inside, data.P, data.images, data.masks, data.sizes, min_depth=0.0, **kw)
    kept = photo_carve(inside, data.P, data.images, data.masks, data.sizes, **kw)
    assert every.carved > 0 and every.shallow == 0
    assert kept.shallow > 0 and kept.carved + kept.shallow == every.carved
    assert kept.carved <= 0.25 * every.carved
    assert _judged(scene, data, inside, kept.inside)[1] <= 0.1 * _judged(scene, data, inside, every.inside)[1]


def test_view_gains_recover_exposure_across_rings_despite_a_lid():
    """Two rings of four views that share a fifth of their points, each view at its own exposure and white
    balance, and a lid whose points every view sees in another colour: the fitted gains are the true ones (up to
    their common scale) within 0.5 %."""
    from dvr.photohull import _view_gains

    gen = torch.Generator().manual_seed(0)
    V, M, lid = 8, 500, 60
    albedo = 0.1 + 0.8 * torch.rand(M, 3, generator=gen)
    exposure = 1 + 0.25 * (2 * torch.rand(V, 1, generator=gen) - 1)
    gains = exposure * (1 + 0.08 * (2 * torch.rand(V, 3, generator=gen) - 1))
    colours = gains[:, None] * albedo[None]
    colours[:, :lid] = 0.1 + 0.8 * torch.rand(V, lid, 3, generator=gen)  # the lid: each view sees another place
    seen = torch.zeros(V, M, dtype=torch.bool)
    seen[:4, :300] = True
    seen[4:, 200:] = True
    seen[:, :lid] = True
    fitted = _view_gains(colours, seen)
    truth = gains / gains.log().mean(0).exp()
    assert fitted.shape == (V, 3) and torch.isfinite(fitted).all()
    assert ((fitted / truth - 1).abs() < 0.005).all()
    assert torch.allclose(_view_gains(colours, torch.zeros_like(seen)), torch.ones(V, 3))  # nothing seen: 1


def _splat_reference(uv, z, H, W, tol):
    """Plain loops: each point's 3×3 pixels, a z-buffer of them, coverage and visibility (the oracle)."""
    V, M = z.shape
    zbuf, cov = np.full((V, H, W), np.inf), np.zeros((V, H * W), bool)
    for v in range(V):
        for m in range(M):
            x0, y0 = int(np.floor(uv[v, m, 0])), int(np.floor(uv[v, m, 1]))
            for y in range(y0 - 1, y0 + 2):
                for x in range(x0 - 1, x0 + 2):
                    if z[v, m] > 0 and 0 <= x < W and 0 <= y < H:
                        zbuf[v, y, x] = min(zbuf[v, y, x], z[v, m])
                        cov[v, y * W + x] = True
    seen = np.zeros((V, M), bool)
    for v in range(V):
        for m in range(M):
            x, y = int(np.floor(uv[v, m, 0])), int(np.floor(uv[v, m, 1]))
            seen[v, m] = z[v, m] > 0 and 0 <= x < W and 0 <= y < H and z[v, m] <= zbuf[v, y, x] + tol[v, 0]
    return cov, seen


def test_splat_coverage_and_visibility_match_plain_loops():
    gen = torch.Generator().manual_seed(3)
    uv = torch.rand(3, 60, 2, generator=gen) * torch.tensor([14.0, 10.0]) - 2.0  # some off the 12×8 image
    z = torch.rand(3, 60, generator=gen) * 4.0 - 0.5  # some behind the camera
    tol = torch.tensor([[0.05], [0.2], [0.0]])
    cov, seen = _splat_reference(uv.numpy(), z.numpy(), 8, 12, tol.numpy())
    assert torch.equal(_coverage(uv, z, 8, 12), torch.from_numpy(cov))
    assert torch.equal(_visible(uv, z, 8, 12, tol), torch.from_numpy(seen))
    assert 0 < seen.sum() < seen.size and 0 < cov.sum() < cov.size  # the case is not trivial
