"""Visual hull: carving lookup, the hull's logit volume, and the tighter working sphere around it."""

import numpy as np
import pytest
import torch
import trimesh

from dvr.data import load_scene
from dvr.hull import (
    grid_points,
    hull_bounding_sphere,
    hull_inside,
    hull_logits,
    lattice_corners,
    mask_lookup,
    near_object,
    outside_hull,
)


def test_bounding_sphere_contains_the_object_and_is_tight(small_ws):
    data = load_scene(small_ws, torch.device("cpu"))
    c, r = hull_bounding_sphere(data.P, data.masks, 64, 1.1, min_views=1)
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
    with pytest.raises(ValueError, match="points must have shape"):
        outside_hull(pts[:, :2], data.P, data.masks)
    with pytest.raises(ValueError, match="P must be"):
        outside_hull(pts, data.P[:, :2], data.masks)


def ring_camera(angle: float) -> torch.Tensor:
    """(3, 4) projection of a 100-px camera on the z = 0 circle of radius 3 at ``angle``, looking at the origin."""
    K = torch.tensor([[50.0, 0, 50], [0, 50.0, 50], [0, 0, 1]])
    c, s = np.cos(angle), np.sin(angle)
    R = torch.tensor([[-s, c, 0.0], [0.0, 0.0, -1.0], [-c, -s, 0.0]], dtype=torch.float32)
    t = -R @ torch.tensor([3 * c, 3 * s, 0.0], dtype=torch.float32)
    return K @ torch.cat([R, t[:, None]], 1)


def test_two_views_carve_where_two_see_and_one_where_only_one_sees():
    """``min_views`` 2: a point that two views see and one calls background stays; a point that only one view
    sees (a sparse capture's sphere edge) is carved by that one; no view: free."""
    P = torch.stack([ring_camera(0.0), ring_camera(np.pi / 2)])
    masks = torch.ones(2, 100, 100)
    masks[0] = 0.0  # view 0 calls everything background
    both, only_0, only_1 = [0.0, 0.0, 0.0], [-1.0, 3.5, 0.0], [3.5, -1.0, 0.0]  # behind view 1; behind view 0
    vals, seen = mask_lookup(torch.tensor([both, only_0, only_1]), P, masks)
    assert seen.tolist() == [[True, True, False], [True, False, True]]
    out = outside_hull(torch.tensor([both, only_0, only_1, [0.0, 0.0, 9.0]]), P, masks, min_views=2)
    assert out.tolist() == [False, True, False, True]
    assert outside_hull(torch.tensor([both]), P, masks, min_views=1).tolist() == [True]


def test_one_view_carves_where_fewer_than_sparse_views_see_the_point():
    """``sparse_views``: a point that three views see and one calls background stays under the two-mask rule, and is
    carved once fewer than ``sparse_views`` views see it (4: yes; 3: no, three views are enough voters)."""
    P = torch.stack([ring_camera(0.0), ring_camera(np.pi / 2), ring_camera(np.pi)])
    masks = torch.ones(3, 100, 100)
    masks[0] = 0.0
    centre = torch.zeros(1, 3)
    assert mask_lookup(centre, P, masks)[1].all()
    assert outside_hull(centre, P, masks, min_views=2).tolist() == [False]
    assert outside_hull(centre, P, masks, min_views=2, sparse_views=3).tolist() == [False]
    assert outside_hull(centre, P, masks, min_views=2, sparse_views=4).tolist() == [True]
    assert hull_inside(P, masks, res=8, min_views=2, sparse_views=4).sum() < hull_inside(P, masks, res=8,
                                                                                          min_views=2).sum()


def test_many_views_outvote_a_few_wrong_masks_with_min_fraction():
    """``min_fraction``: 20 views see the centre and 3 of them call it background. Two views carve it by
    ``min_views`` alone; with a fraction of 0.1 it takes 2 (20 × 0.1, no float rounding up to 3), with 0.2 four, so
    the three wrong masks no longer carve it; never more than all the views that see a point; bad fractions refused."""
    P = torch.stack([ring_camera(a) for a in np.linspace(0, 2 * np.pi, 20, endpoint=False)])
    masks = torch.ones(20, 100, 100)
    masks[:3] = 0.0
    centre = torch.zeros(1, 3)
    assert outside_hull(centre, P, masks, min_views=2).tolist() == [True]
    assert outside_hull(centre, P, masks, min_views=2, min_fraction=0.1).tolist() == [True]
    assert outside_hull(centre, P, masks, min_views=2, min_fraction=0.2).tolist() == [False]
    assert outside_hull(centre, P, torch.zeros(20, 100, 100), min_views=2, min_fraction=1.0).tolist() == [True]
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError, match="min_fraction must lie in"):
            outside_hull(centre, P, masks, min_fraction=bad)


