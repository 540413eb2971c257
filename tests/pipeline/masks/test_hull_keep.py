"""The sparse points no visual hull of the masks carves (pipeline/masks/stage.py ``kept_points``, ``visual_hull``,
through dvr/hull.py ``hull_lattice``'s ``keep``): two masks that miss the base of a box carve it from the hull in every
view; the points SfM triangulated on that base hold it."""

import numpy as np

from dvr.hull import lattice_corners
from pipeline.masks import stage
from tests.pipeline.scene.test_support import _box_and_table_masks

RES = 64


def _base_points() -> np.ndarray:
    """Points on the four sides of the box (0.6 × 0.4, from z = −0.5 up) 0.05–0.15 above the floor."""
    rng = np.random.default_rng(0)
    z = rng.uniform(-0.45, -0.35, 80)
    s = rng.uniform(-1.0, 1.0, 80)
    side = np.arange(80) % 4
    x = np.where(side < 2, np.where(side == 0, 0.3, -0.3), 0.3 * s)
    y = np.where(side < 2, 0.2 * s, np.where(side == 2, 0.2, -0.2))
    return np.stack([x, y, z], 1)


def _logits_at(lg, points: np.ndarray) -> np.ndarray:
    """The hull's logits at the lattice points nearest ``points``, moved 0.02 into the box (its inside)."""
    inner = points * np.array([0.9, 0.9, 1.0])
    idx = np.clip(np.round((inner + 1.0) * RES / 2).astype(int), 0, RES)
    return lg.numpy()[idx[:, 0], idx[:, 1], idx[:, 2]]


def _masks_missing_the_base(views=(0, 1), rows=40):
    cams, masks, _ = _box_and_table_masks(table_radius=0.0)
    for i in views:  # the lowest ``rows`` rows of the box cut away, as GrabCut does where a cream rim meets a table
        ys = np.nonzero(masks[i].any(1))[0]
        masks[i][ys.max() - rows:] = False
    return cams, masks


def test_points_on_a_base_two_masks_missed_stay_in_the_hull():
    cams, masks = _masks_missing_the_base()
    points = _base_points()
    without = stage.visual_hull(masks, cams, RES, 2)
    assert (_logits_at(without, points) < 0).mean() > 0.5  # the two views' cut carved most of the base
    held = stage.visual_hull(masks, cams, RES, 2, keep=points)
    assert (_logits_at(held, points) > 0).all()
    untouched = _box_and_table_masks(table_radius=0.0)[1]  # masks that hold the base: only the points' cells added
    grown = (stage.visual_hull(untouched, cams, RES, 2, keep=points) > 0) & \
        ~(stage.visual_hull(untouched, cams, RES, 2) > 0)
    corners = np.zeros(grown.shape, bool)
    corners[lattice_corners(points, RES)] = True
    assert not (grown.numpy() & ~corners).any()


def test_kept_points_are_the_objects_seen_by_enough_views():
    """Inside the object's sphere (radius < 0.9), above the plane's band, observed by ≥ min_views views."""
    cams, _ = _masks_missing_the_base(views=())
    pts = np.array([[0.0, 0.0, 0.0],      # object, three views
                    [0.0, 0.0, 0.1],      # object, two views
                    [0.95, 0.0, 0.0],     # beyond the object's sphere
                    [0.1, 0.1, -0.49]])   # on the floor z = −0.5
    obs = {"a": [0, 1, 2, 3], "b": [0, 1, 2, 3], "c": [0, 2, 3]}
    assert np.array_equal(stage.kept_points(pts, obs, cams, 3), pts[:1])
    assert np.array_equal(stage.kept_points(pts, obs, cams, 2), pts[:2])
    assert stage.kept_points(pts, obs, cams, 0) is None
    assert stage.kept_points(None, None, cams, 3) is None
    assert stage.kept_points(pts, {"a": [], "b": []}, cams, 1) is None


def test_the_masks_hull_volume_has_the_zero_level_of_the_hull_logits():
    """The masks stage's ±1 hull volume and dvr's distance-transform logits of the same hull give the same marching
    cubes surface, so the same silhouette in every view, pixel for pixel."""
    import torch

    from dvr.data import pad_stack
    from dvr.hull import hull_logits

    cams, masks = _masks_missing_the_base()
    volume = stage.visual_hull(masks, cams, RES, 2)
    assert set(np.unique(volume.numpy())) == {-1.0, 1.0}
    canvas, sizes = (torch.from_numpy(a) for a in pad_stack([m.astype(np.float32) for m in masks]))
    logits = hull_logits(torch.from_numpy(cams.P).float(), canvas, res=RES, min_views=2, min_fraction=0.0,
                         ground=cams.ground, sizes=sizes)
    assert np.array_equal(volume.numpy() > 0, logits.numpy() > 0)
    assert np.abs(logits.numpy()).max() > 1.0  # the logits grow away from the surface; the volume does not
    for a, b in zip(stage.hull_silhouettes(masks, cams, volume), stage.hull_silhouettes(masks, cams, logits)):
        assert np.array_equal(a, b)
