"""The masks' hull resting on the support plane (pipeline/masks/stage.py ``visual_hull``'s ``settle``, through
dvr/hull.py ``hull_lattice`` and ``settled_onto_plane``): masks that all miss the lowest band of a box standing on
the floor (a shiny object's base mirrors the floor, and every view's GrabCut gives it to the floor) float its hull
above the floor; settled, the hull reaches it, while a box held higher keeps the space under it free."""

import numpy as np
import trimesh

from pipeline.masks import stage
from pipeline.render.raycast import MeshCaster, pixel_center_rays
from tests.pipeline.scene.test_support import _ring, _ring_cameras

RES = 64
FLOOR = -0.5


def _cameras():
    C, R = (np.concatenate(x) for x in zip(_ring(height=0.3, target=(0.0, 0.0, -0.2)),
                                             _ring(height=2.5, target=(0.0, 0.0, -0.2))))
    return _ring_cameras(C, R, 500.0)


def _masks_of_box(cams, bottom: float) -> list[np.ndarray]:
    """Every view's mask of a 0.6 × 0.4 box from ``bottom`` up to z = 0.3."""
    box = trimesh.creation.box((0.6, 0.4, 0.3 - bottom),
                               trimesh.transformations.translation_matrix((0, 0, (0.3 + bottom) / 2)))
    caster = MeshCaster(box)
    return [caster.any_hit(*pixel_center_rays(cams.K[i], cams.R[i], cams.centers[i], 320, 240)).reshape(240, 320)
            for i in range(len(cams))]


def _inside_at(lg, points: np.ndarray) -> np.ndarray:
    idx = np.clip(np.round((points + 1.0) * RES / 2).astype(int), 0, RES)
    return lg.numpy()[idx[:, 0], idx[:, 1], idx[:, 2]] > 0


def test_a_hull_floating_just_above_the_floor_settles_onto_it():
    cams = _cameras()
    masks = _masks_of_box(cams, FLOOR + 0.05)  # every mask misses the box's lowest 0.05
    # the band along the box's sides (its middle, hidden from every view, no mask carves)
    band = np.array([[0.27, 0.0, FLOOR + 0.01], [0.27, 0.0, FLOOR + 0.03], [-0.27, 0.1, FLOOR + 0.02],
                     [0.0, 0.17, FLOOR + 0.02]])
    assert not _inside_at(stage.visual_hull(masks, cams, RES, 2), band).any()  # the hull floats
    settled = stage.visual_hull(masks, cams, RES, 2, settle=0.08)
    assert _inside_at(settled, band).all()
    assert not _inside_at(settled, np.array([[0.0, 0.0, FLOOR - 0.03]])).any()  # not below the floor
    assert not _inside_at(settled, np.array([[0.45, 0.0, FLOOR + 0.02], [0.0, 0.35, FLOOR + 0.02]])).any()


def test_a_hull_held_higher_keeps_the_space_under_it():
    cams = _cameras()
    masks = _masks_of_box(cams, FLOOR + 0.3)  # a box 0.3 above the floor: a table top, a cow's belly
    plain = stage.visual_hull(masks, cams, RES, 2) > 0
    settled = stage.visual_hull(masks, cams, RES, 2, settle=0.08) > 0
    assert np.array_equal(plain.numpy(), settled.numpy())


def test_settling_needs_a_support_plane():
    cams = _cameras()
    cams.ground = None
    masks = _masks_of_box(cams, FLOOR + 0.05)
    plain = stage.visual_hull(masks, cams, RES, 2) > 0
    assert np.array_equal(plain.numpy(), (stage.visual_hull(masks, cams, RES, 2, settle=0.08) > 0).numpy())