def test_the_fraction_holds_only_near_the_masks_with_fraction_near():
    """``fraction_near``: 20 views see the centre (it projects to each image's centre pixel) and 3 call it
    background; a fraction of 0.2 keeps it. Where those views' masks end next to it (a thin part they lost, 5 px
    away) the fraction still keeps it; where they end far from it (30 px) the plain two-view rule carves it."""
    P = torch.stack([ring_camera(a) for a in np.linspace(0, 2 * np.pi, 20, endpoint=False)])
    centre = torch.zeros(1, 3)

    def lost(gap: int) -> torch.Tensor:
        masks = torch.ones(20, 100, 100)
        masks[:3, :, : 50 + gap] = 0.0  # three views' masks end ``gap`` px right of the centre pixel
        return masks

    for gap, carved in ((5, False), (30, True)):
        masks = lost(gap)
        assert outside_hull(centre, P, masks, min_views=2, min_fraction=0.2).tolist() == [False]
        assert outside_hull(centre, P, masks, min_views=2, min_fraction=0.2,
                            fraction_near=near_object(masks, 10)).tolist() == [carved]
    masks = lost(30)
    masks[1:3] = 1.0  # one far view alone is fewer than min_views
    assert outside_hull(centre, P, masks, min_views=2, min_fraction=0.2,
                        fraction_near=near_object(masks, 10)).tolist() == [False]


def test_a_point_too_few_views_frame_is_free_with_min_framing():
    """``min_framing``: a point that one view frames, inside its mask (a close-up's corner of the working sphere),
    stays by default and is free with ``min_framing`` 2; the point both views frame stays with 2 and goes with 3;
    ``min_framing`` 0 is refused."""
    P = torch.stack([ring_camera(0.0), ring_camera(np.pi / 2)])
    masks = torch.ones(2, 100, 100)
    both, only_0 = [0.0, 0.0, 0.0], [-1.0, 3.5, 0.0]
    points = torch.tensor([both, only_0])
    assert mask_lookup(points, P, masks)[1].sum(0).tolist() == [2, 1]
    assert outside_hull(points, P, masks).tolist() == [False, False]
    assert outside_hull(points, P, masks, min_framing=2).tolist() == [False, True]
    assert outside_hull(points, P, masks, min_framing=3).tolist() == [True, True]
    with pytest.raises(ValueError, match="min_framing"):
        outside_hull(points, P, masks, min_framing=0)


def test_cut_by_frame_finds_the_masks_that_reach_their_image_edge():
    """A mask inside its frame, one reaching the right edge, one reaching only the canvas's padding beyond its own
    smaller image (not cut), one touching the edge with a single pixel (under 1 % of the border: not cut)."""
    from dvr.hull import cut_by_frame

    masks = torch.zeros(4, 60, 80)
    masks[:, 20:40, 30:50] = 1.0
    masks[1:3, 20:40, 50:] = 1.0
    masks[3, 0, 40] = 1.0  # 1 of the border's 276 pixels
    sizes = torch.tensor([[80, 60], [80, 60], [60, 60], [80, 60]])
    assert cut_by_frame(masks, sizes).tolist() == [False, True, True, False]  # view 2: its own edge at 60
    sizes[2, 0] = 80
    masks[2, :, 60:] = 0.0
    assert cut_by_frame(masks, sizes).tolist() == [False, True, False, False]
    assert cut_by_frame(masks).tolist() == [False, True, False, False]
    with pytest.raises(ValueError, match="cut_by_frame"):
        cut_by_frame(masks[0])


