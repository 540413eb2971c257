"""pipeline/render/raycast.py: pixel-centre rays (whole image or a box of it), the box a mesh's projection can cover,
and the covered pixels cast only inside that box."""

import numpy as np
import pytest
import trimesh

from pipeline.render.raycast import covered_pixels, mesh_intersector, pixel_center_rays, projected_box

W, H = 64, 48
K = np.array([[60.0, 0, W / 2], [0, 60.0, H / 2], [0, 0, 1]])


def _camera(centre):
    """World→camera rotation of a camera at ``centre`` looking at the origin (y down in the image)."""
    f = -np.asarray(centre, float) / np.linalg.norm(centre)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    return np.stack([r, np.cross(f, r), f]), np.asarray(centre, float)


def _all_rays_cover(inter, R, c):
    o, d = pixel_center_rays(K, R, c, W, H)
    return inter.intersects_any(o, d).reshape(H, W)


def test_rays_of_a_box_are_those_of_the_whole_image():
    R, c = _camera([3.0, 0.5, 0.4])
    o, d = pixel_center_rays(K, R, c, W, H)
    ob, db = pixel_center_rays(K, R, c, W, H, (5, 20, 7, 30))
    assert ob.shape == db.shape == (15 * 23, 3)
    assert np.array_equal(db, d.reshape(H, W, 3)[5:20, 7:30].reshape(-1, 3)) and np.array_equal(ob[0], c)


@pytest.mark.parametrize("centre", [[3.0, 0.5, 0.4], [0.2, -2.5, 1.0]])
def test_covered_pixels_equal_casting_every_ray(centre):
    box = trimesh.creation.box(extents=[0.6, 0.4, 0.5])
    inter = mesh_intersector(box)
    R, c = _camera(centre)
    y0, y1, x0, x1 = projected_box(box.vertices, K, R, c, W, H)
    assert 0 < y1 - y0 < H or 0 < x1 - x0 < W  # a box smaller than the image: fewer rays cast
    got = covered_pixels(inter, box.vertices, K, R, c, W, H)
    assert got.any() and np.array_equal(got, _all_rays_cover(inter, R, c))


def test_a_vertex_behind_the_camera_bounds_nothing_and_every_ray_is_cast():
    """A mesh reaching behind the camera projects without bound: no box, and the covered pixels are still exact."""
    R, c = _camera([3.0, 0.5, 0.4])
    slab = trimesh.creation.box(extents=[8.0, 0.3, 0.3])  # from in front of the camera to behind it
    assert projected_box(slab.vertices, K, R, c, W, H) is None
    inter = mesh_intersector(slab)
    got = covered_pixels(inter, slab.vertices, K, R, c, W, H)
    assert got.any() and np.array_equal(got, _all_rays_cover(inter, R, c))


def test_a_mesh_outside_the_image_covers_nothing():
    R, c = _camera([3.0, 0.0, 0.0])
    far_side = trimesh.creation.box(extents=[0.2, 0.2, 0.2])
    far_side.apply_translation([0.0, 5.0, 0.0])  # beside the view, in front of the camera
    y0, y1, x0, x1 = projected_box(far_side.vertices, K, R, c, W, H)
    assert y1 == y0 or x1 == x0
    assert not covered_pixels(mesh_intersector(far_side), far_side.vertices, K, R, c, W, H).any()