def test_near_object_marks_the_pixels_within_px_of_an_object_pixel():
    """1 on the object and less than ``px`` from it (one distance, or one per view), 0 beyond; a mask without object
    is all 0; bad input: one-line ValueError."""
    masks = torch.zeros(2, 9, 9)
    masks[0, 4, 4] = 1.0
    near = near_object(masks, 2.5)
    assert near.shape == masks.shape and near.dtype == masks.dtype
    rows, cols = torch.meshgrid(torch.arange(9.0), torch.arange(9.0), indexing="ij")
    assert torch.equal(near[0], (((rows - 4) ** 2 + (cols - 4) ** 2) < 2.5 ** 2).float())
    assert near[1].sum() == 0
    per_view = near_object(masks, [1.5, 2.5])  # one distance per view
    assert torch.equal(per_view[0], (((rows - 4) ** 2 + (cols - 4) ** 2) < 1.5 ** 2).float())
    for bad in ((masks[0], 2.0), (masks, 0.0), (masks, float("nan"))):
        with pytest.raises(ValueError, match="near_object"):
            near_object(*bad)


def test_one_mask_carves_where_the_point_lies_far_inside_its_background():
    """``near`` (:func:`near_object`): a point that three views see and one calls background stays under the
    two-mask rule when it lies near that view's object pixels, and is carved once it lies farther from them than
    ``px`` (the sure background)."""
    P = torch.stack([ring_camera(0.0), ring_camera(np.pi / 2), ring_camera(np.pi)])
    masks = torch.ones(3, 100, 100)
    masks[0] = 0.0
    masks[0, :, :40] = 1.0  # view 0's object ends 10 px left of the centre, where the origin projects
    centre = torch.zeros(1, 3)
    assert outside_hull(centre, P, masks, min_views=2).tolist() == [False]
    assert outside_hull(centre, P, masks, min_views=2, near=near_object(masks, 20.0)).tolist() == [False]
    assert outside_hull(centre, P, masks, min_views=2, near=near_object(masks, 5.0)).tolist() == [True]
    assert hull_inside(P, masks, res=8, min_views=2, near=near_object(masks, 5.0)).sum() < hull_inside(
        P, masks, res=8, min_views=2).sum()


def test_stacked_maps_read_at_one_projection_equal_each_map_read_alone(small_ws):
    """mask_lookup / view_votes of (V, C, H, W) maps (the masks and their sure-background maps, one projection) give
    each map's own values and counts; outside_hull with ``near`` equals its rule spelled out from separate lookups."""
    from dvr.hull import view_votes

    data = load_scene(small_ws, torch.device("cpu"))
    near = near_object(data.masks, 3.0)
    pts = grid_points(16)
    vals, seen = mask_lookup(pts, data.P, torch.stack([data.masks, near], dim=1), data.sizes)
    for c, maps in enumerate((data.masks, near)):
        alone, seen_alone = mask_lookup(pts, data.P, maps, data.sizes)
        assert torch.equal(vals[:, c], alone) and torch.equal(seen, seen_alone)
    (n_out, n_far), n_seen = view_votes(pts, data.P, torch.stack([data.masks, near], dim=1), data.sizes)
    assert torch.equal(n_out, view_votes(pts, data.P, data.masks, data.sizes)[0])
    assert torch.equal(n_far, view_votes(pts, data.P, near, data.sizes)[0])
    reference = outside_hull(pts, data.P, data.masks, min_views=2, sizes=data.sizes) | (n_far > 0)
    got = outside_hull(pts, data.P, data.masks, min_views=2, sizes=data.sizes, near=near)
    assert torch.equal(got, reference) and (got & ~outside_hull(pts, data.P, data.masks, min_views=2)).any()


@pytest.mark.parametrize("full", [False, True])
def test_hull_lattice_projects_only_the_sphere_and_equals_the_whole_lattice_test(small_ws, full):
    """hull_inside tests only the lattice points inside the unit sphere (about half of them: the masks stage builds
    three 128³ hulls); the lattice equals the plain test of every point (the reference), with masks that make
    the sphere's inside all hull too (full masks: the whole ball, nothing outside it)."""
    data = load_scene(small_ws, torch.device("cpu"))
    masks = torch.ones_like(data.masks) if full else data.masks
    pts = grid_points(24)
    reference = (~(outside_hull(pts, data.P, masks) | (pts.norm(dim=-1) > 1.0))).view(25, 25, 25).numpy()
    got = hull_inside(data.P, masks, res=24)
    assert got.dtype == bool and np.array_equal(got, reference) and got.any()
    assert got.sum() == (pts.norm(dim=-1) <= 1.0).sum() if full else got.sum() < reference.size // 4


def test_carve_along_rays_frees_only_the_segment_in_front():
    from dvr.hull import carve_along_rays, grid_points

    R = 32
    vol = torch.full((R + 1,) * 3, 5.0)
    o = torch.tensor([[-3.0, 0.0, 0.0], [0.0, -3.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    depth = torch.tensor([2.5, 1.5])  # x = −0.5 on the first ray; the second ends before the sphere (entry 2)
    out = carve_along_rays(vol, o, d, depth, value=3.0)
    pts = grid_points(R).view(R + 1, R + 1, R + 1, 3)
    line = out[:, R // 2, R // 2]
    x = pts[:, R // 2, R // 2, 0]
    assert (line[x < -0.5 - 3 ** 0.5 / R - 1e-6] == -3.0).all()  # in front of the depth: free
    assert (line[x >= -0.5] == 5.0).all()  # at and behind the depth: untouched
    assert (out[R // 2, :, R // 2] == 5.0).all()  # the second ray has nothing inside the sphere to carve
    assert (out != vol).sum() == (line != 5.0).sum()  # nothing else changed
    assert torch.equal(carve_along_rays(vol, o, d, torch.zeros(2)), vol)


def test_coarse_points_are_the_fine_lattices_points(small_ws):
    """A coarse lattice read from a finer one is the coarse lattice itself where the resolutions divide (the
    visual hull at 32 from the one at 64), the nearest points where they do not or where it is finer (a photo
    hull's lattice set coarser than the training's); bad input is refused."""
    from dvr.hull import coarse_points, hull_inside

    data = load_scene(small_ws, torch.device("cpu"))
    fine = hull_inside(data.P, data.masks, 64)
    assert np.array_equal(coarse_points(fine, 32), hull_inside(data.P, data.masks, 32))
    assert np.array_equal(coarse_points(fine, 64), fine)
    ramp = np.broadcast_to(np.arange(11)[:, None, None], (11, 11, 11))
    assert coarse_points(ramp, 4)[:, 0, 0].tolist() == [0, 2, 5, 8, 10]  # 2.5 → 2, 7.5 → 8 (round half to even)
    finer = [0, 0, 1, 2, 2, 2, 3, 4, 4, 4, 5, 6, 6, 6, 7, 8, 8, 8, 9, 10, 10]  # k / 2, half to even
    assert coarse_points(ramp, 20)[:, 0, 0].tolist() == finer
    with pytest.raises(ValueError, match="cubic lattice"):
        coarse_points(fine, 0)
    with pytest.raises(ValueError, match="cubic lattice"):
        coarse_points(fine[:, :, :-1], 32)


def test_lattice_corners_of_a_point_are_its_cells_eight():
    i, j, k = lattice_corners(np.array([[0.01, -0.01, 0.99], [1.5, 0.0, 0.0]]), 4)
    assert sorted(zip(i.tolist(), j.tolist(), k.tolist())) == sorted(
        (2 + a, 1 + b, 3 + c) for a in (0, 1) for b in (0, 1) for c in (0, 1))


def test_settled_onto_plane_fills_under_low_points_only_down_to_a_tilted_plane():
    """settled_onto_plane: under an inside lattice point 0.2 above a tilted plane, the lattice points along the
    plane's normal down to the plane fill (none below it); under a point 0.6 above it, nothing; without a low point
    the lattice is returned as it was."""
    from dvr.cameras import plane_height
    from dvr.hull import grid_points, settled_onto_plane

    res = 32
    normal = np.array([0.6, 0.0, 0.8])
    ground = np.array([*normal, 0.5])  # height = n·x + 0.5
    pts = grid_points(res, dtype=torch.float64).numpy()
    h = plane_height(ground, pts)
    low = np.argmin(np.abs(h - 0.2) + np.linalg.norm(pts[:, :2], axis=1))  # a lattice point 0.2 above, near the axis
    high = np.argmin(np.abs(h - 0.6) + np.linalg.norm(pts[:, :2] - 0.3, axis=1))
    inside = np.zeros((res + 1,) * 3, bool)
    inside.reshape(-1)[[low, high]] = True
    out = settled_onto_plane(inside, ground, 0.3)
    added = pts[out.reshape(-1) & ~inside.reshape(-1)]
    assert len(added) >= 3
    assert (plane_height(ground, added) >= -1.0 / res).all() and (plane_height(ground, added) < h[low]).all()
    off_axis = added - pts[low] - np.outer((added - pts[low]) @ normal, normal)  # straight under the low point
    assert np.linalg.norm(off_axis, axis=1).max() <= np.sqrt(3) / res
    assert np.array_equal(settled_onto_plane(inside, ground, 0.15), inside)  # both points higher than that
